"""Replay of a keyed session with a flexible needle, tilted and moved sideways (directions off the axes, the
beam model built from the start pose): `refsim run`'s driver on the replay scene gives the same needle force,
positions and frames, to the bit."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from refsim.interactive.pacing import Pacer
from refsim.interactive.pose import KEYS
from refsim.interactive.session import InteractiveSession
from refsim.io.driver import run_scene
from refsim.scene import load_scene

OVERRIDES = ["mesh.cells=[4, 4, 4]", "needle.rigid=false", "needle.element_count=8"]


def test_a_keyed_flexible_session_replays_to_the_bit(tmp_path):
    session = InteractiveSession(load_scene("cube", OVERRIDES), tmp_path / "keyed.h5")
    pacer = Pacer(session)
    for key, presses, steps in (("Up", 3, 10), ("l", 2, 8), ("Right", 1, 6), ("Down", 1, 5)):
        for _ in range(presses):
            session.target.key(KEYS[key], distance=1e-3, angle=np.radians(2.0))
        for _ in range(steps):
            session.step()
    pacer.finish()
    assert session.status == "complete" and session.state.step == 30
    summary = run_scene(load_scene(session.replay_path), tmp_path / "replay.h5", handle_signals=False)
    assert summary.status == "complete" and summary.steps == 30
    with h5py.File(session.output) as interactive, h5py.File(tmp_path / "replay.h5") as replay:
        directions = interactive["scene/trajectory/samples"][:, 4:7]
        assert np.ptp(directions[:, 0]) > 0.01  # the tilt turned the needle off the z axis
        for name in ("needle_force", "needle_positions", "needle_frames", "base_position", "phase"):
            assert np.array_equal(interactive[f"steps/{name}"][()], replay[f"steps/{name}"][()]), name
        assert np.array_equal(interactive["tissue/positions"][()], replay["tissue/positions"][()])


def test_a_scene_of_several_instruments_is_refused_before_any_file(tmp_path):
    from refsim.io.driver import RunInputError

    with pytest.raises(RunInputError, match=r"steers one needle.*cutter, holder"):
        InteractiveSession(load_scene("two_needles"), tmp_path / "two.h5")
    assert not any(tmp_path.iterdir())
