"""Trajectory and boundary-motion CSV files (refsim.scene.trajectory.read_numeric_csv): a header must name the
columns in their order (the values are read by position), a bad line is named by its line number in the file,
and a file that is not text is named; what is accepted reads the same as before."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.scene.trajectory import read_numeric_csv, read_trajectory_csv

ROWS = "0,0,0,0.4,0,0,-1\n1,0,0,0.39,0,0,-1\n"
HEADER = "t,x,y,z,dx,dy,dz\n"


@pytest.mark.parametrize(
    ("text", "fragments"),
    [
        # dx and dz swapped: before, read by position without a word (a needle pointing along x)
        ("t,x,y,z,dz,dy,dx\n" + ROWS, ["line 1", "header 't,x,y,z,dz,dy,dx'", "t, x, y, z, dx, dy, dz"]),
        ("x,y,z,t,dx,dy,dz\n" + ROWS, ["line 1", "in this order"]),
        ("t;x;y;z;dx;dy;dz\n" + ROWS.replace(",", ";"), ["line 1", "header"]),
        ("# planner\n" + HEADER + "0,0,0,0.4,0,0,-1\n1,0,0,abc,0,0,-1\n", ["line 4", "'1,0,0,abc,0,0,-1'"]),
        (HEADER + ROWS + "2,0,0\n", ["line 4", "expected 7 numbers"]),  # before: numpy's message, no file
        (HEADER + HEADER + ROWS, ["line 2", "expected 7 numbers"]),
        (HEADER + "0,0,0,0.4,0,0,-1\n1,0,0,nan,0,0,-1\n", ["line 3", "non-finite"]),
        (HEADER, ["no rows of numbers"]),
        ("", ["no rows of numbers"]),
    ],
)
def test_a_bad_trajectory_csv_is_named_with_its_line(tmp_path, text, fragments):
    path = tmp_path / "robot.csv"
    path.write_text(text)
    with pytest.raises(ValueError) as error:
        read_trajectory_csv(path)
    message = str(error.value)
    assert message.startswith(f"{path}: ")
    for fragment in fragments:
        assert fragment in message


def test_a_binary_file_is_named(tmp_path):
    path = tmp_path / "robot.csv"
    path.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(
        ValueError, match=r"robot\.csv: not a text \(UTF-8\) CSV file"
    ):  # before: no file named
        read_trajectory_csv(path)


@pytest.mark.parametrize(
    "text",
    [
        HEADER + ROWS,
        ROWS,  # no header
        "\ufeff# exported\nT [s], X [m], Y [m], Z [m], DX, DY, DZ\n\n" + ROWS,  # a BOM, units, upper case
        "# a\n" + HEADER + "# b\n" + ROWS,
    ],
)
def test_accepted_files_read_their_values(tmp_path, text):
    path = tmp_path / "robot.csv"
    path.write_text(text, encoding="utf-8")
    trajectory = read_trajectory_csv(path)
    np.testing.assert_array_equal(trajectory.times, [0.0, 1.0])
    np.testing.assert_array_equal(trajectory.base_positions[:, 2], [0.4, 0.39])


def test_the_boundary_motion_columns_are_checked_too(tmp_path):
    path = tmp_path / "motion.csv"
    path.write_text("t,dz,dy,dx\n0,0,0,0\n1,0,0,0.01\n")
    with pytest.raises(ValueError, match="expected the columns t, dx, dy, dz"):
        read_numeric_csv(path, ("t", "dx", "dy", "dz"), "boundary motion")
