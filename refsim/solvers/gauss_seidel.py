"""Modified (projected, block) Gauss–Seidel for the constraint problem, as in SOFA.

After Duriez et al. (2006, 2009) and Courtecuisse et al. (2014): the multipliers are swept block by block in
row order; each block solves its own law with the others fixed, and the gap δ = W λ + δ_free is kept up to
date by adding the column W[:, j] Δλ_j after every change (so one sweep costs O(row_count²) and no row is
recomputed).

Blocks (the kernels are in :mod:`refsim.solvers.laws`, one per law of the table):

- bilateral row: λ ← λ − ω δ / W_ii (exact for the row);
- unilateral row: λ ← max(0, λ − ω δ / W_ii);
- contact (normal, tangent 1, tangent 2): normal first, λ_n ← max(0, λ_n − ω δ_n / W_nn), zero force when
  it separates; the tangential gap is updated with the normal change, then
  λ_t ← λ_t − 2 ω δ_t / (W_t1t1 + W_t2t2) projected onto the disk ‖λ_t‖ ≤ μ λ_n (SOFA's local Coulomb
  resolution). Its fixed points are exactly the solutions of the De Saxcé law (stick inside the disk with
  δ = 0, slip on it opposing δ_t, δ_n = 0);
- group friction row: λ ← clip(λ − ω δ / W_ii, ±μ (‖λ_G‖ + p)) with the current forces of its group G and
  its preload p;
- box row: λ ← clip(λ − ω δ / W_ii, lower, upper).

A row whose diagonal W_ii is zero (below 1e-14 of the largest diagonal) or negative moves no gap by its own
force: it takes the update's limit as W_ii → 0+, the bound of its admissible set that its gap pushes it to (a
box row with δ < 0 at its upper bound, a friction row at its bound opposing δ, a unilateral or contact row
with δ > 0 at 0: the law's solution for that row), and keeps its multiplier where that bound is infinite (a
violated unilateral or bilateral row, which no force satisfies); the residual tells whether the problem was
solved.
The stopping test is the natural residual (see :mod:`refsim.solvers.residual`); SOFA's increment measure
Σ_j |W_jj Δλ_j| of the last sweep is reported too, and ``criterion="increment"`` stops on it as SOFA does
(Σ_j |W_jj Δλ_j| < tolerance (row_count + 1)), so iteration counts compare with the paper's.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from refsim.kernel_cache import numba
from refsim.solvers.array_checks import all_finite
from refsim.solvers.laws import CONTACT, block_arrays, gauss_seidel_sweep, natural_map_blocks
from refsim.solvers.problem import ConstraintProblem
from refsim.solvers.report import SolverReport
from refsim.solvers.residual import data_scales, residuals

__all__ = ["solve_gauss_seidel"]

logger = logging.getLogger(__name__)

_DIAGONAL_FLOOR = 1e-14
_STOP_MODES = {"residual": 0, "increment": 1, "strict": 2}


@numba.njit(cache=True)
def _residual(kinds, rows, params, members, multipliers, gap, free_norm, error, unit_weight):
    """Natural residual (same definition as refsim.solvers.residual) from a given gap."""
    natural_map_blocks(kinds, rows, params, members, multipliers, gap, unit_weight, error)
    total = 0.0
    for b in range(kinds.shape[0]):
        row = rows[b, 0]
        if kinds[b] == CONTACT:
            en = error[row]
            e1 = error[rows[b, 1]]
            e2 = error[rows[b, 2]]
            total += en * en + e1 * e1 + e2 * e2
        else:
            total += error[row] * error[row]
    scale = max(free_norm, _norm(multipliers), _norm(gap))
    if scale <= 0.0:
        scale = 1.0
    residual = np.sqrt(total) / scale
    if not np.isfinite(residual) or not np.isfinite(scale) or total > 1e300:
        return np.inf
    return residual


@numba.njit(cache=True)
def _data_residual(kinds, rows, params, members, multipliers, gap, weight, data_scale, error):
    """refsim.solvers.data_residual from a given gap: ‖λ − Π(λ − δ̂)‖ / max(‖δ_free‖, F_data) (weight = 1)."""
    natural_map_blocks(kinds, rows, params, members, multipliers, gap, weight, error)
    return _data_from_error(error, data_scale)


@numba.njit(cache=True)
def _data_from_error(error, data_scale):
    """The data residual ‖e‖ / max(‖δ_free‖, F_data) from the unit-weight natural-map error e already computed
    (inf when not finite)."""
    residual = _norm(error) / data_scale
    if not np.isfinite(residual):
        return np.inf
    return residual


@numba.njit(cache=True)
def _norm(vector):
    """Euclidean norm without overflow."""
    largest = 0.0
    for value in vector:
        largest = max(largest, abs(value))
    if largest == 0.0 or not np.isfinite(largest):
        return largest
    total = 0.0
    for value in vector:
        total += (value / largest) ** 2
    return largest * np.sqrt(total)


@numba.njit(cache=True)
def _exact_gap(transposed, free_gap, multipliers, gap):
    """Recompute δ = W λ + δ_free from scratch (removes the drift of the incremental updates)."""
    gap[:] = free_gap
    for j in range(multipliers.shape[0]):
        if multipliers[j] != 0.0:
            column = transposed[j]
            for i in range(gap.shape[0]):
                gap[i] += column[i] * multipliers[j]


@numba.njit(cache=True)
def _gauss_seidel(
    transposed,
    free_gap,
    diagonal,
    kinds,
    rows,
    params,
    members,
    multipliers,
    gap,
    tolerance,
    max_iterations,
    relaxation,
    stop_mode,
    history,
    weight,
    data_scale,
    data_history,
    force_history,
):
    """Sweep until the stopping criterion holds; returns (iterations, increment, status).

    stop_mode: 0 natural residual ≤ tolerance, 1 SOFA's increment, 2 both the natural and the data residual
    (which a diverging λ cannot shrink) ≤ tolerance.

    status: 1 converged, 0 not converged within max_iterations, 2 diverged (non-finite or overflowing values).

    ``weight`` must be ones (the residuals' definition): the data residual of each sweep is taken from the
    error the natural residual leaves, which is the unit-weight natural map.
    """
    free_norm = _norm(free_gap)
    row_count = free_gap.shape[0]
    error = np.zeros(row_count)
    unit_weight = np.ones(row_count)
    increment = np.nan
    for iteration in range(max_iterations):
        increment = gauss_seidel_sweep(
            transposed, diagonal, kinds, rows, params, members, multipliers, gap, relaxation
        )
        residual = _residual(kinds, rows, params, members, multipliers, gap, free_norm, error, unit_weight)
        history[iteration] = residual
        # the data residual from the error _residual left (both are of the unit-weight natural map: the same
        # numbers as _data_residual, without evaluating the map twice per sweep)
        data = _data_from_error(error, data_scale)
        data_history[iteration] = data
        force_history[iteration] = _norm(multipliers)
        if residual == np.inf or not np.isfinite(increment):
            return iteration + 1, increment, 2
        if stop_mode == 1:
            done = increment < tolerance * (row_count + 1)
        else:
            done = residual <= tolerance and (stop_mode == 0 or data <= tolerance)
        if done:
            _exact_gap(transposed, free_gap, multipliers, gap)
            if stop_mode == 1:
                return iteration + 1, increment, 1
            residual = _residual(
                kinds, rows, params, members, multipliers, gap, free_norm, error, unit_weight
            )
            history[iteration] = residual
            if residual <= tolerance and (
                stop_mode == 0
                or _data_residual(kinds, rows, params, members, multipliers, gap, weight, data_scale, error)
                <= tolerance
            ):
                return iteration + 1, increment, 1
    _exact_gap(transposed, free_gap, multipliers, gap)
    return max_iterations, increment, 0


def _growing_without_progress(data_history: np.ndarray, force_history: np.ndarray) -> bool:
    """Over the second half of the sweeps, ‖λ‖ grew by half or more while the data residual fell by < 1 %."""
    count = data_history.size
    if count < 20:
        return False
    half = count // 2
    return bool(
        force_history[-1] > 1.5 * force_history[half] and data_history[-1] >= 0.99 * data_history[half]
    )


def solve_gauss_seidel(
    problem: ConstraintProblem,
    *,
    tolerance: float = 1e-6,
    max_iterations: int = 1000,
    warm_start: np.ndarray | None = None,
    relaxation: float = 1.0,
    criterion: str = "residual",
) -> tuple[np.ndarray, SolverReport]:
    """Solve the constraint problem with the modified Gauss–Seidel of SOFA.

    Parameters
    ----------
    problem : The constraint problem (W need not be symmetric).
    tolerance : Stop when the natural residual is at most this [-] (or, with ``criterion="increment"``, when
        Σ_j |W_jj Δλ_j| < tolerance (row_count + 1) [m], SOFA's test).
    max_iterations : Largest number of sweeps, ≥ 1.
    warm_start : Initial multipliers λ₀ [N], shape (row_count,); zeros when None.
    relaxation : Over-relaxation factor ω in (0, 2).
    criterion : ``"residual"`` (default: natural residual ≤ tolerance), ``"increment"`` (SOFA's) or
        ``"strict"`` (natural and data residual ≤ tolerance). Whatever the criterion, the report gives the
        data residual (:func:`refsim.solvers.data_residual`, which a diverging λ cannot shrink), and a
        criterion met while that stays above the tolerance and ‖λ‖ grows by half or more over the second half
        of the sweeps is reported as divergence (``diverged`` True, ``converged`` False).

    Returns
    -------
    multipliers : λ [N], shape (row_count,).
    report : :class:`~refsim.solvers.SolverReport` with the natural residual recomputed from scratch.
    """
    _check_arguments(tolerance, max_iterations, relaxation, criterion)
    start = time.perf_counter()
    row_count = problem.row_count
    multipliers = (
        np.zeros(row_count)
        if warm_start is None
        else np.array(problem.check_multipliers(warm_start), dtype=np.float64)
    )
    if row_count == 0:
        return multipliers, SolverReport(
            solver="gauss_seidel",
            iterations=0,
            residual=0.0,
            converged=True,
            seconds=time.perf_counter() - start,
            message="empty problem",
            increment=0.0,
            data_residual=0.0,
            path="gauss_seidel",
        )
    compliance = problem.compliance
    transposed = np.array(compliance.T, order="C", copy=True)  # writable: one numba specialisation
    diagonal = np.diag(compliance).copy()
    floor = _DIAGONAL_FLOOR * max(float(np.abs(diagonal).max()), np.finfo(float).tiny)
    diagonal[diagonal <= floor] = 0.0
    kinds, rows, params, members = block_arrays(problem)
    weight = np.ones(row_count)
    data_scale = max(float(np.linalg.norm(problem.free_gap)), data_scales(problem)[1])
    gap = compliance @ multipliers + problem.free_gap
    # (the sweeps write entry i of each history at sweep i; only the first `iterations` entries are read)
    history = np.empty(int(max_iterations))
    data_history = np.empty(int(max_iterations))
    force_history = np.empty(int(max_iterations))
    iterations, increment, status = _gauss_seidel(
        transposed,
        np.array(problem.free_gap, copy=True),
        diagonal,
        kinds,
        rows,
        params,
        members,
        multipliers,
        gap,
        float(tolerance),
        int(max_iterations),
        float(relaxation),
        _STOP_MODES[criterion],
        history,
        weight,
        float(data_scale),
        data_history,
        force_history,
    )
    overflow = status == 2 or not all_finite(multipliers)
    residual, data, converged, growing = _verdict(
        problem,
        multipliers,
        overflow,
        status,
        criterion,
        tolerance,
        data_history[:iterations],
        force_history[:iterations],
    )
    seconds = time.perf_counter() - start
    message = _message(
        problem,
        overflow,
        growing,
        converged,
        criterion,
        iterations,
        residual,
        data,
        increment,
        diagonal,
        force_history,
    )
    return multipliers, SolverReport(
        solver="gauss_seidel",
        iterations=int(iterations),
        residual=residual,
        converged=bool(converged),
        seconds=seconds,
        message=message,
        increment=float(increment),
        history=history[:iterations].copy(),
        data_residual=float(data),
        diverged=bool(overflow or growing),
        path="gauss_seidel",
    )


def _check_arguments(tolerance: float, max_iterations: int, relaxation: float, criterion: str) -> None:
    """The arguments of :func:`solve_gauss_seidel`, each named with its valid range on error."""
    if not (np.isfinite(tolerance) and tolerance >= 0.0):
        raise ValueError(f"tolerance = {tolerance!r}; valid range [0, inf)")
    if int(max_iterations) != max_iterations or max_iterations < 1:
        raise ValueError(f"max_iterations = {max_iterations!r}; valid range: integers >= 1")
    if not (0.0 < relaxation < 2.0):
        raise ValueError(f"relaxation = {relaxation!r}; valid range (0, 2)")
    if criterion not in _STOP_MODES:
        raise ValueError(f"criterion = {criterion!r}; valid values 'residual', 'increment', 'strict'")


def _verdict(problem, multipliers, overflow, status, criterion, tolerance, data_history, force_history):
    """(natural residual, data residual, converged, growing) of the swept multipliers: the criterion met,
    unless the data residual stays above the tolerance while ‖λ‖ grows (divergence); inf and not converged
    after an overflow."""
    if overflow:
        return float("inf"), float("inf"), False, False
    residual, data = residuals(problem, multipliers)
    if criterion == "strict":
        met = bool(residual <= tolerance and data <= tolerance)
    elif criterion == "residual":
        met = bool(residual <= tolerance)
    else:
        met = status == 1
    growing = data > tolerance and _growing_without_progress(data_history, force_history)
    return residual, data, met and not growing, growing


def _message(
    problem,
    overflow,
    growing,
    converged,
    criterion,
    iterations,
    residual,
    data,
    increment,
    diagonal,
    force_history,
) -> str:
    """The report's message (logged at INFO when the solve did not converge)."""
    if overflow:
        message = (
            f"diverged after {iterations} sweeps: multipliers overflow (Gauss-Seidel needs a W with a "
            "positive diagonal that dominates enough, e.g. symmetric positive definite)"
        )
        logger.info("Gauss-Seidel %s: %s", problem.name or "problem", message)
    elif growing:
        message = (
            f"diverging after {iterations} sweeps: ‖λ‖ = {force_history[iterations - 1]:.3e} N grows while "
            f"the data residual stays at {data:.3e} (natural residual {residual:.3e}, which ‖λ‖ divides); "
            "the problem probably has no solution (infeasible or W not positive semi-definite)"
        )
        logger.info("Gauss-Seidel %s: %s", problem.name or "problem", message)
    elif converged:
        return f"{criterion} criterion met after {iterations} sweeps"
    else:
        zero_rows = int(np.count_nonzero(diagonal == 0.0))
        message = (
            f"not converged: {criterion} criterion not met after {iterations} sweeps "
            f"(residual {residual:.3e}, data residual {data:.3e}, increment {increment:.3e}"
            + (f", {zero_rows} rows with zero diagonal cannot be solved alone" if zero_rows else "")
            + ")"
        )
        logger.info("Gauss-Seidel %s: %s", problem.name or "problem", message)
    return message
