"""`refsim compare`'s CSV of their results (refsim.reference.read_their_csv): values must be finite numbers
(a NaN was dropped from a curve and interpolated over, or scored as a failure), a scalar's x empty, a file
that is a folder or not text named; a spreadsheet's byte-order mark is read. No reference package is needed:
the file is read against the case's quantities."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.reference import load_case, read_their_csv, write_their_csv


@pytest.fixture
def good(tmp_path):
    case = load_case("puncture")
    at = case.quantity("indentation_force").at
    values = {
        "indentation_force": np.linspace(0.1, 0.8, len(at)),
        "travel_at_puncture": 1e-3,
        "puncture_force": 0.8,
    }
    path = write_their_csv(case, values, tmp_path / "theirs.csv")
    return case, path


@pytest.mark.parametrize(
    ("old", "new", "fragments"),
    [
        ("puncture_force,,0.8", "puncture_force,,nan", ["column value: 'nan': expected a finite number"]),
        ("puncture_force,,0.8", "puncture_force,,inf", ["column value: 'inf'"]),
        (
            "puncture_force,,0.8",
            "puncture_force,0.001,0.8",
            ["column x: '0.001' for the scalar 'puncture_force'"],
        ),
        (",0.1\n", ",nan\n", ["column value: 'nan'"]),  # the curve's first value: before, dropped silently
    ],
)
def test_non_finite_values_and_misplaced_x_are_named(good, old, new, fragments):
    case, path = good
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(ValueError) as error:
        read_their_csv(path, case)
    message = str(error.value)
    assert message.startswith(f"{path}: line ")
    for fragment in fragments:
        assert fragment in message


def test_a_curve_abscissa_that_is_not_finite_is_named(good):
    case, path = good
    lines = path.read_text().splitlines()
    name, _, value = lines[2].split(",")
    lines[2] = f"{name},nan,{value}"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"line 3, column x: 'nan': expected a finite number"):
        read_their_csv(path, case)


def test_a_byte_order_mark_is_read(good):
    case, path = good
    expected = read_their_csv(path, case)
    path.write_text("\ufeff" + path.read_text(), encoding="utf-8")  # before: "missing column 'quantity'"
    again = read_their_csv(path, case)
    for name, values in expected.items():
        np.testing.assert_array_equal(again[name], values)


def test_a_folder_or_a_binary_file_is_named(good, tmp_path):
    case, _ = good
    folder = tmp_path / "folder.csv"
    folder.mkdir()
    with pytest.raises(ValueError, match=r"folder\.csv: is a directory"):
        read_their_csv(folder, case)
    binary = tmp_path / "binary.csv"
    binary.write_bytes(b"\xff\xfe\x00\x01")
    with pytest.raises(ValueError, match=r"binary\.csv: not a text \(UTF-8\) CSV file"):
        read_their_csv(binary, case)
