"""Closest points on segments and triangles, vectorised over queries.

The triangle kernel is Ericson's Voronoi-region method ("Real-Time Collision Detection", 2005, §5.1.5): the
region of the point (three vertex regions, three edge regions, the face) is decided from six dot products,
here with numpy masks instead of early returns. Triangles whose area vanishes relative to their longest edge
(collinear or coincident vertices) fall back to the closest of their three edges.
"""

from __future__ import annotations

import numpy as np

__all__ = ["closest_points_on_segments", "closest_points_on_triangles", "triangle_normals"]

# A triangle is degenerate when |ab × ac| <= _DEGENERATE_AREA * (longest edge)²: its normal is then lost in
# round-off and the face-region formulas divide by (nearly) zero.
_DEGENERATE_AREA = 1e-12


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
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
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
    barycentric = np.zeros((points.shape[0], 3))
    area2 = np.linalg.norm(
        np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1
    )
    degenerate = area2 <= _DEGENERATE_AREA * _longest_edge_squared(triangles)
    regular = ~degenerate
    barycentric[regular] = _ericson_barycentric(points[regular], triangles[regular])
    if np.any(degenerate):
        barycentric[degenerate] = _degenerate_barycentric(points[degenerate], triangles[degenerate])
    closest = np.einsum("qk,qki->qi", barycentric, triangles)
    return closest, barycentric


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


def _degenerate_barycentric(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of the closest points on degenerate triangles: the closest of their edges."""
    count = points.shape[0]
    starts = triangles[:, [0, 1, 2]].reshape(-1, 3)
    ends = triangles[:, [1, 2, 0]].reshape(-1, 3)
    closest, parameter = closest_points_on_segments(np.repeat(points, 3, axis=0), starts, ends)
    distance2 = np.sum((closest - np.repeat(points, 3, axis=0)) ** 2, axis=1).reshape(count, 3)
    edge = np.argmin(distance2, axis=1)
    t = parameter.reshape(count, 3)[np.arange(count), edge]
    result = np.zeros((count, 3))
    rows = np.arange(count)
    result[rows, edge] = 1.0 - t
    result[rows, (edge + 1) % 3] += t
    return result
