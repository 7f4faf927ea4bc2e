"""Cut rows on a hand-made planar cut in a box: sliding rows along the surface normal, border rows on the front."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.constraints import BILATERAL, CUT_BORDER, CUT_SLIDE, UNILATERAL
from refsim.constraints.cut import cut_block
from refsim.cutting import CutGrowth, TriangulationParameters
from refsim.mesh import box_mesh
from tests.constraints.conftest import rigid_needle, still_geometry

SPACING = 0.5e-3


@pytest.fixture(scope="module")
def planar_cut():
    """A 12 mm box (6 cells per axis); a cut started from a vertical path at (x, y) = (4.1, 6.3) mm running
    along +x by d_t = 2 mm: the plane y = 6.3 mm, x in [4.1, 6.1] mm, z in [4, 12] mm."""
    mesh = box_mesh(size=(0.012, 0.012, 0.012), cells=(6, 6, 6))
    growth = CutGrowth(
        rest_positions=mesh.rest_positions,
        tets=mesh.tets,
        point_spacing=SPACING,
        extent=2e-3,
        parameters=TriangulationParameters.from_degrees(min_angle=10, max_angle=120, max_surface_angle=45),
    )
    top, bottom = np.array([0.0041, 0.0063, 0.012 - 1e-9]), np.array([0.0041, 0.0063, 0.004])
    path = np.linspace(top, bottom, 17)
    cut = growth.start(path, np.array([1.0, 0.0, 0.0]), mesh.rest_positions, step=1)
    return mesh, growth, cut


def test_the_first_surface_is_the_path_swept_along_the_cut_direction(planar_cut):
    _, _, cut = planar_cut
    points = cut.rest_points
    np.testing.assert_allclose(points[:, 1], 0.0063, atol=1e-15)
    assert points[:, 0].min() == pytest.approx(0.0041, abs=1e-12)
    assert points[:, 0].max() == pytest.approx(0.0061, abs=1e-12)
    assert cut.triangle_count > 0


def test_a_needle_in_the_cut_gets_sliding_rows_normal_to_the_surface(planar_cut):
    mesh, _, cut = planar_cut
    # The needle lies in the cut, 1 mm ahead of its back border, shifted 0.1 mm off the plane (+y).
    needle = rigid_needle([0.0051, 0.0064, 0.0045], [0.0, 0.0, -1.0], length=0.02)
    rows, info = cut_block(
        cut, still_geometry(mesh, needle), entry_arc_length=needle.length - 0.0075, spacing=SPACING,
        cut_direction=np.array([1.0, 0.0, 0.0]),
    )
    slide = rows.source == CUT_SLIDE
    assert np.count_nonzero(slide) >= 2 and np.all(rows.kind[slide] == BILATERAL)
    np.testing.assert_allclose(np.abs(rows.directions[slide] @ [0.0, 1.0, 0.0]), 1.0, atol=1e-9)
    # δ = nᵀ(x_needle − x_surface): the 0.1 mm offset, with the sign of the normal.
    signed = rows.free_gap[slide] * (rows.directions[slide] @ [0.0, 1.0, 0.0])
    np.testing.assert_allclose(signed, 1e-4, atol=1e-12)


def test_border_rows_hold_the_needle_behind_the_front(planar_cut):
    mesh, _, cut = planar_cut
    needle = rigid_needle([0.0051, 0.0063, 0.0045], [0.0, 0.0, -1.0], length=0.02)
    rows, info = cut_block(
        cut, still_geometry(mesh, needle), entry_arc_length=needle.length - 0.0075, spacing=SPACING,
        cut_direction=np.array([1.0, 0.0, 0.0]),
    )
    border = rows.source == CUT_BORDER
    assert np.count_nonzero(border) >= 1 and np.all(rows.kind[border] == UNILATERAL)
    np.testing.assert_array_equal(np.flatnonzero(border), info.rows)
    # Only the front (x = 6.1 mm) holds the needle: the rows point back along −x, normal to the needle.
    np.testing.assert_allclose(rows.directions[border] @ [0.0, 0.0, 1.0], 0.0, atol=1e-12)
    assert np.all(rows.directions[border] @ [1.0, 0.0, 0.0] < -0.5)
    np.testing.assert_allclose(rows.points[border][:, 0], 0.0061, atol=1e-9)
    # The needle is 1 mm behind the front: every border gap is about +1 mm (inside the cut).
    np.testing.assert_allclose(rows.free_gap[border], 1e-3, atol=1e-6)


def test_tear_grows_the_front_by_the_extent_along_the_outward_direction(planar_cut):
    mesh, growth, cut = planar_cut
    needle = rigid_needle([0.0051, 0.0063, 0.0045], [0.0, 0.0, -1.0], length=0.02)
    gradients = np.broadcast_to(np.eye(3), (mesh.tets.shape[0], 3, 3))
    grown = growth.tear(
        cut, positions=mesh.rest_positions, deformation_gradients=gradients, outward=np.array([1.0, 0.0, 0.0]),
        cut_direction=np.array([1.0, 0.0, 0.0]), needle=needle, entry_arc_length=needle.length - 0.0075, step=2,
    )
    new = grown.rest_points[cut.point_count:]
    assert new.shape[0] > 0
    assert new[:, 0].max() == pytest.approx(0.0081, abs=1e-9)  # 6.1 mm + d_t
    np.testing.assert_allclose(new[:, 1], 0.0063, atol=1e-12)
    # Prefix-stable: old points and triangles unchanged.
    np.testing.assert_array_equal(grown.rest_points[: cut.point_count], cut.rest_points)
    np.testing.assert_array_equal(grown.triangles[: cut.triangle_count], cut.triangles)
