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
    coulomb_contacts,
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


def test_a_selection_of_steps_is_what_the_full_export_writes_for_them(recorded, tmp_path):
    # The reference build keeps 20 of a run's thousands of problems: exporting only those (and trying FCLib
    # only on the steps of its form) must write for each the same problem and solution as the full export,
    # and solve nothing else.
    full = export_problems(recorded, tmp_path / "all.h5", fclib_folder=tmp_path / "fclib_all")
    steps = [step for step, _ in read_problems(recorded)]
    chosen, tried = steps[1::3], steps[:4]
    part = export_problems(
        recorded, tmp_path / "part.h5", fclib_folder=tmp_path / "fclib_part", steps=chosen, fclib_steps=tried
    )
    assert part["problems"] == len(chosen) < full["problems"]
    everything = {
        step: (problem, solution) for step, problem, solution in read_problem_set(tmp_path / "all.h5")
    }
    exported = read_problem_set(tmp_path / "part.h5")
    assert [step for step, _, _ in exported] == chosen
    for step, problem, solution in exported:
        _same_problem(problem, everything[step][0])
        assert np.array_equal(solution, everything[step][1])
    expected = [path.name for path in full["fclib"] if int(path.stem.split("_")[1]) in tried]
    assert [path.name for path in part["fclib"]] == expected and expected
    with h5py.File(tmp_path / "part.h5", "r") as handle:
        assert handle.attrs["problem_count"] == len(chosen)
    with pytest.raises(ValueError, match="no recorded constraint problem at step"):
        export_problems(recorded, tmp_path / "bad.h5", steps=[steps[-1] + 1000])


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


@pytest.fixture(scope="module")
def capped(tmp_path_factory):
    """The same cube with the scene's default tip (puncture located within the step): before puncture the
    tip's normal row is a box [0, f_p] and its two friction rows are bounded by μ λ_n each."""
    path = tmp_path_factory.mktemp("export_capped") / "cube.h5"
    overrides = ["mesh.cells=[2, 2, 2]", "time.duration=0.3", "output.record_problems=true"]
    assert main(["run", "cube", "-o", str(path), "-q", *[a for o in overrides for a in ("--set", o)]]) == 0
    return path


def _fclib_error(path) -> float:
    """FCLib's error of the file's stored solution, read with h5py and scipy alone (Siconos'
    fc3d_compute_error as ../shared/data/solver-problems/README states it): u = W r + q; per contact
    e = r − P_K(r − u − μ ‖u_t‖ e_n), K the cone ‖r_t‖ ≤ μ r_n; error ‖e‖₂ / max(‖q‖, ‖r‖, ‖u‖)."""
    import scipy.sparse as sparse

    with h5py.File(path, "r") as handle:
        w = handle["fclib_local/W"]
        assert int(w["nz"][0]) == -1  # CSC
        size = int(w["m"][0])
        matrix = sparse.csc_matrix((w["x"][()], w["i"][()], w["p"][()]), shape=(size, size))
        q, mu = handle["fclib_local/vectors/q"][()], handle["fclib_local/vectors/mu"][()]
        assert int(handle["fclib_local/spacedim"][0]) == 3
        r = handle["solution/r"][()]
    u = matrix @ r + q
    rc, uc = r.reshape(-1, 3), u.reshape(-1, 3)
    shifted = rc - uc
    shifted[:, 0] -= mu * np.linalg.norm(uc[:, 1:], axis=1)
    # projection onto the cone ‖t‖ ≤ μ n (inside, polar cone to 0, else onto the boundary)
    n, t = shifted[:, 0], shifted[:, 1:]
    tn = np.linalg.norm(t, axis=1)
    projected = np.zeros_like(shifted)
    inside = tn <= mu * n
    projected[inside] = shifted[inside]
    boundary = ~inside & (mu * tn > -n)
    normal = (n[boundary] + mu[boundary] * tn[boundary]) / (1.0 + mu[boundary] ** 2)
    projected[boundary, 0] = normal
    projected[boundary, 1:] = (mu[boundary] * normal / tn[boundary])[:, None] * t[boundary]
    error = np.linalg.norm((rc - projected).ravel())
    return float(error / max(np.linalg.norm(q), np.linalg.norm(r), np.linalg.norm(u)))


