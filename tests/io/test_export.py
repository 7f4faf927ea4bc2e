"""Reference-data export: problem set with exact solutions, FCLib round trip, force CSV, the `export`
command."""

from __future__ import annotations

import csv

import h5py
import numpy as np
import pytest

from refsim.cli import main
from refsim.io import read_problems, read_results
from refsim.io.export import (
    export_force_csv,
    export_problems,
    is_pure_contact,
    read_problem_set,
    write_fclib,
)
from refsim.solvers import ConstraintProblem, natural_residual
from refsim.solvers.readers import read_fclib


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """The cube on 2 cells per axis for 0.3 s with every problem recorded: contact steps, then insertion.

    The tip contact is the plain Coulomb contact (insertion.puncture_within_step = false, said explicitly): a
    tip capped at f_p (box normal, group friction) is not a pure contact problem, which FCLib holds.
    """
    path = tmp_path_factory.mktemp("export") / "cube.h5"
    assert (
        main(
            [
                "run",
                "cube",
                "-o",
                str(path),
                "-q",
                "--set",
                "mesh.cells=[2, 2, 2]",
                "--set",
                "time.duration=0.3",
                "--set",
                "output.record_problems=true",
                "--set",
                "insertion.puncture_within_step=false",
            ]
        )
        == 0
    )
    return path


def _same_problem(a: ConstraintProblem, b: ConstraintProblem) -> None:
    for name in (
        "compliance",
        "free_gap",
        "bilateral",
        "unilateral",
        "contacts",
        "contact_friction",
        "shaft_friction",
        "shaft_pairs",
        "shaft_friction_coefficient",
        "shaft_normal_preload",
        "box_rows",
        "box_lower",
        "box_upper",
    ):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_problem_set_holds_every_problem_with_its_exact_solution(recorded, tmp_path):
    summary = export_problems(recorded, tmp_path / "set.h5", fclib_folder=tmp_path / "fclib")
    original = read_problems(recorded)
    exported = read_problem_set(tmp_path / "set.h5")
    assert summary["problems"] == len(original) == len(exported) > 0
    kinds = set()
    for (step, problem), (step2, problem2, multipliers) in zip(original, exported, strict=True):
        assert step == step2
        _same_problem(problem, problem2)
        assert natural_residual(problem2, multipliers) <= 1e-8  # the exact solver's tolerance, with margin
        kinds.add(is_pure_contact(problem))
    assert kinds == {True, False}  # contact before the puncture, insertion rows after
    with h5py.File(tmp_path / "set.h5", "r") as handle:
        assert handle.attrs["format"] == "refsim-problem-set"
        group = handle["problems"][sorted(handle["problems"])[0]]
        assert group["compliance"].attrs["units"] == "m/N" and "phase" in group.attrs


def test_fclib_files_round_trip_through_our_reader(recorded, tmp_path):
    summary = export_problems(recorded, tmp_path / "set.h5", fclib_folder=tmp_path / "fclib")
    pure = [(step, p) for step, p in read_problems(recorded) if is_pure_contact(p)]
    assert len(summary["fclib"]) == len(pure) > 0
    for (step, problem), path in zip(pure, summary["fclib"], strict=True):
        assert path.name == f"step_{step:07d}.hdf5"
        back = read_fclib(path)
        order = problem.contacts.reshape(-1)
        assert np.allclose(back.compliance, problem.compliance[np.ix_(order, order)], rtol=0, atol=0)
        assert np.array_equal(back.free_gap, problem.free_gap[order])
        assert np.array_equal(back.contact_friction, problem.contact_friction)
        with h5py.File(path, "r") as handle:
            r, u = handle["solution/r"][()], handle["solution/u"][()]
        assert np.allclose(back.gap(r), u, rtol=0, atol=1e-15)
        assert natural_residual(back, r) <= 1e-8


def test_fclib_needs_pure_contact():
    mixed = ConstraintProblem(
        compliance=np.eye(4), free_gap=np.ones(4), bilateral=[3], contacts=[[0, 1, 2]], contact_friction=[0.1]
    )
    with pytest.raises(ValueError, match="1 of 4 rows are not frictional contacts"):
        write_fclib(mixed, "never.hdf5")


def test_fclib_reorders_scattered_contacts(tmp_path):
    rng = np.random.default_rng(3)
    factor = rng.normal(size=(6, 6))
    problem = ConstraintProblem(
        compliance=factor @ factor.T + np.eye(6),
        free_gap=rng.normal(size=6),
        contacts=[[5, 0, 3], [1, 4, 2]],
        contact_friction=[0.2, 0.4],
    )
    back = read_fclib(write_fclib(problem, tmp_path / "p.hdf5"))
    assert np.array_equal(back.compliance, problem.compliance[np.ix_([5, 0, 3, 1, 4, 2], [5, 0, 3, 1, 4, 2])])
    assert np.array_equal(back.free_gap, problem.free_gap[[5, 0, 3, 1, 4, 2]])


def test_force_csv(recorded, tmp_path):
    results = read_results(recorded)
    rows = list(csv.DictReader(open(export_force_csv(recorded, tmp_path / "f.csv"))))
    assert len(rows) == results.step_count
    assert np.allclose([float(r["force_z_N"]) for r in rows], results.needle_force[:, 2], rtol=1e-8, atol=0)
    assert rows[-1]["phase"] == results.phase_name[-1]


def test_export_command(recorded, tmp_path, capsys):
    assert (
        main(
            [
                "export",
                str(recorded),
                "--csv",
                str(tmp_path / "f.csv"),
                "--problems",
                str(tmp_path / "s.h5"),
                "--fclib",
                str(tmp_path / "fc"),
                "--xdmf",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "FCLib files" in out and (tmp_path / "f.csv").is_file() and recorded.with_suffix(".xdmf").is_file()
    assert main(["export", str(recorded)]) == 2
    bare = tmp_path / "bare.h5"
    assert (
        main(
            [
                "run",
                "cube",
                "-o",
                str(bare),
                "-q",
                "--set",
                "mesh.cells=[2, 2, 2]",
                "--set",
                "time.duration=0.05",
            ]
        )
        == 0
    )
    assert main(["export", str(bare), "--problems", str(tmp_path / "none.h5")]) == 2
    assert "output.record_problems=true" in capsys.readouterr().err
