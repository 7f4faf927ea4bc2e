"""Compliance strategies as values: how a body's step system gives its free motion, W and its correction
(layer 2).

Every deformable body (the tissue, a flexible needle) assembles, at each step, its effective stiffness
A = M/dt² + C/dt + K on its free DoFs (always the same sparsity pattern) and the right-hand side of the free
motion (see :mod:`refsim.fem.integration`): a :class:`StepSystem`. A **strategy** is a plain value (like the
solver factories scikit-fem passes to ``solve``), chosen for the tissue by the scene key
``compliance.strategy``; a flexible needle binds its own (exact, :mod:`refsim.simulation.needle_body`):

``Exact()``
    Factorises A every step (refsim's reference): free motion, W = H A⁻¹ Hᵀ and the correction A⁻¹ Hᵀ λ are
    those of a fresh factorisation, to round-off.
``Refreshed(refresh_every=10, tolerance=1e-10)``
    Factorises A every ``refresh_every`` steps only. The free motion solves the *current* A by conjugate
    gradients preconditioned by the stale factor, to a relative residual ``tolerance``. W and the correction:
    with ``compliance_update="pcg"`` (default) the columns A⁻¹ e_j of the DoFs the rows touch are also solved
    by preconditioned CG on the current A to ``tolerance``, so W is *corrected* (its error is that of the CG
    solves, ‖ΔW‖ ≤ ‖H‖² ‖A⁻¹‖ · tolerance · ‖e_j‖ per column); with ``"stale"`` W comes from the stale factor
    alone and its error is only measured (``against_exact``).
``Precomputed()``
    SOFA's precomputed constraint correction: the rest compliance C₀ = A₀⁻¹ (A at the rest shape) is computed
    once (dense when the body has at most ``dense_limit`` free DoFs, otherwise kept as the rest factor) and
    rotated per node, W = H R C₀ Rᵀ Hᵀ with R block-diagonal (one rotation per 3-DoF group). The free motion
    is CG on the current A preconditioned by the rest factor. For comparison and large interactive runs: its W
    is not the current one (on cube_cut it moves forces markedly).
``Fast()``
    The same W and correction as ``Precomputed`` without assembling or factorising any matrix during the run
    (the rest factor once): the body builds its step system with an operator v ↦ A v applied per tet
    (:mod:`refsim.fem.corotated_matvec`) instead of A, the free motion is CG on that operator preconditioned
    by the rotated rest compliance R C₀ Rᵀ (whose answer alone usually meets the tolerance), and C₀'s columns
    are solved per node the first time a row touches the node, then kept (a memo of the model: one (f, 3)
    solve per node, so its bits depend on no history). Its error against exact is W's: exact for rigid
    motions of the rest shape, bounded by ‖H‖² ‖A⁻¹‖ ‖Ã⁻¹‖ ‖A − Ã‖ (Ã = R A₀ Rᵀ) when the tissue deforms.

Binding a strategy to a body (:meth:`bind`) gives a :class:`BodyCompliance` that keeps what lives across steps
(the analysis, the stale or rest factor). What changes with the run is state: the refreshed strategy's stale
factor is a :class:`StaleFactor` (the matrix it factorised and its age in steps) that the run's state carries
(:meth:`BodyCompliance.carried`, :meth:`BodyCompliance.resume`: a body resumed from a carried factor
factorises its matrix again, which gives the same factor, so a restarted run has the uninterrupted run's
bits). The rest is a memo of the body's model (the rest factor, the symbolic analysis) or of one step (W's
columns for rows H, kept by value); its :meth:`BodyCompliance.step` takes a step system and returns a
:class:`StepCompliance` with ``free_displacement``, :meth:`~StepCompliance.delassus` (W for rows H given as a
scipy CSR matrix of shape (rows, dof_count)) and :meth:`~StepCompliance.correction` (A⁻¹ Hᵀ λ). Every fast
strategy can also compute the exact answer in the same step (``against_exact=True``) and report its errors in
:attr:`StepCompliance.report`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from refsim.fem.linear import make_linear_solver
from refsim.fem.threads import hot_path_threads

__all__ = [
    "STRATEGIES",
    "STRATEGY_VARIANTS",
    "W_UPDATES",
    "StaleFactor",
    "PartialSolveMarks",
    "StepSystem",
    "StepCompliance",
    "BodyCompliance",
    "Exact",
    "Refreshed",
    "Precomputed",
    "Fast",
    "make_strategy",
    "pcg",
    "strategy_variant",
]

#: The compliance strategies (a scene's ``compliance.strategy``).
STRATEGIES = ("exact", "refreshed", "precomputed", "fast")
#: How the refreshed strategy updates W between factorisations (:class:`Refreshed`'s ``compliance_update``, a
#: scene's ``compliance.w_update``); the first is the default.
W_UPDATES = ("pcg", "first_order", "stale")
#: Every strategy with each of its W updates, by the names benchmarks use: "refreshed" with the default
#: update, "refreshed_<update>" with another.
STRATEGY_VARIANTS = tuple(
    variant
    for name in STRATEGIES
    for variant in (
        (name, *(f"{name}_{update}" for update in W_UPDATES[1:])) if name == "refreshed" else (name,)
    )
)


def _times_diagonal(matrix: sp.spmatrix, vectors: np.ndarray) -> np.ndarray:
    """diag(matrix) applied to ``vectors`` (shape (f,) or (f, k))."""
    diagonal = matrix.diagonal()
    return diagonal * vectors if vectors.ndim == 1 else diagonal[:, None] * vectors


def _rotate_nodes(rotations: np.ndarray, values: np.ndarray, *, transpose: bool = False) -> np.ndarray:
    """R v (Rᵀ v when ``transpose``) for values on whole 3-DoF groups, R block-diagonal with one rotation per
    group: rotations (g, 3, 3), values (3g,) or (3g, k), the result of the same shape. The per-node rotation
    of the precomputed and fast strategies (their R C₀ Rᵀ)."""
    grouped = values.reshape(rotations.shape[0], 3, -1)
    turned = np.einsum("gji,gjk->gik" if transpose else "gij,gjk->gik", rotations, grouped)
    return turned.reshape(values.shape)


def _rotate_node_block(rotations: np.ndarray, block: np.ndarray) -> np.ndarray:
    """R_s B R_sᵀ for a square block B on whole 3-DoF groups (rotations (g, 3, 3), B (3g, 3g)): its rows' node
    blocks rotated, then its columns'."""
    left = _rotate_nodes(rotations, block)
    return _rotate_nodes(rotations, left.T).T


