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


@settings(deadline=None)
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


def _exact_distance2(point: np.ndarray, triangle: np.ndarray) -> float:
    """Squared distance from a point to a triangle in exact rational arithmetic (fractions.Fraction).

    The closest point is the plane projection when its barycentric coordinates are all >= 0, otherwise the
    closest point of an edge; with exact arithmetic neither test suffers from cancellation, whatever the
    shape.
    """
    from fractions import Fraction

    p = [Fraction(float(x)) for x in point]
    a, b, c = ([Fraction(float(x)) for x in vertex] for vertex in triangle)

    def sub(u, v):
        return [u[i] - v[i] for i in range(3)]

    def dot(u, v):
        return sum(u[i] * v[i] for i in range(3))

    def cross(u, v):
        return [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]

    def segment(u, v):
        d = sub(v, u)
        length2 = dot(d, d)
        t = Fraction(0) if length2 == 0 else min(Fraction(1), max(Fraction(0), dot(sub(p, u), d) / length2))
        q = [u[i] + t * d[i] for i in range(3)]
        return dot(sub(p, q), sub(p, q))

    best = min(segment(a, b), segment(b, c), segment(c, a))
    normal = cross(sub(b, a), sub(c, a))
    normal2 = dot(normal, normal)
    if normal2 > 0:
        height = dot(normal, sub(p, a)) / normal2
        foot = [p[i] - height * normal[i] for i in range(3)]
        weights = [
            dot(normal, cross(sub(b, foot), sub(c, foot))),
            dot(normal, cross(sub(c, foot), sub(a, foot))),
            dot(normal, cross(sub(a, foot), sub(b, foot))),
        ]
        if min(weights) >= 0:
            best = min(best, height * height * normal2)
    return float(best)


def _slivers(rng, count: int, thickness: float) -> np.ndarray:
    """Triangles whose third vertex lies ``thickness`` × |ab| off the line ab, anywhere along it (a
    sliver)."""
    a, b = rng.uniform(-5, 5, (2, count, 3))
    along = rng.uniform(-1.0, 2.0, count)
    offset = rng.normal(size=(count, 3))
    c = a + along[:, None] * (b - a) + thickness * np.linalg.norm(b - a, axis=1)[:, None] * offset
    return np.stack([a, b, c], axis=1)


@pytest.mark.parametrize("thickness", [0.0, 1e-13, 1e-12, 1e-11, 1e-9, 1e-7, 1e-5, 1e-3, 3e-2])
def test_slivers_against_exact_arithmetic(thickness):
    """Collinear (thickness 0) and nearly collinear triangles, points on and near them: the distance equals
    the exact-arithmetic distance to round-off. Before the fix Ericson's face formulas returned points 6 m off
    here. Tolerance 1e-13 m: round-off of distances between points of coordinates up to 10 m (ε·10 = 2.2e-15)
    times the few dozen operations of the frame computation; thin triangles used to err by up to 6 m (the
    issue).
    """
    rng = np.random.default_rng(11)
    count = 150
    triangles = _slivers(rng, count, thickness)
    weights = rng.dirichlet(np.ones(3), count)
    scale = rng.choice([0.0, 1e-6, 1e-3, 1.0], count)[:, None]
    points = np.einsum("qk,qki->qi", weights, triangles) + scale * rng.normal(size=(count, 3))
    closest, barycentric = closest_points_on_triangles(points, triangles)
    exact = np.sqrt([_exact_distance2(p, t) for p, t in zip(points, triangles, strict=True)])
    np.testing.assert_allclose(np.linalg.norm(points - closest, axis=1), exact, rtol=0, atol=1e-13)
    assert barycentric.min() >= 0.0
    np.testing.assert_allclose(barycentric.sum(axis=1), 1.0, atol=1e-15)


