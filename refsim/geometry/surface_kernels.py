"""Compiled passes over small surfaces and polylines (numba): the cut surface's vertex normals and the closest
points of a polyline, evaluated for a few dozen needle samples every cutting step.

Each does the operations of its NumPy reference in the same order and gives its bits
(``tests/geometry/test_surface_kernels.py``): NumPy's cost there was its many small arrays, not its
arithmetic.
"""

from __future__ import annotations

import numpy as np

from refsim.kernel_cache import numba

__all__ = ["polyline_closest", "vertex_normals"]


def vertex_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit area-weighted vertex normals of a triangle surface, shape (point_count, 3).

    Each vertex sums the (unnormalised) normals (b − a) × (c − a) of its triangles, in the order of the
    triangles' corners (corner 0 of every triangle, then corner 1, then corner 2), and is divided by the
    sum's norm (at least 1e-300: a vertex in no triangle stays zero).

    Parameters
    ----------
    points : Vertex positions [m], shape (point_count, 3).
    triangles : Vertex indices, shape (triangle_count, 3).
    """
    return _vertex_normals(
        np.ascontiguousarray(points, dtype=float), np.ascontiguousarray(triangles, dtype=np.int64)
    )


@numba.njit(cache=True)
def _vertex_normals(points, triangles):  # pragma: no cover - compiled
    count = triangles.shape[0]
    face = np.empty((count, 3))
    for t in range(count):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        u0, u1, u2 = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1], points[b, 2] - points[a, 2]
        v0, v1, v2 = points[c, 0] - points[a, 0], points[c, 1] - points[a, 1], points[c, 2] - points[a, 2]
        face[t, 0] = u1 * v2 - u2 * v1
        face[t, 1] = u2 * v0 - u0 * v2
        face[t, 2] = u0 * v1 - u1 * v0
    summed = np.zeros((points.shape[0], 3))
    for corner in range(3):
        for t in range(count):
            vertex = triangles[t, corner]
            for axis in range(3):
                summed[vertex, axis] += face[t, axis]
    for vertex in range(points.shape[0]):
        x, y, z = summed[vertex, 0], summed[vertex, 1], summed[vertex, 2]
        length = max(np.sqrt(x * x + y * y + z * z), 1e-300)
        for axis in range(3):
            summed[vertex, axis] /= length
    return summed


def polyline_closest(points: np.ndarray, polyline: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest segment of a polyline to each point, and the projection's parameters on it.

    Parameters
    ----------
    points : Query points [m], shape (k, 3).
    polyline : Its vertices [m], shape (s + 1, 3), s ≥ 1.

    Returns
    -------
    segment : The segment whose clamped projection is closest (the first of equal distances), shape (k,).
    parameter : The clamped parameter t ∈ [0, 1] on it, shape (k,).
    raw : The unclamped parameter on it ((p − a)·(b − a) / |b − a|², over 1 for a zero-length segment),
        shape (k,).
    """
    return _polyline_closest(
        np.ascontiguousarray(points, dtype=float), np.ascontiguousarray(polyline, dtype=float)
    )


@numba.njit(cache=True)
def _polyline_closest(points, polyline):  # pragma: no cover - compiled
    count, segments = points.shape[0], polyline.shape[0] - 1
    segment = np.zeros(count, dtype=np.int64)
    parameter = np.zeros(count)
    raw = np.zeros(count)
    for k in range(count):
        best = np.inf
        for s in range(segments):
            a0, a1, a2 = polyline[s, 0], polyline[s, 1], polyline[s, 2]
            d0, d1, d2 = polyline[s + 1, 0] - a0, polyline[s + 1, 1] - a1, polyline[s + 1, 2] - a2
            # einsum over three components sums (p0 + p2) + p1 (refsim.geometry.closest_kernel)
            length = (d0 * d0 + d2 * d2) + d1 * d1
            o0, o1, o2 = points[k, 0] - a0, points[k, 1] - a1, points[k, 2] - a2
            r = ((o0 * d0 + o2 * d2) + o1 * d1) / (length if length > 0.0 else 1.0)
            t = min(max(r, 0.0), 1.0)
            e0 = points[k, 0] - (a0 + t * d0)
            e1 = points[k, 1] - (a1 + t * d1)
            e2 = points[k, 2] - (a2 + t * d2)
            distance = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
            if s == 0 or distance < best or np.isnan(distance):  # np.argmin: the first least, or first NaN
                best = distance
                segment[k], parameter[k], raw[k] = s, t, r
                if np.isnan(distance):
                    break
    return segment, parameter, raw
