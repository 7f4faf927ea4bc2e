"""Compiled part of the closest points on triangles (numba): Ericson's region method on well-shaped triangles.

:func:`refsim.geometry.closest.closest_points_on_triangles` evaluates a few candidate pairs per query (the
tip, the shaft's samples, the needle's samples on the cut); in NumPy its masks and small arrays cost far more
than its arithmetic. This pass does, pair by pair, the operations of the NumPy path in its order (the cross
product's components a₁b₂ − a₂b₁, ...; an einsum of three products sums (p₀ + p₂) + p₁; a norm sums its
squares left to right; Ericson's tests in his order) and gives its bits (``tests/geometry/test_closest.py``).
Thin triangles, and the rare pairs whose coordinates come out negative or non-finite, are left to the NumPy
candidate path as before.
"""

from __future__ import annotations

import numpy as np

from refsim.kernel_cache import numba

__all__ = ["ericson_regular"]


@numba.njit(cache=True, error_model="numpy")
def _dot(x0, x1, x2, y0, y1, y2):  # pragma: no cover - compiled
    # np.einsum("ij,ij->i") over three components: (p₀ + p₂) + p₁
    return (x0 * y0 + x2 * y2) + x1 * y1


@numba.njit(cache=True, error_model="numpy")
def triangle_shape(triangles, index):  # pragma: no cover - compiled
    """|ab × ac| and the longest edge squared of triangle ``index`` of ``triangles`` (t, 3, 3): NumPy's thin
    test's two quantities (`refsim.geometry.closest`), in its operations and order."""
    ax, ay, az = triangles[index, 0, 0], triangles[index, 0, 1], triangles[index, 0, 2]
    bx, by, bz = triangles[index, 1, 0], triangles[index, 1, 1], triangles[index, 1, 2]
    cx, cy, cz = triangles[index, 2, 0], triangles[index, 2, 1], triangles[index, 2, 2]
    # the longest edge squared: edges b − a, c − b, a − c
    e0x, e0y, e0z = bx - ax, by - ay, bz - az
    e1x, e1y, e1z = cx - bx, cy - by, cz - bz
    e2x, e2y, e2z = ax - cx, ay - cy, az - cz
    longest = max(
        _dot(e0x, e0y, e0z, e0x, e0y, e0z),
        _dot(e1x, e1y, e1z, e1x, e1y, e1z),
        _dot(e2x, e2y, e2z, e2x, e2y, e2z),
    )
    acx, acy, acz = cx - ax, cy - ay, cz - az
    n0 = e0y * acz - e0z * acy
    n1 = e0z * acx - e0x * acz
    n2 = e0x * acy - e0y * acx
    return np.sqrt(n0 * n0 + n1 * n1 + n2 * n2), longest


@numba.njit(cache=True, error_model="numpy")
def ericson_regular(points, triangles, thin_area):  # pragma: no cover - compiled
    """Barycentric coordinates (q, 3) of the closest points on the triangles (one per point), |ab × ac| (q,)
    and whether each pair was settled here (q,): a regular triangle (|ab × ac| ≥ thin_area × longest edge²)
    whose coordinates are finite and non-negative; the others have zeros, for the caller's candidate path."""
    count = points.shape[0]
    barycentric = np.zeros((count, 3))
    area = np.empty(count)
    settled = np.zeros(count, dtype=np.bool_)
    for q in range(count):
        area[q], longest = triangle_shape(triangles, q)
        if not area[q] >= thin_area * longest:
            continue
        ax, ay, az = triangles[q, 0, 0], triangles[q, 0, 1], triangles[q, 0, 2]
        bx, by, bz = triangles[q, 1, 0], triangles[q, 1, 1], triangles[q, 1, 2]
        cx, cy, cz = triangles[q, 2, 0], triangles[q, 2, 1], triangles[q, 2, 2]
        abx, aby, abz = bx - ax, by - ay, bz - az
        acx, acy, acz = cx - ax, cy - ay, cz - az
        px, py, pz = points[q, 0], points[q, 1], points[q, 2]
        apx, apy, apz = px - ax, py - ay, pz - az
        bpx, bpy, bpz = px - bx, py - by, pz - bz
        cpx, cpy, cpz = px - cx, py - cy, pz - cz
        d1 = _dot(abx, aby, abz, apx, apy, apz)
        d2 = _dot(acx, acy, acz, apx, apy, apz)
        d3 = _dot(abx, aby, abz, bpx, bpy, bpz)
        d4 = _dot(acx, acy, acz, bpx, bpy, bpz)
        d5 = _dot(abx, aby, abz, cpx, cpy, cpz)
        d6 = _dot(acx, acy, acz, cpx, cpy, cpz)
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        # Ericson's order of the tests: each later test assumes the earlier ones failed.
        if d1 <= 0 and d2 <= 0:
            u, v, w = 1.0, 0.0, 0.0
        elif d3 >= 0 and d4 <= d3:
            u, v, w = 0.0, 1.0, 0.0
        elif vc <= 0 and d1 >= 0 and d3 <= 0:
            v = d1 / (d1 - d3)
            u, w = 1.0 - v, 0.0
        elif d6 >= 0 and d5 <= d6:
            u, v, w = 0.0, 0.0, 1.0
        elif vb <= 0 and d2 >= 0 and d6 <= 0:
            w = d2 / (d2 - d6)
            u, v = 1.0 - w, 0.0
        elif va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            u, v = 0.0, 1.0 - w
        else:
            denominator = va + vb + vc
            v, w = vb / denominator, vc / denominator
            u = 1.0 - v - w
        if np.isfinite(u) and np.isfinite(v) and np.isfinite(w) and u >= 0.0 and v >= 0.0 and w >= 0.0:
            barycentric[q, 0], barycentric[q, 1], barycentric[q, 2] = u, v, w
            settled[q] = True
    return barycentric, area, settled
