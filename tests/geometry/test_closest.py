"""Closest points on segments and triangles: regions, exact vertices, near-degenerate inputs, brute force."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from refsim.geometry import closest_points_on_segments, closest_points_on_triangles, triangle_normals

OFFSETS = [-1e-12, 0.0, 1e-12]


def _segment_reference(point: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Closest point on one segment: clamped orthogonal projection (independent scalar code)."""
    direction = end - start
    length2 = float(direction @ direction)
    if length2 == 0.0:
        return start.copy()
    t = min(1.0, max(0.0, float((point - start) @ direction) / length2))
    return start + t * direction


def _triangle_reference(point: np.ndarray, triangle: np.ndarray) -> np.ndarray:
    """Closest point on one triangle: the plane projection if inside, else the closest of the three edges."""
    a, b, c = triangle
    edges = np.column_stack([b - a, c - a])
    coefficients, *_ = np.linalg.lstsq(edges, point - a, rcond=None)
    if coefficients.min() >= 0 and coefficients.sum() <= 1:
        return a + edges @ coefficients
    candidates = [_segment_reference(point, *pair) for pair in ((a, b), (b, c), (c, a))]
    return min(candidates, key=lambda q: float(np.sum((q - point) ** 2)))


def test_triangles_match_reference_on_random_inputs():
    rng = np.random.default_rng(0)
    triangles = rng.normal(size=(400, 3, 3))
    points = rng.normal(size=(400, 3)) * 2.0
    closest, barycentric = closest_points_on_triangles(points, triangles)
    reference = np.array([_triangle_reference(p, t) for p, t in zip(points, triangles, strict=True)])
    np.testing.assert_allclose(closest, reference, atol=1e-12)
    assert barycentric.min() >= 0.0
    np.testing.assert_allclose(barycentric.sum(axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.einsum("qk,qki->qi", barycentric, triangles), closest, atol=1e-15)


@pytest.mark.parametrize("vertex", range(3))
@pytest.mark.parametrize("offset", OFFSETS)
def test_points_at_vertices(vertex, offset):
    rng = np.random.default_rng(1)
    triangles = rng.normal(size=(100, 3, 3))
    # Move the point away along minus the sum of the unit edges leaving the vertex, plus the normal: that
    # direction d has d·edge <= 0 for both edges, so it stays in the vertex's Voronoi region (offset >= 0).
    here = triangles[:, vertex]
    edges = [triangles[:, (vertex + k) % 3] - here for k in (1, 2)]
    outward = -sum(e / np.linalg.norm(e, axis=1, keepdims=True) for e in edges) + triangle_normals(triangles)
    outward /= np.linalg.norm(outward, axis=1, keepdims=True)
    if offset >= 0.0:
        points = here + offset * outward
        closest, barycentric = closest_points_on_triangles(points, triangles)
        np.testing.assert_array_equal(closest, here)
        np.testing.assert_array_equal(barycentric[:, vertex], 1.0)
    else:  # 1e-12 inside the triangle, towards its centroid: the point is its own closest point
        inward = triangles.mean(axis=1) - here
        points = here - offset * inward / np.linalg.norm(inward, axis=1, keepdims=True)
        closest, barycentric = closest_points_on_triangles(points, triangles)
        np.testing.assert_allclose(closest, points, atol=1e-15)
        np.testing.assert_allclose(barycentric[:, vertex], 1.0, atol=1e-10)


@pytest.mark.parametrize("offset", OFFSETS)
def test_points_on_edges(offset):
    rng = np.random.default_rng(2)
    triangles = rng.normal(size=(300, 3, 3))
    t = rng.uniform(0.05, 0.95, 300)
    on_edge = (1 - t)[:, None] * triangles[:, 0] + t[:, None] * triangles[:, 1]
    normal = triangle_normals(triangles)
    in_plane_out = np.cross(triangles[:, 1] - triangles[:, 0], normal)  # points away from c (right-handed)
    in_plane_out /= np.linalg.norm(in_plane_out, axis=1, keepdims=True)
    for direction in (normal, in_plane_out):
        points = on_edge + offset * direction
        closest, barycentric = closest_points_on_triangles(points, triangles)
        # The closest point is on_edge for outward offsets (>= 0); for −1e-12 along the in-plane direction the
        # point is inside, 1e-12 from the edge, and is its own closest point.
        expected = points if (offset < 0 and direction is in_plane_out) else on_edge
        np.testing.assert_allclose(closest, expected, atol=1e-14)
        assert barycentric.min() >= 0.0
        np.testing.assert_allclose(barycentric[:, :2], np.column_stack([1 - t, t]), atol=1e-10)


@pytest.mark.parametrize("offset", [1e-12, 0.0, 0.3])
def test_points_above_face_interior(offset):
    rng = np.random.default_rng(3)
    triangles = rng.normal(size=(200, 3, 3))
    weights = rng.dirichlet(np.ones(3) * 3, size=200)
    foot = np.einsum("qk,qki->qi", weights, triangles)
    points = foot + offset * triangle_normals(triangles)
    closest, barycentric = closest_points_on_triangles(points, triangles)
    np.testing.assert_allclose(closest, foot, atol=1e-13)
    np.testing.assert_allclose(barycentric, weights, atol=1e-11)
    np.testing.assert_allclose(np.linalg.norm(points - closest, axis=1), offset, atol=1e-14)


def test_degenerate_triangles_fall_back_to_edges():
    rng = np.random.default_rng(4)
    a, d = rng.normal(size=(2, 50, 3))
    collinear = np.stack([a, a + d, a + 2.5 * d], axis=1)
    repeated = np.stack([a, a, a + d], axis=1)
    point_like = np.stack([a, a, a], axis=1)
    points = rng.normal(size=(50, 3))
    for triangles in (collinear, repeated, point_like):
        closest, barycentric = closest_points_on_triangles(points, triangles)
        assert np.all(np.isfinite(closest))
        reference = np.array([_triangle_reference(p, t) for p, t in zip(points, triangles, strict=True)])
        np.testing.assert_allclose(
            np.linalg.norm(points - closest, axis=1), np.linalg.norm(points - reference, axis=1), atol=1e-12
        )
        assert barycentric.min() >= 0.0
        np.testing.assert_allclose(barycentric.sum(axis=1), 1.0, atol=1e-15)
    assert np.all(triangle_normals(collinear) == 0.0)


def test_segments_match_reference_and_endpoints_are_exact():
    rng = np.random.default_rng(5)
    starts, ends, points = rng.normal(size=(3, 500, 3))
    ends[:20] = starts[:20]  # zero-length segments
    closest, parameter = closest_points_on_segments(points, starts, ends)
    reference = np.array([_segment_reference(*row) for row in zip(points, starts, ends, strict=True)])
    np.testing.assert_allclose(closest, reference, atol=1e-13)
    assert parameter.min() >= 0.0 and parameter.max() <= 1.0
    np.testing.assert_array_equal(parameter[:20], 0.0)
    at_start = parameter == 0.0
    at_end = parameter == 1.0
    assert at_start.any() and at_end.any()
    np.testing.assert_array_equal(closest[at_start], starts[at_start])
    np.testing.assert_array_equal(closest[at_end], ends[at_end])


@pytest.mark.parametrize("offset", OFFSETS)
def test_segment_endpoint_neighbourhood(offset):
    starts = np.array([[0.0, 0.0, 0.0]])
    ends = np.array([[1.0, 0.0, 0.0]])
    closest, parameter = closest_points_on_segments(np.array([[1.0 + offset, 0.5, 0.0]]), starts, ends)
    expected = min(1.0, 1.0 + offset)
    assert parameter[0] == pytest.approx(expected, abs=1e-16)
    np.testing.assert_allclose(closest[0], [expected, 0.0, 0.0], atol=1e-16)


def test_shape_errors():
    with pytest.raises(ValueError, match="triangles"):
        closest_points_on_triangles(np.zeros((2, 3)), np.zeros((3, 3, 3)))
    with pytest.raises(ValueError, match="starts"):
        closest_points_on_segments(np.zeros((2, 3)), np.zeros((1, 3)), np.zeros((2, 3)))


@settings(max_examples=40, deadline=None, database=None)
@given(
    arrays(np.float64, (3, 3), elements=st.floats(-5, 5)),
    arrays(np.float64, (3,), elements=st.floats(-8, 8)),
    arrays(np.float64, (64, 3), elements=st.floats(0, 1)),
)
def test_property_closest_is_no_farther_than_any_triangle_point(triangle, point, samples):
    closest, barycentric = closest_points_on_triangles(point[None], triangle[None])
    total = samples.sum(axis=1, keepdims=True)
    weights = np.where(total > 1e-6, samples / np.maximum(total, 1e-6), [1.0, 0.0, 0.0])
    others = weights @ triangle
    distance = np.linalg.norm(point - closest[0])
    assert np.all(np.linalg.norm(others - point, axis=1) >= distance - 1e-9)
    assert barycentric.min() >= 0.0
    assert barycentric.sum() == pytest.approx(1.0, abs=1e-14)
