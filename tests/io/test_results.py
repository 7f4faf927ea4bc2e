"""Results files: round trip of a real run, units everywhere, interrupted runs, refusals, and the schema
page."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from refsim.io import ResultsError, ResultWriter, read_problems, read_results
from refsim.io.schema import all_datasets, reference_markdown
from refsim.simulation import Simulation


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    from refsim.scene import load_scene

    scene = load_scene(
        "cube",
        ["mesh.cells=[4, 4, 4]", "time.duration=0.4", "output.record_problems=true", "output.tissue_every=7"],
    )
    simulation = Simulation(scene)
    path = tmp_path_factory.mktemp("results") / "short.h5"
    records = []
    with ResultWriter(path, scene, simulation.models) as writer:

        def on_step(state, record):
            writer.append(record)
            records.append(record)

        simulation.run(on_step=on_step)
    return path, records, simulation


def test_every_step_round_trips(short_run):
    path, records, simulation = short_run
    results = read_results(path)
    assert results.complete and results.step_count == len(records) == 40
    np.testing.assert_array_equal(results.step, [r.step for r in records])
    np.testing.assert_allclose(results.time, [r.time for r in records])
    np.testing.assert_array_equal(results.needle_positions, np.stack([r.needle_positions for r in records]))
    np.testing.assert_array_equal(results.needle_force, np.stack([r.needle_force for r in records]))
    np.testing.assert_array_equal(results.rest_positions, simulation.models.mesh.rest_positions)
    for record in records:
        rows = results.constraints_at(record.step)
        np.testing.assert_array_equal(rows.forces, record.row_forces)
        np.testing.assert_array_equal(rows.kind, record.row_kind)
        np.testing.assert_array_equal(rows.points, record.row_points)
        if record.tissue_positions is not None:
            np.testing.assert_array_equal(results.tissue_positions_at(record.step), record.tissue_positions)
    # Tissue positions every 7th step and the last one.
    np.testing.assert_array_equal(results.tissue_steps, [7, 14, 21, 28, 35, 40])
    punctures = results.events_named("puncture")
    assert len(punctures) == 1 and punctures[0].force >= 0.8


def test_recorded_problems_rebuild_equal(short_run):
    path, records, _ = short_run
    problems = dict(read_problems(path))
    solved = [r for r in records if r.problem is not None]
    assert len(problems) == len(solved) > 0
    for record in solved:
        rebuilt = problems[record.step]
        np.testing.assert_array_equal(rebuilt.compliance, record.problem.compliance)
        np.testing.assert_array_equal(rebuilt.free_gap, record.problem.free_gap)
        for name in ("bilateral", "unilateral", "contacts", "shaft_friction", "shaft_pairs"):
            np.testing.assert_array_equal(getattr(rebuilt, name), getattr(record.problem, name))


def test_every_dataset_has_units(short_run):
    path, _, _ = short_run
    missing = []
    with h5py.File(path, "r") as results:

        def visit(name, item):
            if isinstance(item, h5py.Dataset) and "units" not in item.attrs:
                missing.append(name)

        results.visititems(visit)
    assert not missing


def test_interrupted_run_keeps_its_completed_steps(tmp_path):
    from refsim.scene import load_scene

    scene = load_scene("cube", ["mesh.cells=[4, 4, 4]", "time.duration=0.4"])
    simulation = Simulation(scene)
    path = tmp_path / "interrupted.h5"

    class Interrupt(Exception):
        pass

    with pytest.raises(Interrupt):
        with ResultWriter(path, scene, simulation.models) as writer:

            def on_step(state, record):
                writer.append(record)
                if record.step == 13:
                    raise Interrupt

            simulation.run(on_step=on_step)
    results = read_results(path)
    assert not results.complete
    assert results.step_count == 13
    np.testing.assert_array_equal(results.step, np.arange(1, 14))


def test_refusals_name_the_file(tmp_path):
    from refsim.scene import load_scene

    scene = load_scene("cube", ["mesh.cells=[2, 2, 2]"])
    simulation = Simulation(scene)
    existing = tmp_path / "existing.h5"
    existing.write_bytes(b"x")
    with pytest.raises((ValueError, FileExistsError), match="existing.h5"):
        ResultWriter(existing, scene, simulation.models)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as handle:
        handle["data"] = np.zeros(3)
    with pytest.raises(ResultsError, match="foreign.h5"):
        read_results(foreign)
    with pytest.raises((ResultsError, FileNotFoundError), match="missing.h5"):
        read_results(tmp_path / "missing.h5")


def test_cut_surface_history_round_trips(tmp_path):
    from refsim.scene import load_scene

    scene = load_scene("cube", ["mesh.cells=[2, 2, 2]"])
    simulation = Simulation(scene)
    path = tmp_path / "cut.h5"
    points = np.array([[0.0, 0.0, 0.05], [0.001, 0.0, 0.05], [0.0, 0.0, 0.051], [0.001, 0.0, 0.051]])
    triangles = np.array([[0, 1, 2], [1, 3, 2]])
    with ResultWriter(path, scene, simulation.models) as writer:
        writer.write_cut_surface(points[:3], np.array([5, 5, 5]), triangles[:1], np.array([5]))
        writer.write_cut_surface(points, np.array([5, 5, 5, 9]), triangles, np.array([5, 9]))
    cut = read_results(path).cut
    np.testing.assert_array_equal(cut.points, points)
    rest, tris = cut.at(6)  # the surface as it was after step 6
    assert len(rest) == 3 and len(tris) == 1


def test_schema_page_is_current():
    page = Path(__file__).resolve().parents[2] / "docs" / "results.md"
    assert page.read_text(encoding="utf-8") == reference_markdown() + "\n", (
        "docs/results.md is stale: regenerate with python -c "
        '"from refsim.io.schema import reference_markdown; print(reference_markdown())" > docs/results.md'
    )
    assert len(all_datasets()) > 20


def test_two_runs_give_the_same_file(tmp_path):
    # Everything but wall-clock times and the creation date is bit-for-bit the same.
    from refsim.cli import main

    paths = [tmp_path / "first.h5", tmp_path / "second.h5"]
    for path in paths:
        assert (
            main(
                [
                    "run",
                    "cube",
                    "-o",
                    str(path),
                    "-q",
                    "--set",
                    "mesh.cells=[4, 4, 4]",
                    "--set",
                    "time.duration=0.5",
                ]
            )
            == 0
        )
    clock = {"steps/stage_seconds", "solver/seconds", "steps/triangulation_seconds"}
    contents = []
    for path in paths:
        data = {}
        with h5py.File(path, "r") as results:

            def visit(name, item, data=data):
                if isinstance(item, h5py.Dataset) and name not in clock:
                    data[name] = item[()]

            results.visititems(visit)
            data["attributes"] = {k: v for k, v in results.attrs.items() if k != "created"}
        contents.append(data)
    first, second = contents
    assert first.keys() == second.keys()
    for name in first:
        if name == "attributes":
            assert first[name].keys() == second[name].keys()
            for key in first[name]:
                assert first[name][key] == second[name][key], key
        else:
            np.testing.assert_array_equal(first[name], second[name], err_msg=name)


def test_criteria_round_trip(short_run):
    # Every criterion the events compared (refsim.simulation.margins) is read back as written, and the
    # reader's event margins are those the run's summary gives from the records.
    from refsim.simulation.summary import RunSummary

    path, records, _ = short_run
    results = read_results(path)
    written = [(r.step, c) for r in records for c in r.criteria]
    assert written, "the short run compares no criterion"
    series = results.criteria
    np.testing.assert_array_equal(series.step, [step for step, _ in written])
    assert list(series.name) == [c.name for _, c in written]
    assert list(series.unit) == [c.unit for _, c in written]
    for field in ("value", "threshold", "accuracy"):
        np.testing.assert_array_equal(getattr(series, field), [getattr(c, field) for _, c in written])
    summary = RunSummary()
    for record in records:
        summary.add(record)
    assert results.event_margins() == summary.event_margins()
    assert [m.name for m in results.event_margins()] == ["puncture"]
