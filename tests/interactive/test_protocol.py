"""The pose stream of `refsim interactive --no-window` (docs/interactive.md, "Protocol"), with a scripted
client: greeting, errors for bad messages (the session goes on), a straight insertion streamed in lock step
with the force read back every step and the puncture seen, the stop; then the replay: `refsim run` on the
replay scene
written beside the results reproduces the interactive run's datasets to the bit."""

from __future__ import annotations

import ctypes.util
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
COARSE = "mesh.cells=[4, 4, 4]"
#: Wall-clock data, different in every run (studies/regression/compare.py ignores the same).
WALL_CLOCK = ("solver/seconds", "steps/stage_seconds", "steps/triangulation_seconds")
#: Straight down the needle (-z) at 10 mm/s: 0.1 mm per 10 ms step; the tip starts 2 mm above the surface.
STEP_DEPTH = 1e-4
POSES = 60

BAD_MESSAGES = {
    "not json": "not a JSON object",
    "[1, 2]": "expected a JSON object",
    '{"base": [0, 0], "direction": [0, 0, -1]}': "'base': expected a list of 3 numbers",
    '{"base": [0, 0, "x"], "direction": [0, 0, -1]}': "'base': expected 3 numbers",
    '{"base": [0, 0, NaN], "direction": [0, 0, -1]}': "NaN is not a number JSON allows",
    '{"base": [0, 0, 0.4], "direction": [0, 0, 0]}': "'direction'",
    '{"base": [2000, 0, 0], "direction": [0, 0, -1]}': "beyond",
    '{"base": [0, 0, 0.4], "direction": [0, 0, -1], "speed": 1}': "unknown key 'speed'",
    '{"t": "now", "base": [0, 0, 0.4], "direction": [0, 0, -1]}': "'t': expected a finite number",
    '{"stop": false}': "a stop message is exactly",
}


def _environment() -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT)}


def _start(arguments: list[str]) -> tuple[subprocess.Popen, int]:
    command = [sys.executable, "-m", "refsim", "interactive", *arguments]
    process = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_environment()
    )
    line = process.stdout.readline()
    if "pose stream on" not in line:
        process.kill()
        pytest.fail(f"no pose stream: {line}{process.stderr.read()}")
    return process, int(line.split(":")[1].split()[0])


def _send(stream, message: str | dict) -> None:
    stream.write((message if isinstance(message, str) else json.dumps(message)) + "\n")
    stream.flush()


@pytest.fixture(scope="module")
def lockstep_session(tmp_path_factory):
    """A lock-step session on the coarse cube: the bad messages, then POSES poses 0.1 mm apart, then stop."""
    folder = tmp_path_factory.mktemp("protocol")
    output = folder / "session.h5"
    process, port = _start(
        ["cube", "--set", COARSE, "--no-window", "--socket", "0", "--lockstep"] + ["-o", str(output)]
    )
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=300) as connection:
            stream = connection.makefile("rw")
            hello = json.loads(stream.readline())
            errors = []
            for message in BAD_MESSAGES:
                _send(stream, message)
                errors.append(json.loads(stream.readline()))
            base, direction = np.array(hello["base"]), hello["direction"]
            sent, replies = [], []
            for index in range(1, POSES + 1):
                pose = base + [0.0, 0.0, -STEP_DEPTH * index]
                sent.append(pose)
                _send(stream, {"t": 0.01 * index, "base": pose.tolist(), "direction": direction})
                replies.append(json.loads(stream.readline()))
            _send(stream, {"stop": True})
            tail = [json.loads(line) for line in stream]
        out, err = process.communicate(timeout=300)
    finally:
        if process.poll() is None:
            process.kill()
    return {
        "output": output,
        "hello": hello,
        "errors": errors,
        "sent": np.array(sent),
        "replies": replies,
        "tail": tail,
        "returncode": process.returncode,
        "stdout": out,
        "stderr": err,
    }


