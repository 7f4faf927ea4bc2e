"""Modified (projected, block) Gauss–Seidel for the constraint problem, as in SOFA.

After Duriez et al. (2006, 2009) and Courtecuisse et al. (2014): the multipliers are swept block by block in
row order; each block solves its own law with the others fixed, and the gap δ = W λ + δ_free is kept up to
date by adding the column W[:, j] Δλ_j after every change (so one sweep costs O(row_count²) and no row is
recomputed).

Blocks:

- bilateral row: λ ← λ − ω δ / W_ii (exact for the row);
- unilateral row: λ ← max(0, λ − ω δ / W_ii);
- contact (normal, tangent 1, tangent 2): normal first, λ_n ← max(0, λ_n − ω δ_n / W_nn), zero force when
  it separates; the tangential gap is updated with the normal change, then
  λ_t ← λ_t − 2 ω δ_t / (W_t1t1 + W_t2t2) projected onto the disk ‖λ_t‖ ≤ μ λ_n (SOFA's local Coulomb
  resolution). Its fixed points are exactly the solutions of the De Saxcé law (stick inside the disk with
  δ = 0, slip on it opposing δ_t, δ_n = 0);
- shaft friction row: λ ← clip(λ − ω δ / W_ii, ±μ (‖(λ_b1, λ_b2)‖ + p)) with the current pair forces and the
  row's normal preload p;
- box row: λ ← clip(λ − ω δ / W_ii, lower, upper).

A row whose diagonal W_ii is zero (below 1e-14 of the largest diagonal) or negative cannot be solved alone:
its multiplier is only projected onto its admissible set, and the residual tells whether the problem was
solved.
The stopping test is the natural residual (see :mod:`refsim.solvers.residual`); SOFA's increment measure
Σ_j |W_jj Δλ_j| of the last sweep is reported too, and ``criterion="increment"`` stops on it as SOFA does
(Σ_j |W_jj Δλ_j| < tolerance (row_count + 1)), so iteration counts compare with the paper's.
"""

from __future__ import annotations

import logging
import time

import numba
import numpy as np

from refsim.solvers.problem import ConstraintProblem
from refsim.solvers.report import SolverReport
from refsim.solvers.residual import natural_residual

__all__ = ["solve_gauss_seidel"]

logger = logging.getLogger(__name__)

_BILATERAL, _UNILATERAL, _CONTACT, _SHAFT, _BOX = 0, 1, 2, 3, 4
_DIAGONAL_FLOOR = 1e-14


def _blocks(problem: ConstraintProblem) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Block kinds (b,), rows (b, 3) and parameters (b, 2) sorted by first row (vectorised)."""
    singles = [(problem.bilateral, _BILATERAL), (problem.unilateral, _UNILATERAL),
               (problem.shaft_friction, _SHAFT), (problem.box_rows, _BOX)]
    kinds = [np.full(len(rows), code, dtype=np.int64) for rows, code in singles]
    rows = [np.column_stack([r, np.zeros((len(r), 2), dtype=np.int64)]) for r, _ in singles]
    params = [np.zeros((len(problem.bilateral), 2)), np.zeros((len(problem.unilateral), 2)),
              np.column_stack([problem.shaft_friction_coefficient, problem.shaft_normal_preload]),
              np.column_stack([problem.box_lower, problem.box_upper])]
    # shaft rows carry their pair in columns 1, 2 of rows and (μ, preload) in params
    rows[2][:, 1:] = problem.shaft_pairs
    kinds.append(np.full(len(problem.contacts), _CONTACT, dtype=np.int64))
    rows.append(problem.contacts.astype(np.int64))
    params.append(np.column_stack([problem.contact_friction, np.zeros(len(problem.contacts))]))
    kind = np.concatenate(kinds)
    row = np.concatenate(rows).astype(np.int64)
    param = np.concatenate(params).astype(np.float64)
    order = np.argsort(row[:, 0], kind="stable")
    return (np.ascontiguousarray(kind[order]), np.ascontiguousarray(row[order]),
            np.ascontiguousarray(param[order]))


@numba.njit(cache=True)
def _apply(transposed, diagonal, multipliers, gap, row, value):
    """Set λ[row] = value and update the gap with W[:, row] Δλ; return |W_rr Δλ|."""
    change = value - multipliers[row]
    if change == 0.0:
        return 0.0
    multipliers[row] = value
    column = transposed[row]
    for i in range(gap.shape[0]):
        gap[i] += column[i] * change
    return abs(diagonal[row] * change)


@numba.njit(cache=True)
def _sweep(transposed, diagonal, kinds, rows, params, multipliers, gap, relaxation):
    """One Gauss–Seidel sweep over all blocks; returns SOFA's increment Σ|W_jj Δλ_j|."""
    increment = 0.0
    for b in range(kinds.shape[0]):
        kind = kinds[b]
        row = rows[b, 0]
        if kind == _CONTACT:
            tangent1 = rows[b, 1]
            tangent2 = rows[b, 2]
            friction = params[b, 0]
            normal_force = multipliers[row]
            if diagonal[row] > 0.0:
                normal_force -= relaxation * gap[row] / diagonal[row]
            if normal_force <= 0.0:
                increment += _apply(transposed, diagonal, multipliers, gap, row, 0.0)
                increment += _apply(transposed, diagonal, multipliers, gap, tangent1, 0.0)
                increment += _apply(transposed, diagonal, multipliers, gap, tangent2, 0.0)
                continue
            increment += _apply(transposed, diagonal, multipliers, gap, row, normal_force)
            force1 = multipliers[tangent1]
            force2 = multipliers[tangent2]
            tangent_diagonal = diagonal[tangent1] + diagonal[tangent2]
            if tangent_diagonal > 0.0:
                force1 -= 2.0 * relaxation * gap[tangent1] / tangent_diagonal
                force2 -= 2.0 * relaxation * gap[tangent2] / tangent_diagonal
            norm = np.sqrt(force1 * force1 + force2 * force2)
            limit = friction * normal_force
            if norm > limit:
                scale = limit / norm
                force1 *= scale
                force2 *= scale
            increment += _apply(transposed, diagonal, multipliers, gap, tangent1, force1)
            increment += _apply(transposed, diagonal, multipliers, gap, tangent2, force2)
            continue
        force = multipliers[row]
        if diagonal[row] > 0.0:
            force -= relaxation * gap[row] / diagonal[row]
        if kind == _UNILATERAL:
            force = max(force, 0.0)
        elif kind == _SHAFT:
            pair1 = multipliers[rows[b, 1]]
            pair2 = multipliers[rows[b, 2]]
            bound = params[b, 0] * (np.sqrt(pair1 * pair1 + pair2 * pair2) + params[b, 1])
            force = min(max(force, -bound), bound)
        elif kind == _BOX:
            force = min(max(force, params[b, 0]), params[b, 1])
        increment += _apply(transposed, diagonal, multipliers, gap, row, force)
    return increment


