"""The hot path's thread limit (refsim.fem.threads): set once by the outermost block, restored on exit."""

from __future__ import annotations

import pytest

from refsim.fem.threads import _controller, hot_path_threads


def _counts() -> list[int]:
    return [info["num_threads"] for info in _controller().info()]


def test_nested_blocks_keep_the_limit_and_the_outer_setting_is_restored():
    before = _counts()
    with hot_path_threads(1):
        inside = _counts()
        assert all(count == 1 for count in inside)
        with hot_path_threads(1):  # nested, same limit: nothing to set
            assert _counts() == inside
        assert _counts() == inside  # the nested block's exit does not lift the outer limit
        with hot_path_threads(2):  # another limit inside: set, then the outer one back
            pass
        assert _counts() == inside
    assert _counts() == before


def test_bad_thread_counts_are_refused():
    for bad in (0, -1, 1.5, "1"):
        with pytest.raises(ValueError, match="threads must be"):
            with hot_path_threads(bad):
                pass
        with hot_path_threads(1), pytest.raises(ValueError, match="threads must be"):  # nested too
            with hot_path_threads(bad):
                pass


def test_a_run_holds_one_thread_through_its_steps_and_callbacks_and_restores_the_callers_setting():
    from refsim.simulation import Simulation
    from tests.conftest import cube_scene

    simulation = Simulation(cube_scene("mesh.cells=[2,2,2]", "time.duration=0.03"))
    seen = []
    with _controller().limit(limits=2):  # the caller's setting: two threads, so that the limit shows
        before = _counts()
        simulation.run(on_step=lambda state, record: seen.append(_counts()))
        assert _counts() == before
    assert len(seen) == simulation.scene.time.step_count
    assert all(count == 1 for counts in seen for count in counts)