def test_capped_tip_contact_is_written_to_fclib_and_its_solution_meets_fclibs_error(capped, tmp_path):
    """The default tip before puncture: its FCLib files read back and their stored solutions meet FCLib's
    own error measure to the tolerance the export asked of solve_exact (1e-10: the measure is the same
    normalised natural map refsim's residual uses, so the solver's stopping test bounds it)."""
    tolerance = 1e-10
    summary = export_problems(
        capped, tmp_path / "set.h5", fclib_folder=tmp_path / "fclib", tolerance=tolerance
    )
    problems = dict(read_problems(capped))
    results = read_results(capped)
    assert not any(is_pure_contact(p) for p in problems.values())  # none was pure contact before
    assert len(summary["fclib"]) > 0
    for path in summary["fclib"]:
        step = int(path.stem.split("_")[1])
        problem = problems[step]
        assert results.phase_name[results.index_of(step)] == "approach"
        assert problem.box_rows.size == 1 and problem.bilateral.size == 0  # the tip: a box normal [0, f_p]
        error = _fclib_error(path)
        assert error <= tolerance, (path.name, error)
        back = read_fclib(path)  # our own reader agrees on the data
        normal = int(problem.box_rows[0])
        with h5py.File(path, "r") as handle:
            r = handle["solution/r"][()]
            assert "inactive here" in handle["fclib_local/info/description"][()].decode()
        assert (
            back.free_gap[0] == problem.free_gap[normal]
            and back.compliance[0, 0] == problem.compliance[normal, normal]
        )
        assert 0.0 < r[0] < problem.box_upper[0]  # loaded, below the cap f_p
    # the insertion steps (bilateral and shaft rows) are not written
    written = {int(p.stem.split("_")[1]) for p in summary["fclib"]}
    assert all(problems[s].bilateral.size == 0 for s in written)


def test_coulomb_contacts_takes_only_what_fclib_holds():
    w = np.eye(3) + 0.1
    tip = {
        "compliance": w,
        "free_gap": np.array([-1e-3, 2e-4, 0.0]),
        "group_friction": [1, 2],
        "group_offsets": [0, 1, 2],
        "group_members": [0, 0],
        "group_friction_coefficient": [0.3, 0.3],
        "box_rows": [0],
        "box_lower": [0.0],
        "box_upper": [0.8],
    }
    contact, caps = coulomb_contacts(ConstraintProblem(**tip))
    assert contact.contacts.tolist() == [[0, 1, 2]] and contact.contact_friction.tolist() == [0.3]
    assert caps.tolist() == [0.8]
    # a preload, two friction coefficients, a bilateral row, a friction row bounded by two rows: not FCLib's
    assert coulomb_contacts(ConstraintProblem(**{**tip, "group_preload": [0.1, 0.1]})) is None
    assert coulomb_contacts(ConstraintProblem(**{**tip, "group_friction_coefficient": [0.3, 0.2]})) is None
    bigger = np.eye(4) + 0.1
    assert (
        coulomb_contacts(
            ConstraintProblem(**{**tip, "compliance": bigger, "free_gap": np.zeros(4), "bilateral": [3]})
        )
        is None
    )
    two = {
        **tip,
        "compliance": bigger,
        "free_gap": np.zeros(4),
        "unilateral": [3],
        "group_offsets": [0, 2, 3],
        "group_members": [0, 3, 0],
    }
    assert coulomb_contacts(ConstraintProblem(**two)) is None


