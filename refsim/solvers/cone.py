"""The exact solver's cone-programming route: the problem formulated as QPs and second-order cone programs,
solved by a back-end, with a fixed point on the friction bounds (the route of
:func:`refsim.solvers.solve_exact` after Newton, and its certificate).

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
4. Polish: a damped least-squares semismooth Newton from the cone route's answer.
"""

from __future__ import annotations

import functools
import logging
import time
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sparse

from refsim.solvers.laws import LAW_NAMES, LAWS
from refsim.solvers.problem import ConstraintProblem
from refsim.solvers.report import SolverReport
from refsim.solvers.residual import data_residual, natural_map_error, natural_residual

__all__ = [
    "available_backends",
    "cone_bounds",
    "cone_route",
    "installed_backends",
    "worst_kind",
]

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


def available_backends() -> list[str]:
    """Names of the QP backends qpsolvers can use on this machine."""
    return list(installed_backends())


@functools.cache
def installed_backends() -> tuple[str, ...]:
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


def cone_bounds(problem: ConstraintProblem, multipliers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


def cone_route(
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
    lower, upper = cone_bounds(problem, multipliers)
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
        cone_bounds(problem, next_multipliers)[1][shaft] - cone_bounds(problem, multipliers)[1][shaft]
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
        worst = worst_kind(problem, best)
        parts.insert(
            0,
            f"not converged: residual {residual:.3e}, data residual "
            f"{data_residual(problem, best):.3e}, tolerance {tolerance:.1e} (largest error in {worst} "
            "rows)",
        )
        logger.info("solve_exact %s: %s", problem.name or "problem", "; ".join(parts))
    return converged


def worst_kind(problem: ConstraintProblem, multipliers: np.ndarray) -> str:
    error, _ = natural_map_error(problem, multipliers)
    return LAW_NAMES[int(problem.row_kinds()[int(np.argmax(np.abs(error)))])]
