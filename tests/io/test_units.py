"""Units of everything that leaves the program: one source per quantity (refsim.io.schema), the unit of each
event's value carried from the rule that computes it (refsim.simulation.records.Event.unit) into the results
file, the end-of-run summary and the force plot's event table.

Reference: the cut criteria of docs/cutting.md. The energy law starts a cut when the lateral force per
inserted length ‖t‖ / L_in reaches G_c (a force per unit length, N/m = J/m²); the paper's law (equation 3)
when the lateral force per insertion point ‖t‖ / n_i exceeds f_c (a force, N). The recorded cut_start value
must therefore be ≥ G_c in N/m under the first and > f_c in N under the second: a value stored or printed in
the other unit fails one of these bounds or the unit checks.
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from refsim.io import ResultWriter, read_results, schema
from refsim.simulation import Simulation
from refsim.simulation.records import EVENT_UNITS, Event
from refsim.simulation.summary import RunSummary, event_value_text

#: Units a dataset may carry: SI units and their products, "1" for counts, indices and codes, "-" for mixed
#: columns (trajectory samples, whose meaning names each column's unit; criteria values, whose unit is each
#: entry's criteria/unit).
KNOWN_UNITS = {"m", "N", "s", "1", "-", "m/N", "N/m", "m^2", "N/m^2", "Pa", "kg/m^3", "1/s", "m/s"}


def test_every_schema_unit_is_known_and_every_event_unit_has_one_dataset():
    for spec in schema.all_datasets() + list(schema.XDMF.values()):
        assert spec.unit in KNOWN_UNITS, spec.path
    assert set(schema.EVENT_VALUE_DATASETS) == set(EVENT_UNITS)
    for unit, name in schema.EVENT_VALUE_DATASETS.items():
        assert schema.EVENTS[name].unit == unit


def test_an_event_refuses_a_unit_no_dataset_holds():
    with pytest.raises(ValueError, match="unit 'kN'"):
        Event("tear", 1.0, "kN")


def test_the_summary_prints_each_event_with_its_own_unit():
    assert event_value_text(207.9, "N/m") == "force per length 207.9 N/m"
    assert event_value_text(0.8, "N") == "force 0.8 N"


def _run(tmp_path, name, overrides):
    from refsim.scene import load_scene

    scene = load_scene(name, overrides)
    simulation = Simulation(scene)
    path = tmp_path / f"{scene.name}.h5"
    events, summary = [], RunSummary()
    with ResultWriter(path, scene, simulation.models) as writer:

        def on_step(state, record):
            writer.append(record)
            summary.add(record)
            events.extend(record.events)

        simulation.run(on_step=on_step)
    return scene, path, events, summary


_SMALL_CUT = ["mesh.cells=[4, 4, 4]", "output.tissue_every=50"]


@pytest.fixture(scope="module", params=["cube", "cube_cut/energy", "cube_cut/paper"])
def run(request, tmp_path_factory):
    """A real run of each built-in scene (4³ cells), both cutting laws for cube_cut."""
    name, _, law = request.param.partition("/")
    overrides = ["mesh.cells=[4, 4, 4]", "time.duration=0.5"] if name == "cube" else list(_SMALL_CUT)
    if law:
        overrides.append(f'cutting.law="{law}"')
    return (law, *_run(tmp_path_factory.mktemp("units"), name, overrides))


def _spec_of(path: str):
    """The schema entry of a dataset path of a results file (per-step names replaced by NNNNNNN)."""
    parts = path.split("/")
    if parts[0] == schema.PROBLEMS_GROUP:
        return schema.PROBLEM_FIELDS.get("/".join(parts[2:]))
    if parts[0] == schema.XDMF_GROUP:
        key = "/".join("NNNNNNN" if part.isdigit() else part for part in parts[1:])
        return schema.XDMF.get(key)
    for group in (schema.STATIC, schema.STEPS, schema.SOLVER, schema.TISSUE, schema.CONSTRAINTS):
        for spec in group.values():
            if spec.path == path:
                return spec
    return {
        spec.path: spec for spec in (*schema.EVENTS.values(), *schema.CRITERIA.values(), *schema.CUT.values())
    }.get(path)


@pytest.mark.slow
def test_every_dataset_of_a_real_file_carries_its_schema_unit(run):
    law, scene, path, events, summary = run
    from refsim.io.xdmf import write_xdmf

    write_xdmf(path)
    checked = []
    with h5py.File(path, "r") as handle:

        def visit(name, item):
            if isinstance(item, h5py.Dataset):
                spec = _spec_of(name)
                assert spec is not None, f"{name}: not in the schema"
                assert item.attrs["units"] == spec.unit, name
                checked.append(name)

        handle.visititems(visit)
    assert "events/force" in checked and "events/force_per_length" in checked


@pytest.mark.slow
def test_each_event_value_is_stored_read_and_printed_in_the_unit_its_rule_computed(run):
    law, scene, path, events, summary = run
    results = read_results(path)
    assert [(e.name, e.unit) for e in results.events] == [(e.name, e.unit) for e in events]
    with h5py.File(path, "r") as handle:
        for index, event in enumerate(events):
            name = schema.EVENT_VALUE_DATASETS[event.unit]
            stored = handle[f"events/{name}"]
            assert stored.attrs["units"] == event.unit
            np.testing.assert_equal(stored[index], event.force)
            for other_unit, other in schema.EVENT_VALUE_DATASETS.items():
                if other_unit != event.unit:
                    assert np.isnan(handle[f"events/{other}"][index])
    starts = [e for e in events if e.name == "cut_start"]
    if not law:
        assert not starts
        return
    assert len(starts) == 1
    start = starts[0]
    text = summary.format()
    from refsim.viz.plots import event_rows

    plotted = {kind: value for kind, _, _, value in event_rows(results)}  # the force plot's event table
    if law == "energy":
        # ‖t‖ / L_in ≥ G_c, in N/m; G_c = 200 J/m² is two hundred times any lateral force of this run in N.
        assert start.unit == "N/m" and start.force >= scene.cutting.fracture_energy
        assert f"cut_start  force per length {start.force:.4g} N/m" in text
        assert plotted["cut_start"].endswith(" N/m")
    else:
        # ‖t‖ / n_i > f_c, in N.
        assert start.unit == "N" and start.force > scene.cutting.cutting_force
        assert f"cut_start  force {start.force:.4g} N" in text
        assert plotted["cut_start"].endswith(" N") and "N/m" not in plotted["cut_start"]
    assert all(e.unit == "N" for e in events if e.name in ("puncture", "tear"))


def test_a_file_of_before_force_per_length_reads_its_energy_cut_start_in_n_per_m(cut_run, tmp_path):
    """A file written before events/force_per_length held every event value in events/force; its scene says
    the law, and under the energy law the cut_start value is a force per unit length."""
    import shutil

    legacy = tmp_path / "legacy.h5"
    shutil.copy(cut_run, legacy)
    with h5py.File(legacy, "a") as handle:
        per_length = handle["events/force_per_length"][()]
        force = handle["events/force"][()]
        merged = np.where(np.isfinite(per_length), per_length, force)
        del handle["events/force_per_length"], handle["events/force"]
        handle.create_dataset("events/force", data=merged).attrs["units"] = "N"
    new, old = read_results(cut_run), read_results(legacy)
    assert [(e.name, e.force, e.unit) for e in old.events] == [(e.name, e.force, e.unit) for e in new.events]
    assert [e.unit for e in old.events if e.name == "cut_start"] == ["N/m"]
