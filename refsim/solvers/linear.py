"""The linear systems of a dense Newton step, in compiled code: the generalised Jacobian J = N + M W − G
assembled dense (:func:`_dense_jacobian`), its explicit rows eliminated (:func:`_reduced_direction_into`), and
the LU solves of what is left (a compiled elimination below :data:`SMALL_LU_BELOW` rows, LAPACK gesv in place
above). Used by the Newton kernel of :mod:`refsim.solvers.newton`, which allocates the work arrays of a
direction once per solve and passes them as one :class:`DirectionWork`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from refsim.kernel_cache import numba
from refsim.solvers.laws import CONTACT, GROUP_FRICTION


class DirectionWork(NamedTuple):
    """The arrays of one Newton direction (J + η I) d = rhs, allocated once per solve and overwritten at each
    iteration (n rows, ``blocks`` law blocks, ``member_count`` group members). numba passes it to compiled
    code as one typed tuple."""

    #: J + η I, shape (n, n)
    jacobian: np.ndarray
    #: the right-hand side −F(λ), shape (n,)
    rhs: np.ndarray
    #: N's blocks, shape (blocks, 3, 3)
    local: np.ndarray
    #: M's blocks (the gap factor of M W), shape (blocks, 3, 3)
    gap_factor: np.ndarray
    #: G's entries ∂b/∂λ of the group bounds, shape (member_count,)
    bound_values: np.ndarray
    #: each row's index in the rows kept A (−1 for an explicit row), shape (n,) int64
    position: np.ndarray
    #: A's rows in order, shape (n,) int64
    active: np.ndarray
    #: c of the explicit rows, shape (n,)
    values: np.ndarray
    #: the reduced right-hand side, then d_A, shape (n,)
    reduced_rhs: np.ndarray
    #: the matrix an LU factorises in place (a copy of J, or the reduced matrix), shape (n, n) C-contiguous
    factors: np.ndarray
    #: LU pivots, shape (n,) of :data:`PIVOT_DTYPE`
    pivots: np.ndarray
    #: the full LU's solution, shape (n,)
    lu_out: np.ndarray
    #: the reduced solve's direction d, shape (n,)
    direction: np.ndarray


#: Dense systems with fewer rows than this are solved by the compiled elimination :func:`_small_lu_inplace`.
SMALL_LU_BELOW = 24


@numba.njit(cache=True)
def _dense_jacobian(compliance, kinds, rows, local, gap_factor, members, bound_values, eta, out):
    """out = N + M W − G + η I (dense)."""
    n = compliance.shape[0]
    out[:, :] = 0.0
    for b in range(kinds.shape[0]):
        size = 3 if kinds[b] == CONTACT else 1
        for i in range(size):
            ri = rows[b, i]
            for j in range(size):
                rj = rows[b, j]
                factor = gap_factor[b, i, j]
                if factor != 0.0:
                    for c in range(n):
                        out[ri, c] += factor * compliance[rj, c]
                out[ri, rj] += local[b, i, j]
            out[ri, ri] += eta
        if kinds[b] == GROUP_FRICTION:
            ri = rows[b, 0]
            for k in range(rows[b, 1], rows[b, 2]):
                out[ri, members[k]] -= bound_values[k]


@numba.njit(cache=True)
def _gesv(matrix, rhs):
    """np.linalg.solve in compiled code (LAPACK gesv)."""
    return np.linalg.solve(matrix, rhs)


@numba.njit(cache=True)
def _small_lu_inplace(work, out):
    """J d = rhs by Gaussian elimination with partial pivoting (the algorithm of LAPACK getf2/getrs,
    unblocked), in place: ``work`` (n, n) holds J on entry and its factors on exit, ``out`` (n,) the
    right-hand side on entry and d on exit when it returns True (False: a pivot exactly zero or not a number,
    LAPACK's info > 0).

    Below :data:`SMALL_LU_BELOW` rows it is faster than numba's call of gesv, which copies J to Fortran order
    and checks it (measured at one thread, compiled loops: 0.08 / 0.40 / 1.30 µs against 0.36 / 1.04 / 2.10 µs
    at n = 3 / 9 / 15; 7.7 against 6.7 µs at n = 30)."""
    n = out.shape[0]
    for k in range(n):
        pivot_row = k
        largest = abs(work[k, k])
        for i in range(k + 1, n):
            value = abs(work[i, k])
            if value > largest:
                largest = value
                pivot_row = i
        if not largest > 0.0:
            return False
        if pivot_row != k:
            for j in range(n):
                swap = work[k, j]
                work[k, j] = work[pivot_row, j]
                work[pivot_row, j] = swap
            swap = out[k]
            out[k] = out[pivot_row]
            out[pivot_row] = swap
        # rows as one-dimensional views: the same operations, about a quarter faster at 9-15 rows (measured
        # 0.74 -> 0.61 µs at 9, 1.94 -> 1.50 µs at 15, copies included; the same bits)
        row_k = work[k]
        pivot = row_k[k]
        out_k = out[k]
        for i in range(k + 1, n):
            row_i = work[i]
            factor = row_i[k] / pivot
            for j in range(k + 1, n):
                row_i[j] -= factor * row_k[j]
            out[i] -= factor * out_k
    for i in range(n - 1, -1, -1):
        row_i = work[i]
        total = out[i]
        for j in range(i + 1, n):
            total -= row_i[j] * out[j]
        out[i] = total / row_i[i]
    return True


# LAPACK's gesv as numba's np.linalg.solve calls it (numba's helper library), without its copies and checks
try:
    from numba.np.linalg import _LAPACK
    from numba.np.linalg import F_INT_nptype as PIVOT_DTYPE

    _XGESV = _LAPACK().numba_xgesv(numba.types.float64)
except (ImportError, AttributeError):  # another numba: np.linalg.solve does the same
    _XGESV = None
    PIVOT_DTYPE = np.int32


if _XGESV is not None:

    @numba.njit(cache=True)
    def _gesv_inplace(transposed, rhs, pivots):
        """A x = rhs by LAPACK gesv, in place: ``transposed`` (m, m) C-contiguous holds Aᵀ (A in Fortran
        order) and gets its LU factors, ``rhs`` (m,) contiguous gets x; ``pivots`` (≥ m,) int work. True when
        A was factorised (LAPACK info 0; the same factors and solution as np.linalg.solve, which copies A to
        Fortran order and checks it for NaN first: measured 35 / 42 µs at m = 69, 15 / 21 µs at m = 46)."""
        m = rhs.shape[0]
        return _XGESV(ord("d"), m, 1, transposed.ctypes, m, pivots.ctypes, rhs.ctypes, m) == 0
else:

    @numba.njit(cache=True)
    def _gesv_inplace(transposed, rhs, pivots):
        """Fallback of the gesv call: np.linalg.solve on Aᵀᵀ."""
        try:
            rhs[:] = np.linalg.solve(transposed.T, rhs)
            return True
        except Exception:  # noqa: BLE001 (numba raises a plain exception for a singular matrix)
            return False


@numba.njit(cache=True)
def _lu_direction_into(jacobian, rhs, work, out, pivots):
    """J d = rhs by LU with partial pivoting, on a copy of J in ``work`` (n, n) C-contiguous: the compiled
    elimination below :data:`SMALL_LU_BELOW` rows, else LAPACK gesv on J in Fortran order; ``out`` (n,) and
    ``pivots`` (n,) of :data:`PIVOT_DTYPE` are work arrays. (d, True) with d in ``out``, or (rhs, False) when
    J is singular (a zero or non-finite pivot)."""
    n = rhs.shape[0]
    out[:] = rhs
    if n < SMALL_LU_BELOW:
        work[:, :] = jacobian
        if _small_lu_inplace(work, out):
            return out, True
        return rhs, False
    for i in range(n):
        for j in range(n):
            work[j, i] = jacobian[i, j]
    if _gesv_inplace(work, out, pivots) and np.all(np.isfinite(out)):
        return out, True
    return rhs, False


@numba.njit(cache=True)
def _reduced_direction_into(kinds, rows, members, work):
    """J d = rhs (``work.jacobian``, ``work.rhs``, a :class:`DirectionWork`) with the explicit rows
    eliminated, d into ``work.direction``; returns False when no row is explicit or the reduced matrix is
    singular (the caller then solves the full system).

    A block is explicit where its projection is constant (N_b = I, M_b = 0: a separated unilateral row or
    contact, a slipping friction row, a box row at a bound): its row i reads J_ii d_i − Σ_k g_k d_{G_k} =
    rhs_i, J_ii = 1 + η, the g_k = ∂b/∂λ of a slipping friction row's group members (no other entry: M_b = 0).
    With E those rows and A the rest: a member in E is a plain row (members are never friction rows), d_j =
    rhs_j / J_jj; so d_i = c_i + Σ_{k: G_k ∈ A} (g_k / J_ii) d_{G_k}, c_i = (rhs_i + Σ_{k: G_k ∈ E} g_k
    rhs_{G_k} / J_{G_k G_k}) / J_ii, and (J_AA + Σ_{i ∈ E} J_{A i} (g / J_ii)ᵀ) d_A = rhs_A − J_AE c: an LU of
    |A| rows instead of n (the cube's insertion steps: the shaft friction rows slip, |A| = 2n/3, about a third
    of the LU's cost).
    ``work.position`` (n,) gets each row's index in A (−1 for E).
    """
    jacobian, rhs, position, values, direction = (
        work.jacobian,
        work.rhs,
        work.position,
        work.values,
        work.direction,
    )
    n = rhs.shape[0]
    m = _partition(kinds, rows, work.local, work.gap_factor, position, work.active)
    if m < 0:
        return False
    _explicit_values(jacobian, rhs, kinds, rows, members, work.bound_values, position, values)
    if m > 0:
        ok, solution = _solve_reduced(kinds, rows, members, work, m)
        if not ok:
            return False
        for a in range(m):
            direction[work.active[a]] = solution[a]
    for i in range(n):
        if position[i] < 0:
            direction[i] = values[i]
    _explicit_directions(jacobian, kinds, rows, members, work.bound_values, position, values, direction)
    return True


@numba.njit(cache=True)
def _partition(kinds, rows, local, gap_factor, position, active):
    """The explicit rows E (blocks whose projection is constant: N_b = I, M_b = 0) and the rest A:
    ``position`` gets each row's index in A (−1 for E), ``active`` A's rows in order; returns |A|, or −1
    when no row is explicit."""
    n = position.shape[0]
    count = 0
    for b in range(kinds.shape[0]):
        size = 3 if kinds[b] == CONTACT else 1
        constant = True
        for i in range(size):
            for j in range(size):
                if gap_factor[b, i, j] != 0.0 or local[b, i, j] != (1.0 if i == j else 0.0):
                    constant = False
        for i in range(size):
            position[rows[b, i]] = -2 if constant else 0
        if constant:
            count += size
    if count == 0:
        return -1
    m = 0
    for i in range(n):
        if position[i] == 0:
            position[i] = m
            active[m] = i
            m += 1
        else:
            position[i] = -1
    return m


@numba.njit(cache=True)
def _explicit_values(jacobian, rhs, kinds, rows, members, bound_values, position, values):
    """c of the explicit rows into ``values``: rhs_j / J_jj, plus for a slipping friction row its explicit
    members' terms g_k rhs_{G_k} / J_{G_k G_k}, over J_ii."""
    n = rhs.shape[0]
    for i in range(n):
        if position[i] < 0:
            values[i] = rhs[i] / jacobian[i, i]
    for b in range(kinds.shape[0]):  # slipping friction rows: their members' contributions
        if kinds[b] != GROUP_FRICTION:
            continue
        row = rows[b, 0]
        if position[row] >= 0:
            continue
        value = rhs[row]
        for k in range(rows[b, 1], rows[b, 2]):
            member = members[k]
            if bound_values[k] != 0.0 and position[member] < 0:
                value += bound_values[k] * rhs[member] / jacobian[member, member]
        values[row] = value / jacobian[row, row]


@numba.njit(cache=True)
def _solve_reduced(kinds, rows, members, work, m):
    """d_A of the reduced system (J_AA + Σ_{i ∈ E} J_{A i} (g / J_ii)ᵀ) d_A = rhs_A − J_AE c (|A| = ``m``),
    solved in place in ``work.factors`` and ``work.reduced_rhs`` (a :class:`DirectionWork`): (False, _) when
    it is singular or its solution not finite, else (True, d_A)."""
    jacobian, rhs, bound_values, position, active = (
        work.jacobian,
        work.rhs,
        work.bound_values,
        work.position,
        work.active,
    )
    values, reduced_rhs, pivots = work.values, work.reduced_rhs, work.pivots
    n = rhs.shape[0]
    # the reduced matrix A in a contiguous (m, m) part of ``work``: as A (C order) for the compiled
    # elimination, as Aᵀ (A in Fortran order) for LAPACK's gesv, so that neither copies it again
    lapack = m >= SMALL_LU_BELOW
    reduced = work.factors.reshape(-1)[: m * m].reshape((m, m))
    for a in range(m):
        source = active[a]
        total = rhs[source]
        if lapack:
            for c in range(m):
                reduced[c, a] = jacobian[source, active[c]]
        else:
            for c in range(m):
                reduced[a, c] = jacobian[source, active[c]]
        for i in range(n):
            if position[i] < 0:
                total -= jacobian[source, i] * values[i]
        reduced_rhs[a] = total
    for b in range(kinds.shape[0]):
        if kinds[b] != GROUP_FRICTION:
            continue
        row = rows[b, 0]
        if position[row] >= 0:
            continue
        for k in range(rows[b, 1], rows[b, 2]):
            column = position[members[k]]
            if bound_values[k] != 0.0 and column >= 0:
                coupling = bound_values[k] / jacobian[row, row]
                for a in range(m):
                    if lapack:
                        reduced[column, a] += jacobian[active[a], row] * coupling
                    else:
                        reduced[a, column] += jacobian[active[a], row] * coupling
    solution = reduced_rhs[:m]  # in place: the work arrays get the factors and the solution
    if lapack:
        if not (_gesv_inplace(reduced, solution, pivots) and np.all(np.isfinite(solution))):
            return False, solution
    elif not _small_lu_inplace(reduced, solution):
        return False, solution
    return True, solution


@numba.njit(cache=True)
def _explicit_directions(jacobian, kinds, rows, members, bound_values, position, values, direction):
    """d of a slipping friction row: c_i plus its members in A, Σ (g_k / J_ii) d_{G_k}."""
    for b in range(kinds.shape[0]):
        if kinds[b] != GROUP_FRICTION:
            continue
        row = rows[b, 0]
        if position[row] >= 0:
            continue
        value = values[row]
        for k in range(rows[b, 1], rows[b, 2]):
            member = members[k]
            if bound_values[k] != 0.0 and position[member] >= 0:
                value += bound_values[k] * direction[member] / jacobian[row, row]
        direction[row] = value
