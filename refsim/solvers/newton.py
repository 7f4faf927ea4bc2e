"""A nonsmooth (semismooth) Newton method on the natural map, for every law of the table.

The map is F(λ) = λ − Π(λ − ρ δ̂(λ)) with δ = W λ + δ_free, δ̂ the De Saxcé modified gap (contacts), Π the
projection of each block on its admissible set (a law of :data:`refsim.solvers.laws.LAWS`; group friction
bounds move with λ) and ρ_i = 1/W_ii [N/m] (equal on the rows of a contact), so that F is a force [N] and its
zeros are the solutions (Alart and Curnier 1991 use the same projection with an augmented Lagrangian; Acary,
Brémond and Huber 2018 compare such Newton variants on FCLib).

A generalised Jacobian is J = N + M W − G, with block-diagonal N = I − D_Π and M = D_Π diag(ρ) T (T the
derivative of the De Saxcé term), and G the derivative of the group bounds; its blocks come from the compiled
kernel :func:`refsim.solvers.laws.jacobian_blocks`, so every law of the table is covered.

Each step solves (J + η I) d = −F: plain Newton (η = 0) while it works, else a Levenberg–Marquardt
regularisation η = min(η_max, ‖F‖ / F_data) 10^(k−1), the level k raised after each failure (a singular
factor, a failed line search) and lowered after each success (W is often singular: redundant contacts). Dense
LAPACK LU below ``sparse_above`` rows or when W is dense, else a sparse LU (SuperLU) of the sparse J.
Globalisation: a non-monotone Armijo line search on θ = ½‖F‖² (Grippo, Lampariello and Lucidi 1986; memory 3
by default); when it fails, a few projected Gauss–Seidel sweeps are taken instead and η is raised; after
repeated failures the method stops and says so (the caller then falls back to the cone route). Stops as soon
as the natural residual and the data residual (:mod:`refsim.solvers.residual`) are at most the tolerance. With
``presweeps`` > 0, projected Gauss–Seidel sweeps come first (:func:`~refsim.solvers.newton_kernel._presweep`:
at most that many, stopped when their observed rate cannot reach the tolerance in time) and Newton starts from
the swept point when it at least halves the start's residual
(:data:`~refsim.solvers.newton_kernel._KEEP_SWEPT`). Dense problems run every iteration in the compiled kernel
of :mod:`refsim.solvers.newton_kernel`; sparse storage, a time limit or minimum-norm steps run the same
iteration in Python (:func:`_solve_layered`).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sparse
import scipy.sparse.linalg as sparse_linalg

from refsim.solvers.gauss_seidel import _data_residual, _residual
from refsim.solvers.laws import (
    CONTACT,
    GROUP_FRICTION,
    block_arrays,
    gauss_seidel_sweep,
    jacobian_blocks,
    law_arrays,
    natural_map_blocks,
)
from refsim.solvers.linear import (
    _dense_jacobian,
    _gesv,
)
from refsim.solvers.newton_kernel import (
    NewtonProblem,
    _dense_newton_fresh,
    _presweep,
    _sweep_arrays,
)
from refsim.solvers.problem import ConstraintProblem
from refsim.solvers.residual import data_scales

__all__ = ["NewtonResult", "solve_newton"]

#: Problems with more rows than this (and a sparse enough W) use sparse storage and a sparse LU.
SPARSE_ABOVE = 300
# : Defaults of :func:`solve_newton`: the largest Levenberg–Marquardt regularisation and the line search's
# memory.
ETA_MAX = 1e-2
LINE_SEARCH_MEMORY = 3
#: Largest density nnz(W) / n² for the sparse path.
SPARSE_DENSITY = 0.15
#: Dense problems up to this many rows solve J d = −F in compiled code (no SciPy call overhead).
_COMPILED_SOLVE_BELOW = 120


@dataclass(slots=True)
class NewtonResult:
    """What :func:`solve_newton` did (internal to the exact solver)."""

    multipliers: np.ndarray
    converged: bool
    iterations: int
    residual: float  # natural residual, from the compiled kernel on the final gap
    data_residual: float
    message: str
    storage: str  # "dense" or "sparse"
    history: np.ndarray
    line_search_failures: int
    fallback_sweeps: int
    #: (natural_residual, data_residual) of ``multipliers`` when the compiled path computed them, else None
    report_residuals: tuple | None = None
    #: Gauss-Seidel sweeps taken before the first Newton iteration (``presweeps``)
    presweeps: int = 0


class _Operator:
    """W in dense or sparse (CSR) storage, with the products and the Jacobian assembly the method needs."""

    def __init__(self, problem: ConstraintProblem, kinds, rows, members, sparse_above: int):
        compliance = problem.compliance
        n = problem.row_count
        self.dense = compliance
        self.sparse = None if takes_fresh_path(problem, sparse_above) else sparse.csr_matrix(compliance)
        self.kinds, self.rows, self.members = kinds, rows, members
        self.n = n
        if self.sparse is not None:
            self._prepare_sparse_pattern()
        else:
            self.jacobian = np.empty((n, n))

    @property
    def storage(self) -> str:
        return "dense" if self.sparse is None else "sparse"

    def gap(self, multipliers, free_gap):
        if self.sparse is None:
            return self.dense @ multipliers + free_gap
        return self.sparse @ multipliers + free_gap

    def _prepare_sparse_pattern(self):
        kinds, rows = self.kinds, self.rows
        contact = kinds == CONTACT
        single = np.flatnonzero(~contact)
        cone = np.flatnonzero(contact)
        # block entries (row, column, block index, i, j)
        i_idx, j_idx = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
        self.block_rows = np.concatenate([rows[single, 0], rows[cone][:, i_idx.reshape(-1)].reshape(-1)])
        self.block_cols = np.concatenate([rows[single, 0], rows[cone][:, j_idx.reshape(-1)].reshape(-1)])
        self.block_index = np.concatenate([single, np.repeat(cone, 9)])
        self.block_i = np.concatenate(
            [np.zeros(single.size, dtype=np.int64), np.tile(i_idx.reshape(-1), cone.size)]
        )
        self.block_j = np.concatenate(
            [np.zeros(single.size, dtype=np.int64), np.tile(j_idx.reshape(-1), cone.size)]
        )
        friction = np.flatnonzero(kinds == GROUP_FRICTION)
        sizes = rows[friction, 2] - rows[friction, 1]
        self.group_rows = np.repeat(rows[friction, 0], sizes)
        self.group_slots = (
            np.concatenate(
                [np.arange(s, e) for s, e in zip(rows[friction, 1], rows[friction, 2], strict=True)]
            )
            if friction.size
            else np.zeros(0, dtype=np.int64)
        )

    def _compiled_solve(self, rhs):
        """J d = rhs by LAPACK gesv inside a compiled function (no Python-side overhead for small J); None
        when J is singular."""
        try:
            return _gesv(self.jacobian, rhs)
        except Exception:  # numba raises a plain exception for a singular matrix
            return None

    def least_squares(self, rhs):
        """Minimum-norm least-squares solution of J d = rhs for the last dense J (LAPACK gelsy)."""
        return scipy.linalg.lstsq(self.jacobian, rhs, cond=1e-12, lapack_driver="gelsy", check_finite=False)[
            0
        ]

    def assemble(self, local, gap_factor, bound_values, eta):
        """The dense J + η I into ``self.jacobian``."""
        _dense_jacobian(
            self.dense,
            self.kinds,
            self.rows,
            local,
            gap_factor,
            self.members,
            bound_values,
            eta,
            self.jacobian,
        )

    def factorize(self, local, gap_factor, bound_values, eta):
        """Factor J + η I; returns a solve(rhs) callable, or None when the factorisation fails."""
        if self.sparse is None:
            self.assemble(local, gap_factor, bound_values, eta)
            if self.n <= _COMPILED_SOLVE_BELOW:
                return self._compiled_solve
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # an exactly singular J is handled below
                    factor = scipy.linalg.lu_factor(self.jacobian, check_finite=False, overwrite_a=False)
            except (ValueError, np.linalg.LinAlgError):
                return None
            if not np.all(np.isfinite(factor[0])) or np.min(np.abs(np.diag(factor[0]))) == 0.0:
                return None
            return lambda rhs: scipy.linalg.lu_solve(factor, rhs, check_finite=False)
        n = self.n
        values_m = gap_factor[self.block_index, self.block_i, self.block_j]
        values_n = local[self.block_index, self.block_i, self.block_j]
        block_m = sparse.csr_matrix((values_m, (self.block_rows, self.block_cols)), shape=(n, n))
        rest = sparse.csr_matrix(
            (
                np.concatenate([values_n, np.full(n, eta), -bound_values[self.group_slots]]),
                (
                    np.concatenate([self.block_rows, np.arange(n), self.group_rows]),
                    np.concatenate([self.block_cols, np.arange(n), self.members[self.group_slots]]),
                ),
            ),
            shape=(n, n),
        )
        jacobian = (block_m @ self.sparse + rest).tocsc()
        try:
            factor = sparse_linalg.splu(jacobian, permc_spec="COLAMD")
        except RuntimeError:
            return None
        return factor.solve


_REASONS = (
    "",
    "iteration cap {cap} reached",
    "the regularised Jacobian could not be factorised",
    "line search failed 9 times in a row",
    "stalled: the best residual did not halve in {stall} iterations",
)


def takes_fresh_path(problem: ConstraintProblem, sparse_above: int = SPARSE_ABOVE) -> bool:
    """Whether W is stored dense (at most ``sparse_above`` rows, or more than :data:`SPARSE_DENSITY` of it
    non-zero; else sparse, :class:`_Operator`): then :func:`solve_newton` (without ``minimum_norm`` or
    ``time_limit``) solves ``problem`` by the one compiled call of :func:`_solve_dense_fresh`, whatever is
    cached on the problem (the call sets the problem up itself, as :func:`~refsim.solvers.laws.block_arrays`
    and :func:`~refsim.solvers.residual.data_scales` do)."""
    n = problem.row_count
    return n <= sparse_above or np.count_nonzero(problem.compliance) > SPARSE_DENSITY * n * n


def _fresh_outcome(
    problem, multipliers, tolerance, max_iterations, eta_max, line_search_memory, stall_iterations, presweeps
) -> tuple:
    """The compiled call of :func:`_solve_dense_fresh`: its raw outcome (best λ, history, iterations, reason,
    line-search failures, fallback sweeps, pre-sweeps, best natural and data residual, the report's natural
    and data residual, asymmetry), W's asymmetry cached on the problem."""
    p = problem
    compliance, free_gap = p.compliance, p.free_gap
    if not (compliance.flags.c_contiguous and free_gap.flags.c_contiguous):
        compliance, free_gap = np.ascontiguousarray(compliance), np.ascontiguousarray(free_gap)
    outcome = _dense_newton_fresh(
        compliance,
        free_gap,
        law_arrays(p),
        multipliers,
        float(tolerance),
        int(max_iterations),
        float(eta_max),
        int(line_search_memory),
        int(stall_iterations),
        int(presweeps),
    )
    if "_asymmetry" not in p.__dict__:
        object.__setattr__(p, "_asymmetry", outcome[-1])
    return outcome