@dataclass(eq=False)
class StepSystem:
    """What a body assembles at one step for the compliance strategies.

    Attributes
    ----------
    dof_count : Number of DoFs of the body.
    free_dofs : Unconstrained DoFs, sorted, shape (f,).
    constrained_dofs : Fixed or prescribed DoFs, sorted, shape (c,).
    matrix : A on the free DoFs [N/m], sparse CSR (f, f), symmetric positive definite, full storage (or its
        upper triangle when ``upper_triangle``), the same pattern at every step of a run.
    rhs : Right-hand side of the free motion on the free DoFs [N], f_ext − f_int(x₀) + (M/dt) v₀ − A_fc Δx_c,
        shape (f,).
    prescribed : Δx on the constrained DoFs over the step [m], shape (c,) (zero for fixed DoFs).
    group_rotations : Callable returning one rotation per 3-DoF group, shape (dof_count // 3, 3, 3) (the
        precomputed strategy's R); None if the body has none.
    rest_matrix : Callable returning A at the rest shape on the free DoFs (same pattern); None if the body has
    none.
    upper_triangle : ``matrix`` holds only A's upper triangle (diagonal included): what a body assembles for a
        strategy whose ``matrix_storage`` is "upper" (:class:`BodyCompliance`).
    operator : Callable v ↦ A v on the free DoFs (shape (f,) or (f, k)) when ``matrix`` is None (a system
        built without a matrix for the fast strategy, :mod:`refsim.fem.corotated_matvec`); None otherwise.
    """

    dof_count: int
    free_dofs: np.ndarray
    constrained_dofs: np.ndarray
    matrix: sp.csr_matrix | None
    rhs: np.ndarray
    prescribed: np.ndarray
    group_rotations: Callable[[], np.ndarray] | None = None
    rest_matrix: Callable[[], sp.csr_matrix] | None = None
    upper_triangle: bool = False
    operator: Callable[[np.ndarray], np.ndarray] | None = None

    def product(self, vectors: np.ndarray) -> np.ndarray:
        """A v on the free DoFs, through the matrix or else the operator."""
        if self.matrix is not None:
            if self.upper_triangle:  # A = U + Uᵀ - diag(U)
                upper = self.matrix
                return upper.dot(vectors) + upper.T.dot(vectors) - _times_diagonal(upper, vectors)
            return self.matrix.dot(vectors)
        return self.operator(vectors)

    @classmethod
    def from_matrices(
        cls,
        matrix: sp.spmatrix,
        rhs: np.ndarray,
        constrained_dofs: np.ndarray | None = None,
        prescribed: np.ndarray | None = None,
        **callables,
    ) -> StepSystem:
        """Eliminate the constrained DoFs of a full system A Δx = rhs (the generic path, e.g. the needle's).

        Parameters
        ----------
        matrix : A on every DoF, shape (n, n).
        rhs : f_ext − f_int + (M/dt) v₀ on every DoF, shape (n,).
        constrained_dofs : DoFs with a given Δx, shape (c,), any order (sorted here); none by default.
        prescribed : Δx on the constrained DoFs, in the order of *sorted* ``constrained_dofs``, shape (c,);
            zero by default.
        """
        matrix = sp.csr_matrix(matrix)
        n = matrix.shape[0]
        constrained = np.unique(
            np.asarray([] if constrained_dofs is None else constrained_dofs, dtype=np.int64)
        )
        if constrained.size and (constrained[0] < 0 or constrained[-1] >= n):
            raise ValueError(
                f"constrained_dofs must lie in [0, {n}), got {constrained.min()}..{constrained.max()}"
            )
        free = np.setdiff1d(np.arange(n), constrained)
        if free.size == 0:
            raise ValueError("every DoF is constrained: nothing to solve")
        rhs = np.asarray(rhs, dtype=float)
        if rhs.shape != (n,):
            raise ValueError(f"rhs must have shape ({n},), got {rhs.shape}")
        reduced_rhs = rhs[free]
        values = np.zeros(constrained.size)
        if prescribed is not None and constrained.size:
            values = np.asarray(prescribed, dtype=float)
            if values.shape != constrained.shape:
                raise ValueError(f"prescribed has shape {values.shape}, expected {constrained.shape}")
            reduced_rhs = reduced_rhs - matrix[free][:, constrained] @ values
        reduced = matrix[free][:, free].tocsr()
        reduced.sort_indices()
        return cls(n, free, constrained, reduced, reduced_rhs, values, **callables)

    def full_matrix(self) -> sp.csr_matrix:
        """A on the free DoFs in full storage: ``matrix`` itself, or a new matrix mirrored from its upper
        triangle when ``upper_triangle``."""
        if not self.upper_triangle:
            return self.matrix
        full = (self.matrix + sp.triu(self.matrix, k=1).T).tocsr()
        full.sort_indices()
        return full

    def expand(self, free_values: np.ndarray, constrained_values: np.ndarray | None = None) -> np.ndarray:
        """A DoF vector (dof_count,) (or (dof_count, k)) from its free part, constrained part zero unless
        given."""
        out = np.zeros((self.dof_count,) + free_values.shape[1:])
        out[self.free_dofs] = free_values
        if constrained_values is not None:
            out[self.constrained_dofs] = constrained_values
        return out


