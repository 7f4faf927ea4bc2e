"""The applied trajectory and the replay scene: what the run applied is what a replay reads, to the bit; holds
are stored as their two ends; the replay scene loads and differs from the original only in its trajectory,
its duration and absolute file paths."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from refsim.interactive.pose import PoseTarget, exact_unit
from refsim.interactive.recording import AppliedTrajectory, replay_paths, toml_document, write_replay_scene
from refsim.scene import load_scene
from refsim.scene.trajectory import read_trajectory_csv


def _session_like(steps: int = 300) -> tuple[AppliedTrajectory, list]:
    """Poses as a session applies them: a target moved at random (translations and turns) with holds
    between, advanced at the speed bound, times summed as the step loop sums them."""
    rng = np.random.default_rng(4)
    base, direction = np.array([0.01, -0.02, 0.4]), exact_unit([0.1, 0.2, -1.0])
    target = PoseTarget(base, direction, needle_length=0.3, max_speed=0.05, max_turn=np.radians(30.0))
    applied = AppliedTrajectory(base, direction)
    time, read = 0.0, [(0.0, *applied.pose(0.0))]
    for step in range(steps):
        if step % 40 == 0:
            goal, pointing = target.target()
            target.set(
                goal + rng.normal(scale=3e-3, size=3), exact_unit(pointing + rng.normal(scale=0.05, size=3))
            )
        time = time + 0.01
        applied.append(time, *target.advance(0.01))
        read.append((time, *applied.pose(time)))  # what the step reads (Controls.at), right after
    return applied, read


def test_the_replay_reads_the_applied_poses_to_the_bit(tmp_path):
    applied, read = _session_like()
    trajectory = read_trajectory_csv(applied.write_csv(tmp_path / "applied.csv"))
    assert trajectory.times.size < len(read)  # the holds are stored as their ends
    for time, expected_base, expected_direction in read:
        base, direction = trajectory.pose(time)
        assert np.array_equal(base, expected_base) and np.array_equal(direction, expected_direction), time


def test_holds_are_stored_as_their_two_ends():
    applied = AppliedTrajectory([0.0, 0.0, 0.4], [0.0, 0.0, -1.0])
    time = 0.0
    for _ in range(50):  # a hold of 50 steps
        time += 0.01
        applied.append(time, [0.0, 0.0, 0.4], [0.0, 0.0, -1.0])
    hold_end = time
    time += 0.01
    applied.append(time, [0.0, 0.0, 0.399], [0.0, 0.0, -1.0])
    samples = applied.samples()
    assert samples.shape == (3, 7)
    assert samples[1, 0] == hold_end and samples[2, 0] == time
    # inside the hold the interpolation returns the held pose exactly
    base, _ = applied.trajectory().pose(0.2345)
    assert np.array_equal(base, [0.0, 0.0, 0.4])


def test_samples_must_move_forward_in_time():
    applied = AppliedTrajectory([0.0, 0.0, 0.4], [0.0, 0.0, -1.0])
    with pytest.raises(ValueError, match="not after"):
        applied.append(0.0, [0.0, 0.0, 0.4], [0.0, 0.0, -1.0])


@pytest.mark.parametrize("name", ["cube_cut", "liver_rigid"])
def test_the_replay_scene_loads_and_changes_only_the_trajectory_duration_and_paths(tmp_path, name):
    scene = load_scene(name)
    applied, _ = _session_like(steps=20)
    csv_path, scene_path = replay_paths(tmp_path / "session.h5")
    assert (csv_path.name, scene_path.name) == ("session.trajectory.csv", "session.replay.toml")
    applied.write_csv(csv_path)
    replay = load_scene(write_replay_scene(scene, csv_path, 20, scene_path))
    original, written = scene.to_dict(), replay.to_dict()
    assert written["trajectory"]["file"] == "session.trajectory.csv"
    assert replay.time.step_count == 20
    if scene.mesh.file is not None:
        assert Path(written["mesh"]["file"]).is_absolute()
        assert Path(written["mesh"]["file"]) == (Path(scene.base_directory) / scene.mesh.file).resolve()
    for section in original:
        if section in ("trajectory", "time", "mesh"):
            continue
        assert written[section] == original[section], section
    written["mesh"]["file"], original["mesh"]["file"] = None, None
    assert written["mesh"] == original["mesh"]
    assert {**written["time"], "duration": None} == {**original["time"], "duration": None}


def test_toml_document_round_trips_plain_data():
    import tomllib

    data = {"name": "x", "a": {"f": 0.1, "i": 3, "b": True, "s": 'q"uote', "l": [[1.5, -2.0], [3.0, 1e-300]]}}
    data["a"]["inf"] = float("inf")
    assert tomllib.loads(toml_document(data, "header")) == data
