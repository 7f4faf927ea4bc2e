"""Results file, in detail: per-step arrays, solver reports, static data, the reader trusting steps_completed,
wrong shapes, bad files and unsupported schema versions (complements test_results.py)."""

from __future__ import annotations

import datetime
import json

import h5py
import numpy as np
import pytest

from refsim.io import ResultsError, ResultWriter, read_problems, read_results, schema
from refsim.scene import load_scene, scene_to_json
from refsim.simulation import STAGES, Simulation

# 0.3 s of the cube: approach, puncture at about 0.21 s, then insertion (30 steps, a few seconds).
OVERRIDES = ["time.duration=0.3", "output.record_problems=true", "output.tissue_every=7"]


def synthetic_cut(tip_x: float = 0.002) -> dict:
    """A small cut surface in rest coordinates inside the cube's top: a 3 x 3 grid in the plane x = tip_x,
    the first row of points created at step 25, the others at step 28; triangles follow their points."""
    y, z = np.meshgrid([0.0, 0.0025, 0.005], [0.1, 0.097, 0.094], indexing="xy")
    points = np.column_stack([np.full(9, tip_x), y.ravel(), z.ravel()])
    point_step = np.array([25, 25, 25, 28, 28, 28, 28, 28, 28])
    triangles = []
    for row in range(2):
        for column in range(2):
            a = 3 * row + column
            triangles += [[a, a + 1, a + 4], [a, a + 4, a + 3]]
    triangles = np.array(triangles)
    return {
        "points": points,
        "point_step": point_step,
        "triangles": triangles,
        "triangle_step": np.where(triangles.max(axis=1) < 3, 25, 28),
    }


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """Write a real run, keeping the records the simulation produced."""
    scene = load_scene("cube", OVERRIDES)
    simulation = Simulation(scene)
    path = tmp_path_factory.mktemp("results") / "cube.h5"
    records = []
    with ResultWriter(path, scene, simulation.models) as writer:

        def on_step(state, record):
            records.append(record)
            writer.append(record)

        simulation.run(on_step=on_step)
        writer.write_cut_surface(**{**synthetic_cut(0.001), "point_step": np.full(9, 30)})  # rewritten below
        writer.write_cut_surface(**synthetic_cut())
    return scene, simulation, path, records


def test_every_step_is_recorded_and_the_run_is_complete(run):
    scene, _, path, records = run
    results = read_results(path)
    assert results.complete
    assert results.step_count == len(records) == scene.time.step_count
    assert results.attributes["steps_completed"] == len(records)
    np.testing.assert_array_equal(results.step, [record.step for record in records])


def test_per_step_arrays_equal_the_records(run):
    _, _, path, records = run
    results = read_results(path)
    np.testing.assert_array_equal(results.time, [r.time for r in records])
    assert list(results.phase_name) == [r.phase for r in records]
    for name in (
        "base_position",
        "needle_positions",
        "needle_frames",
        "needle_force",
        "insertion_point_count",
        "cut_point_count",
        "cut_triangle_count",
        "triangulation_seconds",
    ):
        np.testing.assert_array_equal(
            getattr(results, name), np.array([getattr(r, name) for r in records]), err_msg=name
        )
    assert results.stage_names == STAGES
    for stage in STAGES:
        np.testing.assert_array_equal(results.stage_seconds[stage], [r.stage_seconds[stage] for r in records])


def test_solver_reports_equal_the_records_and_mark_steps_without_solve(run):
    _, _, path, records = run
    solver = read_results(path).solver
    for index, record in enumerate(records):
        report = record.solver
        if report is None:
            assert solver["iterations"][index] == -1 and solver["converged"][index] == -1
            assert np.isnan(solver["residual"][index]) and np.isnan(solver["seconds"][index])
            continue
        assert solver["iterations"][index] == report.iterations
        assert solver["residual"][index] == report.residual
        assert solver["converged"][index] == int(report.converged)
        assert solver["seconds"][index] == report.seconds
        np.testing.assert_array_equal(solver["increment"][index], report.increment)
        assert solver["name"][index] == report.solver


