"""The within-step event in the results file (schema version 2, docs/results.md "A step's end and its
within-step event"): written from the step record, read back, NaN in the other steps; a version-1 file
(without it) is still read, by its stated rule."""

from __future__ import annotations

import shutil

import h5py
import numpy as np
import pytest

from refsim.io import read_results, schema
from refsim.io.driver import run_scene
from refsim.io.export import FORCE_COLUMNS, export_force_csv
from refsim.io.reader import ResultsError
from refsim.scene import load_scene

TOP = 0.1


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """The 4³ cube, a vertical needle from 1 nm above the top face to 0.5 mm below it (dt = 1 ms): one
    puncture through the capped tip contact. The file and the step records."""
    fmt = lambda v: "[" + ", ".join(repr(float(x)) for x in v) + "]"  # noqa: E731
    bases = [np.array([0.00123, 0.00231, TOP - d + 0.32]) for d in (-1e-9, 5e-4)]
    scene = load_scene(
        "cube",
        [
            "mesh.cells=[4, 4, 4]",
            "time.dt=0.001",
            "time.duration=0.15",
            "trajectory.times=[0.0, 0.15]",
            "trajectory.base_positions=[" + ", ".join(fmt(b) for b in bases) + "]",
            "trajectory.directions=[[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]]",
        ],
    )
    path = tmp_path_factory.mktemp("within") / "entry.h5"
    records = []
    run_scene(scene, path, on_step=lambda state, record: records.append(record), handle_signals=False)
    return path, records


def test_the_within_step_state_is_written_read_back_and_nan_elsewhere(written):
    path, records = written
    results = read_results(path)
    assert results.attributes["schema_version"] == schema.SCHEMA_VERSION == 3
    (index,) = [i for i, r in enumerate(records) if r.within_step is not None]
    within = records[index].within_step
    np.testing.assert_array_equal(results.event_needle_force[index], within.needle_force)
    np.testing.assert_array_equal(results.event_tip_force[index], within.tip_force)
    np.testing.assert_array_equal(results.event_point[index], within.point)
    np.testing.assert_array_equal(results.needle_force[index], records[index].needle_force)  # the end
    others = np.arange(results.step_count) != index
    for name in ("event_needle_force", "event_tip_force", "event_point"):
        assert np.isnan(getattr(results, name)[others]).all()
    # The force profile: the give-way in the puncture step, the end force elsewhere.
    np.testing.assert_array_equal(results.profile_force[index], within.needle_force)
    np.testing.assert_array_equal(results.profile_force[others], results.needle_force[others])
    # The puncture point is where the contact gave way.
    np.testing.assert_array_equal(results.puncture_point(), within.point)


def test_a_version_1_file_is_read_with_nan_event_quantities_and_its_needle_force_as_the_profile(
    written, tmp_path
):
    # Reference: SUPPORTED_SCHEMA_VERSIONS and the rule of docs/results.md: a version-1 file has no
    # steps/event_*; they read as NaN and the profile is steps/needle_force (that version's puncture step
    # ended at the give-way).
    path, _ = written
    old = tmp_path / "old.h5"
    shutil.copy(path, old)
    with h5py.File(old, "r+") as handle:
        for quantity in schema.WITHIN_STEP_QUANTITIES:
            del handle[schema.STEPS[quantity.name].path]
        handle.attrs["schema_version"] = 1
    results = read_results(old)
    for quantity in schema.WITHIN_STEP_QUANTITIES:
        values = getattr(results, quantity.name)
        assert values.shape == (results.step_count, *quantity.entry_shape) and np.isnan(values).all()
    np.testing.assert_array_equal(results.profile_force, results.needle_force)
    assert results.puncture_point() is not None


def test_the_needle_strain_is_written_each_step_and_nan_in_a_version_2_file(written, tmp_path):
    # Reference: InstrumentRecord.needle_strain (0 for this rigid needle) written as steps/needle_strain
    # (schema version 3); a version-2 file lacks the dataset and reads it as NaN (StepQuantity.since).
    path, records = written
    results = read_results(path)
    np.testing.assert_array_equal(results.needle_strain, [r.needle_strain for r in records])
    assert not results.needle_strain.any()
    old = tmp_path / "version2.h5"
    shutil.copy(path, old)
    with h5py.File(old, "r+") as handle:
        del handle[schema.STEPS["needle_strain"].path]
        handle.attrs["schema_version"] = 2
    older = read_results(old)
    assert older.needle_strain.shape == (older.step_count,) and np.isnan(older.needle_strain).all()
    np.testing.assert_array_equal(older.needle_force, results.needle_force)


def test_a_file_of_a_newer_version_is_refused_by_name(written, tmp_path):
    path, _ = written
    newer = tmp_path / "newer.h5"
    shutil.copy(path, newer)
    with h5py.File(newer, "r+") as handle:
        handle.attrs["schema_version"] = schema.SCHEMA_VERSION + 1
    with pytest.raises(ResultsError, match="schema version 4 is not supported"):
        read_results(newer)


def test_the_force_csv_carries_the_event_force_beside_the_end_force(written, tmp_path):
    path, records = written
    output = export_force_csv(path, tmp_path / "force.csv")
    lines = output.read_text().splitlines()
    assert lines[0].split(",") == list(FORCE_COLUMNS)
    rows = [dict(zip(FORCE_COLUMNS, line.split(","), strict=True)) for line in lines[1:]]
    (index,) = [i for i, r in enumerate(records) if r.within_step is not None]
    assert float(rows[index]["event_force_z_N"]) == pytest.approx(records[index].within_step.needle_force[2])
    assert float(rows[index]["force_z_N"]) == pytest.approx(records[index].needle_force[2])
    assert all(np.isnan(float(row["event_force_z_N"])) for i, row in enumerate(rows) if i != index)
