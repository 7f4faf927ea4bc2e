"""Compiled parts of the ring coupling (numba): the tissue side of ring-averaged rows, the rings' points.

:func:`refsim.constraints.coupling.ring_weights` gives each insertion point's nodes and weights, the mean of
its ring points' interpolations. A step builds them for every insertion point and for the tip's ring; in
NumPy they took about fifteen calls on arrays of a few dozen entries, each costing more than its arithmetic.
Here one pass per point does the same operations in the same order (``tests/constraints/test_coupling.py``
holds the two to the same bits).
"""

from __future__ import annotations

import numpy as np

from refsim.kernel_cache import numba

__all__ = ["ring_nodes_weights", "ring_point_positions"]

# np.nan_to_num's replacement of +inf and −inf (float64's largest and smallest finite values).
_LARGEST = np.finfo(np.float64).max


@numba.njit(cache=True)
def ring_nodes_weights(
    centre_tets, centre_barycentric, ring_tets, ring_barycentric, mesh_tets
):  # pragma: no cover
    """Nodes and weights of ring-averaged rows, shapes (p, 4 (q + 1)) each (q even or 1).

    Column block 0 is the centre, weight 1 when no ring point is kept, else 0; block 1 + k the ring point k,
    weight (1 / kept count) × its barycentric coordinates when it and its antipode (k + q/2 mod q) lie in the
    tissue, else 0 × its coordinates (NaN read as 0, ±inf as ±the largest float: np.nan_to_num), node 0 of
    tet 0 when it lies outside. The products are NumPy's (share × coordinate, the share a float division).
    """
    points, per_ring = ring_tets.shape
    half = per_ring // 2
    width = 4 * (per_ring + 1)
    nodes = np.empty((points, width), dtype=mesh_tets.dtype)
    weights = np.empty((points, width))
    inside = np.empty(per_ring, dtype=np.bool_)
    for p in range(points):
        count = 0
        for k in range(per_ring):
            kept = ring_tets[p, k] >= 0
            if per_ring > 1:
                kept = kept and ring_tets[p, (k + half) % per_ring] >= 0
            inside[k] = kept
            if kept:
                count += 1
        centre_share = 1.0 if count == 0 else 0.0
        for c in range(4):
            nodes[p, c] = mesh_tets[centre_tets[p], c]
            weights[p, c] = centre_share * centre_barycentric[p, c]
        divisor = float(max(count, 1))
        for k in range(per_ring):
            share = (1.0 if inside[k] else 0.0) / divisor
            tet = ring_tets[p, k] if inside[k] else 0
            for c in range(4):
                value = ring_barycentric[p, k, c]
                if np.isnan(value):
                    value = 0.0
                elif value == np.inf:
                    value = _LARGEST
                elif value == -np.inf:
                    value = -_LARGEST
                nodes[p, 4 * (k + 1) + c] = mesh_tets[tet, c]
                weights[p, 4 * (k + 1) + c] = share * value
    return nodes, weights


@numba.njit(cache=True)
def ring_point_positions(centres, first, second, radius, cosines, sines):  # pragma: no cover
    """Points of rings around centres [m], shape (p, q, 3): centre + ρ (cos θ_k e₁ + sin θ_k e₂), each
    component computed as NumPy's broadcast expression ``centres[:, None] + radius[:, None, None] *
    (cosines * first[:, None] + sines * second[:, None])`` computes it, in that order (the same bits;
    :func:`refsim.constraints.coupling.ring_points`).

    centres, first, second : shape (p, 3). radius : shape (p,). cosines, sines : shape (q,).
    """
    points = centres.shape[0]
    count = cosines.shape[0]
    out = np.empty((points, count, 3))
    for p in range(points):
        for k in range(count):
            for j in range(3):
                out[p, k, j] = centres[p, j] + radius[p] * (
                    cosines[k] * first[p, j] + sines[k] * second[p, j]
                )
    return out
