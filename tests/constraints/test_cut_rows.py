"""Cut rows on a hand-made planar strip in a box: sliding rows along the surface normal wherever the needle
lies in the cut, front rows on the crack tip, with the strength G_c × (the inserted length each stands
for)."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.constraints import BILATERAL, CUT_BORDER, CUT_SLIDE, UNILATERAL
from refsim.constraints.cut import strip_cut_block
from refsim.cutting import CutGrowth
from refsim.cutting.growth import start_strip
from refsim.mesh import box_mesh
from tests.constraints.conftest import rigid_needle, still_geometry

SPACING = 0.5e-3
C_HAT = np.array([1.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def planar_strip():
    """A 12 mm box (6 cells per axis); a strip started from a vertical path at (x, y) = (4.1, 6.3) mm swept
    along +x by 2 mm: the plane y = 6.3 mm, x in [4.1, 6.1] mm, z in [4, 12] mm; its crack tip at x = 6.1
    mm."""
    mesh = box_mesh(size=(0.012, 0.012, 0.012), cells=(6, 6, 6))
    growth = CutGrowth(
        rest_positions=mesh.rest_positions,
        tets=mesh.tets,
        point_spacing=SPACING,
    )
    path = np.linspace([0.0041, 0.0063, 0.012], [0.0041, 0.0063, 0.004], 17)
    cut, strip = start_strip(growth, None, path, C_HAT, mesh.rest_positions, 1, extent=2e-3)
    return mesh, cut, strip


def _rows(planar_strip, needle, strength=np.inf):
    mesh, cut, strip = planar_strip
    return strip_cut_block(
        cut,
        strip,
        still_geometry(mesh, needle),
        stretches=((needle.length - 0.0075, needle.length),),
        spacing=SPACING,
        cut_direction=C_HAT,
        front_strength=strength,
    )


def test_the_strip_is_the_path_swept_along_the_cut_direction(planar_strip):
    _, cut, strip = planar_strip
    np.testing.assert_allclose(cut.rest_points[:, 1], 0.0063, atol=1e-15)
    assert cut.rest_points[:, 0].min() == pytest.approx(0.0041, abs=1e-12)
    np.testing.assert_allclose(strip.front.rest_points[:, 0], 0.0061, atol=1e-12)
    assert strip.layers.shape == (5, 17)  # d_t / d_c + 1 layers of 17 columns


def test_a_needle_in_the_cut_gets_a_sliding_row_at_every_sample(planar_strip):
    # The needle lies in the cut 1 mm behind the crack tip, 0.1 mm off the plane (+y), 7.5 mm inserted.
    needle = rigid_needle([0.0051, 0.0064, 0.0045], [0.0, 0.0, -1.0], length=0.02)
    rows, _ = _rows(planar_strip, needle)
    slide = rows.source == CUT_SLIDE
    # Samples every d_c over [entry − d_c, tip]: 7.5 mm / 0.5 mm + 1, every one inside the strip.
    assert np.count_nonzero(slide) == 16
    assert np.all(rows.kind[slide] == BILATERAL)
    np.testing.assert_allclose(np.abs(rows.directions[slide] @ [0.0, 1.0, 0.0]), 1.0, atol=1e-9)
    signed = rows.free_gap[slide] * (rows.directions[slide] @ [0.0, 1.0, 0.0])
    np.testing.assert_allclose(signed, 1e-4, atol=1e-12)


def test_front_rows_hold_the_needle_behind_the_crack_tip(planar_strip):
    needle = rigid_needle([0.0051, 0.0063, 0.0045], [0.0, 0.0, -1.0], length=0.02)
    rows, front = _rows(planar_strip, needle)
    border = rows.source == CUT_BORDER
    assert np.count_nonzero(border) >= 10 and np.all(rows.kind[border] == UNILATERAL)
    np.testing.assert_array_equal(np.flatnonzero(border), front.rows)
    np.testing.assert_allclose(
        rows.directions[border], np.broadcast_to(-C_HAT, (front.rows.size, 3)), atol=1e-12
    )
    np.testing.assert_allclose(rows.points[border][:, 0], 0.0061, atol=1e-12)
    np.testing.assert_allclose(rows.free_gap[border], 1e-3, atol=1e-12)  # 1 mm behind the tip: inside
    assert rows.force_limit.size == 0 or np.all(np.isinf(rows.force_limit))  # unbounded: the paper's law


def test_front_strength_adds_up_to_gc_times_the_inserted_length(planar_strip):
    needle = rigid_needle([0.0051, 0.0063, 0.0045], [0.0, 0.0, -1.0], length=0.02)
    rows, front = _rows(planar_strip, needle, strength=200.0)
    limits = rows.force_limit[front.rows]
    assert np.all(np.isfinite(limits)) and np.all(limits > 0)
    # Σ ℓ_k = 7.5 mm, the inserted length (every sample's projection lies inside the crack tip's span).
    assert limits.sum() == pytest.approx(200.0 * 0.0075, rel=1e-12)
    problem = rows.problem(np.eye(rows.row_count))
    np.testing.assert_array_equal(problem.box_rows, front.rows)
    np.testing.assert_allclose(problem.box_lower, 0.0)


def test_rows_are_chosen_on_the_start_of_step_state(planar_strip):
    # The needle moves 3 mm ahead during the free motion: the rows are those of where it was (in the cut),
    # their gaps those of where it is (past the crack tip: negative front gaps).
    mesh, cut, strip = planar_strip
    previous = rigid_needle([0.0051, 0.0063, 0.0045], [0.0, 0.0, -1.0], length=0.02)
    free = rigid_needle([0.0081, 0.0063, 0.0045], [0.0, 0.0, -1.0], length=0.02)
    rows, front = strip_cut_block(
        cut,
        strip,
        still_geometry(mesh, previous, needle_free=free),
        stretches=((previous.length - 0.0075, previous.length),),
        spacing=SPACING,
        cut_direction=C_HAT,
    )
    assert np.count_nonzero(rows.source == CUT_SLIDE) == 16
    np.testing.assert_allclose(rows.free_gap[front.rows], -2e-3, atol=1e-12)


def test_friction_on_the_cut_faces_is_bounded_by_each_sliding_row(planar_strip):
    from refsim.constraints import FRICTION

    mesh, cut, strip = planar_strip
    previous = rigid_needle([0.0051, 0.0064, 0.0045], [0.0, 0.0, -1.0], length=0.02)
    free = rigid_needle(
        [0.0052, 0.0064, 0.0043], [0.0, 0.0, -1.0], length=0.02
    )  # 0.1 mm along x, 0.2 mm down
    rows, front = strip_cut_block(
        cut,
        strip,
        still_geometry(mesh, previous, needle_free=free),
        stretches=((previous.length - 0.0075, previous.length),),
        spacing=SPACING,
        cut_direction=C_HAT,
        friction_coefficient=0.3,
    )
    slide = np.flatnonzero((rows.source == CUT_SLIDE) & (rows.kind == BILATERAL))
    friction = np.flatnonzero(rows.kind == FRICTION)
    assert friction.size == 2 * slide.size
    np.testing.assert_array_equal(rows.group_rows, friction)
    np.testing.assert_array_equal(rows.group_members, np.concatenate([slide, slide]))
    np.testing.assert_allclose(rows.group_coefficient, 0.3)
    # Slip gaps: the needle moved 0.2 mm along itself (axial rows) and 0.1 mm across (along x) over the step.
    axial, across = friction[: slide.size], friction[slide.size :]
    np.testing.assert_allclose(rows.free_gap[axial], 2e-4, atol=1e-12)
    np.testing.assert_allclose(np.abs(rows.free_gap[across]), 1e-4, atol=1e-12)
    problem = rows.problem(np.eye(rows.row_count))
    np.testing.assert_array_equal(problem.group_friction, friction)


def _other_needle_rows(planar_strip, needle, inserted):
    """The rows of a needle inserted along the existing cut (no strip of its own: sliding rows only)."""
    mesh, cut, _ = planar_strip
    return strip_cut_block(
        cut,
        None,
        still_geometry(mesh, needle),
        stretches=((needle.length - inserted, needle.length),),
        spacing=SPACING,
        cut_direction=np.zeros(3),
    )


@pytest.mark.parametrize("offset", [0.0, 0.4e-3])
def test_another_needle_on_the_cut_slides_in_it(planar_strip, offset):
    # A second needle within d_c of the cut's plane (y = 6.3 mm), inside its extent, 7.5 mm inserted: every
    # sample on the cut holds it on it.
    needle = rigid_needle([0.0051, 0.0063 + offset, 0.0045], [0.0, 0.0, -1.0], length=0.02)
    rows, _ = _other_needle_rows(planar_strip, needle, 0.0075)
    slide = rows.source == CUT_SLIDE
    assert np.count_nonzero(slide) == 16 and np.all(rows.kind[slide] == BILATERAL)
    np.testing.assert_allclose(np.abs(rows.free_gap[slide]), offset, atol=1e-12)


@pytest.mark.parametrize("offset", [0.6e-3, 3e-3])
def test_a_needle_beside_the_cut_gets_no_sliding_row(planar_strip, offset):
    # Parallel to the cut's plane, further than d_c = 0.5 mm from it, every sample projects inside the cut:
    # it is in intact tissue (it gets insertion points there, refsim.simulation.events), so no row pulls it
    # onto the plane (before: 16 bilateral rows with gaps of `offset`).
    needle = rigid_needle([0.0051, 0.0063 + offset, 0.0045], [0.0, 0.0, -1.0], length=0.02)
    rows, _ = _other_needle_rows(planar_strip, needle, 0.0075)
    assert rows is None


def test_a_needle_crossing_the_cuts_plane_slides_only_where_it_is_on_it(planar_strip):
    # A needle along +y through the cut's plane at x = 5.1 mm, z = 8 mm, from y = 1 mm to 11 mm: its samples
    # project inside the cut all along, but only those within d_c of the plane are on the cut.
    needle = rigid_needle([0.0051, 0.011, 0.008], [0.0, 1.0, 0.0], length=0.02)
    rows, _ = _other_needle_rows(planar_strip, needle, 0.010)
    slide = rows.source == CUT_SLIDE
    distances = np.abs(rows.points[slide][:, 1] - 0.0063)
    assert np.all(np.abs(rows.free_gap[slide]) <= SPACING + 1e-12)
    # Samples every d_c from y = 1 mm: two are within d_c of the plane y = 6.3 mm (y = 6.0 and 6.5 mm).
    assert np.count_nonzero(slide) == 2, rows.free_gap[slide]
    np.testing.assert_allclose(distances, 0.0, atol=1e-12)  # anchored on the plane


def test_a_sample_within_half_a_spacing_beyond_an_end_of_the_crack_tip_faces_its_end():
    """The needle's end samples (at the entry point, at the tip) stand for half a spacing of the inserted
    length each. Once the needle has moved along its axis (pulled back through its cut) the entry sample lies
    on the deformed surface, about 10 um above the surface column the cut laid earlier: with the reach of
    half a spacing it still projects onto the crack tip's end (its front row holds its share, G_c d_c / 2);
    with the round-off tolerance alone it did not, and the row came and went from step to step (the
    withdrawal case). Beyond half a spacing a sample does not face the crack tip."""
    from refsim.constraints.cut import _closest_on_polyline

    d_c = 1.36e-3
    polyline = np.array([[0.0, 0.0, -1e-5 - k * d_c] for k in range(5)])  # top column 10 um below z = 0
    points = np.array(
        [
            [1e-4, 0.0, 0.0],  # the entry sample: 10 um above the top column
            [1e-4, 0.0, -2.0 * d_c],  # interior
            [1e-4, 0.0, 0.49 * d_c],  # just within half a spacing above
            [1e-4, 0.0, 0.6 * d_c],  # beyond it
            [1e-4, 0.0, -4.0 * d_c - 1e-5 - 0.4 * d_c],  # within half a spacing below the deep end
            [1e-4, 0.0, -4.0 * d_c - 1e-5 - 0.6 * d_c],  # beyond it
        ]
    )
    _, _, interior = _closest_on_polyline(points, polyline, reach=0.5 * d_c)
    assert interior.tolist() == [True, True, True, False, True, False]
    _, parameter, strict = _closest_on_polyline(points, polyline)
    assert strict.tolist() == [False, True, False, False, False, False]
    assert parameter[0] == 0.0  # clamped onto the end column


def test_front_rows_are_found_in_a_stack_by_their_roles_wherever_the_block_sits(planar_strip):
    """The front rows and the sliding rows at the front are named by their indices in the strip's block;
    in a stack of blocks (an instrument's rows: insertion points and tip before the cut's, or any order)
    they are the stack's rows of roles FRONT and SLIDING at the same ranks."""
    from dataclasses import replace

    from refsim.constraints.rows import NORMAL, PENETRATION, concatenate

    needle = rigid_needle([0.0058, 0.0063, 0.0045], [0.0, 0.0, -1.0], length=0.02)
    block, front = _rows(planar_strip, needle, strength=200.0)
    # 0.3 mm behind the crack tip: front rows, and sliding rows within 1.5 d_c of the tip (the band)
    assert front.rows.size and front.band_rows.size
    count = block.row_count
    head = replace(  # other rows, of other roles, with gaps of their own
        block,
        free_gap=block.free_gap + 1.0,
        source=np.full(count, PENETRATION, dtype=np.int8),
        role=np.full(count, NORMAL, dtype=np.int8),
    )
    for stack in (concatenate([head, block]), concatenate([block, head]), concatenate([head, block, head])):
        found = front.located_in(block, stack)
        for name in ("free_gap", "force_limit"):
            np.testing.assert_array_equal(getattr(stack, name)[found.rows], getattr(block, name)[front.rows])
            np.testing.assert_array_equal(
                getattr(stack, name)[found.band_rows], getattr(block, name)[front.band_rows]
            )
    with pytest.raises(ValueError, match="role front"):
        front.located_in(block, concatenate([block, block]))  # two strips' rows: which is which is unknown