def pcg(
    matvec: Callable[[np.ndarray], np.ndarray],
    preconditioner: Callable[[np.ndarray], np.ndarray],
    rhs: np.ndarray,
    *,
    tolerance: float,
    max_iterations: int,
    start: np.ndarray | None = None,
) -> tuple[np.ndarray, int, float]:
    """Preconditioned conjugate gradients on the columns of ``rhs`` at once (each column its own CG).

    Parameters
    ----------
    matvec : x ↦ A x for x of shape (n, k), A symmetric positive definite.
    preconditioner : r ↦ P⁻¹ r, P symmetric positive definite (here a stale or rest factor of A).
    rhs : b, shape (n,) or (n, k).
    tolerance : Stop when ‖b − A x‖₂ ≤ tolerance ‖b‖₂ for every column.
    max_iterations : Iteration cap, ≥ 0.
    start : First iterate; P⁻¹ b by default (the stale factor's answer).

    Returns
    -------
    x (shape of ``rhs``), iterations done, the largest relative residual reached.
    """
    b = np.asarray(rhs, dtype=float)
    single = b.ndim == 1
    b2 = b[:, None] if single else b
    norm_b = np.linalg.norm(b2, axis=0)
    norm_b = np.where(norm_b > 0.0, norm_b, 1.0)
    x = preconditioner(b2) if start is None else np.array(start, dtype=float).reshape(b2.shape)
    if x.ndim == 1:
        x = x[:, None]
    r = b2 - matvec(x)
    relative = np.linalg.norm(r, axis=0) / norm_b
    iterations = 0
    if relative.max(initial=0.0) > tolerance and max_iterations > 0:
        z = preconditioner(r)
        z = z[:, None] if z.ndim == 1 else z
        p = z.copy()
        rz = np.einsum("ij,ij->j", r, z)
        while iterations < max_iterations:
            ap = matvec(p)
            pap = np.einsum("ij,ij->j", p, ap)
            active = relative > tolerance
            alpha = np.where(active & (pap > 0.0), rz / np.where(pap > 0.0, pap, 1.0), 0.0)
            x += alpha * p
            r -= alpha * ap
            iterations += 1
            relative = np.linalg.norm(r, axis=0) / norm_b
            if relative.max() <= tolerance:
                break
            z = preconditioner(r)
            z = z[:, None] if z.ndim == 1 else z
            rz_new = np.einsum("ij,ij->j", r, z)
            beta = np.where(rz > 0.0, rz_new / np.where(rz > 0.0, rz, 1.0), 0.0)
            p = z + beta * p
            rz = rz_new
    return (x[:, 0] if single else x), iterations, float(relative.max(initial=0.0))


