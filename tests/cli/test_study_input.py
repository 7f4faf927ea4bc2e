"""`refsim study` with a scene or an override every run shares that does not load: bad input (exit 2) named
before the cluster starts and before anything is written (before: every run failed on a worker, exit 3, with a
study file and a run folder left). A study whose runs fail on their own values still runs (exit 3, each run
named: tests/sweep/test_study_safety.py)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

pytest.importorskip("distributed")

from refsim.cli import EXIT_INPUT, main  # noqa: E402


@pytest.mark.parametrize(
    ("arguments", "fragments"),
    [
        (["nope", "--sweep", "time.dt=0.01,0.02"], ["'nope' is neither a scene file"]),
        (["cube", "--sweep", "time.dt=0.01,0.02", "--set", "foo.x=1"], ["unknown section 'foo'"]),
    ],
)
def test_a_study_none_of_whose_runs_loads_is_refused_before_anything(tmp_path, capsys, arguments, fragments):
    output = tmp_path / "study.h5"
    previous = os.getcwd()
    os.chdir(tmp_path)
    try:
        code = main(["study", *arguments, "-o", str(output), "-q"])
    finally:
        os.chdir(previous)
    error = capsys.readouterr().err
    assert code == EXIT_INPUT, error
    assert "does not load (no run can)" in error
    for fragment in fragments:
        assert fragment in error
    assert list(tmp_path.iterdir()) == []


def test_the_study_file_may_not_be_the_scene_or_the_study_toml(tmp_path, capsys):
    """`-o` naming the scene file or the study's own .toml, with --overwrite: before, replaced by the study
    file."""
    from refsim.scene import load_scene

    scene = tmp_path / "scene.toml"
    scene.write_text(Path(load_scene("cube").source).read_text())
    study = tmp_path / "study.toml"
    study.write_text('name = "s"\nscene = "scene.toml"\n[[sweep]]\nkey = "time.dt"\nvalues = [0.01, 0.02]\n')
    before = {path: path.read_bytes() for path in (scene, study)}
    for arguments, what in (
        ([str(scene), "--sweep", "time.dt=0.01,0.02", "-o", str(scene)], "the study's scene file"),
        ([str(study), "-o", str(study)], "the study file (.toml)"),
        ([str(study), "-o", str(scene)], "the study's scene file"),
    ):
        assert main(["study", *arguments, "--overwrite", "-q"]) == EXIT_INPUT
        assert f": is {what}; give another path" in capsys.readouterr().err
    assert {path: path.read_bytes() for path in (scene, study)} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.toml", "study.toml"]