def converged_message(iterations: int, presweeps: int) -> str:
    """The message of a Newton solve that converged."""
    if presweeps:
        return f"{presweeps} Gauss-Seidel pre-sweep(s), then converged in {iterations} Newton iteration(s)"
    return f"converged in {iterations} Newton iteration(s)"


def _solve_dense_fresh(
    problem, multipliers, tolerance, max_iterations, eta_max, line_search_memory, stall_iterations, presweeps
) -> NewtonResult:
    """solve_newton on dense storage: one compiled call (:func:`_dense_newton_fresh`) for the set-up that
    :func:`~refsim.solvers.laws.block_arrays` (:func:`~refsim.solvers.laws.assemble_blocks` on the packed law
    fields) and :func:`~refsim.solvers.residual.data_scales` make, ‖δ_free‖, W's asymmetry (cached on the
    problem for :meth:`ConstraintProblem.asymmetry`), the kernel's buffers and every Newton iteration
    (:func:`~refsim.solvers.newton_kernel._dense_newton`: no Python call per iteration). What is cached on the
    problem is not read: the kernel recomputes the same set-up by the same compiled operations, bit for bit,
    so a solve is one dispatch and the dense Newton iteration is one compiled entry point (its compilation,
    the longest of refsim's, is paid once per cache, not once per way of reaching it)."""
    outcome = _fresh_outcome(
        problem,
        multipliers,
        tolerance,
        max_iterations,
        eta_max,
        line_search_memory,
        stall_iterations,
        presweeps,
    )
    return _newton_result(*outcome[:-1], tolerance, max_iterations, stall_iterations)