def test_an_active_cap_is_not_written(tmp_path):
    from refsim.io.export import _coulomb_fclib

    # pushed 1 mm into a unit compliance: the uncapped normal force would be 1e-3 / W_nn; a cap below it binds
    problem = ConstraintProblem(
        compliance=np.eye(3) * 1e-3,
        free_gap=np.array([-1e-3, 0.0, 0.0]),
        group_friction=[1, 2],
        group_offsets=[0, 1, 2],
        group_members=[0, 0],
        group_friction_coefficient=[0.3, 0.3],
        box_rows=[0],
        box_lower=[0.0],
        box_upper=[0.5],
    )
    assert _coulomb_fclib(problem, tmp_path / "a.hdf5", "test", 1e-10, "clarabel", "s", 1) is None
    uncapped = ConstraintProblem(
        compliance=np.eye(3) * 1e-3,
        free_gap=np.array([-1e-3, 0.0, 0.0]),
        group_friction=[1, 2],
        group_offsets=[0, 1, 2],
        group_members=[0, 0],
        group_friction_coefficient=[0.3, 0.3],
        box_rows=[0],
        box_lower=[0.0],
        box_upper=[2.0],
    )
    path = _coulomb_fclib(uncapped, tmp_path / "b.hdf5", "test", 1e-10, "clarabel", "s", 1)
    assert path is not None and _fclib_error(path) <= 1e-10
    with h5py.File(path, "r") as handle:
        assert handle["solution/r"][0] == pytest.approx(1.0, rel=1e-9)  # λ_n = 1e-3 m / 1e-3 m/N = 1 N


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


def test_vtu_writes_every_instruments_needle_at_the_step(two_needle_run, tmp_path):
    """Each instrument's needle at a recorded tissue step, read back with VTK's XML reader: its points are
    that instrument's steps/needle_positions of the step, joined node to node by line segments, its
    displacement is from its nodes at t = 0 and its radius is its needle's; `all` adds one .pvd per
    instrument with the tissue's times."""
    from xml.etree import ElementTree as ET

    from vtkmodules.util.numpy_support import vtk_to_numpy

    from refsim.io.export import export_vtu

    results = read_results(two_needle_run)
    files = export_vtu(two_needle_run, "all", tmp_path)
    assert results.instrument_names == ("cutter", "holder")
    for view in results.instruments:
        (name,) = view.instrument_names
        for number in results.tissue_steps:
            points, grid, arrays = _vtk_grid(tmp_path / f"two_{name}_{int(number):07d}.vtu")
            nodes = view.needle_positions[results.index_of(int(number))]
            np.testing.assert_array_equal(points, nodes)
            np.testing.assert_array_equal(arrays["displacement"], nodes - view.needle_rest_nodes)
            np.testing.assert_array_equal(
                arrays["radius"], np.full(len(nodes), results.scene["needle"]["radius"])
            )
            segments = vtk_to_numpy(grid.GetCells().GetConnectivityArray()).reshape(-1, 2)
            np.testing.assert_array_equal(
                segments, np.stack([np.arange(len(nodes) - 1), np.arange(1, len(nodes))], 1)
            )
        collection = ET.parse(tmp_path / f"two_{name}.pvd").getroot().find("Collection")
        np.testing.assert_array_equal(
            [float(item.get("timestep")) for item in collection], results.tissue_times
        )
    # The two needles are apart (4 cm between their entries), not one needle written twice.
    first, second = (
        _vtk_grid(tmp_path / f"two_{n}_{int(results.tissue_steps[-1]):07d}.vtu")[0]
        for n in ("cutter", "holder")
    )
    assert np.linalg.norm(first - second, axis=1).min() > 0.03
    assert sorted(tmp_path.iterdir()) == sorted(files)


def test_vtu_needle_radius_is_each_instruments_own():
    from refsim.io.export import _needle_radii

    scene = {
        "needle": {"radius": 0.008, "length": 0.32},
        "instruments": [{"name": "a"}, {"name": "b", "radius": 0.0005}],
    }
    assert _needle_radii(scene, ("a", "b")) == [0.008, 0.0005]
    assert _needle_radii({"needle": {"radius": 0.001}}, ("needle",)) == [0.001]
