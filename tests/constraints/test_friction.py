"""Friction rows built from normal rows' anchors: slip gaps and Jacobians on a hand-made box."""

from __future__ import annotations

import numpy as np

from refsim.constraints import InsertionPath, friction_rows, slip_gaps
from refsim.geometry import TetLocator
from tests.constraints.conftest import rigid_needle, still_geometry


def test_slip_is_the_relative_tangential_motion_over_the_step():
    tangents = np.array([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8]])
    gaps = slip_gaps(
        tangents,
        needle_free=np.array([[1.0, 2.0, 3.0], [0.0, 1.0, 1.0]]),
        needle_previous=np.array([[0.5, 2.0, 3.0], [0.0, 0.0, 0.0]]),
        tissue_free=np.array([[0.2, 0.0, 0.0], [0.0, 0.5, 0.5]]),
        tissue_previous=np.zeros((2, 3)),
    )
    np.testing.assert_allclose(gaps, [0.5 - 0.2, 0.6 * 0.5 + 0.8 * 0.5], atol=1e-15)


def test_rows_anchored_at_tissue_points_linearise_the_slip(block):
    # The slip is affine in the tissue positions (fixed barycentric anchors): H_tissue Δx = Δδ to round-off.
    rng = np.random.default_rng(3)
    points = np.array([[0.0111, 0.0092, 0.015], [0.0111, 0.0092, 0.011], [0.0111, 0.0092, 0.007]])
    tets, bary = TetLocator(block.rest_positions, block.tets).locate(points)
    path = InsertionPath.empty().appended(tets, bary, 1)
    previous = rigid_needle([0.0111, 0.0092, 0.005], [0.0, 0.0, -1.0])
    free = rigid_needle([0.0111, 0.0092, 0.0047], [0.0, 0.0, -1.0])  # 0.3 mm deeper
    tangents = np.broadcast_to([0.0, 0.0, -1.0], (3, 3))
    arcs, _ = previous.project(points)
    geometry = still_geometry(block, previous, needle_free=free)
    rows = friction_rows(
        geometry,
        tissue_nodes=block.tets[path.tets],
        tissue_weights=path.barycentric,
        arc_lengths=arcs,
        tangents=tangents,
    )
    np.testing.assert_allclose(rows.free_gap, 3e-4, atol=1e-15)
    assert rows.needle_jacobian is None  # a rigid needle is kinematic
    motion = 1e-5 * rng.normal(size=block.rest_positions.shape)
    moved = still_geometry(block, previous, needle_free=free, tissue_free=block.rest_positions + motion)
    again = friction_rows(
        moved,
        tissue_nodes=block.tets[path.tets],
        tissue_weights=path.barycentric,
        arc_lengths=arcs,
        tangents=tangents,
    )
    np.testing.assert_allclose(
        rows.tissue_jacobian @ motion.ravel(), again.free_gap - rows.free_gap, atol=1e-18
    )
