"""The strip cut: triangles by construction, layers laid at the crack tip, material points on the surface."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.cutting import CutGrowth
from refsim.cutting.growth import advance_front, start_strip
from refsim.cutting.metrics import surface_topology
from refsim.cutting.strip import locate_material_points, strip_triangles
from refsim.geometry import TetLocator
from refsim.mesh import box_mesh

SPACING = 0.5e-3


def test_strip_triangles_cover_each_quad_once_with_one_winding():
    back, front = np.arange(0, 5), np.arange(5, 10)
    triangles = strip_triangles(back, front)
    assert triangles.shape == (8, 3)
    points = np.concatenate(
        [
            np.stack([np.zeros(5), np.arange(5.0), np.zeros(5)], 1),
            np.stack([np.ones(5), np.arange(5.0), np.zeros(5)], 1),
        ]
    )
    corners = points[triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    np.testing.assert_allclose(np.abs(normals[:, 2]), 0.5 * 2, atol=1e-12)  # area 1/2 each, |n| = 2 A
    assert np.all(np.sign(normals[:, 2]) == np.sign(normals[0, 2]))
    assert surface_topology(triangles, 10).is_disc


def test_a_column_that_did_not_advance_leaves_no_degenerate_triangle():
    back = np.arange(0, 4)
    front = np.array([0, 4, 5, 6])  # column 0 stayed
    triangles = strip_triangles(back, front)
    assert triangles.shape == (5, 3)
    assert np.all((triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2]))


@pytest.fixture(scope="module")
def growth():
    mesh = box_mesh(size=(0.012, 0.012, 0.012), cells=(6, 6, 6))
    return CutGrowth(mesh.rest_positions, mesh.tets, SPACING)


def test_the_crack_tip_advances_to_the_pushed_material_point_and_layers_follow(growth):
    path = np.linspace([0.0041, 0.0063, 0.012], [0.0041, 0.0063, 0.004], 17)
    cut, strip = start_strip(
        growth, None, path, np.array([1.0, 0.0, 0.0]), growth.rest_positions, 1, extent=0.0
    )
    assert cut.triangle_count == 0 and strip.layers.shape == (1, 17)
    advances = np.full(17, 0.3e-3)
    moved = strip.with_front(
        advance_front(growth, strip, advances, np.array([1.0, 0, 0]), growth.rest_positions)
    )
    np.testing.assert_allclose(moved.front.rest_points[:, 0], 0.0044, atol=1e-12)
    same, not_yet = moved.lay(cut, 2, SPACING)
    assert not_yet.layers.shape == (1, 17) and same.point_count == cut.point_count  # 0.3 mm < d_c
    further = not_yet.with_front(
        advance_front(growth, not_yet, advances, np.array([1.0, 0, 0]), growth.rest_positions)
    )
    grown, laid = further.lay(cut, 3, SPACING)
    assert laid.layers.shape == (2, 17) and grown.triangle_count == 32
    assert surface_topology(grown.triangles, grown.point_count).is_disc


@pytest.mark.parametrize("offset", [-1e-12, 0.0, 1e-12, 1e-7])
def test_points_on_or_a_hair_above_the_surface_are_kept_in_the_tissue(growth, offset):
    # The crack tip on the top face (z = 12 mm) steps outside by round-off or a deformation's bulge.
    point = np.array([[0.0043, 0.0063, 0.012 + offset]])
    tets, bary, inside = locate_material_points(
        TetLocator(growth.rest_positions, growth.tets),
        growth.rest_positions,
        growth.tets,
        point,
        snap_distance=0.5 * SPACING,
    )
    assert inside[0]
    mapped = bary[0] @ growth.rest_positions[growth.tets[tets[0]]]
    # Within round-off the point is kept as it is; farther out it is moved into the tet by clipping its
    # barycentric coordinates, a point of the tet within a few times the distance outside (not the closest).
    assert np.linalg.norm(mapped - point[0]) <= 2.0 * max(offset, 0.0) + 1e-12


def test_points_far_outside_are_outside(growth):
    point = np.array([[0.0043, 0.0063, 0.013]])
    _, _, inside = locate_material_points(
        TetLocator(growth.rest_positions, growth.tets),
        growth.rest_positions,
        growth.tets,
        point,
        snap_distance=0.5 * SPACING,
    )
    assert not inside[0]


def test_columns_added_below_the_strip_join_it_as_a_disc_when_laid(growth):
    # A strip 8 columns deep (4 mm) cut 1 mm along x, then extended by 3 columns below it (the needle inserted
    # deeper while cutting): nothing changes until the next layer, which joins the new columns to the strip.
    from refsim.cutting.strip import CutFront

    path = np.linspace([0.0041, 0.0063, 0.012], [0.0041, 0.0063, 0.008], 9)
    x = np.array([1.0, 0.0, 0.0])
    cut, strip = start_strip(growth, None, path, x, growth.rest_positions, 1, extent=0.0)
    for step in (2, 3):
        strip = strip.with_front(advance_front(growth, strip, np.full(9, SPACING), x, growth.rest_positions))
        cut, strip = strip.lay(cut, step, SPACING)
    assert strip.layers.shape == (3, 9) and surface_topology(cut.triangles, cut.point_count).is_disc
    below = strip.front.rest_points[-1] + np.array([[0, 0, -1.0], [0, 0, -2.0], [0, 0, -3.0]]) * SPACING
    tets, barycentric, inside = locate_material_points(
        TetLocator(growth.rest_positions, growth.tets), growth.rest_positions, growth.tets, below
    )
    assert inside.all()
    extended = strip.extended(
        CutFront(below, tets, barycentric), strip.depths[-1] + SPACING * np.arange(1, 4)
    )
    assert extended.column_count == 12 and np.all(np.diff(extended.depths) > 0)
    # Not due yet: the new columns alone do not lay a layer (their points would join no triangle).
    same, unchanged = extended.lay(cut, 4, SPACING)
    assert same is cut and unchanged.layers.shape == (3, 12)
    moved = extended.with_front(
        advance_front(growth, extended, np.full(12, SPACING), x, growth.rest_positions)
    )
    grown, laid = moved.lay(cut, 5, SPACING)
    topology = surface_topology(grown.triangles, grown.point_count)
    assert laid.layers.shape == (4, 12) and topology.is_disc, topology
    assert (
        grown.triangle_count == cut.triangle_count + 2 * 8 + 3
    )  # a quad per old pair, a fan for the new columns
