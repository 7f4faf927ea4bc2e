"""Timing a scene's runs per compliance strategy (``refsim bench SCENE``): interleaved runs, medians, the
same-run reference, and the comparison of each strategy's run with the exact one.

The machine's load changes: the strategies' runs are interleaved (exact, fast, exact, fast, ...), each
strategy's time per step is the median of its runs, and the reference (one SuperLU factorisation of the
paper's cube, :func:`refsim.fem.bench.superlu_reference_ms`) is timed again beside each run.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from refsim.fem import bench as tissue_bench
from refsim.scene.build import build_models
from refsim.simulation.simulation import Simulation
from refsim.simulation.summary import RunSummary, run_and_keep

__all__ = ["TimedStrategy", "run_for_bench", "time_strategies"]


def run_for_bench(scene) -> tuple[tuple[RunSummary, dict], float]:
    """Run ``scene`` to its end keeping what a comparison of runs needs (``run_and_keep``), and the seconds
    its simulation took to build from the scene's models (the models built before the clock starts)."""
    models = build_models(scene)
    start = time.perf_counter()
    simulation = Simulation(scene, models)
    setup = time.perf_counter() - start
    return run_and_keep(simulation), setup


@dataclass(frozen=True)
class TimedStrategy:
    """One strategy's timed runs of a scene.

    Attributes
    ----------
    scene : The scene as run (its compliance set to the strategy).
    step_ms : Wall time per step of each run [ms], in run order, shape (repeats,).
    setup_ms : Median time to build the simulation [ms] (the fast mode's rest factorisation).
    reference_ms : Median of the reference timed beside each run [ms].
    summary, kept : The summary and kept values (``run_and_keep``) of the median run (the upper middle one
        for an even count).
    """

    scene: object
    step_ms: np.ndarray
    setup_ms: float
    reference_ms: float
    summary: RunSummary
    kept: dict

    @property
    def median_ms(self) -> float:
        """The median time per step of the runs [ms]."""
        return float(np.median(self.step_ms))


def time_strategies(
    scenes: dict, repeats: int, reference: Callable[[], float] | None = None
) -> dict[str, TimedStrategy]:
    """Time each scene of ``scenes`` (strategy name → scene) on ``repeats`` runs, interleaved, after one
    untimed run of each (numba compiles a kernel at its first call: up to minutes after a fresh install, and
    the kernels a cut uses only once the cut starts; not a step's cost). ``reference``: the same-run
    reference [ms], the SuperLU factorisation of the paper's cube by default."""
    if reference is None:
        model = tissue_bench.cube_model(8)
        reference = lambda: tissue_bench.superlu_reference_ms(model)  # noqa: E731
    for scene in scenes.values():
        run_for_bench(scene)
    timed: dict[str, list] = {name: [] for name in scenes}
    for _ in range(repeats):
        for name, scene in scenes.items():
            before = reference()
            (summary, kept), setup = run_for_bench(scene)
            around = 0.5 * (before + reference())
            timed[name].append((1e3 * summary.seconds / max(summary.steps, 1), setup, around, summary, kept))
    out = {}
    for name, runs in timed.items():
        step_ms = np.array([run[0] for run in runs])
        middle = runs[int(np.argsort(step_ms, kind="stable")[len(runs) // 2])]
        out[name] = TimedStrategy(
            scenes[name],
            step_ms,
            1e3 * float(np.median([run[1] for run in runs])),
            float(np.median([run[2] for run in runs])),
            middle[3],
            middle[4],
        )
    return out
