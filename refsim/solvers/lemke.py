"""Lemke's complementary pivoting for the problems without friction: LCPs and MLCPs with any (non-symmetric)
W.

The linear complementarity problem LCP(M, q): find z ≥ 0 with w = M z + q ≥ 0 and zᵀw = 0 — our unilateral
rows (M = W, q = δ_free). Lemke's method (Lemke 1965; Cottle, Pang and Stone 1992, §4.4) adds an artificial
variable z₀ with the covering vector d = 1, w = q + d z₀ + M z, and pivots from the almost-complementary basis
{w} until z₀ leaves the basis (a solution) or the entering column has no positive entry (a secondary ray:
for a copositive-plus M this proves the LCP infeasible). It needs neither symmetry nor monotonicity; it
solves every LCP whose M is a P-matrix, copositive-plus with a feasible LCP, and many others that a Newton or
Gauss–Seidel method cannot (non-monotone, where the merit function has stationary points that are not
solutions).

Bilateral rows (δ = 0, λ free; an MLCP) are eliminated first by their Schur complement when W_bb is
invertible: λ_b = −W_bb⁻¹ (W_bu λ_u + δ_free,b), leaving LCP(W_uu − W_ub W_bb⁻¹ W_bu, q_u − W_ub W_bb⁻¹ q_b);
otherwise each free λ_b is split into two non-negative parts (λ_b = λ_b⁺ − λ_b⁻, with the rows ±δ_b ≥ 0).

The pivots run on a dense tableau in compiled code; the ratio test is lexicographic (no cycling on
degenerate problems) and lets z₀ leave first on a tie. The basis it ends with fixes the active set; the
solution is then recomputed from that active set by an LU solve on the original data (no accumulated pivoting
error), and checked by the natural residual.
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.linalg

from refsim.kernel_cache import numba
from refsim.solvers.laws import BILATERAL, LAWS, UNILATERAL
from refsim.solvers.problem import ConstraintProblem

__all__ = ["LemkeResult", "lemke_applicable", "solve_lemke", "solve_lcp_lemke"]

#: Pivot entries at most this times their round-off bound Σ_k |B⁻¹_ik| max|A_e| count as zero.
_PIVOT_TOLERANCE = 1e-13


class LemkeResult:
    """What :func:`solve_lemke` did."""

    def __init__(self, multipliers, status, pivots, message):
        self.multipliers = multipliers  # λ [N] or None
        self.status = status  # "solved", "ray", "pivot cap", "not applicable"
        self.pivots = pivots
        self.message = message


#: The row fields of every law of the table but bilateral and unilateral.
_OTHER_ROW_FIELDS = tuple(
    name for law in LAWS if law.code not in (BILATERAL, UNILATERAL) for name in law.row_fields
)


def lemke_applicable(problem: ConstraintProblem) -> bool:
    """True for problems of bilateral and unilateral rows only, some unilateral (an LCP or an MLCP): no row of
    any other law of the table."""
    return len(problem.unilateral) > 0 and not any(len(getattr(problem, name)) for name in _OTHER_ROW_FIELDS)


@numba.njit(cache=True)
def _lemke_pivots(matrix, q, max_pivots):
    """Lemke's method on LCP(matrix, q) with covering vector 1.

    Returns (status, basis, values, pivots): status 0 solved, 1 secondary ray, 2 pivot cap; basis[i] the
    variable basic in row i (0..n−1: w_i, n..2n−1: z_i, 2n: z₀), values the basic variables' values.
    """
    n = q.shape[0]
    columns = 2 * n + 1
    # tableau rows: B⁻¹ [I, −M, −1 | q]
    tableau = np.zeros((n, columns + 1))
    for i in range(n):
        tableau[i, i] = 1.0
        for j in range(n):
            tableau[i, n + j] = -matrix[i, j]
        tableau[i, 2 * n] = -1.0
        tableau[i, columns] = q[i]
    basis = np.arange(n)
    candidates = np.empty(n, dtype=np.int64)
    ratios = np.empty(n)
    weights = np.empty(n)
    q_scale = 0.0
    for i in range(n):
        q_scale = max(q_scale, abs(q[i]))
    # z₀ enters; the row of the most negative q leaves (on a tie the last: the tableau then stays
    # lexicographically positive, which the ratio test below keeps)
    row = 0
    for i in range(1, n):
        if q[i] <= q[row]:
            row = i
    entering = 2 * n
    pivots = 0
    while True:
        # pivot on (row, entering)
        value = tableau[row, entering]
        for j in range(columns + 1):
            tableau[row, j] /= value
        for i in range(n):
            if i != row:
                factor = tableau[i, entering]
                if factor != 0.0:
                    for j in range(columns + 1):
                        tableau[i, j] -= factor * tableau[row, j]
        leaving = basis[row]
        basis[row] = entering
        pivots += 1
        if leaving == 2 * n:
            return 0, basis, tableau[:, columns].copy(), pivots
        if pivots >= max_pivots:
            return 2, basis, tableau[:, columns].copy(), pivots
        entering = leaving + n if leaving < n else leaving - n
        # ratio test on the column of the entering variable (it must decrease some basic variable). An entry
        # counts as positive above its round-off: entry i of B⁻¹ A_e carries an error of about
        # ε Σ_k |B⁻¹_ik| |A_ke|, bounded with the original column's largest entry
        if entering < n:
            column_scale = 1.0
        elif entering < 2 * n:
            column_scale = 0.0
            for i in range(n):
                column_scale = max(column_scale, abs(matrix[i, entering - n]))
        else:
            column_scale = 1.0
        count = 0
        for i in range(n):
            weight = 0.0
            for k in range(n):
                weight += abs(tableau[i, k])
            if tableau[i, entering] > _PIVOT_TOLERANCE * weight * column_scale:
                candidates[count] = i
                weights[count] = weight / tableau[i, entering]
                count += 1
        # lexicographic minimum ratio (rows of [q, B⁻¹] over the pivot entry: no cycling), z0's row first.
        # Two values tie when they differ by less than their round-off bound (entry i of column k of [q, B⁻¹]:
        # about ε Σ_j |B⁻¹_ij| times max|q| for q, times 1 for B⁻¹)
        row = -1
        if count > 0:
            for k in range(n + 1):
                column = columns if k == 0 else k - 1
                scale = q_scale if k == 0 else 1.0
                low = np.inf
                for c in range(count):
                    i = candidates[c]
                    value = tableau[i, column]
                    if k == 0:
                        value = max(value, 0.0)
                    value /= tableau[i, entering]
                    ratios[c] = value
                    low = min(low, value)
                kept = 0
                for c in range(count):
                    if ratios[c] <= low + _PIVOT_TOLERANCE * weights[c] * scale:
                        candidates[kept] = candidates[c]
                        weights[kept] = weights[c]
                        kept += 1
                count = kept
                if k == 0:
                    for c in range(count):
                        if basis[candidates[c]] == 2 * n:
                            candidates[0] = candidates[c]
                            count = 1
                            break
                if count == 1:
                    break
            row = candidates[0]
        if row < 0:
            return 1, basis, tableau[:, columns].copy(), pivots


def solve_lcp_lemke(matrix: np.ndarray, q: np.ndarray, max_pivots: int | None = None):
    """z ≥ 0, w = M z + q ≥ 0, zᵀw = 0 by Lemke's method; returns (z or None, status, pivots).

    The active set of the final basis is re-solved on the original data (LU) so that z carries no pivoting
    error; status is "solved", "ray" (secondary ray termination) or "pivot cap".
    """
    matrix = np.ascontiguousarray(matrix, dtype=np.float64)
    q = np.ascontiguousarray(q, dtype=np.float64)
    n = q.size
    if n == 0 or np.all(q >= 0.0):
        return np.zeros(n), "solved", 0
    cap = int(max_pivots) if max_pivots is not None else max(100, 50 * n)
    status, basis, values, pivots = _lemke_pivots(matrix, q, cap)
    if status != 0:
        return None, ("ray" if status == 1 else "pivot cap"), int(pivots)
    z = np.zeros(n)
    basic_z = basis[(basis >= n) & (basis < 2 * n)] - n
    rows = np.flatnonzero((basis >= n) & (basis < 2 * n))
    z[basic_z] = np.maximum(values[rows], 0.0)
    if basic_z.size:
        # the active set's equations M_AA z_A = −q_A, solved on the data (refines the tableau's values)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # ill-conditioned: judged by the check below
                refined = scipy.linalg.solve(
                    matrix[np.ix_(basic_z, basic_z)], -q[basic_z], check_finite=False
                )
        except (np.linalg.LinAlgError, ValueError):
            refined = None
        if (
            refined is not None
            and np.all(np.isfinite(refined))
            and np.all(refined >= -1e-9 * max(1.0, np.abs(refined).max()))
        ):
            z[:] = 0.0
            z[basic_z] = np.maximum(refined, 0.0)
    return z, "solved", int(pivots)


def solve_lemke(problem: ConstraintProblem, max_pivots: int | None = None) -> LemkeResult:
    """Lemke's method on an LCP or MLCP problem (see the module notes); W as given."""
    if not lemke_applicable(problem):
        return LemkeResult(None, "not applicable", 0, "Lemke: only problems of bilateral and unilateral rows")
    W = problem.compliance
    q = problem.free_gap
    n = problem.row_count
    b = np.asarray(problem.bilateral, dtype=np.int64)
    u = np.asarray(problem.unilateral, dtype=np.int64)
    multipliers = np.zeros(n)
    if b.size == 0:
        z, status, pivots = solve_lcp_lemke(W[np.ix_(u, u)], q[u], max_pivots)
        if z is None:
            return LemkeResult(None, status, pivots, f"Lemke: {status} after {pivots} pivots")
        multipliers[u] = z
        return LemkeResult(multipliers, status, pivots, f"Lemke: {pivots} pivots")
    W_bb = W[np.ix_(b, b)]
    W_bu = W[np.ix_(b, u)]
    W_ub = W[np.ix_(u, b)]
    W_uu = W[np.ix_(u, u)]
    schur = None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a singular W_bb is handled below
            factor = scipy.linalg.lu_factor(W_bb, check_finite=False)
        if np.min(np.abs(np.diag(factor[0]))) > 1e-13 * max(np.abs(W_bb).max(), 1e-300):
            schur = factor
    except (np.linalg.LinAlgError, ValueError):
        schur = None
    if schur is not None:
        solved_bu = scipy.linalg.lu_solve(schur, W_bu, check_finite=False)
        solved_q = scipy.linalg.lu_solve(schur, q[b], check_finite=False)
        z, status, pivots = solve_lcp_lemke(W_uu - W_ub @ solved_bu, q[u] - W_ub @ solved_q, max_pivots)
        if z is None:
            return LemkeResult(
                None,
                status,
                pivots,
                f"Lemke (Schur complement of the bilateral rows): {status} after {pivots} pivots",
            )
        multipliers[u] = z
        multipliers[b] = -(solved_bu @ z + solved_q)
        return LemkeResult(
            multipliers, status, pivots, f"Lemke (Schur complement of the bilateral rows): {pivots} pivots"
        )
    # W_bb singular: free multipliers split into two non-negative parts, bilateral rows as ±δ_b ≥ 0
    M = np.block([[W_bb, -W_bb, W_bu], [-W_bb, W_bb, -W_bu], [W_ub, -W_ub, W_uu]])
    z, status, pivots = solve_lcp_lemke(M, np.concatenate([q[b], -q[b], q[u]]), max_pivots)
    if z is None:
        return LemkeResult(None, status, pivots, f"Lemke (split free rows): {status} after {pivots} pivots")
    multipliers[b] = z[: b.size] - z[b.size : 2 * b.size]
    multipliers[u] = z[2 * b.size :]
    return LemkeResult(multipliers, status, pivots, f"Lemke (split free rows): {pivots} pivots")