def test_greeting_names_the_scene_and_the_start_pose(lockstep_session):
    hello = lockstep_session["hello"]
    assert hello["hello"] == "refsim interactive" and hello["protocol"] == 1
    assert hello["scene"] == "cube" and hello["dt"] == 0.01 and hello["mode"] == "lockstep"
    assert hello["base"] == [0.00123, 0.00231, 0.422] and hello["direction"] == [0.0, 0.0, -1.0]


def test_bad_messages_are_answered_with_errors_and_the_session_goes_on(lockstep_session):
    errors = lockstep_session["errors"]
    for index, (reply, expected) in enumerate(zip(errors, BAD_MESSAGES.values(), strict=True)):
        assert set(reply) == {"error"}, reply
        assert reply["error"].startswith(f"line {index + 1}:") and expected in reply["error"], reply
    # no bad message took a step: the first pose gives step 1
    assert lockstep_session["replies"][0]["step"] == 1


def test_each_pose_gives_one_step_at_that_pose_with_the_force_back(lockstep_session):
    replies, sent = lockstep_session["replies"], lockstep_session["sent"]
    assert [reply["step"] for reply in replies] == list(range(1, POSES + 1))
    # 0.1 mm per step is within the speed bound (0.5 mm per step at 0.05 m/s): each pose is applied as sent
    np.testing.assert_array_equal(np.array([reply["base"] for reply in replies]), sent)
    forces = np.array([reply["force"] for reply in replies])
    assert np.all(np.isfinite(forces)) and np.all(forces[:5] == 0.0)  # 2 mm above the surface: no contact


def test_the_puncture_appears_at_the_puncture_force(lockstep_session):
    replies = lockstep_session["replies"]
    punctures = [reply for reply in replies if "puncture" in reply["events"]]
    assert len(punctures) == 1
    puncture = punctures[0]
    # The tip reaches the surface after 20 steps (2 mm); the puncture caps the tip's normal force at
    # insertion.puncture_force = 0.8 N (docs/architecture.md, "Choices"), where the contact gives way. The
    # reply carries the end of the step (docs/interactive.md): the tip then held by its cutting row at
    # insertion.tip_cutting_force = 0.5 N, with the entry point's friction on top, pushing the needle back
    # (+z), below the give-way's f_p.
    assert 20 <= puncture["step"] <= 30
    assert 0.5 * (1 - 1e-6) <= puncture["force"][2] < 0.8
    assert puncture["phase"] == "insertion" and replies[-1]["phase"] == "insertion"


def test_stop_ends_the_session_with_a_final_step_and_the_files(lockstep_session):
    tail = lockstep_session["tail"]
    assert lockstep_session["returncode"] == 0, lockstep_session["stderr"]
    assert tail[0]["step"] == POSES + 1  # the final step (pose held) records the tissue
    done = tail[-1]
    assert done["done"] and done["status"] == "complete" and done["steps"] == POSES + 1
    output = lockstep_session["output"]
    assert Path(done["output"]) == output and Path(done["replay"]) == output.with_name("session.replay.toml")
    assert output.with_name("session.trajectory.csv").is_file()
    with h5py.File(output) as handle:
        assert handle.attrs["complete"] and handle.attrs["steps_completed"] == POSES + 1
        samples = handle["scene/trajectory/samples"][()]
    # the applied trajectory: the start, the 60 poses, the final hold (one sample per step)
    np.testing.assert_array_equal(samples[1 : POSES + 1, 1:4], lockstep_session["sent"])
    assert samples.shape == (POSES + 2, 7)


def _datasets(handle: h5py.File) -> dict:
    found = {}
    handle.visititems(
        lambda name, obj: found.__setitem__(name, obj) if isinstance(obj, h5py.Dataset) else None
    )
    return found


def test_refsim_run_on_the_replay_scene_reproduces_the_run_to_the_bit(lockstep_session, tmp_path):
    output = lockstep_session["output"]
    replay = tmp_path / "replay.h5"
    scene = output.with_name("session.replay.toml")
    result = subprocess.run(
        [sys.executable, "-m", "refsim", "run", str(scene), "-o", str(replay), "-q"],
        capture_output=True,
        text=True,
        env=_environment(),
        timeout=600,
    )
    assert result.returncode == 0, result.stderr
    with h5py.File(output) as interactive, h5py.File(replay) as replayed:
        first, second = _datasets(interactive), _datasets(replayed)
        assert set(first) == set(second)
        compared = 0
        for name, dataset in first.items():
            if name in WALL_CLOCK:
                continue
            a, b = dataset[()], second[name][()]
            if a.dtype.kind in "fc":
                assert np.array_equal(a, b, equal_nan=True), name
            else:
                assert np.array_equal(a, b), name
            compared += 1
        assert {"steps/needle_force", "steps/needle_positions", "tissue/positions"} <= set(first)
        assert compared > 30