@dataclass(frozen=True, eq=False)
class StaleFactor:
    """What the refreshed strategy carries from step to step (part of a run's state).

    Attributes
    ----------
    matrix : The effective stiffness A on the free DoFs it last factorised [N/m], CSR (f, f); never modified.
    age : Steps taken with that factor, ≥ 1 (it is factorised again when ``age`` reaches ``refresh_every``).
    """

    matrix: sp.csr_matrix
    age: int


@dataclass(frozen=True, eq=False)
class PartialSolveMarks:
    """What the exact strategy on PARDISO carries from step to step (part of a run's state): the free-DoF
    positions its analysis marked for partial solves.

    PARDISO's fill-reducing ordering, hence the factor's round-off, depends on the marked positions; carrying
    them makes a step a function of its state (a restarted run analyses with the same marks).

    Attributes
    ----------
    positions : Sorted positions among the free DoFs, shape (k,), int64; read-only.
    """

    positions: np.ndarray


class StepCompliance:
    """The compliance of one body at one step: its free motion, W for rows, and the correction.

    Attributes
    ----------
    system : The step system it was made from.
    free_displacement : Δx_free [m], shape (dof_count,), equal to ``prescribed`` on the constrained DoFs.
    report : What the strategy did this step (``refactorised``, ``pcg_iterations``, ``pcg_residual``, and with
        ``against_exact`` the errors ``free_motion_error`` [m], ``compliance_error`` (relative, Frobenius) and
        ``correction_error`` [m]).
    """

    def __init__(
        self,
        system: StepSystem,
        free_free: np.ndarray,
        columns: Callable,
        report: dict,
        exact: StepCompliance | None = None,
        solve: Callable | None = None,
        block: Callable | None = None,
        apply: Callable | None = None,
        half_solve: Callable | None = None,
        inverse_block: Callable | None = None,
        marked_solve: Callable | None = None,
    ):
        self.system = system
        # positions -> (A⁻¹)_uu, the block of the inverse on the DoFs the rows touch, by a partial solve of
        # the exact factor (exact strategy with PARDISO only); preferred over the forward half
        self._inverse_block = inverse_block
        # load -> A⁻¹ load for a load on the positions inverse_block was last given (the correction's H_uᵀλ):
        # a solve whose forward half follows the elimination tree from them only, the same bits as _solve
        self._marked_solve = marked_solve
        self._half = half_solve  # B -> Y with YᵀY = Bᵀ A⁻¹ B (the factor's forward half), exact strategy only
        self._block = block  # (positions, influence) -> E_uᵀ A⁻¹ E_u, (u, u); influence[positions] by default
        self._apply = apply  # (free load, first guess) -> A⁻¹ load; influence @ (H_uᵀ λ) by default
        self._solve = solve  # the exact factor's solve on the free DoFs (exact strategy only)
        self.free_displacement = system.expand(free_free, system.prescribed)
        self.report = report
        self._columns = columns  # (used free positions) -> A⁻¹ E on the free DoFs, shape (f, u)
        self._exact = exact  # an exact StepCompliance for the error report, or None
        self._cache_key = None  # the CSR arrays of the rows H the cache was computed for (a copy)
        self._cache = None
        if exact is not None:
            report["free_motion_error"] = float(
                np.abs(self.free_displacement - exact.free_displacement).max()
            )

    @property
    def dof_count(self) -> int:
        """Number of DoFs of the body."""
        return self.system.dof_count

    @property
    def free_dofs(self) -> np.ndarray:
        """Unconstrained DoFs, sorted."""
        return self.system.free_dofs

    @property
    def constrained_dofs(self) -> np.ndarray:
        """Fixed or prescribed DoFs, sorted."""
        return self.system.constrained_dofs

    def _influence(self, jacobian: sp.csr_matrix):
        """Used free DoFs of H (positions among the free DoFs), H restricted to them, and A⁻¹ E on them.

        A memo of the last H by value (W and the correction of one step share it): a copy of H's CSR arrays is
        the key, so rows changed in place or rebuilt equal give what a fresh computation gives."""
        jacobian = sp.csr_matrix(jacobian)
        key = (jacobian.shape, jacobian.indptr.copy(), jacobian.indices.copy(), jacobian.data.copy())
        if self._cache_key is not None and _same_rows(self._cache_key, key):
            return self._cache
        if jacobian.shape[1] != self.system.dof_count:
            raise ValueError(
                f"rows must have {self.system.dof_count} columns (DoFs), got {jacobian.shape[1]}"
            )
        # the DoFs the rows touch, sorted (np.unique's answer, in time linear in the DoFs)
        used = np.flatnonzero(np.bincount(jacobian.indices, minlength=jacobian.shape[1]))
        positions = np.searchsorted(self.system.free_dofs, used)
        positions = np.minimum(positions, self.system.free_dofs.size - 1)
        on_free = self.system.free_dofs[positions] == used
        used, positions = used[on_free], positions[on_free]
        restricted = jacobian[:, used].toarray()  # (rows, u): constrained DoFs do not move
        exact = self._solve is not None and self._block is None and self._apply is None
        rows = restricted.shape[0]
        if exact and used.size and self._inverse_block is not None:
            # W = H_u (A⁻¹)_uu H_uᵀ from the block of the inverse on the u DoFs the rows touch, one partial
            # solve (the unit loads E_u, only the components on the marked DoFs computed); the correction then
            # solves the one load H_uᵀλ.
            half = ("block", self._inverse_block(positions))
            self._cache_key, self._cache = key, (positions, restricted, None, half)
            return self._cache
        if exact and used.size and (self._half is not None or rows < used.size):
            # The exact factor: min(rows, u) right-hand sides, the rows' loads H_uᵀ when there are fewer rows
            # than DoFs touched (the ring coupling's rows spread over many tets), else the unit loads E_u.
            # With a Cholesky factor A = Pᵀ L Lᵀ P, only the forward half: Y = L⁻¹ P B and BᵀA⁻¹B = YᵀY (half
            # the work of a solve); the correction then solves the one load H_uᵀλ.
            by_rows = rows < used.size
            loads = np.zeros((self.system.free_dofs.size, rows if by_rows else used.size))
            if by_rows:
                loads[positions] = restricted.T
            else:
                loads[positions, np.arange(used.size)] = 1.0
            if self._half is not None:
                half = ("rows" if by_rows else "units", self._half(loads))
            else:
                half = ("responses", self._solve(loads))
            self._cache_key, self._cache = key, (positions, restricted, None, half)
            return self._cache
        influence = self._columns(positions) if used.size else np.zeros((self.system.free_dofs.size, 0))
        self._cache_key, self._cache = key, (positions, restricted, influence, None)
        return self._cache

    def delassus(self, jacobian: sp.spmatrix) -> np.ndarray:
        """W = H A⁻¹ Hᵀ [m/N] for rows H of shape (rows, dof_count); dense, symmetric, (rows, rows)."""
        with hot_path_threads():
            return self._delassus(jacobian)

    def _delassus(self, jacobian: sp.spmatrix) -> np.ndarray:
        positions, restricted, influence, half = self._influence(jacobian)
        if half is not None:
            form, values = half
            if form == "block":
                compliance = restricted @ values @ restricted.T
            elif form == "rows":
                compliance = values.T @ values
            elif form == "units":
                compliance = restricted @ (values.T @ values) @ restricted.T
            else:
                compliance = restricted @ values[positions]
        else:
            block = influence[positions] if self._block is None else self._block(positions, influence)
            compliance = restricted @ block @ restricted.T
        compliance = 0.5 * (compliance + compliance.T)
        if self._exact is not None:
            reference = self._exact.delassus(jacobian)
            scale = max(np.linalg.norm(reference), np.finfo(float).tiny)
            self.report["compliance_error"] = float(np.linalg.norm(compliance - reference) / scale)
        return compliance

    def correction(self, jacobian: sp.spmatrix, multipliers: np.ndarray) -> np.ndarray:
        """A⁻¹ Hᵀ λ [m] on every DoF (zero on the constrained ones), shape (dof_count,)."""
        with hot_path_threads():
            return self._correction(jacobian, multipliers)

    def _correction(self, jacobian: sp.spmatrix, multipliers: np.ndarray) -> np.ndarray:
        positions, restricted, influence, half = self._influence(jacobian)
        multipliers = np.asarray(multipliers, dtype=float)
        if multipliers.shape != (restricted.shape[0],):
            raise ValueError(f"multipliers must have shape ({restricted.shape[0]},), got {multipliers.shape}")
        weights = restricted.T @ multipliers
        if half is None:
            free = influence @ weights
        elif half[0] == "responses":
            free = half[1] @ multipliers
        else:
            load = np.zeros(self.system.free_dofs.size)
            load[positions] = weights
            sparse = half[0] == "block" and self._marked_solve is not None
            free = self._marked_solve(load) if sparse else self._solve(load)
        if self._apply is not None and positions.size:
            load = np.zeros(self.system.free_dofs.size)
            np.add.at(load, positions, weights)
            free = self._apply(load, free)
        out = self.system.expand(free)
        if self._exact is not None:
            self.report["correction_error"] = float(
                np.abs(out - self._exact.correction(jacobian, multipliers)).max(initial=0.0)
            )
        return out

    def compliance(self, jacobian: sp.spmatrix) -> tuple[np.ndarray, np.ndarray]:
        """W and the responses A⁻¹ Hᵀ [m/N], dense (dof_count, rows), zero on the constrained DoFs: for a body
        whose correction applies the responses itself (``responses @ λ``, the flexible needle)."""
        if self._solve is None:
            positions, restricted, influence, _ = self._influence(jacobian)
            responses = self.system.expand(influence @ restricted.T)
            return self.delassus(jacobian), responses
        # The exact factor: the responses to unit loads on the DoFs the rows touch, combined by H (fewer
        # solves when the rows outnumber those DoFs), else to Hᵀ itself; W = H (A⁻¹Hᵀ).
        jacobian = sp.csr_matrix(jacobian)
        row_count = jacobian.shape[0]
        used = np.unique(jacobian.indices)
        if used.size < row_count:
            unit_loads = np.zeros((self.system.dof_count, used.size))
            unit_loads[used, np.arange(used.size)] = 1.0
            responses = self._solve_full(unit_loads) @ jacobian[:, used].T.toarray()
        else:
            responses = self._solve_full(jacobian.T.toarray())
        compliance = np.asarray(jacobian @ responses)
        return 0.5 * (compliance + compliance.T), responses

    def _solve_full(self, rhs: np.ndarray) -> np.ndarray:
        out = np.zeros_like(rhs)
        if rhs.ndim == 2 and rhs.shape[1] == 0:
            return out
        out[self.system.free_dofs] = self._solve(np.ascontiguousarray(rhs[self.system.free_dofs]))
        return out


