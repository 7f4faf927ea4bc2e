"""Closest points on segments and triangles, vectorised over queries.

The triangle kernel is Ericson's Voronoi-region method ("Real-Time Collision Detection", 2005, §5.1.5): the
region of the point (three vertex regions, three edge regions, the face) is decided from six dot products,
here with numpy masks instead of early returns. Its face-region formulas divide by |ab × ac|², computed as a
difference of products of order (longest edge)⁴: on a sliver (area small against the longest edge squared) the
cancellation leaves barycentric coordinates that are wrong by O(ε L⁴ / |ab × ac|²) and may be negative, and
the returned point can be metres away from the triangle (measured: 6 m on 5 m triangles with |ab × ac| = 1e-11
L²). Thin triangles (|ab × ac| < _THIN_AREA L², and any triangle where Ericson's coordinates come out negative
or non-finite) therefore take a second path that is correct by construction: the closest of the candidates
"the closest point of each edge" and "the orthogonal projection on the plane, when its barycentric coordinates
(from sub-triangle areas) are all non-negative". Every candidate is a point of the triangle, and the true
closest point is either the plane projection (inside) or on an edge, so the minimum is the closest point up to
round-off. The plane projection is computed in the frame of the longest edge (see `_face_barycentric`),
which stays accurate however thin the triangle; exactly collinear or coincident vertices (|ab × ac| = 0) use
the edges only. Well-shaped triangles keep Ericson's formulas (bit for bit the earlier results).
"""

from __future__ import annotations

import numpy as np

__all__ = ["closest_points_on_segments", "closest_points_on_triangles", "cross_rows", "triangle_normals"]

# A triangle is degenerate when |ab × ac| <= _DEGENERATE_AREA * (longest edge)²: its normal is then lost in
# round-off and the face-region formulas divide by (nearly) zero.
_DEGENERATE_AREA = 1e-12
# Triangles with |ab × ac| < _THIN_AREA × (longest edge)² take the candidate path. Ericson's face coordinates
# err by about ε / (|ab × ac| / L²)², 2e-14 relative at this bound: below it the candidates are used instead.
_THIN_AREA = 1e-1


