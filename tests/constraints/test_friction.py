"""Friction rows built from normal rows' anchors: slip gaps and Jacobians on a hand-made box."""

from __future__ import annotations

import numpy as np

from refsim.constraints import NEEDLE, TISSUE, InsertionPath, friction_rows, slip_gaps, stick_offsets
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
    assert NEEDLE not in rows.jacobians  # a rigid needle is kinematic: no DoFs, no Jacobian
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
        rows.jacobians[TISSUE] @ motion.ravel(), again.free_gap - rows.free_gap, atol=1e-18
    )


def _held_spring(steps: int, *, anchored: bool, compliance: float, subgrid: float, push: float):
    """A 1-D stuck friction row in series with a sub-grid spring: a rigid needle along +x moved by ``push``
    [m] in the first step then held; the tissue point is a quasi-static spring of compliance W [m/N] (its
    free motion returns it to rest), the row carries the sub-grid compliance C [m/N]. Returns λ per step [N].

    The simulation's update, by hand: the row's gap is the slip over the step plus, when ``anchored``, the
    offset D from the stick anchor (:func:`stick_offsets`); stuck, δ = (W + C) λ + δ_free = 0; the tissue is
    corrected by −W λ (the row pushes the tissue along −n); the anchor is kept."""
    direction = np.array([[1.0, 0.0, 0.0]])
    base, tissue = 0.0, 0.0  # needle base and tissue point along x [m]
    anchors, forces = np.array([np.nan]), []
    for step in range(steps):
        new_base = base + (push if step == 0 else 0.0)
        arc = np.array([tissue - base])  # the point's projection on the needle at the start of the step
        offsets, anchors = stick_offsets(
            arc,
            needle_points=np.array([[tissue, 0.0, 0.0]]),
            tangents=direction,
            tissue_points=np.array([[tissue, 0.0, 0.0]]),
            anchors=anchors,
            stretch=np.zeros(1),
        )
        free = 0.0  # quasi-static free motion: the unloaded spring is at rest
        slip = (new_base - base) - (free - tissue)
        gap = slip + (offsets[0] if anchored else 0.0)
        force = -gap / (compliance + subgrid)
        base, tissue = new_base, free - compliance * force
        forces.append(force)
    return np.array(forces)


def test_a_stuck_row_in_series_with_its_subgrid_spring_keeps_its_load():
    # Closed form: a needle moved by u against a spring W in series with the annulus C, stuck, holds
    # λ = −u / (W + C) for as long as it is held. Measured over the step alone (no anchor) the row slips by
    # C λ per step and forgets it: λ decays by W / (W + C) every step.
    compliance, subgrid, push = 2e-4, 1e-4, 1e-4
    held = _held_spring(200, anchored=True, compliance=compliance, subgrid=subgrid, push=push)
    expected = -push / (compliance + subgrid)
    np.testing.assert_allclose(held, expected, rtol=1e-12)
    crept = _held_spring(4, anchored=False, compliance=compliance, subgrid=subgrid, push=push)
    ratio = compliance / (compliance + subgrid)
    np.testing.assert_allclose(crept, expected * ratio ** np.arange(4), rtol=1e-12)


def test_stick_offsets_place_unset_anchors_at_the_annulus_stretch():
    # A bent needle's point: tissue 0.3 mm off its projection along the tangent; a set anchor gives
    # D = e + s_a − s, an unset one (NaN) D = the stretch given.
    arcs = np.array([0.010, 0.020])
    tangents = np.array([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8]])
    needle = np.array([[0.0, 0.0, 0.01], [0.0, 0.012, 0.016]])
    tissue = needle - 3e-4 * tangents
    offsets, anchors = stick_offsets(
        arcs,
        needle_points=needle,
        tangents=tangents,
        tissue_points=tissue,
        anchors=np.array([0.0105, np.nan]),
        stretch=np.array([0.0, -2e-5]),
    )
    np.testing.assert_allclose(offsets, [3e-4 + 0.0005, -2e-5], atol=1e-15)
    np.testing.assert_allclose(anchors, [0.0105, 0.020 - 3e-4 - 2e-5], atol=1e-15)


def test_friction_gaps_alone_are_the_gaps_of_the_rows(block):
    # A builder that makes the Jacobians itself (the ring coupling) takes the gaps alone: the same bits.
    from refsim.constraints.friction import friction_gaps

    rng = np.random.default_rng(8)
    points = np.array([[0.0111, 0.0092, 0.015], [0.0111, 0.0092, 0.011]])
    tets, bary = TetLocator(block.rest_positions, block.tets).locate(points)
    previous = rigid_needle([0.0111, 0.0092, 0.005], [0.0, 0.0, -1.0])
    free = rigid_needle([0.0112, 0.0091, 0.0047], [0.0, 0.0, -1.0])
    moved = block.rest_positions + 1e-5 * rng.normal(size=block.rest_positions.shape)
    geometry = still_geometry(block, previous, needle_free=free, tissue_free=moved)
    arcs, _ = previous.project(points)
    tangents = np.broadcast_to([0.0, 0.0, -1.0], (2, 3))
    offsets = np.array([1e-4, -2e-4])
    nodes = block.tets[tets]
    rows = friction_rows(
        geometry,
        tissue_nodes=nodes,
        tissue_weights=bary,
        arc_lengths=arcs,
        tangents=tangents,
        offsets=offsets,
    )
    tissue_previous, tissue_free = geometry.tissue_points(nodes, bary)
    gaps = friction_gaps(
        geometry,
        arc_lengths=arcs,
        tangents=tangents,
        tissue_free=tissue_free,
        tissue_previous=tissue_previous,
        offsets=offsets,
    )
    np.testing.assert_array_equal(gaps, rows.free_gap)
