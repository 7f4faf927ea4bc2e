"""The record-to-datasets conversion of a results file (refsim.io.step_values), on its own."""

import numpy as np
import pytest

from refsim.io.step_values import StepValues, check_shape


def test_check_shape_names_the_file_the_field_and_both_shapes():
    assert check_shape("out.h5", "row_points", np.zeros((2, 3)), (None, 3)).shape == (2, 3)
    with pytest.raises(ValueError, match=r"out\.h5: row_points has shape \(2, 2\), expected \(any, 3\)"):
        check_shape("out.h5", "row_points", np.zeros((2, 2)), (None, 3))
    with pytest.raises(ValueError, match=r"out\.h5: row_kind is not a numeric array"):
        check_shape("out.h5", "row_kind", ["a"], (1,), dtype=np.int8)


def test_a_record_with_another_instrument_count_than_the_file_is_refused():
    class Record:
        step, time, events, criteria, tissue_positions, solver = 3, 0.03, (), (), None, None
        row_forces, row_kind, row_source = np.zeros(0), np.zeros(0), np.zeros(0)
        row_points = row_directions = np.zeros((0, 3))
        instruments = ()

    values = StepValues(
        "out.h5", (), {"n": 4, "k": 2, "b": 1}, np.zeros(0, np.int64), [("a", ""), ("b", "x")]
    )
    with pytest.raises(ValueError, match=r"out\.h5: step 3 has 0 instruments, the file 2 \(a, b\)"):
        values._instrument_values(Record, count=0)
