"""Penetration rows on a hand-made box: the contact normal's switch, the gaps and their Jacobians."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.constraints import (
    FRICTION,
    TISSUE,
    UNILATERAL,
    find_surface_contact,
    penetration_block,
)
from refsim.geometry import SurfaceProjector
from tests.constraints.conftest import rigid_needle, still_geometry

_geometry = still_geometry
_needle = rigid_needle


def _contact(mesh, tip):
    projector = SurfaceProjector(mesh.rest_positions, mesh.boundary_faces)
    return find_surface_contact(projector, mesh.boundary_faces, np.asarray(tip, dtype=float))


def test_above_a_face_the_normal_is_the_face_normal(block):
    contact = _contact(block, [0.0123, 0.0071, 0.0205])
    np.testing.assert_allclose(contact.normal, [0.0, 0.0, 1.0], atol=1e-12)
    assert contact.gap == pytest.approx(0.0005, abs=1e-15)
    np.testing.assert_allclose(contact.point, [0.0123, 0.0071, 0.02], atol=1e-15)


def test_beyond_an_edge_the_normal_points_from_the_edge_to_the_tip(block):
    # Tip outside the top-right edge (x = 0.02, z = 0.02): the closest point is on the edge, and no face
    # normal is right there; the row's normal must be the edge-to-tip direction (the contact-normal switch).
    tip = np.array([0.0203, 0.011, 0.0204])
    contact = _contact(block, tip)
    expected = np.array([0.0003, 0.0, 0.0004]) / 0.0005
    np.testing.assert_allclose(contact.normal, expected, atol=1e-9)
    assert contact.gap == pytest.approx(0.0005, rel=1e-9)


@pytest.mark.parametrize("depth", [0.0, 1e-12, 3e-4])
def test_under_or_on_the_surface_the_face_normal_is_used_and_the_gap_is_negative(block, depth):
    contact = _contact(block, [0.0123, 0.0071, 0.02 - depth])
    np.testing.assert_allclose(contact.normal, [0.0, 0.0, 1.0], atol=1e-12)
    assert contact.gap == pytest.approx(-depth, abs=1e-15)


@pytest.mark.parametrize("friction", [0.0, 0.3])
def test_rows_gaps_and_kinds(block, friction):
    tip = np.array([0.0123, 0.0071, 0.0203])
    previous = _needle(tip, [0.0, 0.0, -1.0])
    moved = _needle(tip + [2e-4, -1e-4, -5e-4], [0.0, 0.0, -1.0])  # down and sideways over the step
    contact = _contact(block, moved.tip)
    rows = penetration_block(
        contact, _geometry(block, previous, needle_free=moved), friction_coefficient=friction
    )
    assert rows.kind[0] == UNILATERAL
    # δ_n = nᵀ(tip_free − contact point): 0.3 mm − 0.5 mm.
    assert rows.free_gap[0] == pytest.approx(-2e-4, abs=1e-15)
    if friction == 0.0:
        assert rows.row_count == 1 and rows.contacts.shape == (0, 3)
        return
    assert rows.row_count == 3 and list(rows.kind[1:]) == [FRICTION, FRICTION]
    np.testing.assert_array_equal(rows.contacts, [[0, 1, 2]])
    np.testing.assert_allclose(rows.contact_friction, [friction])
    # Tangent rows measure the tip's tangential slip over the step (the tissue did not move).
    tangents = rows.directions[1:]
    np.testing.assert_allclose(tangents @ [0.0, 0.0, 1.0], 0.0, atol=1e-15)
    np.testing.assert_allclose(rows.free_gap[1:], tangents @ np.array([2e-4, -1e-4, -5e-4]), atol=1e-17)


def test_tissue_jacobian_linearises_the_normal_and_slip_gaps(block):
    # Every row is affine in the tissue positions with the contact point's barycentric coordinates fixed, so
    # H_tissue Δx equals the change of the gaps to round-off for any tissue motion Δx.
    rng = np.random.default_rng(7)
    tip = np.array([0.0123, 0.0071, 0.0203])
    needle = _needle(tip, [0.0, 0.0, -1.0])
    contact = _contact(block, tip)
    rows = penetration_block(contact, _geometry(block, needle), friction_coefficient=0.2)
    motion = 1e-5 * rng.normal(size=block.rest_positions.shape)
    moved = block.rest_positions + motion
    point = contact.barycentric @ moved[contact.nodes]
    normal_gap = rows.directions[0] @ (tip - point)
    slip = -(point - contact.point)  # the tissue point moved, the needle did not
    change = np.concatenate([[normal_gap - rows.free_gap[0]], rows.directions[1:] @ slip - rows.free_gap[1:]])
    np.testing.assert_allclose(rows.jacobians[TISSUE] @ motion.ravel(), change, atol=1e-17)


def test_a_tip_inside_a_thin_layer_meets_the_face_it_came_through(block):
    # The box is 20 mm tall (top z = 0.02, bottom z = 0). A tip moving down (−z) at 16 mm depth is closest to
    # the bottom face (4 mm), but that face's outward normal (−z) points along the needle: the tip could only
    # reach it from inside. The contact is with the top face it approaches from outside (gap −16 mm).
    tip = [0.0123, 0.0071, 0.004]
    assert _contact(block, tip).normal[2] == pytest.approx(-1.0)  # without the needle's direction
    projector = SurfaceProjector(block.rest_positions, block.boundary_faces)
    down = np.array([0.0, 0.0, -1.0])
    contact = find_surface_contact(projector, block.boundary_faces, np.asarray(tip), down)
    np.testing.assert_allclose(contact.normal, [0.0, 0.0, 1.0], atol=1e-12)
    assert contact.gap == pytest.approx(-0.016, rel=1e-12)
    np.testing.assert_allclose(contact.point, [0.0123, 0.0071, 0.02], atol=1e-15)
    # A needle moving up meets the bottom face.
    up = find_surface_contact(projector, block.boundary_faces, np.asarray(tip), np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(up.normal, [0.0, 0.0, -1.0], atol=1e-12)


# ---------------------------------------------------------------------- a flat tip (insertion.tip_radius)


def test_punch_disc_carries_the_rigid_punch_pressure():
    """The load inside radius ρ of a rigid flat punch of radius a (p ∝ 1/√(a² − ρ²), Sneddon 1946) is
    1 − √(1 − ρ²/a²) of the total; the disc's rings carry it exactly at their band edges ρ = a sin θ_k."""
    from refsim.constraints.penetration import punch_disc

    radius, rings = 0.008, 8
    offsets, weights = punch_disc(radius, rings)
    rho = np.linalg.norm(offsets, axis=1)
    assert weights.sum() == pytest.approx(1.0, abs=1e-14) and np.all(weights > 0.0)
    assert np.all(rho < radius)
    # the disc is balanced: its load has no moment about the centre (the punch's pressure is axisymmetric)
    np.testing.assert_allclose(weights @ offsets, 0.0, atol=1e-15 * radius)
    edges = radius * np.sin(np.linspace(0.0, 0.5 * np.pi, rings + 1)[1:])
    for edge in edges:
        inside = weights[rho < edge].sum()
        assert inside == pytest.approx(1.0 - np.sqrt(1.0 - (edge / radius) ** 2), abs=1e-12)
    with pytest.raises(ValueError, match="tip_radius"):
        punch_disc(0.0)


