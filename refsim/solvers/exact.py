"""The exact reference solver: semismooth Newton first, the cone-programming route as fallback and
certificate.

:func:`solve_exact` runs the Newton method of :mod:`refsim.solvers.newton` on W as given (any law of the
table, non-symmetric W accepted), finishes with Gauss–Seidel sweeps or a monotone Newton where it stalls, and
only then falls back to the cone route below; ``report.path`` says which produced the answer. The cone route:

1. Scaling. λ = τ D z with D a diagonal of 1/√W_ii (one common factor per contact, so that the Coulomb cone
   is unchanged) and τ = ‖D δ_free‖, so that the scaled compliance has a unit diagonal and z is of order one.
2. Frictionless part. min ½ zᵀ(D W D)z + (D δ_free / τ)ᵀz with z ≥ 0 on unilateral rows, fixed bounds on box
   rows and z free on bilateral rows: a convex QP whose KKT conditions are exactly the laws of these rows
   (W is replaced by its symmetric part). Solved through qpsolvers (Clarabel by default, OSQP, or any
   installed backend by name).
3. Friction by a fixed point on the bounds. Group friction rows get the box |λ_s| ≤ μ (‖λ_G‖ + p) with the
   group forces of the previous iterate. Contacts get the second-order cone ‖λ_t‖ ≤ μ λ_n through Clarabel's
   own interface (qpsolvers has no cones), with the De Saxcé modification of the free gap δ_free,n + μ ‖δ_t‖
   from the previous iterate; the KKT conditions of that cone QP are then the Coulomb law (Acary, Cadoux,
   Lemaréchal and Brogliato 2011). Iterate until the bounds stop changing.
4. Polish: Newton iterations (:mod:`refsim.solvers.newton`) from the cone route's answer.

The residuals reported are always recomputed by :func:`refsim.solvers.natural_residual` and
:func:`refsim.solvers.data_residual` on the problem as given; a backend's own "solved" is not believed. On
failure the best multipliers found are returned with the reason.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import time
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sparse

from refsim.solvers.gauss_seidel import solve_gauss_seidel
from refsim.solvers.laws import LAW_NAMES, LAWS
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
from refsim.solvers.residual import data_residual, natural_map_error, natural_residual, residuals

__all__ = ["available_backends", "solve_exact"]

logger = logging.getLogger(__name__)

#: Tight settings for the backends we know; any other qpsolvers backend runs with its defaults.
_BACKEND_OPTIONS = {
    "clarabel": {
        "tol_gap_abs": 1e-12,
        "tol_gap_rel": 1e-12,
        "tol_feas": 1e-12,
        "tol_ktratio": 1e-10,
        "max_iter": 500,
    },
    "osqp": {
        "eps_abs": 1e-10,
        "eps_rel": 1e-10,
        "polish": True,
        "max_iter": 200_000,
        "polish_refine_iter": 10,
    },
}


#: The fixed point tries the Newton polish from an iterate whose residual is below this, every few iterations.
_POLISH_FROM = 1e-3
_POLISH_EVERY = 5
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


def available_backends() -> list[str]:
    """Names of the QP backends qpsolvers can use on this machine."""
    return list(_installed_backends())


@functools.cache
def _installed_backends() -> tuple[str, ...]:
    import qpsolvers  # its list is fixed when it is imported

    return tuple(sorted(qpsolvers.available_solvers))


@dataclass(frozen=True)
class _Scaling:
    """λ = factor * z, factor = τ d (per row)."""

    factor: np.ndarray
    hessian: np.ndarray  # D W_sym D / τ⁰ (unit diagonal where W_ii > 0)
    gap_scale: np.ndarray  # D / τ: scaled linear term = gap_scale * δ_free'
    weight: np.ndarray  # ρ = 1 / W_ii (contact mean) [N/m], the natural-map weights of the Newton polish


def _scaling(problem: ConstraintProblem, symmetric: np.ndarray) -> _Scaling:
    diagonal = np.diag(symmetric).copy()
    largest = float(np.abs(diagonal).max()) if diagonal.size else 1.0
    floor = 1e-14 * max(largest, np.finfo(float).tiny)
    safe = np.where(diagonal > floor, diagonal, max(largest, 1.0) if largest > 0 else 1.0)
    if len(problem.contacts):
        contact_mean = safe[problem.contacts].mean(axis=1)
        safe[problem.contacts] = contact_mean[:, None]
    row_scale = 1.0 / np.sqrt(safe)
    hessian = symmetric * row_scale[:, None] * row_scale[None, :]
    tau = float(np.linalg.norm(row_scale * problem.free_gap))
    tau = tau if tau > 0.0 else 1.0
    return _Scaling(factor=tau * row_scale, hessian=hessian, gap_scale=row_scale / tau, weight=1.0 / safe)


def _bounds(problem: ConstraintProblem, multipliers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds [N] of every row for the current group forces (±inf when none): each law's
    ``bounds`` of :data:`~refsim.solvers.laws.LAWS`."""
    lower = np.full(problem.row_count, -np.inf)
    upper = np.full(problem.row_count, np.inf)
    for law in LAWS:
        if law.bounds is not None:
            law.bounds(problem, multipliers, lower, upper)
    return lower, upper


