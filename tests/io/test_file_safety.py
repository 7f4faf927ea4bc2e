"""The results file is never half-written, never shared by two writers, and damage is named (issue 25).

Each test runs a few steps of the paper's cube on 3³ cells (well under a second per run) or works on a file
such a run wrote, then damages it, locks it, fills the disk or closes the pipe on purpose.
"""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from refsim.io import read_results
from refsim.io.driver import RunInputError, RunWriteError, run_scene
from refsim.io.filelock import FileLock
from refsim.io.reader import ResultsError
from refsim.scene import load_scene

SMALL = ["mesh.cells=[3, 3, 3]", "time.duration=0.1", "output.tissue_every=2"]  # 10 steps
ROOT = Path(__file__).resolve().parents[2]


def _scene(*extra: str):
    return load_scene("cube", SMALL + list(extra))


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("finished") / "run.h5"
    assert run_scene(_scene(), path).complete
    return path


def _copy(source: Path, target: Path) -> Path:
    target.write_bytes(source.read_bytes())
    return target


# ---------------------------------------------------------------------- one writer per file


def test_a_second_writer_is_refused_before_anything_is_truncated(tmp_path, finished):
    """A lock held on the path (as a running `refsim run` holds it): a second run, even with overwrite, stops
    with a bad-input error naming the holder, and the file keeps every byte."""
    path = _copy(finished, tmp_path / "run.h5")
    before = path.read_bytes()
    lock = FileLock(path)  # another process writing it
    try:
        with pytest.raises(RunInputError, match=f"pid {os.getpid()}.*is writing"):
            run_scene(_scene(), path, overwrite=True)
    finally:
        lock.release()
    assert path.read_bytes() == before
    assert not (tmp_path / ".run.h5.lock").exists()
    assert run_scene(_scene(), path, overwrite=True).complete  # once released, the path can be written


def _python(code: str) -> subprocess.CompletedProcess:
    """``code`` run by another Python process on this tree (its output captured as text)."""
    environment = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=environment)


def test_the_lock_is_exclusive_between_processes(tmp_path):
    """flock locks are per open file: a child process cannot take a lock this process holds."""
    path = tmp_path / "run.h5"
    lock = FileLock(path)
    try:
        code = (
            "import sys\nfrom refsim.io.filelock import FileLock, WriterLockedError\n"
            f"try:\n    FileLock({str(path)!r})\nexcept WriterLockedError as e:\n    print(e); sys.exit(7)\n"
        )
        child = _python(code)
        assert child.returncode == 7, child.stderr
        assert str(os.getpid()) in child.stdout
    finally:
        lock.release()
    FileLock(path).release()  # free again


def test_a_failed_static_part_leaves_nothing_and_an_existing_file_untouched(tmp_path, finished, monkeypatch):
    """A full disk before the first step: RunWriteError naming the path and the bytes; no temporary, no
    lock, the old file unchanged (it used to segfault h5py and leave a corrupt file)."""
    import shutil
    from collections import namedtuple

    path = _copy(finished, tmp_path / "run.h5")
    before = path.read_bytes()
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda _: usage(10**6, 10**6 - 1000, 1000))
    with pytest.raises(RunWriteError, match=r"run.h5.*static part.*1000 bytes are free") as error:
        run_scene(_scene(), path, overwrite=True)
    assert error.value.errno == errno.ENOSPC
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5"]


def test_the_file_appears_only_with_its_static_part(tmp_path):
    """While the run's first steps are buffered, the path already holds a readable file (static part, zero
    steps); no temporary is left beside it."""
    seen = []

    def look(state, record):
        if record.step == 1:
            results = read_results(tmp_path / "run.h5")
            seen.append((results.step_count, results.complete, results.rest_positions.shape))
            seen.append(sorted(p.name for p in tmp_path.iterdir()))

    run_scene(_scene(), tmp_path / "run.h5", on_step=look)
    assert seen[0] == (0, False, (64, 3))
    assert seen[1] == [".run.h5.lock", "run.h5"]  # the lock is held while the run writes
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5"]


# ---------------------------------------------------------------------- checksums and damage


def test_every_numeric_dataset_carries_a_checksum(finished):
    with h5py.File(finished, "r") as handle:
        unchecked = []

        def visit(name, item):
            if isinstance(item, h5py.Dataset) and item.dtype.kind != "O" and item.shape != ():
                if not item.fletcher32:
                    unchecked.append(name)

        handle.visititems(visit)
    assert unchecked == []


def _flip_a_bit_in(path: Path, dataset: str) -> None:
    with h5py.File(path, "r") as handle:
        offset = handle[dataset].id.get_chunk_info(0).byte_offset
    data = bytearray(path.read_bytes())
    data[offset + 3] ^= 0x10
    path.write_bytes(bytes(data))


