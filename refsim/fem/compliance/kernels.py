"""Compiled kernels of the fast strategy's rotated rest compliance R C₀ Rᵀ
(:class:`refsim.fem.compliance.Fast`).

C₀ = A₀⁻¹ is kept as the columns C₀ E_g of the free nodes g the rows touched, one (f, 3) solve each, stored
transposed: ``rows[3 s + k]`` is the column C₀ e_{3g+k} of the node in slot s (``slots[g]`` = s),
contiguous. R is block-diagonal, one rotation per free node. Each kernel sums in an order fixed by the node
numbers, never by the slots (the order the nodes were first asked for), so its bits depend on no history: a
restarted run fills its memo in another order and gets the same numbers.
"""

from __future__ import annotations

import numpy as np

from refsim.kernel_cache import numba


@numba.njit(cache=True)
def scatter_columns(indptr, indices, data, where, out):  # pragma: no cover - compiled
    """out[row, where[column]] = value + 0.0 for each entry of a canonical CSR (indptr, indices, data) whose
    column has ``where`` ≥ 0 (out zero beforehand; + 0.0 as toarray's sum into zeros: −0.0 becomes 0.0): the
    dense columns of the rows that W and the correction read (:meth:`StepCompliance._influence`)."""
    for row in range(indptr.size - 1):
        for k in range(indptr[row], indptr[row + 1]):
            column = where[indices[k]]
            if column >= 0:
                out[row, column] = data[k] + 0.0


@numba.njit(cache=True)
def turn_nodes(rotations, values, transpose, out):  # pragma: no cover - compiled
    """out = R v (Rᵀ v when ``transpose``) for v on every free node, rotations (g, 3, 3), v and out (3g,)."""
    for g in range(rotations.shape[0]):
        v0, v1, v2 = values[3 * g], values[3 * g + 1], values[3 * g + 2]
        for i in range(3):
            if transpose:
                out[3 * g + i] = rotations[g, 0, i] * v0 + rotations[g, 1, i] * v1 + rotations[g, 2, i] * v2
            else:
                out[3 * g + i] = rotations[g, i, 0] * v0 + rotations[g, i, 1] * v1 + rotations[g, i, 2] * v2


@numba.njit(cache=True)
def rotated_block(rows, slots, groups, rotations, out):  # pragma: no cover - compiled
    """out = (R C₀ Rᵀ) on the free nodes ``groups`` (sorted), shape (3n, 3n): block (a, b) is
    R_a C₀[a, b] R_bᵀ with C₀[a, b][k, l] = C₀ e_{3b+l} at DoF 3a + k."""
    n = groups.size
    left = np.empty((3, 3))
    for b in range(n):
        column = 3 * slots[groups[b]]
        rb = rotations[groups[b]]
        for a in range(n):
            ra = rotations[groups[a]]
            base = 3 * groups[a]
            # left = R_a C₀[a, b]
            for i in range(3):
                for k in range(3):
                    left[i, k] = (
                        ra[i, 0] * rows[column + k, base]
                        + ra[i, 1] * rows[column + k, base + 1]
                        + ra[i, 2] * rows[column + k, base + 2]
                    )
            # (R_a C₀[a, b]) R_bᵀ
            for i in range(3):
                for j in range(3):
                    out[3 * a + i, 3 * b + j] = (
                        left[i, 0] * rb[j, 0] + left[i, 1] * rb[j, 1] + left[i, 2] * rb[j, 2]
                    )


@numba.njit(cache=True)
def rotated_apply(rows, slots, groups, rotations, load, rest, out):  # pragma: no cover - compiled
    """out = R C₀ Rᵀ load for a load (3g,) on the free nodes ``groups`` (sorted) only; ``rest`` (3g,) is
    scratch (C₀ Rᵀ load, summed node by node in the order of ``groups``)."""
    rest[:] = 0.0
    for index in range(groups.size):
        g = groups[index]
        r = rotations[g]
        l0, l1, l2 = load[3 * g], load[3 * g + 1], load[3 * g + 2]
        column = 3 * slots[g]
        for k in range(3):
            local = r[0, k] * l0 + r[1, k] * l1 + r[2, k] * l2  # (Rᵀ load)_k
            source = rows[column + k]
            for d in range(rest.size):
                rest[d] += source[d] * local
    turn_nodes(rotations, rest, False, out)
