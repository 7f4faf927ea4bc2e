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


def _vtk_grid(path):
    xml = pytest.importorskip("vtkmodules.vtkIOXML")
    from vtkmodules.util.numpy_support import vtk_to_numpy

    reader = xml.vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(path))
    reader.Update()
    grid = reader.GetOutput()
    arrays = {
        grid.GetPointData().GetArrayName(k): vtk_to_numpy(grid.GetPointData().GetArray(k))
        for k in range(grid.GetPointData().GetNumberOfArrays())
    }
    return vtk_to_numpy(grid.GetPoints().GetData()), grid, arrays


def test_vtu_of_a_step_holds_the_deformed_tissue_and_the_cut(cut_run, tmp_path, capsys):
    """`refsim export --vtu STEP`, read back with VTK's XML reader: the points are the recorded tissue
    positions of the step, the displacement is theirs minus rest, the cut triangles are those existing at the
    step with their points mapped by equation 4; meshio.read opens the files too."""
    import meshio
    from vtkmodules.util.numpy_support import vtk_to_numpy

    results = read_results(cut_run)
    step = int(results.tissue_steps[-1])
    assert main(["export", str(cut_run), "--vtu", str(step), "--vtu-folder", str(tmp_path)]) == 0
    tissue_file = tmp_path / f"cut_tissue_{step:07d}.vtu"
    points, grid, arrays = _vtk_grid(tissue_file)
    positions = results.tissue_positions[-1]
    np.testing.assert_array_equal(points, positions)
    np.testing.assert_array_equal(arrays["displacement"], positions - results.rest_positions)
    np.testing.assert_array_equal(np.flatnonzero(arrays["fixed"]), np.sort(results.fixed_nodes))
    index = int(np.flatnonzero(results.step == step)[0])
    scale = np.abs(results.constraints_at(step).forces).sum()
    np.testing.assert_allclose(
        arrays["constraint_force"].sum(axis=0), -results.needle_force[index], rtol=0, atol=1e-12 * scale
    )
    cells = vtk_to_numpy(grid.GetCells().GetConnectivityArray()).reshape(-1, 4)
    np.testing.assert_array_equal(cells, results.tets)
    cut = results.cut
    cut_points, cut_grid, _ = _vtk_grid(tmp_path / f"cut_cut_{step:07d}.vtu")
    expected = np.einsum("pk,pki->pi", cut.barycentric, positions[results.tets[cut.tet_indices]])
    np.testing.assert_array_equal(cut_points, expected)
    assert cut_grid.GetNumberOfCells() == np.count_nonzero(cut.triangle_step <= step) > 0
    assert meshio.read(tissue_file).points.shape == positions.shape


def test_vtu_series_has_every_recorded_step_and_sorted_pvd_times(cut_run, tmp_path):
    from xml.etree import ElementTree as ET

    from refsim.io.export import export_vtu

    results = read_results(cut_run)
    files = export_vtu(cut_run, "all", tmp_path)
    collection = ET.parse(tmp_path / "cut_tissue.pvd").getroot().find("Collection")
    times = [float(item.get("timestep")) for item in collection]
    np.testing.assert_array_equal(times, results.tissue_times)
    assert all((tmp_path / item.get("file")).is_file() for item in collection)
    assert len([f for f in files if "_tissue_" in f.name]) == results.tissue_steps.size
    assert sorted(tmp_path.iterdir()) == sorted(files)  # written whole: no temporary file left


def test_vtu_of_an_unrecorded_step_exits_2_and_writes_nothing(cut_run, tmp_path, capsys):
    assert main(["export", str(cut_run), "--vtu", "17", "--vtu-folder", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err
    assert "--vtu 17: not a recorded tissue step" in error and "25, 50" in error
    assert not (tmp_path / "out").exists()