def _newton_result(
    best,
    history,
    iterations,
    reason,
    failures,
    fallback,
    swept,
    residual,
    data,
    natural,
    data_final,
    tolerance,
    max_iterations,
    stall_iterations,
) -> NewtonResult:
    """The NewtonResult of a compiled dense solve (``history`` already of its recorded length)."""
    # the kernel's scalars arrive as Python floats, ints and bools (numba boxes them): no conversion needed
    converged = residual <= tolerance and data <= tolerance
    if converged:
        message = converged_message(iterations, swept)
    else:
        message = _REASONS[reason].format(cap=max_iterations, stall=stall_iterations)
        if swept:
            message = f"{swept} Gauss-Seidel pre-sweep(s), then {message}"
    return NewtonResult(
        best,
        converged,
        iterations,
        residual,
        data,
        message,
        "dense",
        history,
        failures,
        fallback,
        (
            natural if natural <= math.inf else math.inf,  # NaN compares False: inf
            data_final if data_final <= math.inf else math.inf,
        ),
        swept,
    )


def solve_newton(
    problem: ConstraintProblem,
    *,
    tolerance: float,
    warm_start: np.ndarray | None = None,
    max_iterations: int = 100,
    sparse_above: int = SPARSE_ABOVE,
    eta_max: float = ETA_MAX,
    time_limit: float = np.inf,
    line_search_memory: int = LINE_SEARCH_MEMORY,
    minimum_norm: bool = False,
    stall_iterations: int = 20,
    presweeps: int = 0,
) -> NewtonResult:
    """Semismooth Newton on the natural map (see the module notes).

    Parameters
    ----------
    problem : The constraint problem (W as given: need not be symmetric).
    tolerance : Stop when the natural residual and the data residual are both at most this [-].
    warm_start : Initial multipliers λ₀ [N], shape (row_count,); zeros when None.
    max_iterations : Largest number of Newton iterations.
    sparse_above : Row count above which a sparse W (density ≤ 15 %) is stored and factorised sparse.
    eta_max : Largest Levenberg–Marquardt regularisation η [-] (relative to the unit diagonal of ρ W).
    time_limit : Stop after this many seconds [s].
    line_search_memory : Number of past merit values the non-monotone Armijo test compares with (1: monotone).
    minimum_norm : Take minimum-norm least-squares steps (LAPACK gelsy) instead of LU ones on dense problems.
    stall_iterations : Stop when the best residual has not halved in this many iterations.
    presweeps : At most this many projected Gauss–Seidel sweeps before the first Newton iteration, stopped as
        soon as both residuals meet the tolerance or the sweeps' observed rate cannot reach it within the
        rest; Newton starts from the swept point when it at least halves the start's residual (0: none).

    Returns
    -------
    NewtonResult with the best multipliers found.
    """
    start = time.perf_counter()
    n = problem.row_count
    multipliers = (
        np.zeros(n)
        if warm_start is None
        else np.array(problem.check_multipliers(warm_start), dtype=np.float64)
    )
    if not minimum_norm and not math.isfinite(time_limit) and takes_fresh_path(problem, sparse_above):
        return _solve_dense_fresh(
            problem,
            multipliers,
            tolerance,
            max_iterations,
            eta_max,
            line_search_memory,
            stall_iterations,
            presweeps,
        )
    kinds, rows, params, members = block_arrays(problem)
    weight, force_scale = data_scales(problem)
    free_gap = np.ascontiguousarray(problem.free_gap)
    free_norm = math.sqrt(float(free_gap.dot(free_gap)))  # np.linalg.norm's own formula, without its overhead
    data_scale = max(free_norm, force_scale)
    return _solve_layered(
        problem,
        (kinds, rows, params, members),
        (weight, force_scale, free_gap, free_norm, data_scale),
        multipliers,
        start,
        tolerance=tolerance,
        max_iterations=max_iterations,
        sparse_above=sparse_above,
        eta_max=eta_max,
        time_limit=time_limit,
        line_search_memory=line_search_memory,
        minimum_norm=minimum_norm,
        stall_iterations=stall_iterations,
        presweeps=presweeps,
    )


