"""The run driver (refsim.io.driver.run_scene): how every kind of stop ends, the file it leaves, and
buffering.

Each test runs a few steps of the paper's cube on 3³ cells (a fraction of a second per run) and stops it on
purpose: a signal sent from inside the run, an injected numerical failure, an injected or real write failure.
The file must then hold exactly the steps completed before the stop, ``complete`` false, the reason stored.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from refsim.io import read_results
from refsim.io.driver import RunInputError, check_output_path, run_scene
from refsim.scene import load_scene
from refsim.simulation import Simulation

SMALL = ["mesh.cells=[3, 3, 3]", "time.duration=0.3", "output.tissue_every=2"]  # 30 steps


def _scene(*extra: str):
    return load_scene("cube", SMALL + list(extra))


def test_complete_run_returns_its_summary(tmp_path):
    summary = run_scene(_scene(), tmp_path / "run.h5")
    assert summary.complete and summary.status == "complete" and summary.exit_code == 0
    assert summary.steps == summary.steps_written == 30 and summary.stop_reason == ""
    results = read_results(tmp_path / "run.h5")
    assert results.complete and results.step_count == 30 and results.stop_reason == ""


@pytest.mark.parametrize(
    ("number", "status", "code"), [(signal.SIGTERM, "terminated", 143), (signal.SIGINT, "interrupted", 130)]
)
def test_signals_stop_the_run_and_keep_every_completed_step(tmp_path, number, status, code):
    def send(state, record):
        if record.step == 7:
            os.kill(os.getpid(), number)  # delivered in the main thread before the next step

    previous = signal.getsignal(signal.SIGTERM)
    summary = run_scene(_scene(), tmp_path / "run.h5", on_step=send)
    assert signal.getsignal(signal.SIGTERM) is previous  # the driver restores the handlers
    assert (summary.status, summary.exit_code) == (status, code)
    results = read_results(tmp_path / "run.h5")
    assert not results.complete
    assert results.step_count == summary.steps_written == 7
    np.testing.assert_array_equal(results.step, np.arange(1, 8))
    assert "SIGTERM" in results.stop_reason if number == signal.SIGTERM else "SIGINT" in results.stop_reason


@pytest.mark.parametrize("second", [signal.SIGINT, signal.SIGTERM])
def test_a_second_signal_while_the_file_closes_loses_nothing(tmp_path, monkeypatch, second):
    """An impatient second Ctrl-C (or a SIGTERM) that arrives while the writer closes the file is ignored:
    before, it aborted the close, and the file lost its buffered steps and said "running (or ... killed)"."""
    from refsim.io.writer import ResultWriter

    close = ResultWriter.close

    def signalled_close(self, *args, **kwargs):
        os.kill(os.getpid(), second)  # delivered in the main thread, inside the close
        return close(self, *args, **kwargs)

    monkeypatch.setattr(ResultWriter, "close", signalled_close)

    def send(state, record):
        if record.step == 7:
            os.kill(os.getpid(), signal.SIGINT)

    summary = run_scene(_scene(), tmp_path / "run.h5", on_step=send)
    assert (summary.status, summary.exit_code) == ("interrupted", 130)
    results = read_results(tmp_path / "run.h5")
    assert not results.complete and results.step_count == summary.steps_written == 7
    assert results.stop_reason == "interrupted by SIGINT"


@pytest.mark.parametrize(
    ("number", "status", "code"),
    [
        (signal.SIGTERM, "terminated", 143),
        (signal.SIGINT, "interrupted", 130),
        (signal.SIGHUP, "hangup", 129),
    ],
)
@pytest.mark.parametrize("chained", [True, False])
def test_a_signal_seen_through_another_error_stops_as_that_signal(tmp_path, number, status, code, chained):
    """A signal whose handler runs while compiled code calls back into the interpreter surfaces as another
    error: Numba's dispatcher raises ``SystemError: ... returned a result with an exception set`` with the
    signal's exception as its context (seen on a SIGTERM sent by another process). The run still ends as
    that signal says (status, exit code, reason), never as an internal error; also when the signal's own
    exception was dropped and an unrelated one surfaced (``chained=False``)."""

    def send(state, record):
        if record.step != 7:
            return
        try:
            os.kill(os.getpid(), number)
            for _ in range(1000):  # the handler runs at one of these bytecodes
                pass
        except BaseException:  # noqa: BLE001 - the signal's exception, turned into another error
            if chained:
                # as the dispatcher does: the signal's exception is the context, not the cause
                raise SystemError("CPUDispatcher(<function _locate>) returned a result with an exception set")  # noqa: B904
        raise RuntimeError("an unrelated failure, raised with no link to the signal")

    if number == signal.SIGHUP and signal.getsignal(signal.SIGHUP) is signal.SIG_IGN:
        pytest.skip("SIGHUP is ignored in this process (nohup): the driver keeps running on it by design")
    summary = run_scene(_scene(), tmp_path / "run.h5", on_step=send)
    assert (summary.status, summary.exit_code) == (status, code), summary.stop_reason
    results = read_results(tmp_path / "run.h5")
    assert not results.complete and results.step_count == 7
    assert "internal error" not in results.stop_reason
    assert signal.Signals(number).name in results.stop_reason


@pytest.mark.parametrize(
    ("number", "status", "code"), [(signal.SIGTERM, "terminated", 143), (signal.SIGINT, "interrupted", 130)]
)
def test_a_signal_handled_inside_a_finaliser_is_not_printed_as_ignored(tmp_path, number, status, code):
    """Python runs a signal handler between any two bytecodes, also inside a weakref callback, where the
    handler's exception cannot propagate: it went to ``sys.unraisablehook``, which printed "Exception ignored
    in ... Traceback" on stderr (seen once in CI on a SIGTERM from another process). The run's own hook keeps
    the signal's exception from the previous hook (the signal is recorded and raised again by the run's
    loop) and is removed after the run; the run stops as the signal says."""
    import weakref

    class Payload:
        pass

    def send(state, record):
        if record.step == 7:
            payload = Payload()
            weakref.finalize(payload, lambda: (os.kill(os.getpid(), number), [None for _ in range(1000)]))
            del payload  # the finaliser runs here; the handler raises inside it

    seen = []
    previous = sys.unraisablehook
    sys.unraisablehook = seen.append  # what would print the traceback
    try:
        summary = run_scene(_scene(), tmp_path / "run.h5", on_step=send)
        assert sys.unraisablehook == seen.append  # restored after the run
    finally:
        sys.unraisablehook = previous
    assert (summary.status, summary.exit_code) == (status, code), summary.stop_reason
    assert seen == [], [u.exc_value for u in seen]
    results = read_results(tmp_path / "run.h5")
    assert not results.complete and signal.Signals(number).name in results.stop_reason


def test_the_status_table_is_the_one_the_code_reads():
    """The module docstring's table of statuses and exit codes lists exactly RUN_STATUSES, and a status
    outside it is refused (no run can end in an undocumented way)."""
    import re

    from refsim.io import driver
    from refsim.simulation.summary import RUN_STATUSES, RunSummary

    rows = dict(re.findall(r'"([a-z_]+)"\s+(\d+)\s*$', driver.__doc__, flags=re.MULTILINE))
    assert {name: int(code) for name, code in rows.items()} == {
        name: status.exit_code for name, status in RUN_STATUSES.items()
    }
    assert "hangup" in rows
    with pytest.raises(ValueError, match="'killed'"):
        RunSummary().finish(status="killed", stop_reason="", steps_written=0)
    summary = RunSummary()
    summary.finish(status="hangup", stop_reason="interrupted by SIGHUP", steps_written=3)
    assert (summary.exit_code, summary.stopped_by_signal) == (129, True)


def test_sigterm_from_outside_exits_143(tmp_path):
    """The command line in a child process, terminated by another process while it runs."""
    output = tmp_path / "run.h5"
    child = subprocess.Popen(
        [
            os.environ.get("PYTHON", "python"),
            "-m",
            "refsim",
            "run",
            "cube",
            "-o",
            str(output),
            "-q",
            "--set",
            "mesh.cells=[3, 3, 3]",
            "--set",
            "time.duration=20.0",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])},
    )
    deadline = 120.0
    import time

    start = time.monotonic()
    while time.monotonic() - start < deadline:  # wait until steps are being written
        if output.exists():
            try:
                with h5py.File(output, "r", locking=False) as handle:
                    if int(handle.attrs["steps_completed"]) >= 32:
                        break
            except (OSError, KeyError):
                pass
        time.sleep(0.2)
    child.send_signal(signal.SIGTERM)
    _, error = child.communicate(timeout=120)
    assert child.returncode == 143, error
    assert "Traceback" not in error and "SIGTERM" in error
    results = read_results(output)
    assert not results.complete and results.step_count >= 32 and "SIGTERM" in results.stop_reason


def _poisoned_step(monkeypatch, at_step: int, poison):
    original = Simulation.step

    def step(self, state, **kwargs):
        if state.step + 1 == at_step:
            return poison(self, state, original, **kwargs)
        return original(self, state, **kwargs)

    monkeypatch.setattr(Simulation, "step", step)


def test_singular_factorisation_is_reported_with_exit_3(tmp_path, monkeypatch):
    def singular(self, state, original, **kwargs):
        raise RuntimeError("Factor is exactly singular")  # what scipy's splu says

    _poisoned_step(monkeypatch, 5, singular)
    summary = run_scene(_scene(), tmp_path / "run.h5")
    assert (summary.status, summary.exit_code) == ("numerical", 3)
    assert "step 5" in summary.stop_reason and "singular" in summary.stop_reason
    results = read_results(tmp_path / "run.h5")
    assert not results.complete and results.step_count == 4 and "singular" in results.stop_reason


@pytest.mark.parametrize("value", [np.nan, np.inf, 1e200])
def test_non_finite_and_overflowing_values_stop_the_run(tmp_path, monkeypatch, value):
    def poisoned(self, state, original, **kwargs):
        new_state, record = original(self, state, **kwargs)
        force = record.needle_force.copy()
        force[0] = value
        return new_state, record.with_first(needle_force=force)

    _poisoned_step(monkeypatch, 9, poisoned)
    summary = run_scene(_scene(), tmp_path / "run.h5")
    assert summary.exit_code == 3 and "step 9" in summary.stop_reason
    assert ("non-finite" if not np.isfinite(value) else "overflowing") in summary.stop_reason
    results = read_results(tmp_path / "run.h5")
    assert results.step_count == 8 and np.all(np.isfinite(results.needle_force))


def test_diverging_tissue_stops_the_run(tmp_path, monkeypatch):
    import dataclasses

    def thrown(self, state, original, **kwargs):
        new_state, record = original(self, state, **kwargs)
        tissue = dataclasses.replace(new_state.tissue, positions=new_state.tissue.positions * 1e3)
        return dataclasses.replace(new_state, tissue=tissue), record

    _poisoned_step(monkeypatch, 3, thrown)
    summary = run_scene(_scene(), tmp_path / "run.h5")
    assert summary.exit_code == 3 and "diverges" in summary.stop_reason


def test_diverging_solver_report_stops_the_run(tmp_path, monkeypatch):
    """A solver report flagged diverged (the Gauss–Seidel of issue 10 item 3 sets it) stops with exit 3."""
    import dataclasses

    class Diverged:
        iterations, residual, converged, seconds, diverged, message = 10, 1e30, False, 0.0, True, "λ grows"

    def poisoned(self, state, original, **kwargs):
        new_state, record = original(self, state, **kwargs)
        return new_state, dataclasses.replace(record, solver=Diverged())

    _poisoned_step(monkeypatch, 4, poisoned)
    summary = run_scene(_scene(), tmp_path / "run.h5")
    assert summary.exit_code == 3 and "diverged" in summary.stop_reason


def test_injected_write_failure_keeps_the_blocks_written_before(tmp_path, monkeypatch):
    from refsim.io.writer import ResultWriter

    original = ResultWriter._append
    calls = {"blocks": 0}

    def failing(self, path, values):
        if path == "steps/step":
            calls["blocks"] += 1
        if path == "steps/needle_force" and self._steps_completed >= 8:
            raise OSError(28, "No space left on device")
        return original(self, path, values)

    monkeypatch.setattr(ResultWriter, "_append", failing)
    summary = run_scene(_scene(), tmp_path / "run.h5", buffer_steps=4)
    assert (summary.status, summary.exit_code) == ("write_failed", 3)
    assert "No space left" in summary.stop_reason
    results = read_results(tmp_path / "run.h5")
    assert results.step_count == 8 and not results.complete and "No space left" in results.stop_reason


@pytest.mark.skipif(
    os.geteuid() != 0 or not Path("/bin/mount").exists(), reason="needs root to mount a tmpfs"
)
def test_full_tmpfs_disk(tmp_path):
    """A real full disk: a 1 MiB tmpfs, tissue positions every step (about 3 kB each)."""
    folder = tmp_path / "disk"
    folder.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(folder)]).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        scene = load_scene("cube", ["mesh.cells=[4, 4, 4]", "time.duration=2.2", "output.tissue_every=1"])
        summary = run_scene(scene, folder / "run.h5")
        assert (summary.status, summary.exit_code) == ("write_failed", 3)
        results = read_results(folder / "run.h5")
        assert 0 < results.step_count == summary.steps_written < 220
        assert results.tissue_positions.shape[0] == results.step_count
        assert not results.complete and "space" in results.stop_reason
    finally:
        subprocess.run(["umount", str(folder)])


def test_buffered_blocks_write_the_same_file_as_single_steps(tmp_path):
    scene = _scene("output.record_problems=true")
    run_scene(scene, tmp_path / "one.h5", buffer_steps=1)
    run_scene(scene, tmp_path / "block.h5", buffer_steps=7)
    with h5py.File(tmp_path / "one.h5", "r") as one, h5py.File(tmp_path / "block.h5", "r") as block:
        names = []
        one.visit(names.append)
        for name in names:
            if isinstance(one[name], h5py.Dataset) and "seconds" not in name:
                a, b = one[name][()], block[name][()]
                if a.dtype.kind == "f":
                    np.testing.assert_array_equal(a, b, err_msg=name)
                else:
                    assert np.array_equal(a, b), name


def test_output_path_checks(tmp_path):
    (tmp_path / "afile").write_text("x")
    with pytest.raises(RunInputError, match="afile is a file, not a folder"):
        check_output_path(tmp_path / "afile" / "out.h5", overwrite=False)
    with pytest.raises(RunInputError, match="is a directory"):
        check_output_path(tmp_path, overwrite=True)
    with pytest.raises(RunInputError, match="--overwrite"):
        check_output_path(tmp_path / "afile", overwrite=False)
    assert check_output_path(tmp_path / "new" / "deeper" / "out.h5", overwrite=False).name == "out.h5"


def test_bad_input_writes_nothing(tmp_path):
    scene = load_scene(
        "cube",
        SMALL
        + [
            "trajectory.base_positions=[[0.00123, 0.00231, 0.38], "
            "[0.00123, 0.00231, 0.38], [0.00123, 0.00231, 0.38]]"
        ],
    )
    with pytest.raises(RunInputError, match="inside the tissue"):
        run_scene(scene, tmp_path / "run.h5")
    assert not (tmp_path / "run.h5").exists()


@pytest.mark.parametrize("target", ["scene.toml", "robot.csv"])
def test_the_results_path_may_not_be_an_input_of_the_run(tmp_path, target):
    """`refsim run scene.toml -o scene.toml --overwrite` (or -o its trajectory CSV) replaced the input by the
    results; now bad input naming the file, which is left byte for byte."""
    text = Path(load_scene("cube").source).read_text()
    start, end = text.index("[trajectory]"), text.index("[time]")
    (tmp_path / "scene.toml").write_text(text[:start] + '[trajectory]\nfile = "robot.csv"\n\n' + text[end:])
    (tmp_path / "robot.csv").write_text(
        "t,x,y,z,dx,dy,dz\n0,0.00123,0.00231,0.422,0,0,-1\n1.9,0.00123,0.00231,0.403,0,0,-1\n"
    )
    before = (tmp_path / target).read_bytes()
    scene = load_scene(tmp_path / "scene.toml", SMALL)
    with pytest.raises(RunInputError, match=f"{target}: is .* of this run"):
        run_scene(scene, tmp_path / target, overwrite=True)
    assert (tmp_path / target).read_bytes() == before


def test_a_sigterm_whose_exception_is_swallowed_still_stops_the_run(tmp_path, monkeypatch):
    """Python runs a signal handler between any two bytecodes, also inside a weakref callback or a finaliser,
    where the handler's exception is printed as "ignored" and dropped: the run must stop all the same, after
    the step in which the signal arrived, and say it was terminated."""
    import signal

    def swallowed(self, state, original, **kwargs):
        result = original(self, state, **kwargs)
        try:  # what a weakref callback does with an exception
            signal.raise_signal(signal.SIGTERM)
            for _ in range(1000):  # the handler runs at the next bytecode boundary
                pass
        except BaseException:  # noqa: BLE001 - the swallowing under test
            pass
        return result

    _poisoned_step(monkeypatch, 5, swallowed)
    summary = run_scene(_scene(), tmp_path / "run.h5")
    assert summary.status == "terminated" and "SIGTERM" in summary.stop_reason
    results = read_results(tmp_path / "run.h5")
    assert not results.complete and results.step_count == 5