@numba.njit(cache=True)
def _residual(kinds, rows, params, multipliers, gap, free_norm):
    """Natural residual (same definition as refsim.solvers.residual) from a given gap."""
    total = 0.0
    for b in range(kinds.shape[0]):
        kind = kinds[b]
        row = rows[b, 0]
        if kind == _CONTACT:
            t1 = rows[b, 1]
            t2 = rows[b, 2]
            mu = params[b, 0]
            slip = np.sqrt(gap[t1] * gap[t1] + gap[t2] * gap[t2])
            zn = multipliers[row] - (gap[row] + mu * slip)
            z1 = multipliers[t1] - gap[t1]
            z2 = multipliers[t2] - gap[t2]
            zt = np.sqrt(z1 * z1 + z2 * z2)
            if zt <= mu * zn:
                pn, p1, p2 = zn, z1, z2
            elif mu * zt <= -zn:
                pn, p1, p2 = 0.0, 0.0, 0.0
            else:
                pn = max((zn + mu * zt) / (1.0 + mu * mu), 0.0)
                ratio = mu * pn / zt if zt > 0.0 else 0.0
                p1, p2 = ratio * z1, ratio * z2
            en = multipliers[row] - pn
            e1 = multipliers[t1] - p1
            e2 = multipliers[t2] - p2
            total += en * en + e1 * e1 + e2 * e2
            continue
        if kind == _BILATERAL:
            error = gap[row]
        else:
            z = multipliers[row] - gap[row]
            if kind == _UNILATERAL:
                error = multipliers[row] - max(z, 0.0)
            elif kind == _SHAFT:
                pair1 = multipliers[rows[b, 1]]
                pair2 = multipliers[rows[b, 2]]
                bound = params[b, 0] * (np.sqrt(pair1 * pair1 + pair2 * pair2) + params[b, 1])
                error = multipliers[row] - min(max(z, -bound), bound)
            else:
                error = multipliers[row] - min(max(z, params[b, 0]), params[b, 1])
        total += error * error
    scale = max(free_norm, _norm(multipliers), _norm(gap))
    if scale <= 0.0:
        scale = 1.0
    residual = np.sqrt(total) / scale
    if not np.isfinite(residual) or not np.isfinite(scale) or total > 1e300:
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
def _gauss_seidel(transposed, free_gap, diagonal, kinds, rows, params, multipliers, gap, tolerance,
                  max_iterations, relaxation, stop_on_increment, history):
    """Sweep until the stopping criterion holds; returns (iterations, increment, status).

    status: 1 converged, 0 not converged within max_iterations, 2 diverged (non-finite or overflowing values).
    """
    free_norm = _norm(free_gap)
    row_count = free_gap.shape[0]
    increment = np.nan
    for iteration in range(max_iterations):
        increment = _sweep(transposed, diagonal, kinds, rows, params, multipliers, gap, relaxation)
        residual = _residual(kinds, rows, params, multipliers, gap, free_norm)
        history[iteration] = residual
        if residual == np.inf or not np.isfinite(increment):
            return iteration + 1, increment, 2
        if stop_on_increment:
            done = increment < tolerance * (row_count + 1)
        else:
            done = residual <= tolerance
        if done:
            _exact_gap(transposed, free_gap, multipliers, gap)
            if stop_on_increment:
                return iteration + 1, increment, 1
            residual = _residual(kinds, rows, params, multipliers, gap, free_norm)
            history[iteration] = residual
            if residual <= tolerance:
                return iteration + 1, increment, 1
    _exact_gap(transposed, free_gap, multipliers, gap)
    return max_iterations, increment, 0