def _inequalities(lower: np.ndarray, upper: np.ndarray) -> tuple[sparse.csc_matrix, np.ndarray]:
    """G z ≤ h for the finite bounds lower ≤ z ≤ upper."""
    n = lower.size
    low = np.flatnonzero(np.isfinite(lower))
    up = np.flatnonzero(np.isfinite(upper))
    rows = np.arange(low.size + up.size)
    cols = np.concatenate([low, up])
    vals = np.concatenate([-np.ones(low.size), np.ones(up.size)])
    matrix = sparse.csc_matrix((vals, (rows, cols)), shape=(rows.size, n))
    return matrix, np.concatenate([-lower[low], upper[up]])


def _solve_qp(hessian, linear, lower, upper, backend, options) -> tuple[np.ndarray | None, str]:
    """Box-constrained convex QP through qpsolvers; returns (z or None, status)."""
    import qpsolvers

    inequality, bound = _inequalities(lower, upper)
    matrix = sparse.csc_matrix(hessian)
    kwargs = {"G": inequality, "h": bound} if bound.size else {}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            solution = qpsolvers.solve_problem(
                qpsolvers.Problem(matrix, linear, **kwargs), solver=backend, **options
            )
    except Exception as error:  # a backend failing in any way is a status to report, not a crash
        return None, f"{backend} raised {type(error).__name__}: {error}"
    if solution.x is None or not np.all(np.isfinite(solution.x)):
        return None, f"{backend} returned no solution"
    return np.asarray(solution.x, dtype=float), ("found" if solution.found else f"{backend} not found")


