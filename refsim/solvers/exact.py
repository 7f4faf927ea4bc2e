"""The exact reference solver: semismooth Newton first, the cone-programming route as fallback and
certificate.

:func:`solve_exact` runs the Newton method of :mod:`refsim.solvers.newton` on W as given (any law of the
table, non-symmetric W accepted), finishes with Gauss–Seidel sweeps or a monotone Newton where it stalls, and
only then falls back to the cone route (:mod:`refsim.solvers.cone`: the problem as QPs and second-order cone
programs solved by a back-end, Clarabel by default, then a polish); ``report.path`` says which produced the
answer.

The residuals reported are always recomputed by :func:`refsim.solvers.natural_residual` and
:func:`refsim.solvers.data_residual` on the problem as given; a backend's own "solved" is not believed. On
failure the best multipliers found are returned with the reason.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time

import numpy as np

from refsim.solvers.cone import (
    available_backends,
    cone_route,
    installed_backends,
    worst_kind,
)
from refsim.solvers.gauss_seidel import solve_gauss_seidel
from refsim.solvers.lemke import lemke_applicable, solve_lemke
from refsim.solvers.newton import (
    ETA_MAX,
    LINE_SEARCH_MEMORY,
    _fresh_outcome,
    _newton_result,
    converged_message,
    solve_newton,
    takes_fresh_path,
)
from refsim.solvers.problem import ConstraintProblem
from refsim.solvers.report import SolverReport
from refsim.solvers.residual import data_residual, natural_residual, residuals

__all__ = ["available_backends", "solve_exact"]

logger = logging.getLogger(__name__)

# : Gauss-Seidel sweeps tried when Newton stalls, before the cone route: chunks of _GAUSS_SEIDEL_PROBE, the
# next only : while the rate over the last chunk's second half (linear convergence assumed) reaches the
# tolerance in time.
_GAUSS_SEIDEL_SWEEPS = 2000
_GAUSS_SEIDEL_PROBE = 100
#: Fewest Gauss-Seidel sweeps tried before Newton by method="auto" (see _presweep_budget).
_PRESWEEPS_MIN = 8
#: Newton stops when its best residual has not halved in this many iterations: with "auto" the Gauss-Seidel
#: finish and the cone route follow, so a stall is left sooner (measured on the 74 shared problems and every
#: 10th step of cube and cube_cut, cold: the same 125 of 126 solved with 10 as with 20, local_problem_test
#: 21.2 -> 13.8 ms, GMP6 8.4 -> 3.4 ms, deltasigma_mlcp 7.9 -> 3.8 ms); "newton" keeps 20.
_AUTO_STALL = 10
_NEWTON_STALL = 20


def _presweep_budget(row_count: int) -> int:
    """Gauss–Seidel sweeps tried before Newton (``method="auto"``): max(8, n / 2). A sweep with its residual
    check costs about 2 n² flops, a dense Newton iteration an LU (2/3 n³) and several n² products, so n / 2
    sweeps cost about one or two Newton iterations; the sweeps stop earlier when their rate cannot reach the
    tolerance."""
    return max(_PRESWEEPS_MIN, row_count // 2)


def solve_exact(
    problem: ConstraintProblem,
    *,
    tolerance: float = 1e-9,
    backend: str = "clarabel",
    max_iterations: int = 100,
    symmetry_tolerance: float = 1e-8,
    polish: bool = True,
    backend_options: dict | None = None,
    warm_start: np.ndarray | None = None,
    method: str = "cone",
    newton_iterations: int = 100,
) -> tuple[np.ndarray, SolverReport]:
    """Solve the constraint problem to a tight residual (the reference solution).

    Parameters
    ----------
    problem : The constraint problem; W may be singular and non-symmetric (the Newton path solves it as given;
        the cone route solves with its symmetric part, and the residual is always measured with W as given).
    tolerance : Stop when the natural residual and the data residual (:mod:`refsim.solvers.residual`) are both
        at most this [-]; the report says ``converged`` when they are.
    backend : qpsolvers backend for the QP solves of the cone route (``"clarabel"``, ``"osqp"`` or any name
        of :func:`available_backends`). Contacts (cones) are always solved by Clarabel's own interface.
    max_iterations : Largest number of outer fixed-point iterations of the cone route, ≥ 1.
    symmetry_tolerance : Relative asymmetry ‖W − Wᵀ‖_F / ‖W‖_F [-] above which the message says the cone route
        solved the symmetric part (nothing is rejected any more).
    polish : Let the cone route finish with Newton iterations from its answer.
    backend_options : Options passed to the backend, replacing our tight defaults key by key.
    warm_start : Initial multipliers λ₀ [N], shape (row_count,), for the Newton path (e.g. the previous
    step's).
    method : ``"auto"`` (Newton, then the cone route if Newton did not reach the tolerance; the fast path),
        ``"newton"`` (Newton and its Gauss–Seidel finish only) or ``"cone"`` (the default for now: the cone
        route of before, polished; it keeps the simulation's exact-mode results. Where W is singular and group
        friction bounds grow along its null space the problems have many solutions, and the two routes pick
        different ones; see docs/solvers.md). ``warm_start`` is used by the Newton path only.
    newton_iterations : Largest number of Newton iterations.

    Returns
    -------
    multipliers : λ [N], shape (row_count,), the best found.
    report : :class:`~refsim.solvers.SolverReport`; ``path`` says which method produced the answer
        (``"newton"``, ``"cone"`` or ``"cone+newton"``), ``asymmetry`` the relative asymmetry of W,
        ``message`` the reason when not converged.

    Raises
    ------
    ValueError : For an unknown backend or method, or bad options.
    """
    start = time.perf_counter()
    _check_arguments(tolerance, max_iterations, method, backend)
    if warm_start is not None:
        warm_start = problem.check_multipliers(warm_start)
    if problem.row_count == 0:
        return np.zeros(0), _empty_report(start)
    newton = None
    asymmetry, lemke_note = None, ""
    if method == "cone" or (method == "auto" and warm_start is None and lemke_applicable(problem)):
        answer, asymmetry, lemke_note = _before_newton(problem, method, tolerance, symmetry_tolerance, start)
        if answer is not None:
            return answer
    if method in ("auto", "newton"):
        answer, newton, asymmetry, lemke_note = _newton_route(
            problem,
            method=method,
            tolerance=tolerance,
            warm_start=warm_start,
            newton_iterations=int(newton_iterations),
            symmetry_tolerance=symmetry_tolerance,
            lemke_note=lemke_note,
            start=start,
        )
        if answer is not None:
            return answer
    # "cone" keeps the route of before (its polish goes on to 1e-3 × the tolerance); "auto" stops it at the
    # tolerance (Newton then finishes the data residual if needed)
    multipliers, report = cone_route(
        problem,
        tolerance=tolerance,
        backend=backend,
        max_iterations=max_iterations,
        polish=polish,
        backend_options=backend_options,
        start=start,
        margin=1.0 if method == "auto" else 1e-3,
    )
    return _after_cone_route(
        problem,
        multipliers,
        report,
        method=method,
        tolerance=tolerance,
        polish=polish,
        newton_iterations=int(newton_iterations),
        asymmetry=asymmetry,
        symmetry_tolerance=symmetry_tolerance,
        lemke_note=lemke_note,
        newton=newton,
        start=start,
    )


def _empty_report(start: float) -> SolverReport:
    """The report of a problem without rows."""
    return SolverReport(
        solver="exact/newton",
        iterations=0,
        residual=0.0,
        converged=True,
        seconds=time.perf_counter() - start,
        message="empty problem",
        data_residual=0.0,
        asymmetry=0.0,
        path="newton",
    )


def _before_newton(problem, method: str, tolerance: float, symmetry_tolerance: float, start: float):
    """W's asymmetry, and for "auto" on a non-symmetric LCP/MLCP Lemke's pivoting first (no merit function
    need be convex); (answer or None, asymmetry, Lemke's note).

    The asymmetry is needed before any solve here; else it comes after Newton, whose compiled set-up computes
    it on dense problems (one call: see refsim.solvers.newton._solve_dense_fresh).
    """
    asymmetry = problem.asymmetry()
    note = _asymmetry_note(asymmetry, symmetry_tolerance)
    lemke_note = ""
    if method == "auto" and asymmetry > symmetry_tolerance:
        answer, lemke_note = _lemke_path(problem, tolerance)
        if answer is not None:
            return _lemke_report(problem, answer, lemke_note + note, asymmetry, start), asymmetry, lemke_note
    return None, asymmetry, lemke_note


def _check_arguments(tolerance, max_iterations, method: str, backend: str) -> None:
    """The arguments of :func:`solve_exact` that are checked before anything runs (ValueError naming them)."""
    if not (
        isinstance(tolerance, (int, float, np.floating)) and math.isfinite(tolerance) and tolerance > 0.0
    ):
        raise ValueError(f"tolerance = {tolerance!r}; valid range (0, inf)")
    if int(max_iterations) != max_iterations or max_iterations < 1:
        raise ValueError(f"max_iterations = {max_iterations!r}; valid range: integers >= 1")
    if method not in ("auto", "newton", "cone"):
        raise ValueError(f"method = {method!r}; valid values 'auto', 'newton', 'cone'")
    backends = installed_backends()
    if backend not in backends:
        raise ValueError(f"backend = {backend!r} is not installed; available: {', '.join(backends)}")


def _newton_route(
    problem: ConstraintProblem,
    *,
    method: str,
    tolerance: float,
    warm_start: np.ndarray | None,
    newton_iterations: int,
    symmetry_tolerance: float,
    lemke_note: str,
    start: float,
):
    """The Newton path of :func:`solve_exact` ("auto" and "newton"): Newton, its Gauss–Seidel finish, the
    monotone retry ("newton"), Lemke's pivoting where it applies ("auto").

    Returns
    -------
    (answer, newton, asymmetry, lemke_note): ``answer`` is the final (λ, report) or None when the cone route
    is to follow; ``newton`` the Newton result (None when the fresh path answered).
    """
    presweeps = _presweep_budget(problem.row_count) if method == "auto" else 0
    stall = _AUTO_STALL if method == "auto" else _NEWTON_STALL
    if takes_fresh_path(problem):
        # the one compiled call of dense problems; when it converged (as the report measures it),
        # the report straight from its outcome (what the general code below gives, without its layers: a
        # 3-row problem's whole solve is some 20 µs, of which these layers took about 5)
        start_point = np.zeros(problem.row_count) if warm_start is None else np.array(warm_start, np.float64)
        outcome = _fresh_outcome(
            problem,
            start_point,
            tolerance,
            newton_iterations,
            ETA_MAX,
            LINE_SEARCH_MEMORY,
            stall,
            presweeps,
        )
        answer = _fresh_answer(outcome, tolerance, symmetry_tolerance, start)
        if answer is not None:
            return answer, None, None, lemke_note
        newton = _newton_result(*outcome[:-1], tolerance, newton_iterations, stall)
    else:
        newton = solve_newton(
            problem,
            tolerance=tolerance,
            warm_start=warm_start,
            max_iterations=newton_iterations,
            presweeps=presweeps,
            stall_iterations=stall,
        )
    asymmetry = problem.asymmetry()  # cached by the call above when it computed it
    note = _asymmetry_note(asymmetry, symmetry_tolerance)
    path = _newton_path(newton.presweeps, newton.iterations)
    if not newton.converged and _gauss_seidel_finish(problem, newton, tolerance):
        path = "newton+gauss_seidel"
    if not newton.converged and method == "newton":
        newton = _monotone_retry(problem, newton, tolerance, newton_iterations)
    if path in ("newton", "gauss_seidel", "gauss_seidel+newton") and newton.report_residuals is not None:
        residual, data = newton.report_residuals  # the values residuals() gives, from the compiled path
    else:
        residual, data = residuals(problem, newton.multipliers)
    converged = bool(residual <= tolerance and data <= tolerance)
    if not converged and method == "auto" and lemke_applicable(problem) and not lemke_note:
        answer, lemke_note = _lemke_path(problem, tolerance)
        if answer is not None:
            message = f"newton first: {newton.message}; then " + lemke_note + note
            return _lemke_report(problem, answer, message, asymmetry, start), newton, asymmetry, lemke_note
    if not (converged or method == "newton"):
        return None, newton, asymmetry, lemke_note
    message = _newton_message(
        newton.storage, newton.message, newton.line_search_failures, newton.fallback_sweeps, note
    )
    if not converged:
        message = (
            f"not converged: residual {residual:.3e}, data residual {data:.3e} > tolerance "
            f"{tolerance:.1e} (largest error in {worst_kind(problem, newton.multipliers)} rows); " + message
        )
        logger.info("solve_exact %s: %s", problem.name or "problem", message)
    report = SolverReport(
        solver="exact/newton",
        iterations=newton.iterations,
        residual=residual,
        converged=converged,
        seconds=time.perf_counter() - start,
        message=message,
        history=newton.history,
        data_residual=data,
        asymmetry=asymmetry,
        path=path,
    )
    return (newton.multipliers, report), newton, asymmetry, lemke_note


def _fresh_answer(outcome, tolerance: float, symmetry_tolerance: float, start: float):
    """(λ, report) of the compiled fresh path's outcome when it converged as the report measures it, else
    None."""
    (
        best,
        history,
        iterations,
        _,
        failures,
        fallback,
        swept,
        residual,
        data,
        natural,
        data_final,
        asymmetry,
    ) = outcome
    if not (residual <= tolerance and data <= tolerance and natural <= tolerance and data_final <= tolerance):
        return None
    return best, SolverReport(
        solver="exact/newton",
        iterations=iterations,
        residual=natural,
        converged=True,
        seconds=time.perf_counter() - start,
        history=history,
        data_residual=data_final,
        asymmetry=asymmetry,
        path=_newton_path(swept, iterations),
        message=_newton_message(
            "dense",
            converged_message(iterations, swept),
            failures,
            fallback,
            _asymmetry_note(asymmetry, symmetry_tolerance),
        ),
    )


def _gauss_seidel_finish(problem: ConstraintProblem, newton, tolerance: float) -> bool:
    """Projected Gauss–Seidel from Newton's best point; updates ``newton`` and returns True when it converged.

    Newton stalls where the map is nonsmooth at the solution (friction bounds ‖λ_G‖ at λ_G = 0, cone apices);
    Gauss–Seidel, which such points do not trouble, runs in chunks of _GAUSS_SEIDEL_PROBE sweeps, the next
    only while the rate of the last chunk's second half (linear convergence assumed) reaches the tolerance
    within the sweeps left (where Gauss–Seidel cannot solve the problem, e.g. FCLib's rank-deficient
    local_problem_test, they would be wasted; its rate on a singular W often falls, so it is measured again on
    every chunk).
    """
    multipliers, sweeps = solve_gauss_seidel(
        problem,
        tolerance=tolerance,
        warm_start=newton.multipliers,
        max_iterations=_GAUSS_SEIDEL_PROBE,
        criterion="strict",
    )
    done = sweeps.iterations
    while (
        not sweeps.converged
        and done < _GAUSS_SEIDEL_SWEEPS
        and _gauss_seidel_can_finish(sweeps, tolerance, _GAUSS_SEIDEL_SWEEPS - done)
    ):
        multipliers, sweeps = solve_gauss_seidel(
            problem,
            tolerance=tolerance,
            warm_start=multipliers,
            max_iterations=min(_GAUSS_SEIDEL_PROBE, _GAUSS_SEIDEL_SWEEPS - done),
            criterion="strict",
        )
        done += sweeps.iterations
    sweeps = dataclasses.replace(sweeps, iterations=done)
    if not sweeps.converged:
        return False
    newton.multipliers, newton.converged = multipliers, True
    newton.message += f"; then {sweeps.iterations} Gauss-Seidel sweeps"
    newton.residual, newton.data_residual = sweeps.residual, sweeps.data_residual
    return True


def _monotone_retry(problem: ConstraintProblem, newton, tolerance: float, newton_iterations: int):
    """A monotone line search from Newton's best point; the better of the two results.

    Newton alone ("newton") has no other fallback; with "auto" the cone route follows instead (on the 74
    shared problems and the 520 steps of cube and cube_cut this retry never converged, and took 14 ms on
    local_problem_test).
    """
    second = solve_newton(
        problem,
        tolerance=tolerance,
        warm_start=newton.multipliers,
        max_iterations=newton_iterations,
        line_search_memory=1,
    )
    if second.converged or max(second.residual, second.data_residual) < max(
        newton.residual, newton.data_residual
    ):
        second.iterations += newton.iterations
        second.message += f" (after {newton.iterations} non-monotone iterations: {newton.message})"
        return second
    return newton


def _after_cone_route(
    problem: ConstraintProblem,
    multipliers: np.ndarray,
    report: SolverReport,
    *,
    method: str,
    tolerance: float,
    polish: bool,
    newton_iterations: int,
    asymmetry: float,
    symmetry_tolerance: float,
    lemke_note: str,
    newton,
    start: float,
) -> tuple[np.ndarray, SolverReport]:
    """The answer of :func:`solve_exact` from the cone route's: Newton from it ("auto", as the fast path's
    last resort), the better of it and the Newton path's result, and the report with every route's message."""
    data = data_residual(problem, multipliers)
    path = report.path
    if method == "auto" and polish and (report.residual > tolerance or data > tolerance):
        # the fast path's last resort: Newton from the cone route's answer
        result = solve_newton(
            problem, tolerance=tolerance, warm_start=multipliers, max_iterations=newton_iterations
        )
        if max(result.residual, result.data_residual) < max(report.residual, data):
            multipliers, data, path = result.multipliers, result.data_residual, "cone+newton"
    message = report.message
    if asymmetry > symmetry_tolerance:
        message += f"; the cone route solved the symmetric part of W (asymmetry {asymmetry:.1e})"
    if lemke_note:
        message = f"{lemke_note}; then " + message
    if newton is not None:
        message = f"newton first: {newton.message} (residual {newton.residual:.1e}); then " + message
        if max(newton.residual, newton.data_residual) < max(report.residual, data):
            multipliers, path = newton.multipliers, "newton"
            data = newton.data_residual
    residual = natural_residual(problem, multipliers)
    converged = bool(residual <= tolerance and data <= tolerance)
    return multipliers, SolverReport(
        solver=report.solver,
        iterations=report.iterations,
        residual=residual,
        converged=converged,
        seconds=time.perf_counter() - start,
        message=message,
        history=report.history,
        data_residual=data,
        asymmetry=asymmetry,
        path=path,
    )


def _asymmetry_note(asymmetry: float, symmetry_tolerance: float) -> str:
    """The message's note on a W non-symmetric by more than ``symmetry_tolerance`` (relative), else ""."""
    return f"; W non-symmetric by {asymmetry:.1e} (solved as given)" if asymmetry > symmetry_tolerance else ""


def _newton_path(presweeps: int, iterations: int) -> str:
    """report.path of an answer of the Newton path (pre-sweeps alone, pre-sweeps then Newton, Newton)."""
    if presweeps:
        return "gauss_seidel+newton" if iterations else "gauss_seidel"
    return "newton"


def _newton_message(storage: str, message: str, failures: int, fallback: int, note: str) -> str:
    """report.message of an answer of the Newton path."""
    return (
        f"newton ({storage}): {message}; {failures} line-search failure(s), "
        f"{fallback} fallback sweep(s){note}"
    )


def _gauss_seidel_can_finish(sweeps: SolverReport, tolerance: float, remaining: int) -> bool:
    """Whether the rate of the second half of the sweeps of ``sweeps`` (linear convergence assumed) reaches
    the tolerance within ``remaining`` more sweeps."""
    history = sweeps.history
    half = history.size // 2
    after = max(sweeps.residual, sweeps.data_residual)
    if sweeps.diverged or half == 0 or not (0.0 < history[-1] < history[half]) or not after > 0.0:
        return False
    return bool(
        np.log(tolerance / after) / np.log(history[-1] / history[half]) * (history.size - half) <= remaining
    )


def _lemke_path(problem: ConstraintProblem, tolerance: float):
    """Lemke's pivoting (:mod:`refsim.solvers.lemke`), then Newton from its answer if round-off left it above
    the tolerance; returns ((λ, path, residual, data) or None, message)."""
    result = solve_lemke(problem)
    if result.multipliers is None:
        if result.status == "ray":
            return None, (
                f"{result.message} (secondary ray: no solution found; for a copositive-plus W this "
                "proves the problem infeasible)"
            )
        return None, result.message
    multipliers = result.multipliers
    residual, data = residuals(problem, multipliers)
    path = "lemke"
    message = result.message
    if not (residual <= tolerance and data <= tolerance):
        polished = solve_newton(problem, tolerance=tolerance, warm_start=multipliers)
        if max(polished.residual, polished.data_residual) < max(residual, data):
            multipliers, path = polished.multipliers, "lemke+newton"
            residual, data = residuals(problem, multipliers)
            message += f"; then Newton: {polished.message}"
    if residual <= tolerance and data <= tolerance:
        return (multipliers, path, residual, data), message
    return None, message + f" (residual {residual:.1e}, data residual {data:.1e})"


def _lemke_report(problem, answer, message, asymmetry, start):
    multipliers, path, residual, data = answer
    return multipliers, SolverReport(
        solver="exact/lemke",
        iterations=0,
        residual=residual,
        converged=True,
        seconds=time.perf_counter() - start,
        message=message,
        data_residual=data,
        asymmetry=asymmetry,
        path=path,
    )