def solve_gauss_seidel(problem: ConstraintProblem, *, tolerance: float = 1e-6, max_iterations: int = 1000,
                       warm_start: np.ndarray | None = None, relaxation: float = 1.0,
                       criterion: str = "residual") -> tuple[np.ndarray, SolverReport]:
    """Solve the constraint problem with the modified Gauss–Seidel of SOFA.

    Parameters
    ----------
    problem : The constraint problem (W need not be symmetric).
    tolerance : Stop when the natural residual is at most this [-] (or, with ``criterion="increment"``, when
        Σ_j |W_jj Δλ_j| < tolerance (row_count + 1) [m], SOFA's test).
    max_iterations : Largest number of sweeps, ≥ 1.
    warm_start : Initial multipliers λ₀ [N], shape (row_count,); zeros when None.
    relaxation : Over-relaxation factor ω in (0, 2).
    criterion : ``"residual"`` (default) or ``"increment"``.

    Returns
    -------
    multipliers : λ [N], shape (row_count,).
    report : :class:`~refsim.solvers.SolverReport` with the natural residual recomputed from scratch.
    """
    if not (np.isfinite(tolerance) and tolerance >= 0.0):
        raise ValueError(f"tolerance = {tolerance!r}; valid range [0, inf)")
    if int(max_iterations) != max_iterations or max_iterations < 1:
        raise ValueError(f"max_iterations = {max_iterations!r}; valid range: integers >= 1")
    if not (0.0 < relaxation < 2.0):
        raise ValueError(f"relaxation = {relaxation!r}; valid range (0, 2)")
    if criterion not in ("residual", "increment"):
        raise ValueError(f"criterion = {criterion!r}; valid values 'residual', 'increment'")
    start = time.perf_counter()
    row_count = problem.row_count
    multipliers = (np.zeros(row_count) if warm_start is None
                   else np.array(problem.check_multipliers(warm_start), dtype=np.float64))
    if row_count == 0:
        return multipliers, SolverReport(solver="gauss_seidel", iterations=0, residual=0.0, converged=True,
                                         seconds=time.perf_counter() - start, message="empty problem",
                                         increment=0.0)
    compliance = problem.compliance
    transposed = np.array(compliance.T, order="C", copy=True)  # writable: one numba specialisation
    diagonal = np.diag(compliance).copy()
    floor = _DIAGONAL_FLOOR * max(float(np.abs(diagonal).max()), np.finfo(float).tiny)
    diagonal[diagonal <= floor] = 0.0
    kinds, rows, params = _blocks(problem)
    gap = compliance @ multipliers + problem.free_gap
    history = np.full(int(max_iterations), np.nan)
    iterations, increment, status = _gauss_seidel(
        transposed, np.array(problem.free_gap, copy=True), diagonal, kinds, rows, params, multipliers, gap,
        float(tolerance), int(max_iterations), float(relaxation), criterion == "increment", history)
    diverged = status == 2 or not np.all(np.isfinite(multipliers))
    if diverged:
        residual = float("inf")
        converged = False
    else:
        residual = natural_residual(problem, multipliers)
        converged = bool(residual <= tolerance) if criterion == "residual" else status == 1
    seconds = time.perf_counter() - start
    if diverged:
        message = (f"diverged after {iterations} sweeps: multipliers overflow (Gauss-Seidel needs a W with a "
                   "positive diagonal that dominates enough, e.g. symmetric positive definite)")
        logger.info("Gauss-Seidel %s: %s", problem.name or "problem", message)
    elif converged:
        message = f"{criterion} criterion met after {iterations} sweeps"
    else:
        zero_rows = int(np.count_nonzero(diagonal == 0.0))
        message = (f"not converged: {criterion} criterion not met after {iterations} sweeps "
                   f"(residual {residual:.3e}, increment {increment:.3e}"
                   + (f", {zero_rows} rows with zero diagonal cannot be solved alone" if zero_rows else "")
                   + ")")
        logger.info("Gauss-Seidel %s: %s", problem.name or "problem", message)
    return multipliers, SolverReport(solver="gauss_seidel", iterations=int(iterations), residual=residual,
                                     converged=bool(converged), seconds=seconds, message=message,
                                     increment=float(increment), history=history[:iterations].copy())