def _solve_cone(problem, hessian, linear, lower, upper, options) -> tuple[np.ndarray | None, str]:
    """Cone QP through clarabel.DefaultSolver: box rows, nonnegative rows and Coulomb cones (scaled)."""
    import clarabel

    n = problem.row_count
    contacts = problem.contacts
    mu = problem.contact_friction
    # bounds apply to every row outside the contacts (unilateral, box, shaft rows)
    outside = np.ones(n, dtype=bool)
    outside[contacts.reshape(-1)] = False
    inequality, bound = _inequalities(np.where(outside, lower, -np.inf), np.where(outside, upper, np.inf))
    frictionless = mu == 0.0
    zero_rows = contacts[frictionless][:, 1:].reshape(-1)
    sticky_normals = contacts[frictionless][:, 0]
    cone_contacts = contacts[~frictionless]
    cone_mu = mu[~frictionless]
    blocks, rhs, cones = [], [], []
    if zero_rows.size:
        blocks.append(
            sparse.csc_matrix(
                (np.ones(zero_rows.size), (np.arange(zero_rows.size), zero_rows)), shape=(zero_rows.size, n)
            )
        )
        rhs.append(np.zeros(zero_rows.size))
        cones.append(clarabel.ZeroConeT(zero_rows.size))
    nonnegative = bound.size + sticky_normals.size
    if nonnegative:
        blocks.append(inequality)
        rhs.append(bound)
        blocks.append(
            sparse.csc_matrix(
                (-np.ones(sticky_normals.size), (np.arange(sticky_normals.size), sticky_normals)),
                shape=(sticky_normals.size, n),
            )
        )
        rhs.append(np.zeros(sticky_normals.size))
        cones.append(clarabel.NonnegativeConeT(nonnegative))
    if cone_contacts.size:
        k = cone_contacts.shape[0]
        rows = np.arange(3 * k)
        vals = -np.column_stack([cone_mu, np.ones(k), np.ones(k)]).reshape(-1)
        blocks.append(sparse.csc_matrix((vals, (rows, cone_contacts.reshape(-1))), shape=(3 * k, n)))
        rhs.append(np.zeros(3 * k))
        cones.extend(clarabel.SecondOrderConeT(3) for _ in range(k))
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    for key, value in options.items():
        setattr(settings, key, value)
    constraint = sparse.vstack(blocks).tocsc() if blocks else sparse.csc_matrix((0, n))
    try:
        solver = clarabel.DefaultSolver(
            sparse.triu(sparse.csc_matrix(hessian)).tocsc(),
            linear,
            constraint,
            np.concatenate(rhs) if rhs else np.zeros(0),
            cones,
            settings,
        )
        solution = solver.solve()
    except Exception as error:  # reported, not raised
        return None, f"clarabel raised {type(error).__name__}: {error}"
    x = np.asarray(solution.x, dtype=float)
    if x.size != n or not np.all(np.isfinite(x)):
        return None, f"clarabel status {solution.status} without a finite solution"
    return x, str(solution.status)


