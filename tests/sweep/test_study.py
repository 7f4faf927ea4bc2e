"""A small study end to end on a one-worker LocalCluster: the command line, the study file, failures,
resuming."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from refsim.cli import main
from refsim.scene import load_scene
from refsim.sweep import load_study, read_study, run_study
from refsim.sweep.study import run_folder

# The cube on 2 cells per axis for 0.35 s: the tip touches the top at 0.2 s and punctures; a few seconds a
# run.
BASE = ["mesh.cells=[2, 2, 2]", "time.duration=0.35", "output.tissue_every=10"]


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    folder = tmp_path_factory.mktemp("study")
    text = f"""
name = "small"
scene = "cube"
set = {BASE!r}
quantities = ["needle_force@end", "puncture_force", "displacement@0.0,0.0,0.09"]
[[sweep]]
key = "insertion.spacing"
values = [2e-3, 1e-3, 5e-4]
[[case]]
label = "bad spacing"
set = ["insertion.spacing=-1.0"]
[reference]
label = "exact"
set = ['solver.method="exact"']
""".replace("'", '"').replace('["solver.method="exact""]', "['solver.method=\"exact\"']")
    (folder / "small.toml").write_text(text)
    output = folder / "small.h5"
    code = main(
        ["study", str(folder / "small.toml"), "-o", str(output), "--workers", "1", "-q", "--no-warm-up"]
    )
    return folder, output, code


def test_study_file_indexes_the_runs(study):
    folder, output, code = study
    assert code == 3  # one run failed: the exit code of a simulation error
    data = read_study(output)
    runs = data["runs"]
    assert runs["status"] == ["complete", "complete", "complete", "failed"]
    assert "insertion.spacing = -1.0" in runs["error"][3] and "SceneError" in runs["error"][3]
    assert np.allclose(runs["values"]["insertion.spacing"][:3], [2e-3, 1e-3, 5e-4])
    assert np.isnan(runs["values"]["insertion.spacing"][3])
    assert np.all(np.isfinite(runs["ms_per_step"][:3])) and np.all(runs["steps"][:3] == 35)
    assert np.all(np.isfinite(runs["quantities"]["puncture_force"][:3]))
    for name in runs["file"][:3]:
        with h5py.File(output.parent / name, "r") as handle:
            assert handle.attrs["complete"]
        assert (output.parent / name).with_suffix(".xdmf").is_file()
    assert data["reference"]["status"] == "complete" and data["reference"]["label"] == "exact"
    assert np.all(runs["errors"]["force_history"][:3] >= 0.0)
    assert data["attributes"]["format"] == "refsim-study" and data["attributes"]["runs_failed"] == 1
    keys = {(row["key"], row["quantity"]) for row in data["convergence"]}
    assert ("insertion.spacing", "needle_force@end") in keys


def test_resume_runs_only_what_is_missing(study):
    folder, output, _ = study
    before = read_study(output)["runs"]
    files = [output.parent / name for name in before["file"]]
    files[0].unlink()
    with h5py.File(files[1], "a") as handle:  # an interrupted run: complete = False
        handle.attrs["complete"] = False
    after = run_study(load_study(folder / "small.toml"), output, workers=1, progress=False, warm_up=True)[
        "runs"
    ]
    assert np.isfinite(after["seconds"][0]) and np.isfinite(after["seconds"][1])  # run again
    assert after["seconds"][2] == before["seconds"][2]  # reused: not run, its timing kept from the study file
    assert np.isfinite(after["cpu_ms_per_step"][0]) and after["cpu_ms_per_step"][0] > 0.0
    assert after["status"][:3] == ["complete"] * 3 and after["status"][3] == "failed"
    for name in ("needle_force@end", "puncture_force"):
        assert np.allclose(
            after["quantities"][name][:3], before["quantities"][name][:3]
        )  # deterministic runs
    assert sorted(p.name for p in run_folder(output).glob("*.h5")) == sorted(
        p.name for p in files[:3] + [output.parent / read_study(output)["reference"]["file"]]
    )


def test_runs_are_reused_by_content_not_by_path(tmp_path):
    """A study reuses a complete run only when the content key its results file records (resolved scene, the
    files it names, numerics digest) is the run's now: an unchanged scene file is reused, an edited one (same
    path, same overrides, same run id) is run again, a file of another git commit with the same numerics is
    reused, and a file of other numerics is run again."""
    from refsim.sweep import StudySpec, Sweep
    from refsim.sweep.study import start_client, stop_client
    from refsim.sweep.worker import file_key, is_current, run_key

    text = (Path(__file__).parents[2] / "refsim" / "scenes" / "cube.toml").read_text()
    scene = tmp_path / "cube.toml"
    scene.write_text(text)
    spec = StudySpec(
        name="content",
        scene=str(scene),
        sweeps=(Sweep("insertion.spacing", (2e-3,), "none"),),
        overrides=tuple(BASE),
        quantities=("needle_force@end",),
    )
    output = tmp_path / "content.h5"
    path = run_folder(output) / spec.runs()[0].file_name

    def created() -> tuple:
        """(modification time [ns], the scene the file records): a reused file is read, never written."""
        with h5py.File(path, "r") as handle:
            recorded = handle.attrs["scene"]
        return path.stat().st_mtime_ns, recorded

    client, cluster = start_client(None, 1)
    try:
        run_study(spec, output, client=client, progress=False, warm_up=False)
        first, recorded = created()
        assert "500000.0" in recorded
        key = run_key(load_scene(str(scene), list(spec.runs()[0].overrides)))
        assert file_key(path) == key and is_current(path, key)
        # unchanged: reused (the same file, not written again)
        run_study(spec, output, client=client, progress=False, warm_up=False)
        assert created()[0] == first
        # the scene file edited in place (E = 500 kPa → 600 kPa): the same run id, run again on the new scene
        scene.write_text(text.replace("youngs_modulus = 500e3", "youngs_modulus = 600e3"))
        assert not is_current(path, run_key(load_scene(str(scene), list(spec.runs()[0].overrides))))
        runs = run_study(spec, output, client=client, progress=False, warm_up=False)["runs"]
        second, recorded = created()
        assert second != first and "600000.0" in recorded and "500000.0" not in recorded
        assert runs["status"] == ["complete"] and np.isfinite(runs["seconds"][0])
        # a file recorded by another commit whose numerics are the same (a docs or tests commit): reused
        with h5py.File(path, "a") as handle:
            handle.attrs["git_commit"] = "0" * 40
        second = created()[0]
        run_study(spec, output, client=client, progress=False, warm_up=False)
        assert created()[0] == second
        # a file whose key is another numerics digest's: stale, run again
        with h5py.File(path, "a") as handle:
            handle.attrs["run_key"] = "0" * 64
        second = created()[0]
        run_study(spec, output, client=client, progress=False, warm_up=False)
        assert created()[0] != second
        assert file_key(path) == run_key(load_scene(str(scene), list(spec.runs()[0].overrides)))
    finally:
        stop_client(client, cluster)


def test_command_line_sweeps(tmp_path):
    code = main(
        [
            "study",
            "cube",
            "--sweep",
            "insertion.spacing=2e-3,1e-3",
            "--sweep",
            "solver.tolerance=1e-6",
            *sum((["--set", s] for s in BASE), []),
            "-o",
            str(tmp_path / "cli.h5"),
            "--workers",
            "1",
            "-q",
            "--no-warm-up",
        ]
    )
    assert code == 0
    runs = read_study(tmp_path / "cli.h5")["runs"]
    assert runs["label"] == [
        "insertion.spacing=0.002, solver.tolerance=1e-06",
        "insertion.spacing=0.001, solver.tolerance=1e-06",
    ]


def test_bad_command_line_is_an_input_error(tmp_path, capsys):
    assert main(["study", "cube", "-o", str(tmp_path / "x.h5")]) == 2
    assert "--sweep" in capsys.readouterr().err
    assert main(["study", "cube", "--sweep", "insertion.nokey=1,2", "-o", str(tmp_path / "x.h5")]) == 2
    assert "has no key 'nokey'" in capsys.readouterr().err


def test_the_run_key_follows_the_numerics_not_the_docs_or_tests(tmp_path):
    """The numerics digest of a copy of the refsim checkout: editing a docs page, a test, the command line, a
    figure module or the study machinery leaves it (and so every run key) unchanged; editing a numerics source
    file (a solver, an element) or a built-in scene changes it."""
    import shutil

    from refsim.sweep.worker import numerics_digest, numerics_files

    source = Path(__file__).parents[2]
    checkout = tmp_path / "checkout"
    shutil.copytree(source / "refsim", checkout / "refsim", ignore=shutil.ignore_patterns("__pycache__"))
    (checkout / "docs").mkdir()
    (checkout / "docs" / "reference.md").write_text("# page\n")
    (checkout / "tests").mkdir()
    (checkout / "tests" / "test_x.py").write_text("def test_x():\n    pass\n")
    package = checkout / "refsim"
    names = {p.relative_to(package).as_posix() for p in numerics_files(package)}
    expected = {
        "fem/tissue.py",
        "simulation/simulation.py",
        "io/writer.py",
        "io/driver.py",
        "scenes/cube.toml",
    }
    assert expected | {"mesh/data/liver_phantom_coarse.vtu", "solvers/__init__.py"} <= names
    assert not any(n.startswith(("viz/", "sweep/", "reference/", "cli.py")) for n in names)
    before = numerics_digest(package)
    assert before == numerics_digest(source / "refsim")
    for edited in (
        "docs/reference.md",
        "tests/test_x.py",
        "refsim/cli.py",
        "refsim/viz/__init__.py",
        "refsim/sweep/study.py",
        "refsim/reference/page.py",
    ):
        with open(checkout / edited, "a") as handle:
            handle.write("\n# an edit\n")
        assert numerics_digest(package) == before, edited
    for edited in ("refsim/solvers/__init__.py", "refsim/fem/__init__.py", "refsim/scenes/cube.toml"):
        path = checkout / edited
        text = path.read_text()
        path.write_text(text + "\n# an edit\n")
        assert numerics_digest(package) != before, edited
        path.write_text(text)
        assert numerics_digest(package) == before, edited