def test_a_real_time_session_steps_on_its_own_and_reports_the_real_time_factor(tmp_path):
    process, port = _start(
        ["cube", "--set", COARSE, "--no-window", "--socket", "0", "-o", str(tmp_path / "rt.h5")]
    )
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=300) as connection:
            stream = connection.makefile("rw")
            hello = json.loads(stream.readline())
            assert hello["mode"] == "realtime"
            _send(stream, {"base": hello["base"], "direction": hello["direction"]})
            replies = [json.loads(stream.readline()) for _ in range(30)]  # steps come without more poses
            _send(stream, {"stop": True})
            tail = [json.loads(line) for line in stream]
        process.communicate(timeout=300)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0
    steps = [reply["step"] for reply in replies]
    assert steps == list(range(steps[0], steps[0] + 30))
    rates = [reply["rtf"] for reply in replies[2:]]
    assert all(rate is not None and 0.0 < rate for rate in rates)
    assert tail[-1]["done"] and tail[-1]["status"] == "complete"


@pytest.mark.parametrize("host", ["0.0.0.0", "192.0.2.1"])
def test_a_non_loopback_bind_is_refused_before_anything_is_written(tmp_path, host):
    output = tmp_path / "refused.h5"
    command = [sys.executable, "-m", "refsim", "interactive", "cube", "--no-window", "--socket", "0"]
    result = subprocess.run(
        command + ["--host", host, "-o", str(output)], capture_output=True, text=True, env=_environment()
    )
    assert result.returncode == 2
    assert f"--host {host}" in result.stderr and "not a loopback address" in result.stderr
    assert "Traceback" not in result.stderr and not output.exists()


def test_headless_needs_the_pose_stream(tmp_path):
    command = [
        sys.executable,
        "-m",
        "refsim",
        "interactive",
        "cube",
        "--no-window",
        "-o",
        str(tmp_path / "x.h5"),
    ]
    result = subprocess.run(command, capture_output=True, text=True, env=_environment())
    assert result.returncode == 2 and "--no-window needs the pose stream" in result.stderr


def test_the_window_without_a_display_is_refused_with_the_ways_out(tmp_path):
    environment = {
        key: value for key, value in _environment().items() if key not in ("DISPLAY", "WAYLAND_DISPLAY")
    }
    command = [sys.executable, "-m", "refsim", "interactive", "cube", "-o", str(tmp_path / "x.h5")]
    result = subprocess.run(command, capture_output=True, text=True, env=environment)
    assert result.returncode == 2 and "needs a display" in result.stderr and "--no-window" in result.stderr
    assert not (tmp_path / "x.h5").exists()


@pytest.mark.skipif(ctypes.util.find_library("X11") is None, reason="libX11 absent: no X display to check")
def test_the_window_on_a_display_nobody_serves_is_refused_naming_it(tmp_path):
    """DISPLAY set to a display no X server serves: VTK would only warn and the session end after one step
    with exit code 0; the command refuses it before any work, naming the display."""
    environment = {key: value for key, value in _environment().items() if key != "WAYLAND_DISPLAY"}
    environment["DISPLAY"] = ":4711"  # no server: display numbers that high are not in use here
    command = [sys.executable, "-m", "refsim", "interactive", "cube", "-o", str(tmp_path / "x.h5")]
    result = subprocess.run(command, capture_output=True, text=True, env=environment)
    assert result.returncode == 2, result.stderr
    assert (
        "cannot connect to the X server of DISPLAY=:4711" in result.stderr and "--no-window" in result.stderr
    )
    assert not (tmp_path / "x.h5").exists()
