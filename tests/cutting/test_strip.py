"""The strip cut: triangles by construction, layers laid at the crack tip, material points on the surface."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.constraints.needle_geometry import RigidNeedleGeometry
from refsim.cutting import CutGrowth
from refsim.cutting.growth import advance_front, crack_tip_targets, start_strip
from refsim.cutting.metrics import surface_topology
from refsim.cutting.strip import (
    CutStrip,
    locate_material_points,
    recorded_strip,
    recorded_surface,
    strip_triangles,
)
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


def test_a_strip_left_is_recorded_up_to_its_crack_tip_with_that_last_layer(growth):
    # A needle leaving its strip leaves the cut up to the crack tip (recorded_surface: a layer laid at the
    # crack tip however little it moved past the last layer) and the strip with that layer (recorded_strip:
    # the strip the tissue keeps, the one a needle found in it cuts on from): the same surface, the strip's
    # last layer those new points, at the crack tip's rest positions.
    path = np.linspace([0.0041, 0.0063, 0.012], [0.0041, 0.0063, 0.004], 17)
    direction = np.array([1.0, 0.0, 0.0])
    cut, strip = start_strip(growth, None, path, direction, growth.rest_positions, 1, extent=0.0)
    moved = strip.with_front(
        advance_front(growth, strip, np.full(17, 0.3e-3), direction, growth.rest_positions)
    )  # 0.3 mm: less than d_c, no layer yet
    surface, left = recorded_strip(cut, moved, 5)
    recorded = recorded_surface(cut, moved, 5)
    np.testing.assert_array_equal(surface.triangles, recorded.triangles)
    np.testing.assert_array_equal(surface.rest_points, recorded.rest_points)
    assert left.layers.shape == (2, 17) and surface.triangle_count == 32
    np.testing.assert_allclose(surface.rest_points[left.last_layer], moved.front.rest_points, atol=1e-15)
    assert np.all(surface.created_step[left.last_layer] == 5)
    # Nothing moved, or no strip: both as given.
    assert recorded_strip(surface, left, 6) == (surface, left)
    assert recorded_strip(cut, None, 6) == (cut, None)


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


def _extended_strip(growth):
    """A strip 8 columns deep (4 mm) cut 1 mm along x at steps 2 and 3, then extended at step 4 by a block of
    3 columns below it, their crack tip on the needle's line 1 mm ahead of the path (the needle inserted
    deeper while cutting)."""
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
        CutFront(below, tets, barycentric), strip.depths[-1] + SPACING * np.arange(1, 4), 4
    )
    assert extended.column_count == 12 and np.all(np.diff(extended.depths) > 0)
    return cut, extended, below, x


def _area(cut) -> float:
    corners = cut.rest_points[cut.triangles]
    return float(
        0.5
        * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum()
    )


def _assert_manifold(cut) -> None:
    """Each edge in at most two triangles, no degenerate triangle, no isolated point."""
    topology = surface_topology(cut.triangles, cut.point_count)
    assert topology.non_manifold_edges == 0 and topology.isolated_points == 0, topology
    corners = cut.rest_points[cut.triangles]
    doubled = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    assert doubled.min() > 1e-6 * SPACING**2


def test_a_block_added_below_the_strip_is_laid_from_the_needle_line_even_when_the_strip_stands(growth):
    # The strip stands (its crack tip does not move) while the block below it is cut 1.5 mm along x (the
    # needle deeper, pushed sideways, the tissue moving under the upper part: an organ under breathing).
    # The block is laid on its own: its first layer on the needle's line where it was added, its second at
    # the crack tip; the tissue between the old strip's laid points and the block was not cut when they were
    # laid, so no triangle joins them. Swept: 2 pairs × 1.5 mm × d_c.
    cut, extended, below, x = _extended_strip(growth)
    same, unchanged = extended.lay(cut, 5, SPACING)
    assert same is cut and unchanged is extended  # nothing moved: nothing to lay
    front = extended.front.rest_points.copy()
    front[9:] += 3 * SPACING * x
    moved = extended.with_front(
        advance_front(growth, extended, np.r_[np.zeros(9), np.full(3, 3 * SPACING)], x, growth.rest_positions)
    )
    np.testing.assert_allclose(moved.front.rest_points, front, atol=1e-12)
    grown, laid = moved.lay(cut, 5, SPACING)
    assert grown.point_count == cut.point_count + 6  # the block's first layer and its crack tip
    np.testing.assert_allclose(grown.rest_points[cut.point_count : cut.point_count + 3], below, atol=1e-12)
    np.testing.assert_allclose(grown.rest_points[cut.point_count + 3 :], front[9:], atol=1e-12)
    new = grown.triangles[cut.triangle_count :]
    assert new.shape == (4, 3) and np.all(new >= cut.point_count)  # nothing joins the old strip's points
    np.testing.assert_allclose(_area(grown) - _area(cut), 2 * 3 * SPACING * SPACING, rtol=1e-9)
    _assert_manifold(grown)
    # Two pieces until the strip has points laid after the block was added (its points laid before border
    # tissue below it that was not cut): the layer that moves it from them is not joined to the block, the
    # next one is.
    assert surface_topology(grown.triangles, grown.point_count).boundary_loops == 2
    for step, pieces in ((6, 2), (7, 1)):
        laid = laid.with_front(advance_front(growth, laid, np.full(12, SPACING), x, growth.rest_positions))
        previous = grown
        grown, laid = laid.lay(grown, step, SPACING)
        _assert_manifold(grown)
        assert surface_topology(grown.triangles, grown.point_count).boundary_loops == pieces
    assert surface_topology(grown.triangles, grown.point_count).is_disc
    across = grown.triangles[previous.triangle_count :]
    assert across.shape == (2 * 11, 3)  # a quad per pair, the pair across the blocks included


def test_a_lone_column_below_the_strip_waits_for_a_neighbour_it_can_join(growth):
    # One column added below a standing strip and cut: alone, its points would join no triangle (the old
    # strip's points were laid before it was added), so it is not laid until its neighbour is laid again.
    from refsim.cutting.strip import CutFront

    cut, extended, _, x = _extended_strip(growth)
    single = CutStrip(
        extended.layers[:, :10],
        CutFront(
            extended.front.rest_points[:10], extended.front.tet_indices[:10], extended.front.barycentric[:10]
        ),
        extended.depths[:10],
        CutFront(
            extended.origins.rest_points[:10],
            extended.origins.tet_indices[:10],
            extended.origins.barycentric[:10],
        ),
        extended.births[:10],
    )
    moved = single.with_front(
        advance_front(growth, single, np.r_[np.zeros(9), 3 * SPACING], x, growth.rest_positions)
    )
    same, unchanged = moved.lay(cut, 5, SPACING)
    assert same is cut and unchanged is moved
    both = moved.with_front(
        advance_front(growth, moved, np.r_[np.full(9, SPACING), 0.0], x, growth.rest_positions)
    )
    grown, laid = both.lay(cut, 6, SPACING)  # the strip moves from points laid before the column was added
    assert laid.layers[-1, 9] < 0 and surface_topology(grown.triangles, grown.point_count).is_disc
    again = laid.with_front(advance_front(growth, laid, np.full(10, SPACING), x, growth.rest_positions))
    joined, laid = again.lay(grown, 7, SPACING)  # now it has a neighbour to join: its two layers, and a third
    _assert_manifold(joined)
    assert surface_topology(joined.triangles, joined.point_count).is_disc
    assert laid.layers[-1, 9] >= 0 and laid.layers[-2, 9] >= 0


def test_a_column_just_below_the_tip_is_taken_to_the_needles_line_at_its_own_depth():
    # Columns at depths 0, 1, 2, 2.8, 3.6 mm below the tissue surface; a vertical needle 2.5 mm in (its tip at
    # z = 0, the surface at z = 2.5 mm). A column within half a spacing (0.5 mm) below the tip is reached, on
    # the needle's line at its own depth (z = −0.3 mm): not at the tip point, which would move it up along
    # the needle; one deeper is not reached.
    spacing = 1e-3
    strip = type("Strip", (), {"depths": np.array([0.0, 1.0, 2.0, 2.8, 3.6]) * 1e-3})()
    needle = RigidNeedleGeometry(np.array([0.0, 0.0, 0.05]), np.array([0.0, 0.0, -1.0]), 0.05)
    targets, reached = crack_tip_targets(strip, needle, 0.0475, np.arange(5), spacing)
    np.testing.assert_allclose(targets[:4, 2], [2.5e-3, 1.5e-3, 0.5e-3, -0.3e-3], atol=1e-15)
    np.testing.assert_allclose(targets[:, :2], 0.0, atol=0.0)
    assert reached.tolist() == [True, True, True, True, False]
