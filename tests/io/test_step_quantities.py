"""The per-instrument step quantities are one table, ``refsim.io.schema.INSTRUMENT_STEP_QUANTITIES``: each row
is a ``steps/`` dataset of every instrument with the row's unit, dtype and shape, written from the
``InstrumentRecord`` attribute it names; a ``StepRecord`` reads the first instrument's fields through."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.io import schema
from refsim.simulation.records import InstrumentRecord, StepRecord


def test_every_step_quantity_is_an_instrument_dataset_of_its_row():
    for quantity in schema.INSTRUMENT_STEP_QUANTITIES:
        spec = schema.STEPS[quantity.name]
        assert spec.path in schema.INSTRUMENT_DATASETS
        assert (spec.unit, spec.dtype, spec.entry_shape) == (
            quantity.unit,
            quantity.dtype,
            quantity.entry_shape,
        )
        assert quantity.attribute in InstrumentRecord.__dataclass_fields__
    names = [quantity.name for quantity in schema.INSTRUMENT_STEP_QUANTITIES]
    assert len(set(names)) == len(names)


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