@pytest.mark.parametrize(
    "shape", ["two_coincident", "all_coincident", "collinear_middle", "collinear_outside"]
)
def test_degenerate_shapes_by_name(shape):
    """Coincident and collinear vertices, each ordering: closest point exact (exact-arithmetic reference), the
    barycentric coordinates a valid convex combination, and a point of the segment hull returned as itself."""
    rng = np.random.default_rng(12)
    a, d = rng.normal(size=(2, 60, 3))
    triangles = {
        "two_coincident": np.stack([a, a + d, a], axis=1),
        "all_coincident": np.stack([a, a, a], axis=1),
        "collinear_middle": np.stack([a, a + 2.0 * d, a + 0.5 * d], axis=1),
        "collinear_outside": np.stack([a + d, a + 0.5 * d, a - 3.0 * d], axis=1),
    }[shape]
    points = rng.normal(size=(60, 3)) * 3.0
    points[:20] = a[:20] + rng.uniform(0.0, 1.0, (20, 1)) * d[:20]  # on the segment [a, a + d]
    closest, barycentric = closest_points_on_triangles(points, triangles)
    exact = np.sqrt([_exact_distance2(p, t) for p, t in zip(points, triangles, strict=True)])
    np.testing.assert_allclose(np.linalg.norm(points - closest, axis=1), exact, atol=1e-13)
    if shape != "all_coincident":
        np.testing.assert_allclose(closest[:20], points[:20], atol=1e-14)
    assert barycentric.min() >= 0.0
    np.testing.assert_allclose(barycentric.sum(axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.einsum("qk,qki->qi", barycentric, triangles), closest, atol=1e-15)


_coordinate = st.floats(-5, 5, allow_nan=False)


@st.composite
def _thin_triangles(draw):
    """Triangles from hypothesis, thin ones included: c = a + s (b − a) + h n with h from 0 to 1."""
    a = np.array(draw(st.tuples(_coordinate, _coordinate, _coordinate)))
    b = np.array(draw(st.tuples(_coordinate, _coordinate, _coordinate)))
    along = draw(st.floats(-1.5, 2.5))
    height = draw(st.sampled_from([0.0, 1e-14, 1e-12, 1e-10, 1e-8, 1e-6, 1e-4, 1e-2, 1.0]))
    normal = np.array(draw(st.tuples(_coordinate, _coordinate, _coordinate)))
    return np.stack([a, b, a + along * (b - a) + height * normal])


@settings(deadline=None)
@given(
    _thin_triangles(), arrays(np.float64, (3,), elements=st.floats(-8, 8)), st.floats(0, 1), st.floats(0, 1)
)
def test_property_thin_triangles_match_exact_arithmetic(triangle, point, u, v):
    """Any triangle, slivers included, and points near it (the failure of issue 10 was a sliver)."""
    near = triangle[0] + u * (triangle[1] - triangle[0]) + v * (1 - u) * (triangle[2] - triangle[0])
    for query in (point, near, near + 1e-9 * point):
        closest, barycentric = closest_points_on_triangles(query[None], triangle[None])
        exact = np.sqrt(_exact_distance2(query, triangle))
        assert abs(np.linalg.norm(query - closest[0]) - exact) <= 1e-13 * (
            1.0 + np.abs(triangle).max() + np.abs(query).max()
        )
        assert barycentric.min() >= 0.0


@pytest.mark.parametrize("kind", ["random", "thin", "grid", "near_faces"])
def test_compiled_ericson_is_numpys_bit_for_bit(kind):
    # The compiled pass repeats the NumPy path's operations in its order (cross product, einsum's order of
    # three products, the norm's sum, Ericson's tests): the same coordinates, areas and settled pairs, for
    # well-shaped, thin (left to the candidate path) and grid-aligned triangles (ties in the region tests).
    from refsim.geometry.closest import _THIN_AREA, _ericson_path
    from refsim.geometry.closest_kernel import ericson_regular

    rng = np.random.default_rng(["random", "thin", "grid", "near_faces"].index(kind))
    count, scale = 20_000, 10.0 ** rng.uniform(-3, 1)
    triangles = rng.standard_normal((count, 3, 3)) * scale
    points = rng.standard_normal((count, 3)) * scale
    if kind == "thin":
        along = triangles[:, 0] + (triangles[:, 1] - triangles[:, 0]) * rng.random((count, 1))
        triangles[:, 2] = along + rng.standard_normal((count, 3)) * scale * 10.0 ** rng.uniform(
            -9, 0, (count, 1)
        )
    if kind == "grid":
        triangles, points = np.round(triangles / scale * 4), np.round(points / scale * 4)
    if kind == "near_faces":
        points = triangles.mean(axis=1) + rng.standard_normal((count, 3)) * scale * 1e-3
    expected = _ericson_path(points, triangles)
    got = ericson_regular(points, triangles, _THIN_AREA)
    for a, b in zip(got, expected, strict=True):
        np.testing.assert_array_equal(a, b)
    assert 0 < np.count_nonzero(expected[2]) and (kind != "thin" or not np.all(expected[2]))


def test_cross_rows_are_np_cross_bit_for_bit():
    # The row-wise cross product of the detection's hot paths against np.cross (its NumPy reference): random
    # rows over many magnitudes, parallel and zero rows, signed zeros, infinities and NaN.
    from refsim.geometry.closest import cross_rows

    rng = np.random.default_rng(23)
    a = rng.standard_normal((400, 3)) * 10.0 ** rng.integers(-8, 8, size=(400, 1))
    b = rng.standard_normal((400, 3)) * 10.0 ** rng.integers(-8, 8, size=(400, 1))
    b[:20] = 3.0 * a[:20]
    a[20:30] = 0.0
    a[30:40] = -0.0
    a[40, 1], b[41, 2], a[42, 0] = np.inf, -np.inf, np.nan
    got = cross_rows(a, b)
    expected = np.cross(a, b)
    assert got.shape == expected.shape and got.dtype == expected.dtype
    np.testing.assert_array_equal(got, expected)
    finite = np.isfinite(expected)
    np.testing.assert_array_equal(np.signbit(got[finite]), np.signbit(expected[finite]))
    np.testing.assert_array_equal(cross_rows(a[:0], b[:0]), np.cross(a[:0], b[:0]))