def test_a_bit_flip_is_detected_and_named(tmp_path, finished):
    """One bit of the needle force history changed on the disk: reading names the dataset and the checksum;
    without the filter it would be read as a wrong force."""
    path = _copy(finished, tmp_path / "flipped.h5")
    _flip_a_bit_in(path, "steps/needle_force")
    with pytest.raises(ResultsError, match=r"flipped.h5.*'steps/needle_force' is damaged.*Fletcher-32"):
        read_results(path)


@pytest.mark.parametrize("value", [-1, 11, 2.5, True])
def test_steps_completed_out_of_range_is_damage(tmp_path, finished, value):
    path = _copy(finished, tmp_path / "run.h5")
    with h5py.File(path, "r+") as handle:
        handle.attrs["steps_completed"] = value
    with pytest.raises(ResultsError, match=r"steps_completed = .* not an integer in \[0, 10\]"):
        read_results(path)


def test_a_truncated_file_says_so_with_its_sizes(tmp_path, finished):
    path = tmp_path / "cut.h5"
    data = finished.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ResultsError, match=rf"truncated: {len(data) // 2} bytes of the {len(data)}"):
        read_results(path)


def test_a_file_a_run_is_writing_is_not_called_damaged(tmp_path, finished):
    """Reading a file while a run writes it (the run holds HDF5's lock and refsim's): before, "damaged";
    now the writer's pid and that the file can be read once the run ends."""
    path = _copy(finished, tmp_path / "run.h5")
    lock = FileLock(path)
    handle = h5py.File(path, "a")  # held as the run's writer holds it
    try:
        code = (
            "from refsim.io import read_results\n"
            f"try:\n    read_results({str(path)!r})\nexcept ValueError as e:\n    print(e)\n"
        )
        child = _python(code)
    finally:
        handle.close()
        lock.release()
    assert f"process {os.getpid()} is writing this file" in child.stdout, child.stdout + child.stderr
    assert "damaged" not in child.stdout
    assert read_results(path).complete


def test_a_file_that_is_not_hdf5_says_so(tmp_path):
    path = tmp_path / "text.h5"
    path.write_text("hello")
    with pytest.raises(ResultsError, match="not an HDF5 file"):
        read_results(path)


# ---------------------------------------------------------------------- signals and pipes


def test_sighup_stops_the_run_like_sigterm(tmp_path):
    """A terminal that closes stops the run like SIGTERM. The test sets SIGHUP's default disposition first:
    a test process started under ``nohup`` (or by a runner that ignores SIGHUP) inherits SIGHUP ignored,
    which the run rightly leaves ignored (the next test), and the run would then complete."""

    def send(state, record):
        if record.step == 4:
            os.kill(os.getpid(), signal.SIGHUP)

    inherited = signal.signal(signal.SIGHUP, signal.SIG_DFL)
    try:
        summary = run_scene(_scene(), tmp_path / "run.h5", on_step=send)
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_DFL
    finally:
        signal.signal(signal.SIGHUP, inherited)
    assert (summary.status, summary.exit_code) == ("hangup", 129)
    results = read_results(tmp_path / "run.h5")
    assert not results.complete and results.step_count == 4 and "SIGHUP" in results.stop_reason


def test_an_ignored_sighup_is_left_ignored(tmp_path):
    """`nohup refsim run ...` ignores SIGHUP: the run must go on when the terminal closes."""

    def send(state, record):
        if record.step == 4:
            os.kill(os.getpid(), signal.SIGHUP)

    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        summary = run_scene(_scene(), tmp_path / "run.h5", on_step=send)
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, previous)
    assert summary.complete and read_results(tmp_path / "run.h5").step_count == 10


def test_a_closed_pipe_does_not_change_the_exit_code(tmp_path):
    """`refsim run ... | true` (a reader that closes the pipe at once; `| head` does it when it has its
    lines): the run completes, exits 0 and writes its XDMF sidecar (before: exit 2, no sidecar)."""
    output = tmp_path / "run.h5"
    command = (
        f"{sys.executable} -m refsim run cube -o {output} -q "
        + " ".join(f"--set '{item}'" for item in SMALL)
        + " | true; echo ${PIPESTATUS[0]}"
    )
    done = subprocess.run(
        ["bash", "-c", command],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert done.stdout.strip() == "0", done.stderr
    assert "Traceback" not in done.stderr and "BrokenPipe" not in done.stderr
    assert output.with_suffix(".xdmf").is_file()
    assert read_results(output).complete


def test_the_step_data_of_a_run_is_kept_by_the_checksummed_writer(finished):
    """The filter changes nothing in what is read back: the steps are 1..10 and every force is finite."""
    results = read_results(finished)
    np.testing.assert_array_equal(results.step, np.arange(1, 11))
    assert np.all(np.isfinite(results.needle_force))
