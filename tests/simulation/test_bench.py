"""Timing a scene per strategy (``refsim.simulation.bench``, what ``refsim bench SCENE`` prints): interleaved
runs, the median and the run it comes from, the reference timed beside each run."""

from __future__ import annotations

import numpy as np

from refsim.scene import load_scene
from refsim.simulation.bench import time_strategies


def test_strategies_are_timed_on_interleaved_runs_and_report_their_median_run():
    # A tiny cube (2 cells, 0.1 s) in two strategies, 3 rounds. The reference is a counter: two readings per
    # timed run (before and after it), none for the untimed first runs; the median is one of the runs' times
    # and its summary is that run's (the same step count as the scene).
    scenes = {
        name: load_scene(
            "cube", ["mesh.cells=[2, 2, 2]", "time.duration=0.1", f'compliance.strategy="{name}"']
        )
        for name in ("exact", "fast")
    }
    readings = []

    def reference():
        readings.append(len(readings))
        return float(len(readings))

    timed = time_strategies(scenes, 3, reference=reference)
    assert list(timed) == ["exact", "fast"] and len(readings) == 2 * 3 * 2
    for name, run in timed.items():
        assert run.step_ms.shape == (3,) and np.all(run.step_ms > 0.0)
        assert run.median_ms == float(np.median(run.step_ms)) and run.median_ms in run.step_ms
        assert run.summary.steps == scenes[name].time.step_count == len(run.kept["needle_force"])
        assert run.setup_ms > 0.0 and run.scene is scenes[name]
    # interleaved: exact's k-th run is read between readings 4k + 1 and 4k + 2 (fast's between 4k + 3 and
    # 4k + 4), so its references are 1.5, 5.5, 9.5 and fast's 3.5, 7.5, 11.5
    assert timed["exact"].reference_ms == 5.5 and timed["fast"].reference_ms == 7.5