def test_a_point_tip_has_no_area(block):
    contact = _contact(block, [0.0123, 0.0071, 0.0205])
    assert contact.area_nodes is None
    nodes, weights, point = contact.loaded()
    assert nodes is contact.nodes and weights is contact.barycentric and point is contact.point


def test_a_flat_tip_spreads_its_row_over_its_face(block):
    """A tip of radius 4 mm 0.5 mm above the top face of the 20 mm block (2 x 2 cells: the disc covers parts
    of all four top cells). The row measures the punch-weighted mean of the surface under the disc: a rigid
    translation of the tissue along the normal moves it by exactly that translation, a tilt about the tip's
    axis (zero mean by the disc's balance) not at all, and its gap is the tip's height."""
    tip = np.array([0.0101, 0.0098, 0.0205])
    direction = np.array([0.0, 0.0, -1.0])
    projector = SurfaceProjector(block.rest_positions, block.boundary_faces)
    contact = find_surface_contact(projector, block.boundary_faces, tip, direction, tip_radius=0.004)
    assert contact.gap == pytest.approx(5e-4, abs=1e-15)
    assert contact.area_weights.sum() == pytest.approx(1.0, abs=1e-14)
    np.testing.assert_allclose(contact.area_point, [0.0101, 0.0098, 0.02], atol=1e-15)
    # the entry point (if the tip punctures) is the centre's closest point
    np.testing.assert_allclose(contact.point, [0.0101, 0.0098, 0.02], atol=1e-15)
    needle = _needle(tip, direction)
    rows = penetration_block(contact, _geometry(block, needle), friction_coefficient=0.0)
    assert rows.row_count == 1 and rows.free_gap[0] == pytest.approx(5e-4, abs=1e-15)
    touched = np.unique(rows.jacobians[TISSUE].indices // 3)
    top = np.flatnonzero(np.isclose(block.rest_positions[:, 2], 0.02))
    assert touched.size > 3 and set(touched) <= set(top)  # more than one face's nodes, all on the top face
    lift = np.zeros_like(block.rest_positions)
    lift[:, 2] = 1e-4
    assert (rows.jacobians[TISSUE] @ lift.ravel())[0] == pytest.approx(-1e-4, rel=1e-12)
    tilt = np.zeros_like(block.rest_positions)
    tilt[:, 2] = 1e-3 * (block.rest_positions[:, 0] - tip[0]) - 2e-3 * (block.rest_positions[:, 1] - tip[1])
    assert abs((rows.jacobians[TISSUE] @ tilt.ravel())[0]) < 1e-18