def _newton_step(
    problem: ConstraintProblem, multipliers: np.ndarray, weight: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Semismooth Newton direction for the natural map F(λ) = λ − Π(λ − ρ δ̂(λ)); returns (F, direction).

    A generalised Jacobian J = I − D_Π (I − ρ ∂δ̂/∂λ) − ∂Π/∂b ∂b/∂λ, D_Π the Jacobian of the projection of
    each row or contact, ∂b/∂λ the derivative of the shaft bounds; the step solves J Δ = −F by least squares
    (J is singular when W is). With D_Π ∈ {0, 1} on rows without friction this is the active-set solve. The
    weights ρ ≈ 1/W_ii (equal within a contact) balance forces and gaps; they do not change the zeros of F.
    """
    n = problem.row_count
    error, gap = natural_map_error(problem, multipliers, weight)
    weighted = weight * gap
    gap_jacobian = problem.compliance.copy()
    projection = np.zeros((n, n))
    bound_term = np.zeros((n, n))
    for law in LAWS:  # each law writes its own rows (laws.py: the Python form of jacobian_blocks)
        law.projection(problem, multipliers, gap, weighted, weight, projection, gap_jacobian, bound_term)
    jacobian = np.eye(n) - projection + projection @ (weight[:, None] * gap_jacobian) - bound_term
    # QR with column pivoting (LAPACK gelsy): rank-revealing like the SVD, several times faster
    direction = scipy.linalg.lstsq(jacobian, -error, cond=1e-14, lapack_driver="gelsy", check_finite=False)[0]
    return error, direction


def _least_squares_polish(problem, multipliers, residual, tolerance, weight, max_steps=50, margin=1e-3):
    """Semismooth Newton with a backtracking line search on ‖F‖² until the natural residual is ≤ margin ×
    tolerance; returns (λ, residual, steps accepted)."""
    accepted = 0
    best, best_residual = multipliers, residual
    for _ in range(max_steps):
        if best_residual <= margin * tolerance:
            break
        error, direction = _newton_step(problem, multipliers, weight)
        merit = float(error @ error)
        if not np.all(np.isfinite(direction)):
            break
        step = 1.0
        while step > 1e-6:
            candidate = multipliers + step * direction
            candidate_error, _ = natural_map_error(problem, candidate, weight)
            if candidate_error @ candidate_error <= (1.0 - 1e-4 * step) * merit:
                break
            step *= 0.5
        else:
            break
        multipliers = candidate
        accepted += 1
        candidate_residual = natural_residual(problem, candidate)
        if candidate_residual < best_residual:
            best, best_residual = candidate, candidate_residual
    return best, best_residual, accepted


def _polish(problem, multipliers, residual, tolerance, weight, max_steps=50, margin=1e-3):
    """The cone route's polish: the damped least-squares Newton of the previous exact solver (unchanged, so
    the cone route returns the multipliers it returned before); returns (λ, natural residual, steps)."""
    return _least_squares_polish(
        problem, multipliers, residual, tolerance, weight, max_steps=max_steps, margin=margin
    )


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
    multipliers, report = _cone_route(
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
    it on small fresh problems (one call: see refsim.solvers.newton._solve_dense_fresh).
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
    backends = _installed_backends()
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
        # the one compiled call of small fresh problems; when it converged (as the report measures it),
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
            f"{tolerance:.1e} (largest error in {_worst_kind(problem, newton.multipliers)} rows); " + message
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


def _cone_route(
    problem: ConstraintProblem,
    *,
    tolerance: float,
    backend: str,
    max_iterations: int,
    polish: bool,
    backend_options: dict | None,
    start: float,
    margin: float = 1e-3,
) -> tuple[np.ndarray, SolverReport]:
    """The cone-programming route (steps 1-4 of the module notes) on the symmetric part of W."""
    solver_name = f"exact/{backend}"
    n = problem.row_count
    if n == 0:
        return np.zeros(0), SolverReport(
            solver=solver_name,
            iterations=0,
            residual=0.0,
            converged=True,
            seconds=time.perf_counter() - start,
            message="empty problem",
        )
    options, cone_options = _route_options(backend, backend_options)
    symmetric = 0.5 * (problem.compliance + problem.compliance.T)
    scaling = _scaling(problem, symmetric)
    has_contacts = len(problem.contacts) > 0
    needs_fixed_point = has_contacts or len(problem.friction_groups()[0]) > 0

    multipliers = np.zeros(n)  # the iterate whose forces set the shaft bounds
    best, best_residual = multipliers, natural_residual(problem, multipliers)
    history = []
    status = "not started"
    modified_gap = problem.free_gap.copy()
    iterations = 0
    settled = False
    damping = 1.0
    polish_steps = 0
    previous_residual = np.inf
    for iterations in range(1, int(max_iterations) + 1):
        z, status = _scaled_solve(problem, scaling, multipliers, modified_gap, backend, options, cone_options)
        if z is None:
            history.append(np.nan)
            break
        new_multipliers = scaling.factor * z
        residual = natural_residual(problem, new_multipliers)
        history.append(residual)
        if residual < best_residual:
            best, best_residual = new_multipliers, residual
        if not needs_fixed_point:
            settled = True
            break
        if polish and residual <= _POLISH_FROM and (iterations - 1) % _POLISH_EVERY == 0:
            candidate, candidate_residual, steps = _polish(
                problem, new_multipliers, residual, tolerance, scaling.weight, max_steps=20, margin=margin
            )
            polish_steps += steps
            if candidate_residual < best_residual:
                best, best_residual = candidate, candidate_residual
            if best_residual <= tolerance:
                settled = True
                break
        # bounds of the next iterate: pair forces and De Saxcé slip terms; damped once the iterates oscillate
        if residual > previous_residual:
            damping = 0.5
        previous_residual = residual
        next_multipliers = damping * new_multipliers + (1.0 - damping) * multipliers
        new_gap, unchanged = _next_bounds(problem, multipliers, next_multipliers, modified_gap, tolerance)
        multipliers, modified_gap = next_multipliers, new_gap
        if unchanged or residual <= 1e-3 * tolerance:
            settled = True
            break
    if polish and best_residual > margin * tolerance:
        best, best_residual, steps = _polish(
            problem, best, best_residual, tolerance, scaling.weight, margin=margin
        )
        polish_steps += steps
        history.append(best_residual)
    residual = natural_residual(problem, best)
    parts = [f"{iterations} {'cone' if has_contacts else 'QP'} solve(s), last status {status}"]
    if needs_fixed_point:
        parts.append(
            "fixed point on the friction bounds "
            + ("settled" if settled else f"not settled after {iterations} iterations")
            + (", damped after oscillating" if damping < 1.0 else "")
        )
    parts += [f"{polish_steps} least-squares Newton polish step(s)"] if polish else []
    converged = _cone_verdict(problem, best, residual, tolerance, parts)
    return best, SolverReport(
        solver=solver_name,
        iterations=iterations,
        residual=residual,
        converged=converged,
        seconds=time.perf_counter() - start,
        message="; ".join(parts),
        history=np.array(history, dtype=float),
        path="cone",
    )


def _route_options(backend: str, backend_options: dict | None) -> tuple[dict, dict]:
    """The options of the QP backend and of Clarabel's cone interface: our tight defaults, replaced key by key
    by ``backend_options`` (the cone's only when the backend is Clarabel)."""
    options = dict(_BACKEND_OPTIONS.get(backend, {}))
    options.update(backend_options or {})
    cone_options = dict(_BACKEND_OPTIONS["clarabel"])
    if backend == "clarabel":
        cone_options.update(backend_options or {})
    return options, cone_options


def _scaled_solve(problem, scaling, multipliers, modified_gap, backend, options, cone_options):
    """One solve of the cone route in scaled variables z (λ = factor z): the cone QP with contacts, else the
    QP, with the friction bounds of ``multipliers`` and the modified free gap; (z or None, status)."""
    lower, upper = _bounds(problem, multipliers)
    linear = scaling.gap_scale * modified_gap
    if len(problem.contacts) > 0:
        return _solve_cone(
            problem, scaling.hessian, linear, lower / scaling.factor, upper / scaling.factor, cone_options
        )
    return _solve_qp(
        scaling.hessian, linear, lower / scaling.factor, upper / scaling.factor, backend, options
    )


def _next_bounds(problem, multipliers, next_multipliers, modified_gap, tolerance: float):
    """The De Saxcé-modified free gap of the next cone-route iterate, and whether the fixed point settled:
    the modified gap and the friction bounds changed by at most 1e-3 × the tolerance (relative)."""
    gap = problem.compliance @ next_multipliers + problem.free_gap
    new_gap = problem.free_gap.copy()
    if len(problem.contacts) > 0:
        slip = np.linalg.norm(gap[problem.contacts[:, 1:]], axis=1)
        new_gap[problem.contacts[:, 0]] += problem.contact_friction * slip
    change_gap = np.linalg.norm(new_gap - modified_gap)
    shaft = problem.friction_groups()[0]
    change_bound = np.linalg.norm(
        _bounds(problem, next_multipliers)[1][shaft] - _bounds(problem, multipliers)[1][shaft]
    )
    scale_gap = max(np.linalg.norm(problem.free_gap), np.linalg.norm(gap), np.finfo(float).tiny)
    scale_force = max(np.linalg.norm(next_multipliers), np.finfo(float).tiny)
    unchanged = change_gap <= 1e-3 * tolerance * scale_gap and change_bound <= 1e-3 * tolerance * scale_force
    return new_gap, bool(unchanged)


def _cone_verdict(problem, best, residual: float, tolerance: float, parts: list) -> bool:
    """Whether the cone route's answer meets the tolerance in both residuals; when not, the reason is put
    first in ``parts`` (the message) and logged."""
    converged = bool(residual <= tolerance)
    converged = bool(converged and data_residual(problem, best) <= tolerance)
    if not converged:
        worst = _worst_kind(problem, best)
        parts.insert(
            0,
            f"not converged: residual {residual:.3e}, data residual "
            f"{data_residual(problem, best):.3e}, tolerance {tolerance:.1e} (largest error in {worst} "
            "rows)",
        )
        logger.info("solve_exact %s: %s", problem.name or "problem", "; ".join(parts))
    return converged


def _worst_kind(problem: ConstraintProblem, multipliers: np.ndarray) -> str:
    error, _ = natural_map_error(problem, multipliers)
    return LAW_NAMES[int(problem.row_kinds()[int(np.argmax(np.abs(error)))])]
