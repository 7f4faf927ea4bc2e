"""Checks of a constraint problem's arrays, compiled (no temporaries): read by the problem's validation
(:mod:`refsim.solvers.problem`) and the solvers' guards (:mod:`refsim.solvers.gauss_seidel`,
:mod:`refsim.solvers.newton_kernel`). The laws themselves are :mod:`refsim.solvers.laws`."""

from __future__ import annotations

import numpy as np

from refsim.kernel_cache import numba

__all__ = ["all_finite", "relative_asymmetry"]


@numba.njit(cache=True)
def all_finite(vector):
    """Whether every entry of a 1-D array is finite (np.isfinite(v).all() without its temporary)."""
    for value in vector:
        if not np.isfinite(value):
            return False
    return True


@numba.njit(cache=True)
def relative_asymmetry(matrix):
    """‖A − Aᵀ‖_F / ‖A‖_F of a square matrix (0 for a zero matrix), without temporaries; overflow-safe by
    scaling with the largest entry."""
    n = matrix.shape[0]
    largest = 0.0
    for i in range(n):
        for j in range(n):
            largest = max(largest, abs(matrix[i, j]))
    if largest == 0.0 or not np.isfinite(largest):
        return 0.0 if largest == 0.0 else np.nan
    skew = 0.0
    total = 0.0
    for i in range(n):
        total += (matrix[i, i] / largest) ** 2
        for j in range(i + 1, n):
            a = matrix[i, j] / largest
            b = matrix[j, i] / largest
            total += a * a + b * b
            skew += 2.0 * (a - b) * (a - b)
    return np.sqrt(skew) / np.sqrt(total)
