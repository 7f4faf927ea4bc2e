"""`refsim study` with a scene or an override every run shares that does not load: bad input (exit 2) named
before the cluster starts and before anything is written (before: every run failed on a worker, exit 3, with a
study file and a run folder left). A study whose runs fail on their own values still runs (exit 3, each run
named: tests/sweep/test_study_safety.py)."""

from __future__ import annotations

import os

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
