"""The puncture step's two states (docs/coupling.md, "The puncture step"; docs/results.md): the capped tip
contact gives way at f_p inside the step, the step is solved again with the insertion phase's rows, and its
record holds both: the give-way (``StepRecord.within_step``) and the end of the step (every other field)."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.constraints import PENETRATION, TIP
from refsim.scene import load_scene
from refsim.simulation import Simulation
from refsim.simulation.margins import CriterionSeries, assess

ENTRY = (0.00123, 0.00231)
TOP = 0.1
NEEDLE_LENGTH = 0.32


def _straight_entry(*overrides):
    """The cube on 4³ cells, a vertical needle whose tip goes from 1 nm above the top face to 0.5 mm below it
    in 0.15 s at dt = 1 ms (the normal force builds over tens of steps before f_p)."""
    fmt = lambda v: "[" + ", ".join(repr(float(x)) for x in v) + "]"  # noqa: E731
    bases = [np.array([*ENTRY, TOP - d + NEEDLE_LENGTH]) for d in (-1e-9, 5e-4)]
    scene = load_scene(
        "cube",
        [
            "mesh.cells=[4, 4, 4]",
            "time.dt=0.001",
            "time.duration=0.15",
            "trajectory.times=[0.0, 0.15]",
            "trajectory.base_positions=[" + ", ".join(fmt(b) for b in bases) + "]",
            "trajectory.directions=[[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]]",
            *overrides,
        ],
    )
    records = []
    Simulation(scene).run(on_step=lambda state, record: records.append(record))
    return scene, records


@pytest.fixture(scope="module")
def straight_entry():
    return _straight_entry()


def test_a_puncture_steps_record_holds_the_give_way_at_f_p_and_the_end_of_the_step(straight_entry):
    # Reference: the capped tip contact carries f_p when it gives way (insertion.puncture_within_step), to the
    # solve's accuracy (the puncture criterion's, refsim.simulation.margins); after it, the step solved again
    # holds the tip by its cutting row, capped at f_cut < f_p (insertion.tip_cutting_force), and the entry
    # point's rows: the end of the step records no tip contact, and its force is Σ λ n over its own rows.
    scene, records = straight_entry
    f_p, f_cut = scene.insertion.puncture_force, scene.insertion.tip_cutting_force
    assert f_cut < f_p
    held = [r for r in records if r.within_step is not None]
    punctured = [r for r in records if any(e.name == "puncture" for e in r.events)]
    assert len(punctured) == 1 and held == punctured
    record = held[0]
    within = record.within_step
    assert within.event == "puncture"
    series = CriterionSeries.of(
        [r.step for r in records for _ in r.criteria], [c for r in records for c in r.criteria]
    )
    (margin,) = assess([(r.step, e.name) for r in records for e in r.events], series)
    accuracy = margin.at_event.accuracy
    assert accuracy < 1e-2 * f_p
    # The give-way: the tip contact's normal force is f_p along the top face's normal (+z).
    assert abs(within.tip_force[2] - f_p) <= accuracy
    # A vertical entry on the needle's only rows: the needle force of the give-way is the tip's.
    assert abs(within.needle_force[2] - f_p) <= accuracy + np.linalg.norm(within.tip_force[:2])
    assert abs(within.point[2] - TOP) < 1e-3  # on the top face (its indentation: µm)
    # The end of the step: no tip contact row, the tip's cutting row at most f_cut, and the force of its rows.
    assert not np.any((record.row_source == PENETRATION) & (record.row_role != TIP))
    tip = record.row_role == TIP
    assert np.count_nonzero(tip) == 1 and record.row_forces[tip][0] <= f_cut * (1 + 1e-6)
    end = (record.row_directions * record.row_forces[:, None]).sum(axis=0)
    np.testing.assert_allclose(record.needle_force, end, rtol=0, atol=1e-12)
    assert record.needle_force[2] < f_p - 10 * accuracy  # released below the peak
    # The criteria recorded are the give-way's (the puncture's, asked above f_p).
    assert margin.at_event.value >= f_p - accuracy


def test_the_steps_without_a_within_step_event_record_none(straight_entry):
    _, records = straight_entry
    assert sum(r.within_step is not None for r in records) == 1
    assert all(r.within_step is None for r in records if not r.events)


def test_a_plain_tip_contact_holds_the_tip_to_the_steps_end_and_records_no_within_step_event():
    # Reference: without the cap (insertion.puncture_within_step = false) the puncture is decided after the
    # step, on a contact that held the tip throughout it: nothing gives way inside the step.
    _, records = _straight_entry("insertion.puncture_within_step=false")
    assert any(e.name == "puncture" for r in records for e in r.events)
    assert all(r.within_step is None for r in records)