def test_constraints_events_and_tissue_equal_the_records(run):
    _, _, path, records = run
    results = read_results(path)
    for record in records:
        rows = results.constraints_at(record.step)
        np.testing.assert_array_equal(rows.kind, record.row_kind)
        np.testing.assert_array_equal(rows.source, record.row_source)
        np.testing.assert_array_equal(rows.points, record.row_points)
        np.testing.assert_array_equal(rows.directions, record.row_directions)
        np.testing.assert_array_equal(rows.forces, record.row_forces)
    expected_events = [(r.step, e.name, e.force) for r in records for e in r.events]
    assert expected_events, "the run should puncture"
    got = [(e.step, e.name, e.force) for e in results.events]
    assert [g[:2] for g in got] == [e[:2] for e in expected_events]
    np.testing.assert_array_equal([g[2] for g in got], [e[2] for e in expected_events])
    tissue = [r for r in records if r.tissue_positions is not None]
    np.testing.assert_array_equal(results.tissue_steps, [r.step for r in tissue])
    np.testing.assert_array_equal(results.tissue_positions, np.array([r.tissue_positions for r in tissue]))
    # nearest recorded state: steps 7, 14, 21, 28 and the last one (30) are recorded
    np.testing.assert_array_equal(results.tissue_positions_at(16), tissue[1].tissue_positions)
    np.testing.assert_array_equal(results.tissue_positions_at(29), tissue[-2].tissue_positions)
    assert results.nearest_tissue_step(30) == 30
    with pytest.raises(ResultsError, match="no step 999"):
        results.constraints_at(999)


def test_static_data_and_root_attributes(run):
    scene, simulation, path, _ = run
    results = read_results(path)
    mesh = simulation.models.mesh
    np.testing.assert_array_equal(results.rest_positions, mesh.rest_positions)
    np.testing.assert_array_equal(results.tets, mesh.tets)
    np.testing.assert_array_equal(results.faces, mesh.boundary_faces)
    np.testing.assert_array_equal(results.fixed_nodes, simulation.models.tissue.fixed_nodes)
    np.testing.assert_allclose(
        results.needle_rest_nodes, simulation.initial_state().needle.positions, rtol=0, atol=1e-15
    )
    assert results.scene == json.loads(scene_to_json(scene))
    assert results.scene_name == scene.name == "cube"
    assert results.attributes["schema_version"] == schema.SCHEMA_VERSION
    created = datetime.datetime.fromisoformat(results.attributes["created"])
    assert created.utcoffset() == datetime.timedelta(0)
    commit = results.attributes["git_commit"]
    assert commit == "unknown" or len(commit) == 40


def test_every_dataset_carries_the_units_of_the_schema(run):
    _, _, path, _ = run
    specs = {spec.path: spec for spec in schema.all_datasets()}
    seen = []

    def check(name, item):
        if isinstance(item, h5py.Dataset):
            key = name if name in specs else "problems/step_NNNNNNN/" + name.rsplit("/", 1)[-1]
            assert key in specs, f"dataset {name} is not in the schema"
            assert item.attrs["units"] == specs[key].unit, name
            seen.append(name)

    with h5py.File(path, "r") as handle:
        handle.visititems(check)
    # every dataset of the schema except the optional cut coordinates and the rows' instrument (several
    # instruments only) is in this one-needle file
    for spec in schema.all_datasets():
        if spec.path.startswith("problems/") or spec.name in ("tet_indices", "barycentric"):
            continue
        if spec.path == schema.CONSTRAINTS["instrument"].path:
            assert spec.path not in seen
            continue
        assert spec.path in seen, spec.path


def test_problems_are_rebuilt_equal(run):
    _, _, path, records = run
    problems = read_problems(path)
    recorded = [r for r in records if r.problem is not None]
    assert [step for step, _ in problems] == [r.step for r in recorded]
    assert len(problems) > 0
    for (step, problem), record in zip(problems, recorded, strict=False):
        for spec in schema.PROBLEM_FIELDS.values():
            np.testing.assert_array_equal(
                getattr(problem, spec.name),
                getattr(record.problem, spec.name),
                err_msg=f"step {step} {spec.name}",
            )
    assert [step for step, _ in read_problems(path, steps=[22, 25])] == [22, 25]


