"""The compiled dense Newton kernel of :func:`refsim.solvers.newton.solve_newton`: the whole iteration in one
numba call (no Python call per iteration), in named stages: the start with its Gauss–Seidel pre-sweeps
(:func:`_start`, :func:`_presweep`), the direction of each step (:func:`_newton_direction`: Jacobian blocks,
J + η I, the reduced or full solve of :mod:`refsim.solvers.linear`), the next point (:func:`_next_point`:
line search or fallback sweeps) and the bookkeeping of :func:`_dense_newton`; and the set-up of the problem
in the same call (:func:`_dense_newton_fresh`, the one entry point Python calls: each entry point compiles
the whole iteration again inside it). The problem goes down the stages as one named tuple,
:class:`NewtonProblem`; the work arrays are allocated once per solve (:func:`_workspace`) and handed down as
two more, :class:`_IterateWork` and :class:`~refsim.solvers.linear.DirectionWork`. The method is described
in :mod:`refsim.solvers.newton`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from refsim.kernel_cache import numba
from refsim.solvers.array_checks import relative_asymmetry
from refsim.solvers.gauss_seidel import _data_from_error, _residual
from refsim.solvers.laws import (
    assemble_blocks,
    gauss_seidel_sweep,
    jacobian_blocks,
    natural_map_blocks,
)
from refsim.solvers.linear import (
    PIVOT_DTYPE,
    DirectionWork,
    _dense_jacobian,
    _lu_direction_into,
    _reduced_direction_into,
)
from refsim.solvers.residual import _gap_into, _residual_pair, _scales

__all__: list[str] = []  # internal to refsim.solvers.newton

#: Pre-sweeps abandoned by their rate rule leave Newton's start unchanged unless they at least multiplied its
#: max(natural, data residual) by this. Measured on the 106 benchmark problems from a cold start: a point the
#: sweeps barely improved is no better a Newton start (OneObject-i1028-138, 0.92 of the start's residual after
#: 3 sweeps: 16 Newton iterations from it, 11 from the start; relay1, 0.97: not converged in 10 from it,
#: converged from the start), where a halving one is (LMGC_100: 1.5e-8 after 72 sweeps, 4 iterations).
_KEEP_SWEPT = 0.5


class NewtonProblem(NamedTuple):
    """The constraint problem as every stage of the kernel reads it: W, δ_free, the law blocks of
    :func:`~refsim.solvers.laws.assemble_blocks` and the scales of :func:`~refsim.solvers.residual._scales`
    (one tuple handed down, so that no stage takes these by position)."""

    #: W, C-contiguous (n, n)
    compliance: np.ndarray
    #: δ_free (n,)
    free_gap: np.ndarray
    #: the law of each block
    kinds: np.ndarray
    #: each block's rows
    rows: np.ndarray
    #: each block's law parameters
    params: np.ndarray
    #: the rows each block's bound depends on
    members: np.ndarray
    #: the natural map's weight per row
    weight: np.ndarray
    #: ‖δ_free‖
    free_norm: float
    #: the data residual's scale, max(‖δ_free‖, F_data)
    data_scale: float
    #: F_data, the forces' scale
    force_scale: float


@numba.njit(cache=True)
def _finite_and_short(direction, limit):
    total = 0.0
    for value in direction:
        if not np.isfinite(value):
            return False
        total += value * value
    return np.sqrt(total) <= limit


@numba.njit(cache=True)
def _sweep_arrays(compliance):
    """Wᵀ (C order) and the diagonal with entries ≤ 1e-14 max|W_jj| set to 0, as Gauss–Seidel takes them."""
    n = compliance.shape[0]
    transposed = np.ascontiguousarray(compliance.T)
    diagonal = np.diag(compliance).copy()
    floor = 1e-14 * max(np.abs(diagonal).max(), 2.2250738585072014e-308)
    for i in range(n):
        if diagonal[i] <= floor:
            diagonal[i] = 0.0
    return transposed, diagonal


@numba.njit(cache=True)
def _presweep(
    problem,
    transposed,
    diagonal,
    best,
    best_value,
    tolerance,
    budget,
    scratch,
    unit,
    candidate,
    gap,
):
    """Projected Gauss–Seidel sweeps from ``best`` (the start), at most ``budget``, while their observed rate
    can reach the tolerance within the budget: stops when the natural and data residual are both ≤ the
    tolerance (checked on the sweeps' incremental gap, then confirmed on the gap recomputed from scratch), or
    when r_k / r_(k-2), taken as the square of a linear rate, predicts more sweeps than are left (or does not
    fall). ``best`` gets the best point of the sweeps when they converged, or when it at least halves the
    start's ``best_value`` (judged on a gap from scratch: :data:`_KEEP_SWEPT`); returns (sweeps, the
    max(natural, data residual) of ``best`` on exit, whether ``best`` was replaced, its natural and data
    residual then (on the gap from scratch: what the caller would compute again; NaN when not replaced),
    whether they meet the tolerance)."""
    compliance, free_gap, free_norm, data_scale = (
        problem.compliance,
        problem.free_gap,
        problem.free_norm,
        problem.data_scale,
    )
    kinds, rows, params, members = problem.kinds, problem.rows, problem.params, problem.members
    candidate[:] = best  # ``candidate`` and ``gap`` (n,): work arrays
    _gap_into(compliance, candidate, free_gap, gap)
    values = np.empty(budget)
    swept = budget
    for k in range(budget):
        gauss_seidel_sweep(transposed, diagonal, kinds, rows, params, members, candidate, gap, 1.0)
        residual = _residual(kinds, rows, params, members, candidate, gap, free_norm, scratch, unit)
        data = _data_from_error(scratch, data_scale)
        value = max(residual, data)
        values[k] = value
        if not np.isfinite(value):
            swept = k + 1
            break
        if residual <= tolerance and data <= tolerance:
            _gap_into(compliance, candidate, free_gap, gap)  # confirmed on a gap without the sweeps' drift
            residual = _residual(kinds, rows, params, members, candidate, gap, free_norm, scratch, unit)
            data = _data_from_error(scratch, data_scale)
            if residual <= tolerance and data <= tolerance:
                best[:] = candidate
                return k + 1, max(residual, data), True, residual, data, True
        if k >= 2:
            ratio = value / values[k - 2]
            # sweeps still needed at rate √ratio: 2 log(tol / value) / log(ratio)
            if not ratio < 1.0 or 2.0 * np.log(tolerance / value) / np.log(ratio) > budget - k - 1:
                swept = k + 1
                break
    if np.all(np.isfinite(candidate)):
        _gap_into(compliance, candidate, free_gap, gap)
        residual = _residual(kinds, rows, params, members, candidate, gap, free_norm, scratch, unit)
        data = _data_from_error(scratch, data_scale)
        if max(residual, data) <= _KEEP_SWEPT * best_value:
            best[:] = candidate
            return (
                swept,
                max(residual, data),
                True,
                residual,
                data,
                residual <= tolerance and data <= tolerance,
            )
    return swept, best_value, False, np.nan, np.nan, False


class _IterateWork(NamedTuple):
    """The Newton kernel's own vectors, shape (n,) each (the direction's are a :class:`DirectionWork`)."""

    #: ones: the unit weights of the residual kernels
    unit: np.ndarray
    #: the natural map F(λ) of the iterate (and, after a line search, of its last candidate)
    error: np.ndarray
    #: the residual kernels' work vector
    scratch: np.ndarray
    #: δ of the iterate (swaps with ``candidate_gap`` on each accepted step)
    gap: np.ndarray
    #: the best point found
    best: np.ndarray
    #: the line search's candidate (swaps with the iterate on each accepted step)
    candidate: np.ndarray
    #: δ of the candidate
    candidate_gap: np.ndarray
    #: the pre-sweeps' point
    sweep_point: np.ndarray
    #: the pre-sweeps' gap
    sweep_gap: np.ndarray
    #: the start, then the iterate (the caller's array is not written)
    start: np.ndarray


@numba.njit(cache=True)
def _workspace(n, blocks, memory_length, member_count):
    """The dense Newton kernel's work arrays: every float one a view into one allocation, every int one into
    another (an allocation costs about 0.1 µs in compiled code, and a small problem needs some thirty of
    them). Returns (the iterate's vectors, an :class:`_IterateWork`; the merit memory (memory_length,); the
    direction's arrays, a :class:`DirectionWork` with ``bound_values`` zeros)."""
    floats = np.empty(15 * n + 2 * n * n + 18 * blocks + memory_length + member_count)
    ints = np.empty(2 * n, dtype=np.int64)
    vectors = floats[: 15 * n].reshape((15, n))
    vectors[0] = 1.0
    at = 15 * n
    matrices = floats[at : at + 2 * n * n].reshape((2, n, n))
    at += 2 * n * n
    local = floats[at : at + 9 * blocks].reshape((blocks, 3, 3))
    gap_factor = floats[at + 9 * blocks : at + 18 * blocks].reshape((blocks, 3, 3))
    at += 18 * blocks
    memory = floats[at : at + memory_length]
    bound_values = floats[at + memory_length :]
    bound_values[:] = 0.0
    pivots = np.empty(n, dtype=PIVOT_DTYPE)
    iterate = _IterateWork(
        vectors[0],
        vectors[1],
        vectors[2],
        vectors[3],
        vectors[4],
        vectors[5],
        vectors[6],
        vectors[11],
        vectors[12],
        vectors[13],
    )
    direction = DirectionWork(
        matrices[0],
        vectors[8],
        local,
        gap_factor,
        bound_values,
        ints[:n],
        ints[n:],
        vectors[9],
        vectors[10],
        matrices[1],
        pivots,
        vectors[14],
        vectors[7],
    )
    return iterate, memory, direction


@numba.njit(cache=True)
def _direction(kinds, rows, members, work, limit, unregularised):
    """The Newton direction d of J d = rhs (``work``, a :class:`DirectionWork`): the reduced solve
    (:func:`_reduced_direction_into` into ``work.direction``), an LU when it fails, and on an exactly
    singular unregularised J (a zero pivot) the minimum-norm least-squares step. Returns (d, ok: finite and
    no longer than ``limit``, 1 when the least-squares step was taken else 0).

    A factorised J whose step is absurdly long (nearly singular) goes to the regularised step of the next
    iteration (an LU, not an SVD). Measured (best of 7, one thread, method="auto", cold): there the
    least-squares step was rejected as too long as well on Rover1040 / 1041 / 3865 (93-98 -> 65-67 us without
    it) and did not help GMP6 (2.7 -> 1.1 ms); PD_mlcp, which its least-squares steps answer, has an exactly
    singular J."""
    direction = work.direction
    ok = _reduced_direction_into(kinds, rows, members, work)
    factored = True
    if not ok:
        direction, ok = _lu_direction_into(work.jacobian, work.rhs, work.factors, work.lu_out, work.pivots)
        factored = ok
    ok = ok and _finite_and_short(direction, limit)
    if unregularised and not factored:
        direction = np.linalg.lstsq(work.jacobian, work.rhs, 1e-12)[0]
        return direction, _finite_and_short(direction, limit), 1
    return direction, ok, 0


@numba.njit(cache=True, inline="always")  # a stage of _dense_newton, inlined: no compile of its own
def _newton_direction(problem, multipliers, gap, error, theta, eta_max, level, work):
    """One iteration's linear stage: the Jacobian blocks at λ, J + η I assembled dense (η = 0 at level 0,
    else min(η_max, ‖F‖/F_data) 10^(level−1), at least 1e-14) and the direction of J d = −F
    (:func:`_direction`, steps longer than 1e4 max(‖λ‖, F_data) rejected). Returns what :func:`_direction`
    returns."""
    kinds, rows, members, force_scale = problem.kinds, problem.rows, problem.members, problem.force_scale
    n = multipliers.shape[0]
    jacobian_blocks(
        kinds,
        rows,
        problem.params,
        members,
        multipliers,
        gap,
        problem.weight,
        work.local,
        work.gap_factor,
        work.bound_values,
    )
    relative = np.sqrt(2.0 * theta) / force_scale
    eta = 0.0
    if level > 0:
        eta = max(min(eta_max, relative) * 10.0 ** (level - 1), 1e-14)
    _dense_jacobian(
        problem.compliance,
        kinds,
        rows,
        work.local,
        work.gap_factor,
        members,
        work.bound_values,
        eta,
        work.jacobian,
    )
    limit = 1e4 * max(np.sqrt(np.dot(multipliers, multipliers)), force_scale)
    for i in range(n):
        work.rhs[i] = -error[i]
    return _direction(kinds, rows, members, work, limit, level == 0)


@numba.njit(cache=True)
def _line_search(problem, multipliers, direction, theta, reference, candidate, candidate_gap, error):
    """The non-monotone Armijo backtracking from λ along d: the first step 1, 1/2, ... ≥ 2⁻¹² whose merit
    θ(λ + s d) ≤ reference − 1e-4 s 2θ. The candidate, its gap and its natural-map error are left in the
    buffers. Returns (accepted, the last candidate's θ)."""
    n = multipliers.shape[0]
    step = 1.0
    candidate_theta = theta
    while step >= 2.0**-12:
        for i in range(n):
            candidate[i] = multipliers[i] + step * direction[i]
        _gap_into(problem.compliance, candidate, problem.free_gap, candidate_gap)
        natural_map_blocks(
            problem.kinds,
            problem.rows,
            problem.params,
            problem.members,
            candidate,
            candidate_gap,
            problem.weight,
            error,
        )
        candidate_theta = 0.5 * np.dot(error, error)
        if candidate_theta <= reference - 1e-4 * step * 2.0 * theta:
            return True, candidate_theta
        step *= 0.5
    return False, candidate_theta


@numba.njit(cache=True)
def _fallback_sweeps(problem, transposed, diagonal, multipliers, candidate, candidate_gap, error):
    """The line search's fallback: ten projected Gauss–Seidel sweeps from λ into the candidate buffers (its
    gap recomputed after them, its natural-map error into ``error``); returns its merit θ."""
    compliance, free_gap, weight = problem.compliance, problem.free_gap, problem.weight
    kinds, rows, params, members = problem.kinds, problem.rows, problem.params, problem.members
    candidate[:] = multipliers
    _gap_into(compliance, candidate, free_gap, candidate_gap)
    for _ in range(10):
        gauss_seidel_sweep(transposed, diagonal, kinds, rows, params, members, candidate, candidate_gap, 1.0)
    _gap_into(compliance, candidate, free_gap, candidate_gap)
    natural_map_blocks(kinds, rows, params, members, candidate, candidate_gap, weight, error)
    return 0.5 * np.dot(error, error)


@numba.njit(cache=True, inline="always")  # a stage of _dense_newton, inlined: no compile of its own
def _start(problem, multipliers, tolerance, presweeps, work):
    """The start of :func:`_dense_newton`: the merit θ, natural and data residual of the start λ
    (``multipliers``, ``work.start``; ``work.gap`` and ``work.error`` get its gap and natural map,
    ``work.best`` the start), then up to ``presweeps`` Gauss–Seidel sweeps (:func:`_presweep`), whose point
    replaces the start when they improve it. Returns (θ, residual, data residual, max of both, pre-sweeps
    taken, Wᵀ and the sweeps' diagonal (empty when no sweep was taken))."""
    gap, error, scratch, unit, best = work.gap, work.error, work.scratch, work.unit, work.best
    compliance, free_gap, weight = problem.compliance, problem.free_gap, problem.weight
    kinds, rows, params, members = problem.kinds, problem.rows, problem.params, problem.members
    free_norm, data_scale = problem.free_norm, problem.data_scale
    transposed = np.empty((0, 0))
    diagonal = np.empty(0)
    _gap_into(compliance, multipliers, free_gap, gap)
    natural_map_blocks(kinds, rows, params, members, multipliers, gap, weight, error)
    theta = 0.5 * np.dot(error, error)
    residual = _residual(kinds, rows, params, members, multipliers, gap, free_norm, scratch, unit)
    data = _data_from_error(scratch, data_scale)  # the error _residual left in scratch
    best_value = max(residual, data)
    best[:] = multipliers
    swept = 0
    if presweeps > 0 and not (residual <= tolerance and data <= tolerance):
        transposed, diagonal = _sweep_arrays(compliance)
        swept, value, replaced, residual_swept, data_swept, done = _presweep(
            problem,
            transposed,
            diagonal,
            best,
            best_value,
            tolerance,
            presweeps,
            scratch,
            unit,
            work.sweep_point,
            work.sweep_gap,
        )
        if (
            replaced
        ):  # start Newton from the swept point (its residuals as computed here, on a gap from scratch)
            multipliers[:] = best
            residual = residual_swept
            data = data_swept
            best_value = value
            if not done:  # Newton's merit at the new start (not needed when the sweeps solved the problem)
                _gap_into(compliance, multipliers, free_gap, gap)
                natural_map_blocks(kinds, rows, params, members, multipliers, gap, weight, error)
                theta = 0.5 * np.dot(error, error)
    return theta, residual, data, best_value, swept, transposed, diagonal


@numba.njit(cache=True, inline="always")  # a stage of _dense_newton, inlined: no compile of its own
def _next_point(
    problem, multipliers, direction, theta, reference, transposed, diagonal, candidate, candidate_gap, error
):
    """The candidate after λ: the line search along d (:func:`_line_search`), or when it fails ten
    Gauss–Seidel sweeps from λ (:func:`_fallback_sweeps`; Wᵀ and the diagonal made on first use). The
    candidate, its gap and natural map are left in ``candidate``, ``candidate_gap`` and ``error``. Returns
    (accepted, the candidate's θ, Wᵀ, diagonal)."""
    accepted, candidate_theta = _line_search(
        problem,
        multipliers,
        direction,
        theta,
        reference,
        candidate,
        candidate_gap,
        error,
    )
    if not accepted:
        if transposed.shape[0] == 0:
            transposed, diagonal = _sweep_arrays(problem.compliance)
        candidate_theta = _fallback_sweeps(
            problem,
            transposed,
            diagonal,
            multipliers,
            candidate,
            candidate_gap,
            error,
        )
    return accepted, candidate_theta, transposed, diagonal


@numba.njit(cache=True)
def _dense_newton(
    problem,
    multipliers,
    tolerance,
    max_iterations,
    eta_max,
    memory_size,
    stall_iterations,
    presweeps,
    history,
    counts,
    final,
):
    """The dense Newton iteration of :func:`solve_newton` in compiled code, on ``problem``, a
    :class:`NewtonProblem` (the same steps, line search and
    Gauss–Seidel fallback; no Python call per iteration). ``multipliers`` is the start on entry and the best
    point on exit; ``history`` (max_iterations + 1,) gets the residual after each iteration.

    Its stages: the start with up to ``presweeps`` projected Gauss–Seidel sweeps (:func:`_start`), then per
    iteration the direction (:func:`_newton_direction`), the next point (:func:`_next_point`) and the
    bookkeeping here (regularisation level, best point, history, stop reasons). Returns (the best λ,
    iterations, its residual, its data residual, reason): reason 0 converged, 1 iteration cap, 2 the
    regularised Jacobian could not be factorised, 3 the line search failed 9 times in a row, 4 stalled.
    ``counts`` gets (line-search failures, fallback sweeps, least-squares steps, history length, pre-sweeps),
    ``final`` the natural and data residual of the answer as :func:`refsim.solvers.residuals` computes them.
    """
    kinds, rows, params, members = problem.kinds, problem.rows, problem.params, problem.members
    n = problem.free_gap.shape[0]
    work, memory, linear = _workspace(n, kinds.shape[0], max(memory_size, 1), members.shape[0])
    unit, error, scratch, best = work.unit, work.error, work.scratch, work.best
    work.start[:] = multipliers  # the caller's array is not written
    multipliers = work.start
    theta, residual, data, best_value, swept, transposed, diagonal = _start(
        problem, multipliers, tolerance, presweeps, work
    )
    best_residual = residual
    best_data = data
    # multipliers / gap and candidate / candidate_gap swap roles on each accepted step
    gap, candidate, candidate_gap = work.gap, work.candidate, work.candidate_gap
    memory[0] = theta
    stored = 1
    history[0] = residual
    recorded = 1
    failures = 0
    consecutive = 0
    fallback = 0
    singular_steps = 0
    since_progress = 0
    level = 0
    iterations = 0
    reason = 0
    converged = residual <= tolerance and data <= tolerance
    while not converged:
        if iterations >= max_iterations:
            reason = 1
            break
        iterations += 1
        direction, ok, singular = _newton_direction(
            problem, multipliers, gap, error, theta, eta_max, level, linear
        )
        singular_steps += singular
        if not ok:
            failures += 1
            consecutive += 1
            level = min(level + 1, 8)
            if consecutive > 8:
                reason = 2
                break
            continue
        reference = memory[0]
        for k in range(1, min(stored, memory_size)):
            reference = max(reference, memory[k])
        accepted, candidate_theta, transposed, diagonal = _next_point(
            problem,
            multipliers,
            direction,
            theta,
            reference,
            transposed,
            diagonal,
            candidate,
            candidate_gap,
            error,
        )
        stop = False
        if not accepted:
            failures += 1
            consecutive += 1
            fallback += 10
            level = min(level + 1, 8)
            stop = consecutive > 8
        else:
            consecutive = 0
            level = max(level - 1, 0)
        # the candidate becomes the iterate: the two pairs of buffers swap roles
        multipliers, candidate = candidate, multipliers
        gap, candidate_gap = candidate_gap, gap
        theta = candidate_theta
        residual = _residual(kinds, rows, params, members, multipliers, gap, problem.free_norm, scratch, unit)
        data = _data_from_error(scratch, problem.data_scale)  # the error _residual left in scratch
        if stop:
            if max(residual, data) < best_value:
                best_value = max(residual, data)
                best[:] = multipliers
                best_residual = residual
                best_data = data
            reason = 3
            break
        memory[stored % memory_size] = theta
        stored += 1
        history[recorded] = residual
        recorded += 1
        if max(residual, data) < 0.5 * best_value:
            since_progress = 0
        else:
            since_progress += 1
        if max(residual, data) < best_value:
            best_value = max(residual, data)
            best[:] = multipliers
            best_residual = residual
            best_data = data
        converged = residual <= tolerance and data <= tolerance
        if not converged and since_progress >= stall_iterations:
            reason = 4
            break
    counts[0] = failures
    counts[1] = fallback
    counts[2] = singular_steps
    counts[3] = recorded
    counts[4] = swept
    # the report's residuals of the answer, by the kernel of refsim.solvers.natural_residual / data_residual
    final[0], final[1] = _residual_pair(
        problem.compliance, problem.free_gap, kinds, rows, params, members, best, problem.force_scale
    )
    return best.copy(), iterations, best_residual, best_data, reason


@numba.njit(cache=True)
def _dense_newton_fresh(
    compliance,
    free_gap,
    fields,
    multipliers,
    tolerance,
    max_iterations,
    eta_max,
    memory_size,
    stall_iterations,
    presweeps,
):
    """The set-up of a fresh problem (block arrays and data scales from its packed law fields ``fields`` of
    :func:`~refsim.solvers.laws.law_arrays`, ‖δ_free‖, W's asymmetry), then :func:`_dense_newton` (W and
    δ_free C-contiguous). Returns (best λ, the history, iterations, reason, line-search failures, fallback
    sweeps, pre-sweeps, best natural and data residual, the report's natural and data residual, W's relative
    asymmetry): scalars rather than arrays, which cost more to return to Python."""
    kinds, rows, params, members, scaling = assemble_blocks(fields)
    weight, force_scale = _scales(
        compliance, free_gap, scaling[0], scaling[1], scaling[2], scaling[3], scaling[4]
    )
    free_norm = np.sqrt(np.dot(free_gap, free_gap))  # the dot product of solve_newton's layered path
    history = np.empty(max_iterations + 1)
    counts = np.zeros(5, dtype=np.int64)
    final = np.empty(2)
    asymmetry = relative_asymmetry(compliance)
    data_scale = max(free_norm, force_scale)
    problem = NewtonProblem(
        compliance, free_gap, kinds, rows, params, members, weight, free_norm, data_scale, force_scale
    )
    best, iterations, residual, data, reason = _dense_newton(
        problem,
        multipliers,
        tolerance,
        max_iterations,
        eta_max,
        memory_size,
        stall_iterations,
        presweeps,
        history,
        counts,
        final,
    )
    return (
        best,
        history[: counts[3]].copy(),
        iterations,
        reason,
        counts[0],
        counts[1],
        counts[4],
        residual,
        data,
        final[0],
        final[1],
        asymmetry,
    )
