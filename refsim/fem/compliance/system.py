"""The step's system A Δv = b on a body's free DoFs (:class:`StepSystem`), its compliance W = H A⁻¹ Hᵀ and
correction for a step (:class:`StepCompliance`), what a strategy carries between steps, and the shared kernels
(PCG, per-node rotations). The strategies that fill them: :mod:`refsim.fem.compliance.bodies`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from refsim.fem.threads import hot_path_threads


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
class FreeMotionStart:
    """What the fast strategy carries from step to step (part of a run's state): where the next free motion's
    conjugate gradients start.

    The next start is x₀ = x' + R C₀ Rᵀ (b − A' x'), x' the last free displacement and A' x' its image under
    the last step's operator (b' − r', the last right-hand side less the residual the CG left): one
    preconditioned Richardson step from x' on this step's load. What R C₀ Rᵀ misses of A⁻¹ on the last load is
    in x' already (the last solve found it), and neither the last residual nor the preconditioner's error on
    the whole load is carried on: a step that changes the load and the rotations little starts close to its
    answer however far R C₀ Rᵀ b alone is from it.

    Attributes
    ----------
    displacement : x', Δx_free on the free DoFs of the last step [m], shape (f,); read-only.
    load : A' x' [N], shape (f,); read-only.
    """

    displacement: np.ndarray
    load: np.ndarray


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
    report : What the strategy did this step (``refactorised``, ``pcg_iterations``, ``pcg_residual``; the fast
        strategy's ``pcg_carried_start``, whether its CG started from the last step's free motion
        (:class:`FreeMotionStart`), ``pcg_start_residual``, the relative residual of its start, and
        ``rest_blocks_solved``; and with ``against_exact`` the errors ``free_motion_error`` [m],
        ``compliance_error`` (relative, Frobenius) and ``correction_error`` [m]).
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
        if type(jacobian) is not sp.csr_matrix:  # (a CSR matrix is read as it is: no new wrapper)
            jacobian = sp.csr_matrix(jacobian)
        arrays = (jacobian.shape, jacobian.indptr, jacobian.indices, jacobian.data)
        if self._cache_key is not None and _same_rows(self._cache_key, arrays):
            return self._cache
        key = (jacobian.shape, jacobian.indptr.copy(), jacobian.indices.copy(), jacobian.data.copy())
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
        restricted = _dense_columns(jacobian, used)  # (rows, u): constrained DoFs do not move
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


def _dense_columns(matrix: sp.csr_matrix, columns: np.ndarray) -> np.ndarray:
    """``matrix[:, columns].toarray()`` for sorted, distinct ``columns``: the entries copied into place when
    the CSR is canonical (sorted indices, no duplicates: the same numbers, without SciPy's column slicing;
    one compiled pass, :func:`refsim.fem.compliance.kernels.scatter_columns`), else SciPy's answer (which sums
    duplicates)."""
    if not matrix.has_canonical_format:
        return matrix[:, columns].toarray()
    from refsim.fem.compliance.kernels import scatter_columns

    where = np.full(matrix.shape[1], -1, dtype=np.int64)
    where[columns] = np.arange(columns.size)
    out = np.zeros((matrix.shape[0], columns.size))
    scatter_columns(matrix.indptr, matrix.indices, matrix.data, where, out)
    return out


def _same_rows(first: tuple, second: tuple) -> bool:
    """Whether two keys of :meth:`StepCompliance._influence` (shape, indptr, indices, data) are equal."""
    if first[0] != second[0]:
        return False
    # np.array_equal's test (same shape, every entry ==) without its conversions: the keys hold arrays
    for a, b in zip(first[1:], second[1:], strict=True):
        if a.shape != b.shape or not (a == b).all():
            return False
    return True