def _same_rows(first: tuple, second: tuple) -> bool:
    """Whether two keys of :meth:`StepCompliance._influence` (shape, indptr, indices, data) are equal."""
    if first[0] != second[0]:
        return False
    return all(np.array_equal(a, b) for a, b in zip(first[1:], second[1:], strict=True))


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

    def resume(self, carried: StaleFactor | None) -> None:
        """Continue from ``carried`` (:meth:`carried` of some earlier step, or None: a run's start)."""

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
        self._solver.factorise(system.matrix)
        solver = self._solver
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
            {"refactorised": True},
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


@dataclass(frozen=True)
class Exact:
    """Refactorise every step (the reference).

    Parameters
    ----------
    linear_solver : "auto" (default: :func:`refsim.fem.linear.default_linear_solver`), "pardiso", "cholmod" or
        "superlu".
    """

    linear_solver: str = "auto"
    name: str = field(default="exact", init=False)

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

    def __post_init__(self) -> None:
        _check_common(self.linear_solver, self.against_exact)
        if (
            not isinstance(self.refresh_every, int)
            or isinstance(self.refresh_every, bool)
            or self.refresh_every < 1
        ):
            raise ValueError(f"refresh_every = {self.refresh_every!r}: expected an integer >= 1")
        if not (0.0 < self.tolerance < 1.0):
            raise ValueError(f"tolerance = {self.tolerance!r}: expected a number in (0, 1)")
        if not isinstance(self.max_iterations, int) or self.max_iterations < 1:
            raise ValueError(f"max_iterations = {self.max_iterations!r}: expected an integer >= 1")
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

    def __post_init__(self) -> None:
        _check_common(self.linear_solver, self.against_exact)
        if not (0.0 < self.tolerance < 1.0):
            raise ValueError(f"tolerance = {self.tolerance!r}: expected a number in (0, 1)")
        if not isinstance(self.max_iterations, int) or self.max_iterations < 1:
            raise ValueError(f"max_iterations = {self.max_iterations!r}: expected an integer >= 1")

    def bind(self) -> BodyCompliance:
        """A fresh per-body, per-run compliance."""
        return _PrecomputedBody(self)


