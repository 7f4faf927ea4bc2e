"""The per-instrument step quantities are one table, ``refsim.io.schema.INSTRUMENT_STEP_QUANTITIES``: each row
is a ``steps/`` dataset of every instrument with the row's unit, dtype and shape, written from the
``InstrumentRecord`` attribute it names; a ``StepRecord`` reads the first instrument's fields through."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from refsim.io import schema
from refsim.simulation.records import InstrumentRecord, StepRecord, WithinStep


def test_every_step_quantity_is_an_instrument_dataset_of_its_row():
    for quantity in schema.INSTRUMENT_STEP_QUANTITIES:
        spec = schema.STEPS[quantity.name]
        assert spec.path in schema.INSTRUMENT_DATASETS
        assert (spec.unit, spec.dtype, spec.entry_shape) == (
            quantity.unit,
            quantity.dtype,
            quantity.entry_shape,
        )
        first, *rest = quantity.attribute.split(".")
        assert first in InstrumentRecord.__dataclass_fields__
        if rest:  # read through the within-step state, which a step may not have
            assert rest == [rest[0]] and rest[0] in WithinStep.__dataclass_fields__
    names = [quantity.name for quantity in schema.INSTRUMENT_STEP_QUANTITIES]
    assert len(set(names)) == len(names)


def test_a_within_step_quantity_is_nan_in_a_step_without_the_event_and_its_value_in_one():
    # Reference: schema.WITHIN_STEP_QUANTITIES (NaN in steps without a within-step event).
    part = _part("needle", 0.5)
    within = WithinStep(
        event="puncture",
        needle_force=np.array([0.0, 0.0, 0.8]),
        tip_force=np.array([0.0, 0.1, 0.8]),
        point=np.array([0.0, 0.0, 0.1]),
    )
    held = replace(part, within_step=within)
    for quantity in schema.WITHIN_STEP_QUANTITIES:
        assert quantity.since == 2
        assert np.isnan(quantity.value(part)).all() and quantity.value(part).shape == quantity.entry_shape
        field = quantity.attribute.split(".")[1]
        assert quantity.value(held) is getattr(within, field)


def _part(name: str, force: float) -> InstrumentRecord:
    return InstrumentRecord(
        name=name,
        phase="insertion",
        events=(),
        base_position=np.zeros(3),
        needle_positions=np.zeros((2, 3)),
        needle_frames=np.tile(np.eye(3), (2, 1, 1)),
        needle_force=np.array([force, 0.0, 0.0]),
        insertion_point_count=3,
    )


def _record(*parts: InstrumentRecord) -> StepRecord:
    empty = np.zeros(0)
    return StepRecord(
        step=1,
        time=0.01,
        tissue_positions=None,
        row_kind=empty,
        row_source=empty,
        row_points=np.zeros((0, 3)),
        row_directions=np.zeros((0, 3)),
        row_forces=empty,
        solver=None,
        instruments=parts,
    )


def test_a_step_record_reads_its_first_instrument():
    record = _record(_part("first", 1.0), _part("second", 2.0))
    for name in InstrumentRecord.__dataclass_fields__:
        if name != "name":
            assert getattr(record, name) is getattr(record.instruments[0], name)
    changed = record.with_first(needle_force=np.array([5.0, 0.0, 0.0]))
    assert changed.needle_force[0] == 5.0 and changed.instruments[1].needle_force[0] == 2.0
    assert record.needle_force[0] == 1.0  # the record itself is unchanged
    with pytest.raises(AttributeError, match="no attribute 'not_a_field'"):
        _ = record.not_a_field
