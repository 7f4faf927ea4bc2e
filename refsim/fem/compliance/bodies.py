"""The compliance strategies (exact, refreshed, precomputed, fast), each a factory and the body it binds to:
how A⁻¹ is applied for a step's free motion, W and correction (:mod:`refsim.fem.compliance`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from refsim.fem.compliance.system import (
    FreeMotionStart,
    PartialSolveMarks,
    StaleFactor,
    StepCompliance,
    StepSystem,
    _rotate_nodes,
    pcg,
)
from refsim.fem.linear import make_linear_solver
from refsim.fem.threads import hot_path_threads

#: How the refreshed strategy updates W between factorisations (:class:`Refreshed`'s ``compliance_update``, a
#: scene's ``compliance.w_update``); the first is the default.
W_UPDATES = ("pcg", "first_order", "stale")


class BodyCompliance:
    """A strategy bound to one body for a run: holds the factor(s) that live across steps.

    What a step changes is returned by :meth:`carried` and taken back by :meth:`resume`, so that the run's
    state holds it; what a body keeps besides is a memo of its model (and ``steps``, a count no result
    reads).

    ``matrix_storage`` is what its steps read of ``StepSystem.matrix``: "full", or "upper" when the upper
    triangle is enough (the exact strategy on PARDISO), so that the body may assemble only that."""

    matrix_storage = "full"

    def __init__(self, strategy) -> None:
        self.strategy = strategy
        self.steps = 0
        self._exact = (
            _ExactBody(strategy.linear_solver, partial=False)
            if getattr(strategy, "against_exact", False)
            else None
        )

    def carried(self) -> StaleFactor | None:
        """What the next step depends on besides the model: None (the exact and precomputed strategies)."""
        return None

    def linear_counts(self) -> tuple[int, int | None] | None:
        """(numeric factorisations, analyses) its linear solver made for this body's steps in this process
        (not an error-report twin's); analyses None where each factorisation orders anew (SuperLU); None
        without a solver that counts."""
        solver = getattr(self, "_solver", None)
        factorisations = getattr(solver, "factorisations", None)
        if factorisations is None:
            return None
        return int(factorisations), getattr(solver, "analyses", None)

    def resume(self, carried: StaleFactor | None) -> None:
        """Continue from ``carried`` (:meth:`carried` of some earlier step, or None: a run's start)."""

    def prepare(self, system: StepSystem) -> None:
        """Set up, before the first step, what the strategy keeps for the whole run from the body's rest
        state (``system``: a system of the body, e.g. ``TissueModel.rest_system``): the fast and precomputed
        strategies factorise the rest matrix here, so that no step pays it (the first step would, else).
        Nothing for the strategies that factorise the step's own matrix; nothing when already prepared."""

    def step(self, system: StepSystem) -> StepCompliance:
        """The compliance of this step's system (advances the strategy's step counter)."""
        with hot_path_threads():
            return self._counted_step(system)

    def _counted_step(self, system: StepSystem) -> StepCompliance:
        if system.upper_triangle and self.matrix_storage != "upper":
            raise ValueError(
                "this strategy reads A in full storage; the system holds its upper triangle only"
            )
        exact = self._exact.step(system) if self._exact is not None else None
        result = self._step(system, exact)
        self.steps += 1
        return result

    def _step(self, system: StepSystem, exact) -> StepCompliance:  # pragma: no cover - abstract
        raise NotImplementedError


class _ExactBody(BodyCompliance):
    def __init__(self, linear_solver: str, *, partial: bool = True) -> None:
        self.strategy = None
        self.steps = 0
        self._exact = None
        self._solver = make_linear_solver(linear_solver)
        # W by partial solves where the solver has them (PARDISO); an error-report twin (partial=False) keeps
        # the plain analysis, so that its bits depend on no history
        self._partial = partial and hasattr(self._solver, "inverse_block")
        self.matrix_storage = getattr(self._solver, "storage", "full")

    def carried(self) -> PartialSolveMarks | None:
        """The positions the factor's analysis marked for partial solves; None when none are (or no partial
        solves)."""
        if not self._partial or self._solver.marked is None:
            return None
        marks = self._solver.marked.copy()
        marks.setflags(write=False)
        return PartialSolveMarks(marks)

    def resume(self, carried: PartialSolveMarks | None) -> None:
        """Continue with the marks of ``carried`` (None: a plain analysis); the analysis runs again only when
        they differ from the solver's."""
        if not self._partial:
            return
        self._solver.mark(carried.positions if isinstance(carried, PartialSolveMarks) else None)

    def _inverse_block(self, system: StepSystem, positions: np.ndarray) -> np.ndarray:
        """(A⁻¹)_uu on ``positions``; when they are not the marked ones, the analysis marks exactly them and
        the matrix is factorised again. Exactly those: the partial solve's work and the ordering's fill grow
        with the marked set (docs/speed.md)."""
        solver = self._solver
        marked = solver.marked
        if marked is None or not np.array_equal(positions, marked):
            solver.mark(positions)
        return solver.inverse_block(positions)

    def _step(self, system: StepSystem, exact) -> StepCompliance:
        solver = self._solver
        before = getattr(solver, "factorisations", None)
        solver.factorise(system.matrix)  # kept when it is the last matrix, bit for bit (a tissue at rest)
        refactorised = before is None or solver.factorisations != before
        free = solver.solve(system.rhs)
        size = system.free_dofs.size

        def columns(positions):
            unit = np.zeros((size, positions.size))
            unit[positions, np.arange(positions.size)] = 1.0
            return solver.solve(unit)

        return StepCompliance(
            system,
            free,
            columns,
            {"refactorised": refactorised},
            exact,
            solver.solve,
            half_solve=getattr(solver, "half_solve", None),
            inverse_block=(
                (lambda positions: self._inverse_block(system, positions)) if self._partial else None
            ),
            marked_solve=solver.solve_marked if self._partial else None,
        )


def _check_common(linear_solver: str, against_exact: bool) -> None:
    if not isinstance(linear_solver, str):
        raise ValueError(f"linear_solver must be a string, got {linear_solver!r}")
    if not isinstance(against_exact, bool):
        raise ValueError(f"against_exact must be true or false, got {against_exact!r}")


def _check_iterative(tolerance: float, max_iterations: int) -> None:
    """The PCG settings of the iterating strategies: a relative tolerance in (0, 1), an iteration cap ≥ 1."""
    if not (0.0 < tolerance < 1.0):
        raise ValueError(f"tolerance = {tolerance!r}: expected a number in (0, 1)")
    if not isinstance(max_iterations, int) or max_iterations < 1:
        raise ValueError(f"max_iterations = {max_iterations!r}: expected an integer >= 1")


@dataclass(frozen=True)
class Exact:
    """Refactorise every step (the reference); a matrix equal to the last one, bit for bit (a tissue at rest),
    keeps its factor.

    Parameters
    ----------
    linear_solver : "auto" (default: :func:`refsim.fem.linear.default_linear_solver`), "pardiso", "cholmod" or
        "superlu".
    """

    linear_solver: str = "auto"
    name: str = field(default="exact", init=False)

    @classmethod
    def configured(
        cls,
        *,
        refresh_every: int,
        linear_solver: str,
        against_exact: bool,
        tolerance: float | None,
        w_update: str,
    ) -> Exact:
        """From a scene's ``compliance`` section (make_strategy): the keys this strategy reads."""
        return cls(linear_solver=linear_solver)

    def __post_init__(self) -> None:
        _check_common(self.linear_solver, False)

    def bind(self) -> BodyCompliance:
        """A fresh per-body, per-run compliance."""
        body = _ExactBody(self.linear_solver)
        body.strategy = self
        return body


class _RefreshedBody(BodyCompliance):
    def __init__(self, strategy: Refreshed) -> None:
        super().__init__(strategy)
        self._solver = make_linear_solver(strategy.linear_solver)
        self._age = None
        self._factored = None  # the matrix of the stale factor

    def carried(self) -> StaleFactor | None:
        """The stale factor's matrix and age; None before the first step."""
        return None if self._age is None else StaleFactor(self._factored, self._age)

    def resume(self, carried: StaleFactor | None) -> None:
        """Continue from a carried factor: its matrix factorised again (unless it is the one held) and its
        age; None refactorises at the next step."""
        if carried is None:
            self._age = self._factored = None
            return
        if carried.matrix is not self._factored:
            self._solver.factorise(carried.matrix)
            self._factored = carried.matrix
        self._age = carried.age

    def _step(self, system: StepSystem, exact) -> StepCompliance:
        strategy = self.strategy
        refactorised = self._age is None or self._age >= strategy.refresh_every
        if refactorised:
            self._solver.factorise(system.matrix)
            self._factored = system.matrix.copy()
            self._age = 0
        self._age += 1
        solver, matrix = self._solver, system.matrix
        if refactorised:
            free, iterations, residual = solver.solve(system.rhs), 0, 0.0
        else:
            free, iterations, residual = pcg(
                matrix.dot,
                solver.solve,
                system.rhs,
                tolerance=strategy.tolerance,
                max_iterations=strategy.max_iterations,
            )
        report = {"refactorised": refactorised, "pcg_iterations": iterations, "pcg_residual": residual}
        size = system.free_dofs.size

        def columns(positions):
            unit = np.zeros((size, positions.size))
            unit[positions, np.arange(positions.size)] = 1.0
            if refactorised or strategy.compliance_update in ("stale", "first_order"):
                return solver.solve(unit)
            solution, column_iterations, column_residual = pcg(
                matrix.dot,
                solver.solve,
                unit,
                tolerance=strategy.tolerance,
                max_iterations=strategy.max_iterations,
            )
            report["column_pcg_iterations"] = column_iterations
            report["column_pcg_residual"] = column_residual
            return solution

        block = apply = None
        if strategy.compliance_update == "first_order" and not refactorised:
            change = _difference(matrix, self._factored)

            def block(positions, influence):
                # A⁻¹ = A₀⁻¹ − A₀⁻¹ ΔA A₀⁻¹ + O(‖A₀⁻¹ΔA‖²): E_uᵀA⁻¹E_u ≈ Z₀[u] − Z₀ᵀ ΔA Z₀, Z₀ = A₀⁻¹ E_u.
                first = influence[positions] - influence.T @ (change @ influence)
                return 0.5 * (first + first.T)

            def apply(load, start):
                solution, load_iterations, _ = pcg(
                    matrix.dot,
                    solver.solve,
                    load,
                    tolerance=strategy.tolerance,
                    max_iterations=strategy.max_iterations,
                    start=start,
                )
                report["correction_pcg_iterations"] = load_iterations
                return solution

        return StepCompliance(system, free, columns, report, exact, block=block, apply=apply)


def _difference(matrix: sp.csr_matrix, reference: sp.csr_matrix) -> sp.csr_matrix:
    """matrix − reference, on their common pattern when they share it (the usual case: one pattern per
    run)."""
    if (
        matrix.shape == reference.shape
        and matrix.nnz == reference.nnz
        and np.array_equal(matrix.indptr, reference.indptr)
        and np.array_equal(matrix.indices, reference.indices)
    ):
        return sp.csr_matrix(
            (matrix.data - reference.data, matrix.indices, matrix.indptr), shape=matrix.shape
        )
    return (matrix - reference).tocsr()


@dataclass(frozen=True)
class Refreshed:
    """Factorise every ``refresh_every`` steps; free motion (and by default W's columns) by PCG on the current
    A.

    Parameters
    ----------
    refresh_every : Steps between factorisations, ≥ 1 (1 is the exact strategy with extra CG checks).
    tolerance : Relative residual of the PCG solves, in (0, 1).
    max_iterations : PCG iteration cap per solve, ≥ 1.
    compliance_update : "pcg" (W's columns solved on the current A to ``tolerance``), "stale" (the stale
        factor's W and correction) or "first_order" (W corrected to first order, W ≈ H(Z₀ − Z₀ᵀ(A − A₀)Z₀)Hᵀ
        with Z₀ = A₀⁻¹E_u from the stale factor, error O(‖A₀⁻¹(A − A₀)‖²) relative; the correction by PCG to
        ``tolerance``).
    linear_solver : As for :class:`Exact`.
    against_exact : Also compute the exact answer each step and report the errors (for benchmarks).
    """

    refresh_every: int = 10
    tolerance: float = 1e-10
    max_iterations: int = 200
    compliance_update: str = "pcg"
    linear_solver: str = "auto"
    against_exact: bool = False
    name: str = field(default="refreshed", init=False)

    @classmethod
    def configured(
        cls,
        *,
        refresh_every: int,
        linear_solver: str,
        against_exact: bool,
        tolerance: float | None,
        w_update: str,
    ) -> Refreshed:
        """From a scene's ``compliance`` section (make_strategy): the keys this strategy reads."""
        return cls(
            refresh_every=refresh_every,
            tolerance=cls.tolerance if tolerance is None else tolerance,
            linear_solver=linear_solver,
            against_exact=against_exact,
            compliance_update=w_update,
        )

    def __post_init__(self) -> None:
        _check_common(self.linear_solver, self.against_exact)
        if (
            not isinstance(self.refresh_every, int)
            or isinstance(self.refresh_every, bool)
            or self.refresh_every < 1
        ):
            raise ValueError(f"refresh_every = {self.refresh_every!r}: expected an integer >= 1")
        _check_iterative(self.tolerance, self.max_iterations)
        if self.compliance_update not in W_UPDATES:
            raise ValueError(
                f"compliance_update = {self.compliance_update!r}: expected one of {', '.join(W_UPDATES)}"
            )

    def bind(self) -> BodyCompliance:
        """A fresh per-body, per-run compliance."""
        return _RefreshedBody(self)


class _PrecomputedBody(BodyCompliance):
    def __init__(self, strategy: Precomputed) -> None:
        super().__init__(strategy)
        self._solver = make_linear_solver(strategy.linear_solver)
        self._dense = None
        self._ready = False

    def prepare(self, system: StepSystem) -> None:
        if not self._ready:
            self._prepare(system)

    def _prepare(self, system: StepSystem) -> None:
        if system.rest_matrix is None or system.group_rotations is None:
            raise ValueError(
                "the precomputed strategy needs a body with a rest matrix and per-node rotations"
            )
        if (
            system.dof_count % 3
            or np.any(np.diff(system.free_dofs.reshape(-1, 3), axis=1) != 1)
            or np.any(system.free_dofs.reshape(-1, 3)[:, 0] % 3)
        ):
            raise ValueError("the precomputed strategy needs whole 3-DoF groups free or constrained")
        self._solver.factorise(system.rest_matrix())
        size = system.free_dofs.size
        if size <= self.strategy.dense_limit:
            self._dense = self._solver.solve(np.eye(size))
        self._groups = system.free_dofs.reshape(-1, 3)[:, 0] // 3
        self._ready = True

    def _rest_columns(self, loads: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """C₀ applied to loads supported on the free positions ``positions``, shape (f, k)."""
        if self._dense is not None:
            return self._dense[:, positions] @ loads[positions]
        return self._solver.solve(loads)

    def _step(self, system: StepSystem, exact) -> StepCompliance:
        if not self._ready:
            self._prepare(system)
        strategy = self.strategy
        free, iterations, residual = pcg(
            system.matrix.dot,
            self._solver.solve,
            system.rhs,
            tolerance=strategy.tolerance,
            max_iterations=strategy.max_iterations,
        )
        report = {"refactorised": False, "pcg_iterations": iterations, "pcg_residual": residual}
        rotations = system.group_rotations()[self._groups]  # (f/3, 3, 3), one per free node
        size = system.free_dofs.size

        def columns(positions):
            # Rᵀ e_j: only the 3-DoF groups of the used DoFs carry a load.
            groups = np.unique(positions // 3)
            support = (3 * groups[:, None] + np.arange(3)).ravel()
            unit = np.zeros((size, positions.size))
            unit[positions, np.arange(positions.size)] = 1.0
            loads = np.zeros_like(unit)
            loads[support] = _rotate_nodes(rotations[groups], unit[support], transpose=True)
            return _rotate_nodes(rotations, self._rest_columns(loads, support))

        return StepCompliance(system, free, columns, report, exact)


@dataclass(frozen=True)
class Precomputed:
    """The rest compliance rotated per node (SOFA's precomputed constraint correction); free motion by PCG.

    Parameters
    ----------
    tolerance, max_iterations : Of the free motion's PCG (preconditioned by the rest factor).
    dense_limit : Largest free DoF count for which C₀ is stored dense (f² · 8 bytes).
    linear_solver, against_exact : As for :class:`Refreshed`.
    """

    tolerance: float = 1e-10
    max_iterations: int = 500
    dense_limit: int = 4000
    linear_solver: str = "auto"
    against_exact: bool = False
    name: str = field(default="precomputed", init=False)

    @classmethod
    def configured(
        cls,
        *,
        refresh_every: int,
        linear_solver: str,
        against_exact: bool,
        tolerance: float | None,
        w_update: str,
    ) -> Precomputed:
        """From a scene's ``compliance`` section (make_strategy): the keys this strategy reads."""
        return cls(
            tolerance=cls.tolerance if tolerance is None else tolerance,
            linear_solver=linear_solver,
            against_exact=against_exact,
        )

    def __post_init__(self) -> None:
        _check_common(self.linear_solver, self.against_exact)
        _check_iterative(self.tolerance, self.max_iterations)

    def bind(self) -> BodyCompliance:
        """A fresh per-body, per-run compliance."""
        return _PrecomputedBody(self)


class _FastBody(BodyCompliance):
    def __init__(self, strategy: Fast) -> None:
        super().__init__(strategy)
        self._solver = make_linear_solver(strategy.linear_solver, precision=strategy.rest_precision)
        # without the error report, the tissue builds its step system with an operator and no matrix
        self.matrix_free = not strategy.against_exact
        self._ready = False
        self._carried = None  # FreeMotionStart: the last free motion, where the next CG starts from

    @property
    def rest_precision(self) -> str:
        """The rest factor's precision, "single" or "double": the strategy's where the solver has a choice
        (PARDISO), else double."""
        return getattr(self._solver, "precision", "double")

    def carried(self) -> FreeMotionStart | None:
        """The last free displacement and its image under the last operator (the next free motion's start);
        None before the first step."""
        return self._carried

    def resume(self, carried: FreeMotionStart | None) -> None:
        """Continue from ``carried`` (None: the next free motion starts from R C₀ Rᵀ b, as a run's first)."""
        self._carried = carried

    def prepare(self, system: StepSystem) -> None:
        if not self._ready:
            self._prepare(system)

    def _prepare(self, system: StepSystem) -> None:
        if system.rest_matrix is None or system.group_rotations is None:
            raise ValueError("the fast strategy needs a body with a rest matrix and per-node rotations")
        if (
            system.dof_count % 3
            or np.any(np.diff(system.free_dofs.reshape(-1, 3), axis=1) != 1)
            or np.any(system.free_dofs.reshape(-1, 3)[:, 0] % 3)
        ):
            raise ValueError("the fast strategy needs whole 3-DoF groups free or constrained")
        self._solver.factorise(system.rest_matrix())
        self._groups = system.free_dofs.reshape(-1, 3)[:, 0] // 3
        self._size = system.free_dofs.size
        # C₀ = A₀⁻¹ column blocks, one per free node, solved the first time a row touches the node and stored
        # transposed (refsim.fem.compliance.kernels): ``_slot[g]`` is its block in ``_rows`` (-1: not yet)
        self._slot = np.full(self._groups.size, -1, dtype=np.int64)
        self._rows = np.zeros((0, self._size))
        self._filled = 0
        self._ready = True

    def _rest_blocks(self, groups: np.ndarray) -> None:
        """Solve the C₀ blocks of the free node groups ``groups`` not held yet.

        Each node's block is one (f, 3) solve of the rest factor, done once per run whatever else is asked
        with it, so the memo's bits depend on no history (a restarted run computes the same blocks)."""
        missing = groups[self._slot[groups] < 0]
        if not missing.size:
            return
        needed = 3 * (self._filled + missing.size)
        if needed > self._rows.shape[0]:
            grown = np.zeros((max(needed, 2 * self._rows.shape[0]), self._size))
            grown[: 3 * self._filled] = self._rows[: 3 * self._filled]
            self._rows = grown
        unit = np.zeros((self._size, 3))
        for group in missing:  # each node once per run (the memo's bits: one solve per node)
            unit[3 * group : 3 * group + 3] = np.eye(3)
            self._rows[3 * self._filled : 3 * self._filled + 3] = self._solver.solve(unit).T
            unit[3 * group : 3 * group + 3] = 0.0
            self._slot[group] = self._filled
            self._filled += 1

    def _step(self, system: StepSystem, exact) -> StepCompliance:
        from refsim.fem.compliance.kernels import rotated_apply, rotated_block, turn_nodes

        if not self._ready:
            self._prepare(system)
        strategy = self.strategy
        # (f/3, 3, 3), one per free node
        rotations = np.ascontiguousarray(system.group_rotations()[self._groups])
        solver, size = self._solver, self._size
        turned = np.empty(size)

        def warped(load: np.ndarray) -> np.ndarray:
            # R C₀ Rᵀ load: the rest compliance in each node's rotated frame
            turn_nodes(rotations, load, True, turned)
            out = np.empty(size)
            turn_nodes(rotations, solver.solve(turned), False, out)
            return out

        # The start (FreeMotionStart): the last step's free displacement x' plus R C₀ Rᵀ on what it leaves of
        # this step's load under the last step's operator, b − A' x'; R C₀ Rᵀ b on a run's first step.
        carried = self._carried
        rhs = system.rhs
        start = warped(rhs) if carried is None else carried.displacement + warped(rhs - carried.load)
        free, iterations, residual, start_residual, left = _pcg(
            system.product,
            warped,
            rhs,
            start,
            tolerance=strategy.tolerance,
            max_iterations=strategy.max_iterations,
        )
        # A x as the CG knows it, b − r: its recursive residual r is b − A x to round-off
        displacement, load = free.copy(), rhs - left
        displacement.setflags(write=False)
        load.setflags(write=False)
        self._carried = FreeMotionStart(displacement, load)
        report = {
            "refactorised": False,
            "pcg_iterations": iterations,
            "pcg_residual": residual,
            "pcg_carried_start": carried is not None,
            "pcg_start_residual": start_residual,
        }
        before = self._filled

        def inverse_block(positions):
            # (R C₀ Rᵀ)_uu from the C₀ blocks of the nodes the rows touch (positions sorted, and so their
            # nodes: np.unique's answer is each run's first)
            nodes = positions // 3
            groups = nodes[np.flatnonzero(np.diff(nodes, prepend=-1))]
            self._rest_blocks(groups)
            block = np.empty((3 * groups.size, 3 * groups.size))
            rotated_block(self._rows, self._slot, groups, rotations, block)
            report["rest_blocks_solved"] = self._filled - before
            if positions.size == block.shape[0]:  # whole nodes: the support itself
                return block
            support = (3 * groups[:, None] + np.arange(3)).ravel()
            where = np.searchsorted(support, positions)
            return block[np.ix_(where, where)]

        def apply(load):
            # R C₀ Rᵀ load for a load on few nodes (the correction's Hᵀλ), from the same C₀ blocks
            load = np.asarray(load, dtype=float)
            if load.ndim == 2:
                return np.column_stack([apply(column) for column in load.T]).reshape(load.shape)
            groups = np.flatnonzero(np.any(load.reshape(-1, 3) != 0.0, axis=1))
            out = np.zeros(size)
            if groups.size:
                self._rest_blocks(groups)
                load = np.ascontiguousarray(load)
                rotated_apply(self._rows, self._slot, groups, rotations, load, turned, out)
            return out

        return StepCompliance(system, free, None, report, exact, apply, inverse_block=inverse_block)


def _pcg(
    product,
    preconditioner,
    rhs: np.ndarray,
    start: np.ndarray,
    *,
    tolerance: float,
    max_iterations: int,
) -> tuple[np.ndarray, int, float, float, np.ndarray]:
    """Preconditioned CG on one right-hand side b (f,) to ‖b − A x‖₂ ≤ tolerance ‖b‖₂, from ``start``.

    A start whose residual exceeds ‖b‖ (a step that changed the load) is replaced by 0, whose first iteration
    is P⁻¹ b scaled to its A-norm optimum. Returns x, iterations, the relative residual reached, the start's
    relative residual, and the last residual vector r (b − A x to round-off)."""
    norm_b = float(np.sqrt(rhs @ rhs))
    norm_b = norm_b if norm_b > 0.0 else 1.0
    x = np.array(start, dtype=float)
    r = rhs - product(x)
    if float(np.sqrt(r @ r)) > norm_b:
        x = np.zeros_like(rhs)
        r = np.array(rhs, dtype=float)
    relative = start_relative = float(np.sqrt(r @ r)) / norm_b
    iterations = 0
    if relative > tolerance and max_iterations > 0:
        z = preconditioner(r)
        p = z.copy()
        rz = float(r @ z)
        while iterations < max_iterations:
            ap = product(p)
            pap = float(p @ ap)
            if not pap > 0.0:
                break
            alpha = rz / pap
            x += alpha * p
            r -= alpha * ap
            iterations += 1
            relative = float(np.sqrt(r @ r)) / norm_b
            if relative <= tolerance:
                break
            z = preconditioner(r)
            rz_new = float(r @ z)
            p *= rz_new / rz if rz > 0.0 else 0.0
            p += z
            rz = rz_new
    return x, iterations, relative, start_relative, r


@dataclass(frozen=True)
class Fast:
    """No matrix assembled or factorised during the run: the rest compliance rotated per node for W and the
    correction, free motion by CG on the current A applied per tet, preconditioned by the same rotated rest
    compliance and started from the last step's free displacement x' plus R C₀ Rᵀ (b − A' x') (carried,
    :class:`refsim.fem.compliance.FreeMotionStart`; R C₀ Rᵀ b on a run's first step).

    Parameters
    ----------
    tolerance, max_iterations : Of the free motion's PCG (relative residual ‖b − A x‖/‖b‖; iteration cap); a
        scene's ``compliance.tolerance`` sets the first. The free motion's relative error is then at most
        κ(A) · tolerance (a worst case), and what it leaves is not lost: the residual force is in the next
        step's right-hand side, so a state at rest is the exact one. 1e-2: where the start alone meets it
        (most steps), a step costs one rest-factor solve and one product; the needle force against the exact
        run is within W's error on the built-in scenes (docs/speed.md, "What it costs in accuracy").
    linear_solver : The rest factor's solver, as for :class:`Exact`.
    rest_precision : The rest factor's precision where the solver has a choice (PARDISO), "single" or
        "double". Single: each solve reads half the bytes, from memory at every step (the rest of a step
        leaves the factor out of the caches); its round-off, about κ(A₀) · 6e-8 relative, is far below what
        R C₀ Rᵀ leaves of A⁻¹, the free motion's CG residual is measured in double precision, and W and the
        correction come from the same C₀ blocks (docs/speed.md gives the errors against the exact mode).
    against_exact : As for :class:`Refreshed` (the step system is then assembled, for the exact twin).
    """

    tolerance: float = 1e-2
    max_iterations: int = 200
    linear_solver: str = "auto"
    rest_precision: str = "single"
    against_exact: bool = False
    name: str = field(default="fast", init=False)

    @classmethod
    def configured(
        cls,
        *,
        refresh_every: int,
        linear_solver: str,
        against_exact: bool,
        tolerance: float | None,
        w_update: str,
    ) -> Fast:
        """From a scene's ``compliance`` section (make_strategy): the keys this strategy reads."""
        return cls(
            tolerance=cls.tolerance if tolerance is None else tolerance,
            linear_solver=linear_solver,
            against_exact=against_exact,
        )

    def __post_init__(self) -> None:
        _check_common(self.linear_solver, self.against_exact)
        _check_iterative(self.tolerance, self.max_iterations)
        if self.rest_precision not in ("single", "double"):
            raise ValueError(f"rest_precision = {self.rest_precision!r}: expected 'single' or 'double'")

    def bind(self) -> BodyCompliance:
        """A fresh per-body, per-run compliance."""
        return _FastBody(self)


#: The compliance strategies by name (a scene's ``compliance.strategy``): a new strategy is its class here.
STRATEGY_CLASSES = {strategy.name: strategy for strategy in (Exact, Refreshed, Precomputed, Fast)}
#: Their names.
STRATEGIES = tuple(STRATEGY_CLASSES)
#: Every strategy with each of its W updates, by the names benchmarks use: "refreshed" with the default
#: update, "refreshed_<update>" with another.
STRATEGY_VARIANTS = tuple(
    variant
    for name in STRATEGIES
    for variant in (
        (name, *(f"{name}_{update}" for update in W_UPDATES[1:])) if name == Refreshed.name else (name,)
    )
)
