"""Studies refuse what they cannot do safely (issue 25): a name that is a path, an -o that is another file,
a worker count out of range, an unreachable scheduler; the LocalCluster listens on loopback only, with TLS,
and keeps its scratch space private; a failed run is named."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import h5py
import pytest

from refsim.cli import main
from refsim.sweep import load_study, study_from_options
from refsim.sweep import study as study_module
from refsim.sweep.study import LOOPBACK, check_study_output, start_client, stop_client

BASE = ["mesh.cells=[2, 2, 2]", "time.duration=0.35", "output.tissue_every=10"]


def _study_file(folder: Path, name: str, *, case: str = "insertion.spacing=-1.0") -> Path:
    path = folder / "study.toml"
    path.write_text(
        f'name = "{name}"\nscene = "cube"\nset = {BASE!r}\n'.replace("'", '"')
        + f'[[case]]\nlabel = "bad spacing"\nset = ["{case}"]\n'
    )
    return path


@pytest.mark.parametrize("name", ["/tmp/elsewhere", "../up", "a/b", "..", ".hidden", ""])
def test_a_study_name_cannot_be_a_path(tmp_path, name):
    """The name picks the study file <name>_study.h5 when -o is absent: before, '/tmp/elsewhere' wrote
    there."""
    with pytest.raises(ValueError, match=r"name = .*: a study name must be a plain file name"):
        load_study(_study_file(tmp_path, name))


def test_a_default_name_from_a_file_name_is_made_valid():
    spec = study_from_options("my scene (v2).toml", ["insertion.spacing=1e-3,2e-3"])
    assert spec.name == "my_scene__v2_"


def test_an_existing_output_that_is_not_this_study_is_refused(tmp_path):
    spec = load_study(_study_file(tmp_path, "small"))
    results = tmp_path / "results.h5"
    results.write_bytes(b"a run's results")
    with pytest.raises(ValueError, match=r"results.h5: exists and is not a refsim study file.*--overwrite"):
        check_study_output(spec, results)
    assert check_study_output(spec, results, overwrite=True) == results
    other = tmp_path / "other_study.h5"
    with h5py.File(other, "w") as handle:
        handle.attrs.update({"format": "refsim-study", "name": "other", "scene": "cube"})
        handle.create_group("runs")
    with pytest.raises(ValueError, match=r"holds another study \(name 'other'"):
        check_study_output(spec, other)
    with h5py.File(other, "a") as handle:
        handle.attrs["name"] = "small"
    assert check_study_output(spec, other) == other  # the same study: resumed
    assert results.read_bytes() == b"a run's results"


def test_a_study_moved_with_its_scene_resumes_and_another_scene_is_refused(tmp_path):
    """The same study is the same name and the same scene: the same path, or a scene file with the same bytes
    (a package's case scene in another checkout), recorded as the scene's SHA-256; a scene with other bytes at
    another path is another study."""
    first, moved, changed = (tmp_path / name for name in ("first", "moved", "changed"))
    for folder, text in ((first, "# a scene\n"), (moved, "# a scene\n"), (changed, "# another scene\n")):
        folder.mkdir()
        (folder / "scene.toml").write_text(text)
    spec = study_from_options(str(first / "scene.toml"), ["insertion.spacing=1e-3,2e-3"])
    output = tmp_path / "study.h5"
    with h5py.File(output, "w") as handle:
        handle.attrs.update(
            {
                "format": "refsim-study",
                "name": spec.name,
                "scene": str(first / "scene.toml"),
                "scene_sha256": study_module._scene_digest(first / "scene.toml"),
            }
        )
        handle.create_group("runs")
    (first / "scene.toml").unlink()  # the study's first folder is gone: only the recorded digest is left
    for folder, resumed in ((moved, True), (changed, False)):
        other = study_from_options(str(folder / "scene.toml"), ["insertion.spacing=1e-3,2e-3"])
        assert other.name == spec.name
        if resumed:
            assert check_study_output(other, output) == output
        else:
            with pytest.raises(ValueError, match="holds another study"):
                check_study_output(other, output)


@pytest.mark.parametrize("workers", ["-1", "0", str(4 * (os.cpu_count() or 1) + 1)])
def test_a_worker_count_out_of_range_is_bad_input(tmp_path, capsys, workers):
    """--workers -1 used to hang."""
    study = _study_file(tmp_path, "small")
    assert main(["study", str(study), "-o", str(tmp_path / "s.h5"), "--workers", workers, "-q"]) == 2
    assert f"--workers = {workers}: expected an integer in [1, " in capsys.readouterr().err
    assert not (tmp_path / "s.h5").exists()


def test_an_unreachable_scheduler_is_named(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(study_module, "SCHEDULER_TIMEOUT", 1)
    study = _study_file(tmp_path, "small")
    code = main(["study", str(study), "-o", str(tmp_path / "s.h5"), "--scheduler", "tcp://127.0.0.1:9", "-q"])
    assert code == 2
    assert "--scheduler tcp://127.0.0.1:9: cannot reach a Dask scheduler" in capsys.readouterr().err


def test_the_local_cluster_listens_on_loopback_with_tls_and_private_scratch():
    client, cluster = start_client(workers=1)
    try:
        assert cluster.scheduler_address.startswith(f"tls://{LOOPBACK}:")
        assert f"//{LOOPBACK}:" in cluster.dashboard_link
        workers = client.scheduler_info()["workers"]
        assert workers and all(address.startswith(f"tls://{LOOPBACK}:") for address in workers)
        # <private folder>/dask-scratch-space/worker-...: the private folder is the one start_client made
        private = {Path(info["local_directory"]).parents[1] for info in workers.values()}
        assert all(root.name.startswith("refsim-dask-") for root in private)
        assert private and all(stat.S_IMODE(root.stat().st_mode) == 0o700 for root in private)
    finally:
        stop_client(client, cluster)
    assert all(not root.exists() for root in private)  # removed with the cluster


def test_a_failed_run_is_named_with_its_reason(tmp_path, capsys):
    study = _study_file(tmp_path, "small")
    output = tmp_path / "s.h5"
    assert main(["study", str(study), "-o", str(output), "--workers", "1", "-q", "--no-warm-up"]) == 3
    err = capsys.readouterr().err
    assert "(bad spacing): failed:" in err and "insertion.spacing" in err and "s_runs/" in err


def _sigpipe_ignored() -> bool:
    """SIGPIPE's disposition at the C level (SigIgn of /proc/self/status), not Python's cached one."""
    import signal

    mask = int(Path("/proc/self/status").read_text().split("SigIgn:")[1].split()[0], 16)
    return bool(mask & (1 << (signal.SIGPIPE - 1)))


def test_a_study_ignores_sigpipe_again_after_a_library_reset_it():
    """gmsh.initialize() resets SIGPIPE to its default (kill) at the C level; a Dask client in that process
    then died with exit 141 when a worker closed its socket (the test suite, after the phantom tests)."""
    import ctypes
    import signal

    libc = ctypes.CDLL(None)
    libc.signal.restype = ctypes.c_void_p
    libc.signal(int(signal.SIGPIPE), ctypes.c_void_p(0))  # SIG_DFL, behind Python's back, as gmsh does
    try:
        assert not _sigpipe_ignored()
        study_module._ignore_sigpipe()
        assert _sigpipe_ignored()
    finally:
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)