class _FastBody(BodyCompliance):
    def __init__(self, strategy: Fast) -> None:
        super().__init__(strategy)
        self._solver = make_linear_solver(strategy.linear_solver)
        # without the error report, the tissue builds its step system with an operator and no matrix
        self.matrix_free = not strategy.against_exact
        self._ready = False

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
        # C₀ = A₀⁻¹ column blocks, one (f, 3) block per free node, solved the first time a row touches the
        # node: ``_slot[g]`` is its block in ``_store`` (-1: not yet)
        self._slot = np.full(self._groups.size, -1, dtype=np.int64)
        self._store = np.zeros((self._size, 0))
        self._filled = 0
        self._ready = True

    def _rest_blocks(self, groups: np.ndarray) -> np.ndarray:
        """The columns of ``_store`` holding C₀ E_g for the free node groups ``groups`` (sorted, unique),
        shape (3 · groups.size,), solving the blocks not held yet.

        Each node's block is one (f, 3) solve of the rest factor, done once per run whatever else is asked
        with it, so the memo's bits depend on no history (a restarted run computes the same blocks)."""
        missing = groups[self._slot[groups] < 0]
        if missing.size:
            needed = 3 * (self._filled + missing.size)
            if needed > self._store.shape[1]:
                grown = np.zeros((self._size, max(needed, 2 * self._store.shape[1])))
                grown[:, : 3 * self._filled] = self._store[:, : 3 * self._filled]
                self._store = grown
            unit = np.zeros((self._size, 3))
            for group in missing:  # each node once per run (the memo's bits: one solve per node)
                unit[3 * group : 3 * group + 3] = np.eye(3)
                self._store[:, 3 * self._filled : 3 * self._filled + 3] = self._solver.solve(unit)
                unit[3 * group : 3 * group + 3] = 0.0
                self._slot[group] = self._filled
                self._filled += 1
        return (3 * self._slot[groups][:, None] + np.arange(3)).ravel()

    def _step(self, system: StepSystem, exact) -> StepCompliance:
        if not self._ready:
            self._prepare(system)
        strategy = self.strategy
        rotations = system.group_rotations()[self._groups]  # (f/3, 3, 3), one per free node
        solver = self._solver

        def warped(load: np.ndarray) -> np.ndarray:
            # R C₀ Rᵀ load: the rest compliance in each node's rotated frame
            return _rotate_nodes(rotations, solver.solve(_rotate_nodes(rotations, load, transpose=True)))

        free, iterations, residual = pcg(
            system.product,
            warped,
            system.rhs,
            tolerance=strategy.tolerance,
            max_iterations=strategy.max_iterations,
        )
        report = {"refactorised": False, "pcg_iterations": iterations, "pcg_residual": residual}
        before = self._filled

        def inverse_block(positions):
            # (R C₀ Rᵀ)_uu from the C₀ blocks of the nodes the rows touch
            groups = np.unique(positions // 3)
            support = (3 * groups[:, None] + np.arange(3)).ravel()
            columns = self._rest_blocks(groups)  # (solves the new blocks, which may grow the store)
            block = self._store[np.ix_(support, columns)]  # C₀ on the support
            # R_s C₀ R_sᵀ, R_s block-diagonal
            rotated = _rotate_node_block(rotations[groups], block)
            where = np.searchsorted(support, positions)
            report["rest_blocks_solved"] = self._filled - before
            return rotated[np.ix_(where, where)]

        def apply(load):
            # R C₀ Rᵀ load for a load on few nodes (the correction's Hᵀλ), from the same C₀ blocks
            load = np.asarray(load, dtype=float)
            grouped = load.reshape(rotations.shape[0], 3, -1)
            groups = np.flatnonzero(np.any(grouped != 0.0, axis=(1, 2)))
            if groups.size == 0:
                return np.zeros_like(load)
            local = _rotate_nodes(
                rotations[groups], grouped[groups].reshape(3 * groups.size, -1), transpose=True
            )
            # only the load's node blocks, in node order: the product's bits then depend on no history
            rest = self._store[:, self._rest_blocks(groups)] @ local
            return _rotate_nodes(rotations, rest).reshape(load.shape)

        return StepCompliance(system, free, None, report, exact, apply, inverse_block=inverse_block)


@dataclass(frozen=True)
class Fast:
    """No matrix assembled or factorised during the run: the rest compliance rotated per node for W and the
    correction, free motion by CG on the current A applied per tet, preconditioned by the same rotated rest
    compliance.

    Parameters
    ----------
    tolerance, max_iterations : Of the free motion's PCG (relative residual; iteration cap). The free motion's
        relative error is then at most κ(A) · tolerance (a worst case). 1e-4: on the medium liver 1.2 CG
        iterations per step against 2.1 for 1e-6, with the same needle-force error against exact (cube_cut:
        4.24e-2 N at 1e-6, 1e-4 and 1e-2; medium liver: 2.2e-5 and 2.3e-5 N): W's error dominates.
    linear_solver : The rest factor's solver, as for :class:`Exact`.
    against_exact : As for :class:`Refreshed` (the step system is then assembled, for the exact twin).
    """

    tolerance: float = 1e-4
    max_iterations: int = 200
    linear_solver: str = "auto"
    against_exact: bool = False
    name: str = field(default="fast", init=False)

    def __post_init__(self) -> None:
        _check_common(self.linear_solver, self.against_exact)
        if not (0.0 < self.tolerance < 1.0):
            raise ValueError(f"tolerance = {self.tolerance!r}: expected a number in (0, 1)")
        if not isinstance(self.max_iterations, int) or self.max_iterations < 1:
            raise ValueError(f"max_iterations = {self.max_iterations!r}: expected an integer >= 1")

    def bind(self) -> BodyCompliance:
        """A fresh per-body, per-run compliance."""
        return _FastBody(self)


def strategy_variant(variant: str) -> tuple[str, str]:
    """The strategy and W update of a name of :data:`STRATEGY_VARIANTS` ("refreshed_stale" ->
    ("refreshed", "stale"); a strategy alone has the default update)."""
    if variant not in STRATEGY_VARIANTS:
        raise ValueError(f"compliance strategy {variant!r}: expected one of {', '.join(STRATEGY_VARIANTS)}")
    name, _, update = variant.partition("_")
    return name, update or W_UPDATES[0]


def make_strategy(
    name: str = "exact",
    *,
    refresh_every: int = 10,
    linear_solver: str = "auto",
    against_exact: bool = False,
    tolerance: float = 1e-10,
    w_update: str | None = None,
):
    """The one factory of compliance strategies: a scene's ``compliance`` section, or a benchmark's variant.

    Parameters
    ----------
    name : A strategy of :data:`STRATEGIES`, or a variant of :data:`STRATEGY_VARIANTS` ("refreshed_stale"),
        which also sets the W update.
    refresh_every : Of :class:`Refreshed`.
    linear_solver : "auto", "pardiso", "cholmod" or "superlu".
    against_exact : Report errors against exact each step (fast strategies only; ignored by exact).
    tolerance : PCG tolerance of the refreshed and precomputed strategies (the fast one keeps its own,
        :attr:`Fast.tolerance`).
    w_update : Of :class:`Refreshed` (its ``compliance_update``), one of :data:`W_UPDATES`; None: the
        variant's, else "pcg". A variant's update and another ``w_update`` together are an error.
    """
    name, update = strategy_variant(name)
    if w_update is not None and update != W_UPDATES[0] and w_update != update:
        raise ValueError(f"compliance strategy {name}_{update}: its W update is {update!r}, not {w_update!r}")
    w_update = w_update or update
    if name == "exact":
        return Exact(linear_solver=linear_solver)
    if name == "refreshed":
        return Refreshed(
            refresh_every=refresh_every,
            tolerance=tolerance,
            linear_solver=linear_solver,
            against_exact=against_exact,
            compliance_update=w_update,
        )
    if name == "fast":
        return Fast(linear_solver=linear_solver, against_exact=against_exact)
    return Precomputed(tolerance=tolerance, linear_solver=linear_solver, against_exact=against_exact)