class _LayeredMaps:
    """The maps of the Python Newton iteration (:func:`_solve_layered`) over an :class:`_Operator`: the merit
    θ = ½‖F‖², the natural and data residuals, Gauss–Seidel sweeps, and the direction of a step. ``error``
    (n,) holds F of the last point :meth:`merit` was taken at."""

    def __init__(self, problem: ConstraintProblem, blocks: tuple, scales: tuple, sparse_above: int):
        kinds, rows, params, members = blocks
        self.problem = problem
        self.blocks = blocks
        self.weight, self.force_scale, self.free_gap, self.free_norm, self.data_scale = scales
        n = problem.row_count
        self.unit = np.ones(n)
        self.operator = _Operator(problem, kinds, rows, members, sparse_above)
        self.error = np.empty(n)
        self.scratch = np.empty(n)
        self.local = np.empty((kinds.size, 3, 3))
        self.gap_factor = np.empty((kinds.size, 3, 3))
        self.bound_values = np.zeros(members.size)
        self._transposed = None
        self._diagonal = None

    def merit(self, force):
        """(θ(λ), δ(λ)); F(λ) into ``error``."""
        gap = self.operator.gap(force, self.free_gap)
        natural_map_blocks(*self.blocks, force, gap, self.weight, self.error)
        return 0.5 * float(self.error @ self.error), gap

    def residuals(self, force, gap):
        """(natural residual, data residual) of λ with its gap."""
        return (
            _residual(*self.blocks, force, gap, self.free_norm, self.scratch, self.unit),
            _data_residual(*self.blocks, force, gap, self.unit, self.data_scale, self.scratch),
        )

    def sweeps(self, force, count):
        """``count`` projected Gauss–Seidel sweeps from a copy of λ (Wᵀ and its diagonal made on first
        use)."""
        if self._transposed is None:
            compliance = self.problem.compliance
            self._transposed = np.array(compliance.T, order="C", copy=True)
            self._diagonal = np.diag(compliance).copy()
            floor = 1e-14 * max(float(np.abs(self._diagonal).max()), np.finfo(float).tiny)
            self._diagonal[self._diagonal <= floor] = 0.0
        force = force.copy()
        gap = self.operator.gap(force, self.free_gap)
        for _ in range(count):
            gauss_seidel_sweep(self._transposed, self._diagonal, *self.blocks, force, gap, 1.0)
        return force

    def presweeps(self, multipliers, theta, gap, residual, data, tolerance, presweeps):
        """Up to ``presweeps`` Gauss–Seidel sweeps from λ (:func:`_presweep`); returns (λ, θ, δ, residual,
        data residual, sweeps taken), the swept point's when it replaced the start."""
        if not presweeps > 0 or (residual <= tolerance and data <= tolerance):
            return multipliers, theta, gap, residual, data, 0
        compliance = np.ascontiguousarray(self.problem.compliance)
        start_point = multipliers.copy()
        n = multipliers.size
        kernel_problem = NewtonProblem(
            compliance,
            self.free_gap,
            *self.blocks,
            self.weight,
            float(self.free_norm),
            float(self.data_scale),
            float(self.force_scale),
        )
        swept, _, replaced, _, _, _ = _presweep(
            kernel_problem,
            *_sweep_arrays(compliance),
            start_point,
            max(residual, data),
            float(tolerance),
            int(presweeps),
            self.scratch,
            self.unit,
            np.empty(n),
            np.empty(n),
        )
        if replaced:  # the residuals again on this path's own gap (sparse storage: another product)
            multipliers = start_point
            theta, gap = self.merit(multipliers)
            residual, data = self.residuals(multipliers, gap)
        return multipliers, theta, gap, residual, data, swept

    def direction(self, multipliers, gap, theta, level, eta_max, minimum_norm):
        """The step of (J + η I) d = −F at λ (η as in :func:`_newton_direction`): a least-squares step when
        asked (dense, level 0) or when the dense J is exactly singular at level 0, else an LU. Returns (d, or
        None when it failed or is not finite or longer than 1e4 max(‖λ‖, F_data); 1 when an unasked
        least-squares step was taken else 0)."""
        operator = self.operator
        jacobian_blocks(
            *self.blocks, multipliers, gap, self.weight, self.local, self.gap_factor, self.bound_values
        )
        relative = np.sqrt(2.0 * theta) / self.force_scale
        eta = 0.0 if level == 0 else max(min(eta_max, relative) * 10.0 ** (level - 1), 1e-14)
        if level == 0 and operator.sparse is None and minimum_norm:
            operator.assemble(self.local, self.gap_factor, self.bound_values, 0.0)
            direction = operator.least_squares(-self.error)
        else:
            solve = operator.factorize(self.local, self.gap_factor, self.bound_values, eta)
            direction = None if solve is None else solve(-self.error)
        limit = 1e4 * max(np.linalg.norm(multipliers), self.force_scale)
        # an exactly singular dense J (no LU): the least-squares (rank-revealing QR) step instead; a direction
        # far longer than the forces in play (a nearly singular J) is regularised next iteration, as in the
        # compiled kernel (see _dense_newton)
        singular = 0
        if level == 0 and not minimum_norm and operator.sparse is None and direction is None:
            direction = operator.least_squares(-self.error)
            singular = 1
        if direction is None or not np.all(np.isfinite(direction)) or np.linalg.norm(direction) > limit:
            return None, singular
        return direction, singular

    def line_search(self, multipliers, direction, theta, reference):
        """The non-monotone Armijo backtracking of :func:`_line_search`: (accepted, candidate, its θ, its
        gap)."""
        step = 1.0
        while step >= 2.0**-12:
            candidate = multipliers + step * direction
            candidate_theta, candidate_gap = self.merit(candidate)
            if candidate_theta <= reference - 1e-4 * step * 2.0 * theta:
                return True, candidate, candidate_theta, candidate_gap
            step *= 0.5
        return False, candidate, candidate_theta, candidate_gap