def test_cut_surface_history_is_rewritten_and_sliced_by_step(run):
    _, _, path, _ = run
    cut = read_results(path).cut
    expected = synthetic_cut()
    np.testing.assert_array_equal(cut.points, expected["points"])  # the second write replaced the first
    np.testing.assert_array_equal(cut.point_step, expected["point_step"])
    points, triangles = cut.at(26)
    assert points.shape == (3, 3) and triangles.shape == (0, 3)
    points, triangles = cut.at(28)
    assert points.shape == (9, 3) and triangles.shape == (8, 3)
    assert cut.tet_indices is None


def test_interrupted_run_keeps_its_completed_steps(tmp_path, run):
    scene, simulation, _, _ = run
    path = tmp_path / "interrupted.h5"
    completed = 5

    def on_step(state, record):
        if record.step > completed:
            raise KeyboardInterrupt
        writer.append(record)

    with pytest.raises(KeyboardInterrupt):
        with ResultWriter(path, scene, simulation.models) as writer:
            Simulation(scene, simulation.models).run(steps=10, on_step=on_step)
    results = read_results(path)
    assert not results.complete
    assert results.step_count == completed
    np.testing.assert_array_equal(results.step, np.arange(1, completed + 1))
    assert results.constraint_offsets.shape == (completed + 1,)


def test_reader_trusts_steps_completed_over_dataset_lengths(tmp_path, run):
    """A write cut short mid-step leaves datasets longer than steps_completed: the reader cuts them."""
    _, _, path, records = run
    copy = tmp_path / "partial.h5"
    copy.write_bytes(path.read_bytes())
    with h5py.File(copy, "r+") as handle:
        handle.attrs["steps_completed"] = 22
        handle.attrs["complete"] = False
    results = read_results(copy)
    assert results.step_count == 22 and not results.complete
    assert results.constraint_forces.shape[0] == sum(r.row_forces.size for r in records[:22])
    assert list(results.tissue_steps) == [7, 14, 21]
    assert [step for step, _ in read_problems(copy)] == [
        r.step for r in records[:22] if r.problem is not None
    ]


def test_overwriting_is_refused_unless_asked(tmp_path, run):
    scene, simulation, _, _ = run
    path = tmp_path / "exists.h5"
    path.write_bytes(b"previous results")
    with pytest.raises(FileExistsError, match="exists.h5"):
        ResultWriter(path, scene, simulation.models)
    assert path.read_bytes() == b"previous results"
    with ResultWriter(path, scene, simulation.models, overwrite=True):
        pass
    assert read_results(path).step_count == 0


def test_append_rejects_a_record_of_the_wrong_shape(tmp_path, run):
    scene, simulation, _, records = run
    with ResultWriter(tmp_path / "bad.h5", scene, simulation.models) as writer:
        with pytest.raises(ValueError, match="needle_positions has shape"):
            writer.append(records[0].with_first(needle_positions=np.zeros((3, 3))))


def test_bad_files_give_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.h5"):
        read_results(tmp_path / "missing.h5")
    text = tmp_path / "notes.h5"
    text.write_text("not hdf5")
    with pytest.raises(ResultsError, match="not an HDF5 file"):
        read_results(text)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as handle:
        handle["data"] = np.arange(3)
    with pytest.raises(ResultsError, match="not a refsim results file"):
        read_results(other)
    with pytest.raises(ResultsError, match="not a refsim results file"):
        read_problems(other)


def test_unsupported_schema_version_is_named(tmp_path, run):
    _, _, path, _ = run
    copy = tmp_path / "future.h5"
    copy.write_bytes(path.read_bytes())
    with h5py.File(copy, "r+") as handle:
        handle.attrs["schema_version"] = 99
    with pytest.raises(ResultsError, match="schema version 99 is not supported"):
        read_results(copy)
