"""Insertion rows on a hand-made box, for a tilted needle and for entries on a face, an edge and a vertex."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.constraints import BILATERAL, FRICTION, InsertionPath, insertion_block
from refsim.geometry import TetLocator
from tests.constraints.conftest import rigid_needle, still_geometry


def _path(mesh, points):
    tets, bary = TetLocator(mesh.rest_positions, mesh.tets).locate(np.asarray(points, dtype=float))
    assert np.all(tets >= 0)
    return InsertionPath.empty().appended(tets, bary, 1)


@pytest.mark.parametrize(
    "entry",
    [
        [0.0123, 0.0071, 0.02],  # inside a face
        [0.01, 0.0071, 0.02],  # on a mesh edge (x = 0.01 is a grid plane)
        [0.01, 0.01, 0.02],  # on a mesh vertex
    ],
)
@pytest.mark.parametrize("tilt", [0.0, 30.0])
def test_lateral_rows_are_normal_to_the_needle_and_measure_the_offset(block, entry, tilt):
    angle = np.radians(tilt)
    direction = np.array([np.sin(angle), 0.0, -np.cos(angle)])
    entry = np.asarray(entry, dtype=float)
    points = entry + np.outer([1e-9, 2e-3, 4e-3], direction)
    path = _path(block, points)
    tip = entry + 5e-3 * direction
    previous = rigid_needle(tip, direction)
    shift = np.array([1e-4, -2e-4, 5e-5])
    free = rigid_needle(tip + shift, direction)
    rows = insertion_block(
        path, still_geometry(block, previous, needle_free=free), friction_coefficient=0.2, normal_preload=0.01
    )
    kinds = rows.kind.reshape(3, 3)
    assert np.all(kinds[:, :2] == BILATERAL) and np.all(kinds[:, 2] == FRICTION)
    directions = rows.directions.reshape(3, 3, 3)
    np.testing.assert_allclose(directions[:, :2] @ direction, 0.0, atol=1e-15)
    np.testing.assert_allclose(directions[:, 2], np.broadcast_to(direction, (3, 3)), atol=1e-15)
    gaps = rows.free_gap.reshape(3, 3)
    np.testing.assert_allclose(gaps[:, :2], directions[:, :2] @ shift, atol=1e-15)
    np.testing.assert_allclose(gaps[:, 2], shift @ direction, atol=1e-15)
    np.testing.assert_array_equal(rows.shaft_pairs, [[0, 1], [3, 4], [6, 7]])
    np.testing.assert_allclose(rows.shaft_normal_preload, 0.01)


def test_without_friction_only_the_lateral_rows(block):
    path = _path(block, [[0.0123, 0.0071, 0.015]])
    needle = rigid_needle([0.0123, 0.0071, 0.01], [0.0, 0.0, -1.0])
    rows = insertion_block(path, still_geometry(block, needle), friction_coefficient=0.0)
    assert rows.row_count == 2 and rows.shaft_rows.size == 0


def test_a_negative_preload_is_rejected(block):
    path = _path(block, [[0.0123, 0.0071, 0.015]])
    needle = rigid_needle([0.0123, 0.0071, 0.01], [0.0, 0.0, -1.0])
    with pytest.raises(ValueError, match="normal_preload"):
        insertion_block(path, still_geometry(block, needle), friction_coefficient=0.1, normal_preload=-1.0)