def _solve_layered(
    problem: ConstraintProblem,
    blocks: tuple,
    scales: tuple,
    multipliers: np.ndarray,
    start: float,
    *,
    tolerance: float,
    max_iterations: int,
    sparse_above: int,
    eta_max: float,
    time_limit: float,
    line_search_memory: int,
    minimum_norm: bool,
    stall_iterations: int,
    presweeps: int,
) -> NewtonResult:
    """The Newton iteration of :func:`solve_newton` in Python over :class:`_Operator` (sparse storage, a time
    limit or minimum-norm steps): ``blocks`` (kinds, rows, params, members) of
    :func:`~refsim.solvers.laws.block_arrays`, ``scales`` (ρ, F_data, δ_free, ‖δ_free‖, the data residual's
    scale), ``multipliers`` the start, ``start`` the solve's perf_counter start. Its stages are the methods of
    :class:`_LayeredMaps` (pre-sweeps, direction, line search); this loop keeps the regularisation level, the
    best point, the history and the stop reasons."""
    maps = _LayeredMaps(problem, blocks, scales, sparse_above)
    theta, gap = maps.merit(multipliers)
    residual, data = maps.residuals(multipliers, gap)
    multipliers, theta, gap, residual, data, swept = maps.presweeps(
        multipliers, theta, gap, residual, data, tolerance, presweeps
    )
    best = (max(residual, data), multipliers.copy(), residual, data)
    memory = [theta]
    history = [residual]
    failures = consecutive = fallback = singular_steps = since_progress = 0
    level = 0  # regularisation level: 0 plain Newton, k > 0: η = min(η_max, ‖F‖/F_data) 10^(k−1)
    iterations = 0
    message = ""
    converged = residual <= tolerance and data <= tolerance
    while not converged:
        if iterations >= max_iterations:
            message = f"iteration cap {max_iterations} reached"
            break
        if time.perf_counter() - start > time_limit:
            message = f"time limit {time_limit:.1f} s reached"
            break
        iterations += 1
        direction, singular = maps.direction(multipliers, gap, theta, level, eta_max, minimum_norm)
        singular_steps += singular
        if direction is None:
            failures += 1
            consecutive += 1
            level = min(level + 1, 8)
            if consecutive > 8:
                message = "the regularised Jacobian could not be factorised"
                break
            continue
        reference = max(memory[-int(line_search_memory) :])
        accepted, candidate, candidate_theta, candidate_gap = maps.line_search(
            multipliers, direction, theta, reference
        )
        if not accepted:
            # fallback: projected Gauss-Seidel sweeps from the current point, more regularisation next time
            failures += 1
            consecutive += 1
            fallback += 10
            level = min(level + 1, 8)
            candidate = maps.sweeps(multipliers, 10)
            candidate_theta, candidate_gap = maps.merit(candidate)
            if consecutive > 8:
                message = f"line search failed {consecutive} times in a row"
                multipliers, theta, gap = candidate, candidate_theta, candidate_gap
                residual, data = maps.residuals(multipliers, gap)
                if max(residual, data) < best[0]:
                    best = (max(residual, data), multipliers.copy(), residual, data)
                break
        else:
            consecutive = 0
            level = max(level - 1, 0)
        multipliers, theta, gap = candidate, candidate_theta, candidate_gap
        memory.append(theta)
        residual, data = maps.residuals(multipliers, gap)
        history.append(residual)
        if max(residual, data) < 0.5 * best[0]:
            since_progress = 0
        else:
            since_progress += 1
        if max(residual, data) < best[0]:
            best = (max(residual, data), multipliers.copy(), residual, data)
        converged = residual <= tolerance and data <= tolerance
        if not converged and since_progress >= stall_iterations:
            message = f"stalled: the best residual did not halve in {stall_iterations} iterations"
            break
    _, multipliers, residual, data = best
    converged = residual <= tolerance and data <= tolerance
    if converged:
        message = converged_message(iterations, swept)
    elif swept:
        message = f"{swept} Gauss-Seidel pre-sweep(s), then " + message
    return NewtonResult(
        multipliers=multipliers,
        converged=bool(converged),
        iterations=iterations,
        residual=float(residual),
        data_residual=float(data),
        message=message,
        storage=maps.operator.storage,
        history=np.array(history),
        line_search_failures=failures,
        fallback_sweeps=fallback,
        presweeps=swept,
    )