def _check_points(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (q, 3), got {points.shape}")
    return points


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def closest_points_on_segments(
    points: np.ndarray, starts: np.ndarray, ends: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Closest points on segments (one segment per point).

    Parameters
    ----------
    points : Query points [m], shape (q, 3).
    starts : Segment start points [m], shape (q, 3).
    ends : Segment end points [m], shape (q, 3); a segment with ``ends == starts`` is a point.

    Returns
    -------
    closest : Closest points [m], shape (q, 3); exactly ``starts`` or ``ends`` when the parameter is 0 or 1.
    parameter : Position along each segment, ``closest = (1 − t) start + t end``, in [0, 1], shape (q,).
    """
    points = _check_points(points)
    starts = np.asarray(starts, dtype=float)
    ends = np.asarray(ends, dtype=float)
    if starts.shape != points.shape or ends.shape != points.shape:
        raise ValueError(
            f"starts and ends must have the shape of points {points.shape}, got {starts.shape}, {ends.shape}"
        )
    direction = ends - starts
    length2 = _dot(direction, direction)
    projection = _dot(points - starts, direction)
    nonzero = length2 > 0.0
    parameter = np.zeros(points.shape[0])
    parameter[nonzero] = np.clip(projection[nonzero] / length2[nonzero], 0.0, 1.0)
    closest = (1.0 - parameter)[:, None] * starts + parameter[:, None] * ends
    return closest, parameter


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of two float arrays of shape (n, 3), shape (n, 3): ``np.cross(a, b)``'s bits
    (each component a_i b_j − a_j b_i, its two products and their difference rounded as np.cross rounds
    them; ``tests/geometry/test_closest.py``) without its axis handling, which costs tens of µs on the few
    rows of a step."""
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    out = np.empty((a.shape[0], 3), dtype=np.result_type(a, b))
    out[:, 0] = a1 * b2 - a2 * b1
    out[:, 1] = a2 * b0 - a0 * b2
    out[:, 2] = a0 * b1 - a1 * b0
    return out


def triangle_normals(triangles: np.ndarray) -> np.ndarray:
    """Unit normals of triangles, right-handed in the vertex order (a, b, c): (b − a) × (c − a).

    Parameters
    ----------
    triangles : Triangle vertices [m], shape (f, 3, 3).

    Returns
    -------
    Unit normals, shape (f, 3); zero for degenerate triangles.
    """
    triangles = np.asarray(triangles, dtype=float)
    normals = cross_rows(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    longest2 = _longest_edge_squared(triangles)
    good = lengths > _DEGENERATE_AREA * longest2
    normals[good] /= lengths[good, None]
    normals[~good] = 0.0
    return normals


def _longest_edge_squared(triangles: np.ndarray) -> np.ndarray:
    edges = triangles[:, [1, 2, 0]] - triangles
    return np.max(np.einsum("fij,fij->fi", edges, edges), axis=1)


def closest_points_on_triangles(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest points on triangles (one triangle per point), Ericson's region method.

    Parameters
    ----------
    points : Query points [m], shape (q, 3).
    triangles : Triangle vertices (a, b, c) [m], shape (q, 3, 3); degenerate triangles (collinear or
        coincident vertices) are allowed.

    Returns
    -------
    closest : Closest points [m], shape (q, 3), ``closest = Σ barycentric[:, k] triangles[:, k]``; exactly a
        vertex in a vertex region.
    barycentric : Barycentric coordinates of the closest points, shape (q, 3), non-negative, summing to one.
    """
    points = _check_points(points)
    triangles = np.asarray(triangles, dtype=float)
    if triangles.shape != (points.shape[0], 3, 3):
        raise ValueError(f"triangles must have shape ({points.shape[0]}, 3, 3), got {triangles.shape}")
    from refsim.geometry.closest_kernel import ericson_regular  # numba: imported on first use

    # Ericson's coordinates on the regular triangles, compiled (the bits of _ericson_path); they are
    # non-negative in every region in exact arithmetic, anything else is round-off: those pairs and the thin
    # triangles take the candidate path.
    barycentric, area2, settled = ericson_regular(
        np.ascontiguousarray(points), np.ascontiguousarray(triangles), _THIN_AREA
    )
    careful = ~settled
    if np.any(careful):
        with_face = area2[careful] > 0.0
        barycentric[careful] = _candidate_barycentric(points[careful], triangles[careful], with_face)
    closest = np.einsum("qk,qki->qi", barycentric, triangles)
    return closest, barycentric


def _ericson_path(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The regular triangles' part of :func:`closest_points_on_triangles` in NumPy (the compiled
    :func:`refsim.geometry.closest_kernel.ericson_regular`'s reference): barycentric coordinates (q, 3),
    zero where not settled, |ab × ac| (q,) and whether Ericson's formulas settled each pair (q,)."""
    barycentric = np.zeros((points.shape[0], 3))
    longest2 = _longest_edge_squared(triangles)
    area2 = np.linalg.norm(
        np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1
    )
    regular = area2 >= _THIN_AREA * longest2
    ericson = _ericson_barycentric(points[regular], triangles[regular])
    trusted = np.all(np.isfinite(ericson), axis=1) & np.all(ericson >= 0.0, axis=1)
    settled = np.zeros(points.shape[0], dtype=bool)
    settled[np.flatnonzero(regular)[trusted]] = True
    barycentric[settled] = ericson[trusted]
    return barycentric, area2, settled


def _ericson_barycentric(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of the closest points on non-degenerate triangles, shape (q, 3)."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    ab, ac = b - a, c - a
    ap, bp, cp = points - a, points - b, points - c
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4

    result = np.zeros((points.shape[0], 3))
    done = np.zeros(points.shape[0], dtype=bool)

    def assign(mask: np.ndarray, values: np.ndarray) -> None:
        take = mask & ~done
        result[take] = values[take] if values.ndim == 2 else values
        done[take] = True

    # Ericson's order of the tests: each later test assumes the earlier ones failed.
    with np.errstate(divide="ignore", invalid="ignore"):
        assign((d1 <= 0) & (d2 <= 0), np.array([1.0, 0.0, 0.0]))  # vertex a
        assign((d3 >= 0) & (d4 <= d3), np.array([0.0, 1.0, 0.0]))  # vertex b
        v = d1 / (d1 - d3)
        assign((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1.0 - v, v, np.zeros_like(v)], axis=1))  # ab
        assign((d6 >= 0) & (d5 <= d6), np.array([0.0, 0.0, 1.0]))  # vertex c
        w = d2 / (d2 - d6)
        assign((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1.0 - w, np.zeros_like(w), w], axis=1))  # ac
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        assign(
            (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), np.stack([np.zeros_like(w), 1.0 - w, w], axis=1)
        )  # bc
        denominator = va + vb + vc
        v, w = vb / denominator, vc / denominator
        assign(np.ones_like(done), np.stack([1.0 - v - w, v, w], axis=1))  # face
    return result


def _candidate_barycentric(points: np.ndarray, triangles: np.ndarray, with_face: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of the closest points on thin or degenerate triangles, shape (q, 3).

    The closest of four candidates, each a point of the triangle: the closest point of each edge, and (where
    ``with_face``) the plane projection when its sub-area coordinates are all non-negative. Ties go to the
    edges, so a point in a vertex region gets that vertex exactly.
    """
    count = points.shape[0]
    rows = np.arange(count)
    starts = triangles[:, [0, 1, 2]].reshape(-1, 3)
    ends = triangles[:, [1, 2, 0]].reshape(-1, 3)
    repeated = np.repeat(points, 3, axis=0)
    closest, parameter = closest_points_on_segments(repeated, starts, ends)
    distance2 = np.sum((closest - repeated) ** 2, axis=1).reshape(count, 3)
    edge = np.argmin(distance2, axis=1)
    t = parameter.reshape(count, 3)[rows, edge]
    result = np.zeros((count, 3))
    result[rows, edge] = 1.0 - t
    result[rows, (edge + 1) % 3] += t
    best = distance2[rows, edge]

    if np.any(with_face):
        index = np.flatnonzero(with_face)
        weights = _face_barycentric(points[index], triangles[index])
        inside = np.all(np.isfinite(weights), axis=1) & np.all(weights >= 0.0, axis=1)
        face_point = np.einsum("qk,qki->qi", weights, triangles[index])
        face_distance2 = np.sum((face_point - points[index]) ** 2, axis=1)
        better = inside & (face_distance2 < best[index])
        result[index[better]] = weights[better]
    return result


def _face_barycentric(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of the plane projections of points on thin (non-degenerate) triangles, (q, 3).

    Computed in the frame of the longest edge (u, v), opposite vertex w: ê along v − u, ê₂ the unit part of
    w − u normal to ê (the triangle's height H = |w − u − c₁ ê|, c₁ = (w − u)·ê). The point's offset from the
    edge's line, d − x ê, is small near a sliver, so the in-plane coordinate y = ê₂·(d − x ê) suffers little
    from the ill-determined plane (direction error ε L / H), and the coordinates
    b_w = y / H, b_v = (x − b_w c₁) / |v − u|, b_u = 1 − b_v − b_w rebuild u + x ê + y ê₂ to round-off even
    where b_w itself is inaccurate. May be negative (the projection is outside): the caller tests.
    """
    count = points.shape[0]
    rows = np.arange(count)
    edges = triangles[:, [1, 2, 0]] - triangles
    longest = np.argmax(np.einsum("fij,fij->fi", edges, edges), axis=1)
    u = triangles[rows, longest]
    v = triangles[rows, (longest + 1) % 3]
    w = triangles[rows, (longest + 2) % 3]
    edge = v - u
    edge_length = np.sqrt(_dot(edge, edge))
    along = edge / edge_length[:, None]
    c = w - u
    c1 = _dot(c, along)
    across = c - c1[:, None] * along
    height = np.sqrt(_dot(across, across))
    offset = points - u
    x = _dot(offset, along)
    with np.errstate(
        divide="ignore", invalid="ignore"
    ):  # height 0 (collinear to round-off): non-finite, rejected
        across /= height[:, None]
        y = _dot(across, offset - x[:, None] * along)
        weight_w = y / height
        weight_v = (x - weight_w * c1) / edge_length
    result = np.zeros((count, 3))
    result[rows, longest] = 1.0 - weight_v - weight_w
    result[rows, (longest + 1) % 3] = weight_v
    result[rows, (longest + 2) % 3] = weight_w
    return result
