"""Compiled passes over small surfaces and polylines (numba): the cut surface's vertex normals, whether a
closest point lies inside an open surface, and the closest points of a polyline, evaluated for a few dozen
needle samples every cutting step.

Each does the operations of its NumPy reference in the same order and gives its bits
(``tests/geometry/test_surface_kernels.py``; the inside test against ``CutSurface._inside_reference`` in
``tests/cutting/test_surface.py``): NumPy's cost there was its many small arrays, not its arithmetic.
"""

from __future__ import annotations

import numpy as np

from refsim.geometry.closest_kernel import _dot  # np.einsum("qi,qi->q")'s order: (p₀ + p₂) + p₁
from refsim.kernel_cache import numba

__all__ = ["inside_surface", "polyline_closest", "vertex_normals"]


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


def inside_surface(
    points: np.ndarray,
    corners: np.ndarray,
    barycentric: np.ndarray,
    local: np.ndarray,
    tolerance: float,
    edge_keys: np.ndarray,
    edge_uses: np.ndarray,
    key_base: int,
    border_points: np.ndarray,
) -> np.ndarray:
    """Whether each query projects inside an open triangle surface, from its closest point, shape (q,) bool
    (:meth:`refsim.cutting.CutSurface.closest_points`).

    Inside when the orthogonal projection on the closest triangle's plane has all three barycentric
    coordinates ≥ −``tolerance`` (non-finite ones count as −∞); else, a closest point on an edge (one
    coordinate ≤ ``tolerance``) is inside when the edge is used by two triangles, one at a vertex (two) when
    the vertex is not on the border.

    Parameters
    ----------
    points : Query points [m], shape (q, 3).
    corners : The closest triangles' vertices [m], shape (q, 3, 3).
    barycentric : The closest points' barycentric coordinates there, shape (q, 3).
    local : The closest triangles' vertex indices, shape (q, 3).
    tolerance : Tolerance on barycentric coordinates.
    edge_keys : Undirected edge keys min·key_base + max, sorted, shape (e,); ``edge_uses`` their triangle
        counts, shape (e,).
    key_base : max(point_count, 1).
    border_points : The border's vertices, sorted, shape (b,).
    """
    return _inside_surface(
        np.ascontiguousarray(points, dtype=float),
        np.ascontiguousarray(corners, dtype=float),
        np.ascontiguousarray(barycentric, dtype=float),
        np.ascontiguousarray(local, dtype=np.int64),
        float(tolerance),
        np.ascontiguousarray(edge_keys, dtype=np.int64),
        np.ascontiguousarray(edge_uses),
        int(key_base),
        np.ascontiguousarray(border_points, dtype=np.int64),
    )


@numba.njit(cache=True)
def _sorted_index(values, key):  # pragma: no cover - compiled
    # np.clip(np.searchsorted(values, key), 0, len - 1)
    position = np.searchsorted(values, key)
    return min(max(position, 0), values.shape[0] - 1)


@numba.njit(cache=True, error_model="numpy")
def _inside_surface(
    points, corners, barycentric, local, tolerance, edge_keys, edge_uses, key_base, border_points
):  # pragma: no cover - compiled
    count = points.shape[0]
    inside = np.empty(count, dtype=np.bool_)
    for q in range(count):
        # the projection's coordinates on the triangle's plane: refsim.cutting.surface._plane_barycentric's
        # operations in its order
        ax, ay, az = corners[q, 0, 0], corners[q, 0, 1], corners[q, 0, 2]
        v0x, v0y, v0z = corners[q, 1, 0] - ax, corners[q, 1, 1] - ay, corners[q, 1, 2] - az
        v1x, v1y, v1z = corners[q, 2, 0] - ax, corners[q, 2, 1] - ay, corners[q, 2, 2] - az
        v2x, v2y, v2z = points[q, 0] - ax, points[q, 1] - ay, points[q, 2] - az
        d00 = _dot(v0x, v0y, v0z, v0x, v0y, v0z)
        d01 = _dot(v0x, v0y, v0z, v1x, v1y, v1z)
        d11 = _dot(v1x, v1y, v1z, v1x, v1y, v1z)
        d20 = _dot(v2x, v2y, v2z, v0x, v0y, v0z)
        d21 = _dot(v2x, v2y, v2z, v1x, v1y, v1z)
        denominator = d00 * d11 - d01 * d01
        v = (d11 * d20 - d01 * d21) / denominator
        w = (d00 * d21 - d01 * d20) / denominator
        u = 1.0 - v - w
        projected_inside = True
        for value in (u, v, w):
            if not np.isfinite(value) or not value >= -tolerance:
                projected_inside = False
        if projected_inside:
            inside[q] = True
            continue
        zeros = 0
        first_zero, first_nonzero = -1, -1
        for k in range(3):
            if barycentric[q, k] <= tolerance:
                zeros += 1
                if first_zero < 0:
                    first_zero = k
            elif first_nonzero < 0:
                first_nonzero = k
        if zeros == 1:  # on the edge opposite the zero coordinate: inside when two triangles share it
            start, end = local[q, (first_zero + 1) % 3], local[q, (first_zero + 2) % 3]
            key = min(start, end) * key_base + max(start, end)
            if edge_keys.shape[0] == 0:
                inside[q] = False
                continue
            position = _sorted_index(edge_keys, key)
            uses = edge_uses[position] if edge_keys[position] == key else 0
            inside[q] = uses >= 2
        elif zeros == 2:  # at the vertex of the non-zero coordinate: inside off the border
            vertex = local[q, first_nonzero]
            if border_points.shape[0] == 0:
                inside[q] = True
                continue
            position = _sorted_index(border_points, vertex)
            inside[q] = border_points[position] != vertex
        else:
            inside[q] = False
    return inside


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
