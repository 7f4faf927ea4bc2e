"""Sparse symmetric positive definite solvers: PARDISO, refsim's supernodal Cholesky, CHOLMOD or SuperLU
(layer 2).

Every body's effective stiffness A = M/dt² + C/dt + K keeps one sparsity pattern for a whole run (the free
DoFs of a fixed mesh), so a solver is made **for a pattern**: the symbolic analysis (fill-reducing ordering,
elimination tree) is done once, and each step only refactorises numerically.

Backends, in the order of :func:`default_linear_solver`:

``"pardiso"``
    Intel oneMKL PARDISO (x86-64 only), called through ctypes in oneMKL's runtime library ``mkl_rt``, which
    the ``mkl`` wheel installs (the ``pypardiso`` dependency brings it; refsim does not import pypardiso,
    whose import searches all of ``sys.prefix`` for the library: :func:`_mkl_runtime_candidates`): real SPD
    (mtype 2), upper triangle, zero-based. Phase 11 (analysis) once per pattern, phase 22 (numeric Cholesky)
    per step, phase 33 (solve) per right-hand side block.
``"supernodal"``
    refsim's own supernodal Cholesky (:mod:`refsim.fem.supernodal`: numba loops around the BLAS and LAPACK
    that SciPy ships), upper triangle read. Its fill-reducing ordering is PARDISO's METIS nested dissection
    (read from a PARDISO analysis) where oneMKL loads, else SuperLU's minimum degree of A + Aᵀ
    (``supernodal:metis`` / ``supernodal:minimum-degree`` force one). Analysis once per pattern, numeric
    factorisation per step; partial solves for W (:meth:`SupernodalSolver.inverse_block`) follow the
    elimination tree's paths from the marked positions, and its factor does not depend on the marks. Its
    numeric factorisation is faster than PARDISO's on this project's matrices, its partial solves slower:
    per step neither wins (docs/speed.md), so it comes second, and first where oneMKL does not load.
``"cholmod"``
    CHOLMOD (scikit-sparse), only when it imports: it has no wheel here and needs a system SuiteSparse.
    Symbolic analysis once, ``cholesky_inplace`` per step.
``"superlu"``
    SciPy's SuperLU in its symmetric mode (no off-diagonal pivoting), with a fill-reducing column ordering
    (``MMD_AT_PLUS_A`` by default: the minimum degree of A + Aᵀ, which suits a symmetric matrix; ``COLAMD`` is
    what refsim used before). SuperLU has no separate symbolic phase in SciPy: each step orders and
    factorises.

The choice is forced by ``REFSIM_LINEAR_SOLVER=pardiso|supernodal|cholmod|superlu`` (or a scene's
``compliance.linear_solver`` key through :func:`make_linear_solver`); :func:`linear_solver_info` returns the
choice and the versions for the results file.
"""

from __future__ import annotations

import ctypes
import importlib.metadata
import os
import platform
from functools import lru_cache

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = [
    "LINEAR_SOLVERS",
    "ENVIRONMENT_VARIABLE",
    "LinearSolverError",
    "SuperLUSolver",
    "PardisoSolver",
    "SupernodalSolver",
    "CholmodSolver",
    "available_linear_solvers",
    "default_linear_solver",
    "make_linear_solver",
    "linear_solver_info",
]

LINEAR_SOLVERS = ("pardiso", "supernodal", "cholmod", "superlu")
ENVIRONMENT_VARIABLE = "REFSIM_LINEAR_SOLVER"
SUPERLU_ORDERINGS = ("MMD_AT_PLUS_A", "COLAMD", "MMD_ATA", "NATURAL")
DEFAULT_SUPERLU_ORDERING = "MMD_AT_PLUS_A"


class LinearSolverError(RuntimeError):
    """A linear solver is not available here or failed (the message names which and why)."""


def _check_square(matrix: sp.spmatrix) -> sp.csr_matrix:
    matrix = sp.csr_matrix(matrix)
    if matrix.shape[0] != matrix.shape[1] or matrix.shape[0] == 0:
        raise ValueError(f"matrix must be square and non-empty, got shape {matrix.shape}")
    matrix.sort_indices()
    return matrix


class SuperLUSolver:
    """SuperLU (SciPy) in symmetric mode with a fill-reducing ordering.

    Parameters
    ----------
    ordering : Column ordering, one of ``MMD_AT_PLUS_A`` (default), ``COLAMD``, ``MMD_ATA``, ``NATURAL``.
    """

    name = "superlu"
    storage = "full"  # it factorises what it is given: A in full storage

    def __init__(self, ordering: str = DEFAULT_SUPERLU_ORDERING) -> None:
        if ordering not in SUPERLU_ORDERINGS:
            raise ValueError(f"SuperLU ordering {ordering!r}: expected one of {', '.join(SUPERLU_ORDERINGS)}")
        self.ordering = ordering
        self._factor = None
        self._size = 0
        self._pattern = None  # (indptr, indices) of the factor held, copied
        self._values = FactorisedValues()  # its values

    def factorise(self, matrix: sp.spmatrix) -> None:
        """Factorise A (symmetric positive definite, full storage), replacing the previous factor (kept when
        A is the matrix it factorised, bit for bit)."""
        csc = sp.csc_matrix(matrix)
        if csc.shape[0] != csc.shape[1]:
            raise ValueError(f"matrix must be square, got shape {csc.shape}")
        pattern = self._pattern
        if (
            self._factor is not None
            and pattern is not None
            and np.array_equal(pattern[0], csc.indptr)
            and np.array_equal(pattern[1], csc.indices)
            and self._values.unchanged(csc.data)
        ):
            return
        self._factor, self._pattern = None, None
        self._values.forget()
        # A is SPD: no pivoting off the diagonal (SuperLU's symmetric mode), which also halves the cost of a
        # solve.
        self._factor = spla.splu(
            csc, permc_spec=self.ordering, diag_pivot_thresh=0.0, options={"SymmetricMode": True}
        )
        self._size = csc.shape[0]
        self._pattern = (csc.indptr.copy(), csc.indices.copy())
        self._values.keep(csc.data)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """A⁻¹ rhs for rhs of shape (n,) or (n, k)."""
        if self._factor is None:
            raise LinearSolverError("superlu: solve before factorise")
        return self._factor.solve(np.ascontiguousarray(rhs, dtype=float))

    @property
    def factorisations(self) -> int:
        """Numeric factorisations made (a factorisation of the values held keeps the factor: not counted)."""
        return self._values.factorisations

    @property
    def description(self) -> dict:
        return {"name": self.name, "ordering": self.ordering}


class FactorisedValues:
    """A copy of the values of the matrix a solver factorised last: a factorisation asked for the same
    values, bit for bit, keeps the factor (a tissue at rest assembles the same matrix step after step, and the
    factor of the same values is the same factor). ``factorisations`` counts the numeric factorisations."""

    def __init__(self) -> None:
        self._values: np.ndarray | None = None
        self.factorisations = 0

    def unchanged(self, values: np.ndarray) -> bool:
        """Whether ``values`` are those kept, bit for bit (a NaN never is)."""
        kept = self._values
        return kept is not None and kept.shape == values.shape and bool(np.array_equal(kept, values))

    def keep(self, values: np.ndarray) -> None:
        """A numeric factorisation of ``values`` was made: copy them (into the last copy's memory when the
        size is the same)."""
        if self._values is None or self._values.shape != values.shape:
            self._values = np.array(values, dtype=float)
        else:
            np.copyto(self._values, values)
        self.factorisations += 1

    def forget(self) -> None:
        """No factor is held (released, or a new pattern): the next factorisation is made."""
        self._values = None


def _same_memory(first: np.ndarray, second: np.ndarray) -> bool:
    """Whether two arrays are the same elements of the same memory (an array and a view of it in full)."""
    one, other = first.__array_interface__, second.__array_interface__
    return (
        one["data"] == other["data"] and one["shape"] == other["shape"] and one["strides"] == other["strides"]
    )


def _all_among(values: np.ndarray, sorted_set: np.ndarray) -> bool:
    """Whether every one of ``values`` is in ``sorted_set`` (sorted, unique)."""
    where = np.searchsorted(sorted_set, values)
    inside = where < sorted_set.size
    return bool(np.all(inside) and np.array_equal(sorted_set[where], values))


def _marked_rhs(rhs: np.ndarray, size: int, marked: np.ndarray | None) -> np.ndarray:
    """The right-hand side of a solve_marked, checked: shape (size,), zero off the ``marked`` positions
    (not checked when there are none: the caller solves whole)."""
    rhs = np.asarray(rhs, dtype=float)
    if rhs.shape != (size,):
        raise ValueError(f"rhs must have shape ({size},), got {rhs.shape}")
    if marked is not None and np.count_nonzero(rhs) != np.count_nonzero(rhs[marked]):
        raise ValueError("solve_marked: the rhs has non-zeros off the marked positions")
    return rhs


_ONE, _ZERO = ctypes.c_int32(1), ctypes.c_int32(0)
_MTYPE_SPD = ctypes.c_int32(2)  # PARDISO's matrix type: real symmetric positive definite
_UNUSED = np.zeros(1)  # what an unused array argument points to


class PardisoSolver:
    """oneMKL PARDISO, real symmetric positive definite: analysis once per pattern, numeric refactorisation
    per step.

    Parameters
    ----------
    ordering : PARDISO's fill-in reducing ordering, iparm[1]: 0 minimum degree, 2 METIS nested dissection.
    """

    name = "pardiso"
    storage = "upper"  # it reads A's upper triangle only: full storage or the upper triangle alone will do

    def __init__(self, ordering: int = 2) -> None:
        self._pardiso = _pardiso_function()
        self.ordering = int(ordering)
        self._pt = np.zeros(64, dtype=np.int64)
        self._iparm = np.zeros(64, dtype=np.int32)
        self._iparm[0] = 1  # we supply the parameters
        self._iparm[1] = self.ordering
        self._iparm[7] = 0  # no iterative refinement
        self._iparm[9] = 13  # pivot perturbation 1e-13 (not used for SPD)
        self._iparm[17] = -1  # report nnz(L)
        self._iparm[34] = 1  # zero-based indices
        self._iparm_input = self._iparm.copy()  # phase 11 writes outputs into iparm: restored before each
        self._marked = None  # sorted positions marked for partial solves (iparm[30] = 1) by the analysis
        self._unit_buffers = None  # (loads, solutions) of the last partial solve, reused (inverse_block)
        self._perm = np.zeros(1, dtype=np.int32)
        self._pattern_key = None
        self._pattern_arrays = None
        self._upper = None  # positions in the CSR data of the upper-triangle entries (None: all of them)
        self._ia = self._ja = self._a = None
        self._n = 0
        self._analysed = False  # the handle holds an analysis (phase 11 ran; phase -1 not since)
        self._factorised = False
        self._released = False  # release() ran and no factorise since
        self._values = FactorisedValues()  # the values of the factor held
        self.analyses = 0  # phase-11 analyses made (a new pattern, or new partial-solve marks)
        self._pt_address, self._iparm_address = self._pt.ctypes.data, self._iparm.ctypes.data
        self._perm_address = self._perm.ctypes.data
        self._a_address = self._ia_address = self._ja_address = _UNUSED.ctypes.data

    def __del__(self) -> None:
        try:
            self.release()
        except Exception:  # noqa: BLE001 - freeing at interpreter exit must not raise
            pass

    def release(self) -> None:
        """Free oneMKL's memory of the handle (phase -1) and forget the pattern, factor and marks: a solve
        afterwards raises :class:`LinearSolverError`; :meth:`factorise` starts again from a new analysis.
        Releasing twice is harmless (the handle is freed once)."""
        self._release_handle()
        self._pattern_key = self._pattern_arrays = None
        self._upper = None
        self._ia = self._ja = self._a = None
        self._a_address = self._ia_address = self._ja_address = _UNUSED.ctypes.data
        self._marked = None
        self._unit_buffers = None
        self._n = 0
        self._values.forget()
        self._released = True

    def _release_handle(self) -> None:
        """Phase -1 on an analysed handle, then a zeroed ``pt`` (what a first analysis expects)."""
        if self._analysed:
            self._analysed = self._factorised = False
            try:
                self._call(-1)
            finally:
                self._pt[:] = 0

    def _call(
        self, phase: int, b: np.ndarray | None = None, x: np.ndarray | None = None, nrhs: int = 1
    ) -> None:
        """One call of ``pardiso``; b, x: the right-hand sides and the solutions of a solve phase (Fortran
        order), unused otherwise.

        Arrays go by address, taken once for those that live across calls (``.ctypes.data_as`` costs about
        10 µs an array, and a call passes eight)."""
        error = ctypes.c_int32(0)
        self._pardiso(
            self._pt_address,
            ctypes.byref(_ONE),
            ctypes.byref(_ONE),
            ctypes.byref(_MTYPE_SPD),
            ctypes.byref(ctypes.c_int32(phase)),
            ctypes.byref(ctypes.c_int32(self._n)),
            self._a_address,
            self._ia_address,
            self._ja_address,
            self._perm_address,
            ctypes.byref(ctypes.c_int32(nrhs)),
            self._iparm_address,
            ctypes.byref(_ZERO),
            _UNUSED.ctypes.data if b is None else b.ctypes.data,
            _UNUSED.ctypes.data if x is None else x.ctypes.data,
            ctypes.byref(error),
        )
        if error.value != 0:
            raise LinearSolverError(
                f"pardiso phase {phase} failed with error {error.value} (oneMKL error code)"
            )

    def factorise(self, matrix: sp.spmatrix) -> None:
        """Factorise A (symmetric positive definite, full storage or its upper triangle alone: only the upper
        triangle is read); the analysis runs when the pattern is new. An upper triangle alone is read in
        place (no copy): its values must not change before the next factorisation. The values factorised
        last, bit for bit, keep the factor (:class:`FactorisedValues`)."""
        matrix = _check_square(matrix)
        last = self._pattern_arrays
        if (
            last is not None
            and _same_memory(last[0], matrix.indptr)
            and _same_memory(last[1], matrix.indices)
        ):
            # The very arrays of last time (one FreePattern per run; SciPy hands out views of them, and they
            # are held here, so that their memory cannot be recycled).
            key = self._pattern_key
        else:
            key = (matrix.shape[0], matrix.nnz, hash(matrix.indptr.tobytes()), hash(matrix.indices.tobytes()))
        self._pattern_arrays = (matrix.indptr, matrix.indices)
        if key != self._pattern_key:
            rows = np.repeat(np.arange(matrix.shape[0]), np.diff(matrix.indptr))
            upper_entries = np.flatnonzero(matrix.indices >= rows)
            self._upper = None if upper_entries.size == matrix.nnz else upper_entries
            upper = sp.triu(matrix, format="csr")
            upper.sort_indices()
            self._n = matrix.shape[0]
            self._ia = upper.indptr.astype(np.int32)
            self._ja = upper.indices.astype(np.int32)
            self._ia_address, self._ja_address = self._ia.ctypes.data, self._ja.ctypes.data
            if self._marked is not None and (self._marked.size and self._marked[-1] >= self._n):
                self._marked = None  # marked for another matrix
            self._set_values(matrix)
            self._analyse()
            self._pattern_key = key
        else:
            unchanged = self._factorised and self._values.unchanged(self._set_values(matrix))
            if unchanged:  # the factor held is this matrix's, bit for bit
                return
        self._numeric()
        self._released = False

    def _numeric(self) -> None:
        """Phase 22 on the values set: the factor held afterwards, or none if it fails."""
        self._factorised = False
        self._values.forget()
        self._call(22)
        self._values.keep(self._a)
        self._factorised = True

    def _set_values(self, matrix: sp.csr_matrix) -> np.ndarray:
        """The values of A's upper triangle in PARDISO's order (the data itself when it holds nothing else),
        passed from now on; returned."""
        if self._upper is None:
            self._a = np.ascontiguousarray(matrix.data, dtype=float)
        else:
            self._a = np.ascontiguousarray(matrix.data[self._upper], dtype=float)
        self._a_address = self._a.ctypes.data
        return self._a

    def _analyse(self) -> None:
        """Phase 11 on the current pattern: plain, or for partial solves on the marked positions.

        Always on a fresh handle: an analysed one is released first (phase -1). oneMKL's phase 11 on a handle
        it has analysed before corrupts the C heap after a marked (iparm[30] = 1), then a plain, then a
        marked analysis ("munmap_chunk(): invalid pointer", "free(): invalid size": a second run of a
        simulation, whose first step goes back to the plain analysis), even with every array kept alive."""
        self._release_handle()
        self._iparm[:] = self._iparm_input
        if self._marked is None:
            self._perm = np.zeros(1, dtype=np.int32)
        else:
            self._perm = np.zeros(self._n, dtype=np.int32)
            self._perm[self._marked] = 1
            self._iparm[30] = 1
        self._perm_address = self._perm.ctypes.data
        self._call(11)
        self.analyses += 1
        self._analysed = True
        self._iparm[30] = 0  # full solves unless a partial one asks

    def fill_reducing_order(self, matrix: sp.spmatrix) -> np.ndarray:
        """PARDISO's fill-reducing ordering of ``matrix``'s pattern (its METIS nested dissection by default):
        ``order[k]`` is the original index of the k-th pivot. A phase 11 on a handle of its own (iparm[4] = 2
        returns the permutation), released before returning; this solver's state is not touched."""
        matrix = _check_square(matrix)
        other = PardisoSolver(self.ordering)
        try:
            upper = sp.triu(matrix, format="csr")
            upper.sort_indices()
            other._n = matrix.shape[0]
            other._ia = upper.indptr.astype(np.int32)
            other._ja = upper.indices.astype(np.int32)
            other._a = np.ascontiguousarray(upper.data, dtype=float)
            other._ia_address, other._ja_address = other._ia.ctypes.data, other._ja.ctypes.data
            other._a_address = other._a.ctypes.data
            other._perm = np.zeros(other._n, dtype=np.int32)  # PARDISO writes n entries into it
            other._perm_address = other._perm.ctypes.data
            other._iparm[:] = other._iparm_input
            other._iparm[4] = 2  # return the permutation
            other._call(11)
            other._analysed = True
            # perm[k] is the original index of the k-th pivot (measured: its inverse as an ordering fills L
            # 3.5 times more on the cube)
            return other._perm.astype(np.int64)
        finally:
            other.release()

    def _unfactorised(self) -> LinearSolverError:
        """The error of a solve without a factor: never factorised, or released since."""
        if self._released:
            return LinearSolverError("pardiso: solve after release (factorise the matrix again first)")
        return LinearSolverError("pardiso: solve before factorise")

    @property
    def marked(self) -> np.ndarray | None:
        """The positions the analysis marked for :meth:`inverse_block` (sorted), or None."""
        return self._marked

    def mark(self, positions: np.ndarray | None) -> None:
        """Analyse for partial solves on ``positions`` (sorted, unique; None: a plain analysis).

        The fill-reducing ordering, hence the factor's round-off, depends on the marked positions: the
        factor and every solve are a function of (pattern, values, marked positions). When the marks change
        on a factorised matrix, it is analysed and factorised again (same values)."""
        if positions is not None:
            positions = np.asarray(positions, dtype=np.int64)
        same = (positions is None and self._marked is None) or (
            positions is not None and self._marked is not None and np.array_equal(positions, self._marked)
        )
        if same:
            return
        self._marked = None if positions is None else positions.copy()
        if self._n and self._pattern_key is not None:
            factorised = self._factorised
            self._analyse()
            if factorised:
                self._numeric()

    def inverse_block(self, positions: np.ndarray) -> np.ndarray:
        """(A⁻¹)[positions][:, positions], shape (u, u), by one partial solve (oneMKL iparm[30] = 1): the
        right-hand sides are the unit loads on ``positions`` and only the marked components of the
        solutions are computed, so the work follows the elimination tree's paths from those positions, not
        the whole factor. ``positions`` (sorted) must lie among :attr:`marked`."""
        if not self._factorised:
            raise self._unfactorised()
        positions = np.asarray(positions, dtype=np.int64)
        marked = self._marked
        if marked is None or not _all_among(positions, marked):
            raise ValueError("inverse_block: the positions must be marked first (mark)")
        count = positions.size
        if count == 0:
            return np.zeros((0, 0))
        # The (n, count) loads and solutions are kept from call to call (fresh ones cost more in page faults
        # than the partial solve's arithmetic); the loads are zero outside the unit entries, set and reset
        # here, and only the marked rows of the solutions are read.
        if self._unit_buffers is None or self._unit_buffers[0].shape != (self._n, count):
            self._unit_buffers = (
                np.zeros((self._n, count), order="F"),
                np.zeros((self._n, count), order="F"),
            )
        loads, out = self._unit_buffers
        columns = np.arange(count)
        loads[positions, columns] = 1.0
        self._iparm[30] = 1
        try:
            self._call(33, loads, out, count)
        finally:
            self._iparm[30] = 0
            loads[positions, columns] = 0.0
        return out[positions]

    def solve_marked(self, rhs: np.ndarray) -> np.ndarray:
        """A⁻¹ rhs for a rhs of shape (n,) that is zero off the :attr:`marked` positions, every component of
        the solution computed (oneMKL iparm[30] = 2: the forward substitution follows the elimination tree
        from the marked positions only, the backward one is whole). Equal to :meth:`solve` bit for bit (the
        skipped work is on zeros); about half its time on the cube's matrix."""
        if not self._factorised:
            raise self._unfactorised()
        rhs = _marked_rhs(rhs, self._n, self._marked)
        if self._marked is None:
            return self.solve(rhs)
        b = np.ascontiguousarray(rhs)
        x = np.zeros(self._n)
        self._iparm[30] = 2
        try:
            self._call(33, b, x, 1)
        finally:
            self._iparm[30] = 0
        return x

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """A⁻¹ rhs for rhs of shape (n,) or (n, k)."""
        if not self._factorised:
            raise self._unfactorised()
        rhs = np.asarray(rhs, dtype=float)
        if rhs.shape[0] != self._n:
            raise ValueError(f"rhs has {rhs.shape[0]} rows, the matrix {self._n}")
        if rhs.ndim == 2 and rhs.shape[1] == 0:
            return np.zeros_like(rhs)
        b = np.asfortranarray(rhs)
        x = np.zeros_like(b, order="F")
        self._call(33, b, x, 1 if rhs.ndim == 1 else rhs.shape[1])
        return np.ascontiguousarray(x)

    def half_solve(self, rhs: np.ndarray) -> np.ndarray:
        """The forward half of a solve, Y = L⁻¹ P rhs for A = Pᵀ L Lᵀ P (phase 331): Yᵀ Y = rhsᵀ A⁻¹ rhs.

        rhs of shape (n, k); half the work of :meth:`solve` for a compliance rhsᵀ A⁻¹ rhs.
        """
        if not self._factorised:
            raise self._unfactorised()
        rhs = np.asarray(rhs, dtype=float)
        if rhs.ndim != 2 or rhs.shape[0] != self._n:
            raise ValueError(f"rhs must have shape ({self._n}, k), got {rhs.shape}")
        if rhs.shape[1] == 0:
            return np.zeros_like(rhs)
        b = np.asfortranarray(rhs)
        y = np.zeros_like(b, order="F")
        self._call(331, b, y, rhs.shape[1])
        return np.ascontiguousarray(y)

    @property
    def factorisations(self) -> int:
        """Numeric factorisations made (a factorisation of the values held keeps the factor: not counted)."""
        return self._values.factorisations

    @property
    def description(self) -> dict:
        return {
            "name": self.name,
            "ordering": {0: "minimum degree", 2: "METIS"}.get(self.ordering, self.ordering),
        }


SUPERNODAL_ORDERINGS = ("auto", "metis", "minimum-degree")


class SupernodalSolver:
    """refsim's own supernodal Cholesky (:mod:`refsim.fem.supernodal`): analysis once per pattern, numeric
    factorisation per step in compiled loops and SciPy's BLAS / LAPACK, one thread.

    Parameters
    ----------
    ordering : The fill-reducing ordering: ``metis`` (PARDISO's METIS nested dissection, read from its
        analysis), ``minimum-degree`` (SuperLU's minimum degree of A + Aᵀ, from one SuperLU factorisation at
        the analysis), or ``auto`` (default: ``metis`` where PARDISO loads, else ``minimum-degree``).
    """

    name = "supernodal"
    storage = "upper"  # it reads A's upper triangle only (column ≥ row): full storage or the upper triangle

    def __init__(self, ordering: str = "auto") -> None:
        if ordering not in SUPERNODAL_ORDERINGS:
            raise ValueError(
                f"supernodal ordering {ordering!r}: expected one of {', '.join(SUPERNODAL_ORDERINGS)}"
            )
        if ordering == "auto":
            ordering = "metis" if _available("pardiso") else "minimum-degree"
        elif ordering == "metis":
            _pardiso_function()  # raises LinearSolverError where oneMKL does not load
        self.ordering = ordering
        self._factor = None
        self._pattern_key = None
        self._pattern_arrays = None
        self._marked = None
        self._paths = None  # (supernodes, compact, columns) of the marked positions' etree paths
        self._values = FactorisedValues()  # the values of the factor held
        self.analyses = 0  # analyses made (one per new pattern)
        self._released = False

    def release(self) -> None:
        """Forget the pattern, factor and marks (a solve afterwards raises :class:`LinearSolverError`)."""
        self._factor = None
        self._pattern_key = self._pattern_arrays = None
        self._marked = None
        self._paths = None
        self._values.forget()
        self._released = True

    def _order(self, matrix: sp.csr_matrix) -> np.ndarray:
        if self.ordering == "metis":
            return PardisoSolver().fill_reducing_order(matrix)
        # SuperLU orders while it factorises: give it the symmetric pattern as a diagonally dominant M-matrix
        # (SPD whatever A's storage)
        pattern = sp.csr_matrix((np.ones(matrix.nnz), matrix.indices, matrix.indptr), shape=matrix.shape)
        pattern = ((pattern + pattern.T) > 0).astype(float)
        pattern.setdiag(0.0)
        pattern.eliminate_zeros()
        degree = np.asarray(pattern.sum(axis=1)).ravel()
        lu = spla.splu(
            sp.csc_matrix(sp.diags(degree + 1.0) - pattern),
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
        # perm_c[i] is the position of column i
        order = np.empty(matrix.shape[0], dtype=np.int64)
        order[lu.perm_c] = np.arange(matrix.shape[0])
        return order

    def factorise(self, matrix: sp.spmatrix) -> None:
        """Factorise A (symmetric positive definite; full storage or its upper triangle alone: only the upper
        triangle is read); the analysis runs when the pattern is new. The values factorised last, bit for bit,
        keep the factor (:class:`FactorisedValues`)."""
        from refsim.fem.supernodal import NotPositiveDefinite, SymbolicFactor

        matrix = _check_square(matrix)
        last = self._pattern_arrays
        if (
            last is not None
            and _same_memory(last[0], matrix.indptr)
            and _same_memory(last[1], matrix.indices)
        ):
            key = self._pattern_key  # the very arrays of last time (see PardisoSolver.factorise)
        else:
            key = (matrix.shape[0], matrix.nnz, hash(matrix.indptr.tobytes()), hash(matrix.indices.tobytes()))
        self._pattern_arrays = (matrix.indptr, matrix.indices)
        if key != self._pattern_key or self._factor is None:
            self._factor = SymbolicFactor(matrix, self._order(matrix))
            self.analyses += 1
            self._pattern_key = key
            if self._marked is not None and self._marked.size and self._marked[-1] >= matrix.shape[0]:
                self._marked = None  # marked for another matrix
            self._paths = None
            self._values.forget()
        elif self._factor.factorised and self._values.unchanged(matrix.data):
            return  # the factor held is this matrix's, bit for bit
        try:
            self._factor.factorise(matrix.data)
        except NotPositiveDefinite as error:
            self._values.forget()
            raise LinearSolverError(f"supernodal: {error}") from None
        self._values.keep(matrix.data)
        self._released = False

    def _factorised(self):
        if self._factor is None or not self._factor.factorised:
            if self._released:
                raise LinearSolverError("supernodal: solve after release (factorise the matrix again first)")
            raise LinearSolverError("supernodal: solve before factorise")
        return self._factor

    @property
    def marked(self) -> np.ndarray | None:
        """The positions marked for :meth:`inverse_block` (sorted), or None."""
        return self._marked

    def mark(self, positions: np.ndarray | None) -> None:
        """Mark ``positions`` (sorted, unique; None: none) for partial solves. The factor does not depend on
        the marks (unlike PARDISO's): nothing is factorised again."""
        if positions is not None:
            positions = np.asarray(positions, dtype=np.int64).copy()
        self._marked = positions
        self._paths = None

    def _marked_paths(self):
        if self._paths is None:
            self._paths = self._factor.paths(self._marked)
        return self._paths

    def inverse_block(self, positions: np.ndarray) -> np.ndarray:
        """(A⁻¹)[positions][:, positions] = Yᵀ Y with Y = L⁻¹ P E (E the unit loads on ``positions``), the
        forward solves restricted to the supernodes on the elimination-tree paths from the marked positions
        (the only rows of Y that are not zero). ``positions`` (sorted) must lie among :attr:`marked`."""
        factor = self._factorised()
        positions = np.asarray(positions, dtype=np.int64)
        marked = self._marked
        if marked is None or not _all_among(positions, marked):
            raise ValueError("inverse_block: the positions must be marked first (mark)")
        if positions.size == 0:
            return np.zeros((0, 0))
        return factor.inverse_block(positions, self._marked_paths())

    def solve_marked(self, rhs: np.ndarray) -> np.ndarray:
        """A⁻¹ rhs for a rhs of shape (n,) that is zero off the :attr:`marked` positions: the forward
        substitution visits the supernodes on the marked positions' etree paths only, the backward one all.
        Equal to :meth:`solve` bit for bit (the skipped work is on zeros)."""
        factor = self._factorised()
        rhs = _marked_rhs(rhs, factor.n, self._marked)
        if self._marked is None:
            return self.solve(rhs)
        return factor.solve(rhs, self._marked_paths()[0])

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """A⁻¹ rhs for rhs of shape (n,) or (n, k)."""
        factor = self._factorised()
        rhs = np.asarray(rhs, dtype=float)
        if rhs.shape[0] != factor.n:
            raise ValueError(f"rhs has {rhs.shape[0]} rows, the matrix {factor.n}")
        if rhs.ndim == 2 and rhs.shape[1] == 0:
            return np.zeros_like(rhs)
        return factor.solve(rhs)

    def half_solve(self, rhs: np.ndarray) -> np.ndarray:
        """The forward half of a solve, Y = L⁻¹ P rhs for A = Pᵀ L Lᵀ P: Yᵀ Y = rhsᵀ A⁻¹ rhs; rhs (n, k)."""
        factor = self._factorised()
        rhs = np.asarray(rhs, dtype=float)
        if rhs.ndim != 2 or rhs.shape[0] != factor.n:
            raise ValueError(f"rhs must have shape ({factor.n}, k), got {rhs.shape}")
        if rhs.shape[1] == 0:
            return np.zeros_like(rhs)
        return factor.forward(rhs)

    @property
    def factorisations(self) -> int:
        """Numeric factorisations made (a factorisation of the values held keeps the factor: not counted)."""
        return self._values.factorisations

    @property
    def description(self) -> dict:
        described = {"name": self.name, "ordering": self.ordering}
        if self._factor is not None:
            described["supernodes"] = int(self._factor.first.size - 1)
            described["factor_entries"] = self._factor.nnz
        return described


class CholmodSolver:
    """CHOLMOD (scikit-sparse): symbolic analysis once per pattern, numeric Cholesky per step."""

    name = "cholmod"
    storage = "full"

    def __init__(self) -> None:
        try:
            from sksparse import cholmod
        except ImportError as error:  # pragma: no cover - depends on the machine
            raise LinearSolverError(f"cholmod: scikit-sparse does not import here ({error})") from None
        self._cholmod = cholmod
        self._factor = None
        self._pattern_key = None

    def factorise(self, matrix: sp.spmatrix) -> None:  # pragma: no cover - needs scikit-sparse
        csc = sp.csc_matrix(matrix)
        key = (csc.shape[0], csc.nnz, hash(csc.indptr.tobytes()), hash(csc.indices.tobytes()))
        if key != self._pattern_key or self._factor is None:
            self._factor = self._cholmod.analyze(csc)
            self._pattern_key = key
        self._factor.cholesky_inplace(csc)

    def solve(self, rhs: np.ndarray) -> np.ndarray:  # pragma: no cover - needs scikit-sparse
        return self._factor(np.asarray(rhs, dtype=float))

    @property
    def description(self) -> dict:  # pragma: no cover
        return {"name": self.name}


#: The environment variable naming oneMKL's runtime library, as pypardiso reads it.
MKL_RT_VARIABLE = "PYPARDISO_MKL_RT"


def _mkl_runtime_candidates() -> list[str]:
    """Paths of oneMKL's runtime library ``mkl_rt`` to try, in order: ``$PYPARDISO_MKL_RT``, then the
    library folders of the ``mkl`` wheel (``sys.prefix/lib``, the user base's ``lib``; ``Library/bin`` on
    Windows), then the wheel's own file list, then the system's library search (``ctypes.util.find_library``).

    Only those folders are listed, not searched recursively (pypardiso's search globs all of ``sys.prefix``:
    seconds)."""
    import glob
    import site
    import sys

    override = os.environ.get(MKL_RT_VARIABLE, "").strip()
    if override:
        return [override]
    found = []
    for base in dict.fromkeys((sys.prefix, site.USER_BASE)):
        for folder in ("lib", os.path.join("Library", "bin")):
            names = glob.glob(os.path.join(glob.escape(os.path.join(base, folder)), "*mkl_rt*"))
            found += sorted((name for name in names if _is_shared_library(name)), key=len)
    if found:
        return found
    try:
        files = importlib.metadata.files("mkl") or []
    except importlib.metadata.PackageNotFoundError:
        files = []
    found = [
        str(entry.locate()) for entry in files if "mkl_rt" in entry.name and _is_shared_library(entry.name)
    ]
    if found:
        return sorted(found, key=len)
    import ctypes.util

    system = ctypes.util.find_library("mkl_rt")
    return [system] if system else []


def _is_shared_library(name: str) -> bool:
    base = os.path.basename(name)
    return ".so" in base or base.endswith((".dll", ".dylib"))


@lru_cache(maxsize=1)
def _pardiso_function():
    """oneMKL's ``pardiso`` entry point from the ``mkl_rt`` library (:func:`_mkl_runtime_candidates`), loaded
    once per process."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        raise LinearSolverError(
            f"pardiso: oneMKL wheels exist for x86-64 only, this machine is {platform.machine()}"
        )
    candidates = _mkl_runtime_candidates()
    library, failures = None, []
    for path in candidates:
        try:
            library = ctypes.CDLL(path)
            break
        except OSError as error:
            failures.append(f"{path}: {error}")
    if library is None:
        tried = "; ".join(failures) if failures else "no file named *mkl_rt* found"
        raise LinearSolverError(
            f"pardiso: oneMKL's runtime library mkl_rt did not load ({tried}); install the mkl wheel "
            f"(pip install pypardiso) or set {MKL_RT_VARIABLE} to the library's path"
        )
    function = library.pardiso
    function.argtypes = [ctypes.c_void_p] * 16  # addresses (arrays) and byref(c_int32) (scalars)
    function.restype = None
    return function


@lru_cache(maxsize=None)
def _available(name: str) -> bool:
    try:
        _construct(name)
    except LinearSolverError:
        return False
    return True


def available_linear_solvers() -> tuple[str, ...]:
    """The backends that work on this machine, in order of preference."""
    return tuple(name for name in LINEAR_SOLVERS if _available(name))


def _construct(name: str):
    if name.startswith("superlu:"):
        return SuperLUSolver(name.split(":", 1)[1].upper())
    if name.startswith("supernodal:"):
        return SupernodalSolver(name.split(":", 1)[1].lower())
    if name == "pardiso":
        return PardisoSolver()
    if name == "supernodal":
        return SupernodalSolver()
    if name == "cholmod":
        return CholmodSolver()
    if name == "superlu":
        return SuperLUSolver()
    raise ValueError(f"linear solver {name!r}: expected one of {', '.join(LINEAR_SOLVERS)} or 'auto'")


def default_linear_solver() -> str:
    """The backend used when none is asked for: ``$REFSIM_LINEAR_SOLVER`` if set, else the first available."""
    forced = os.environ.get(ENVIRONMENT_VARIABLE, "").strip().lower()
    if forced and forced != "auto":
        if forced.split(":", 1)[0] not in LINEAR_SOLVERS:
            raise ValueError(
                f"{ENVIRONMENT_VARIABLE}={forced!r}: expected one of {', '.join(LINEAR_SOLVERS)} or 'auto'"
            )
        return forced
    return available_linear_solvers()[0]


def make_linear_solver(name: str | None = None):
    """A new solver instance of backend ``name`` ("auto" or None: :func:`default_linear_solver`).

    ``"superlu:ORDERING"`` picks SuperLU's column ordering (e.g. ``superlu:COLAMD``, refsim's former choice).

    Raises
    ------
    LinearSolverError
        When the backend asked for does not work here (the message says why).
    """
    if name is None or name == "auto":
        name = default_linear_solver()
    return _construct(name)


def _version(distribution: str) -> str | None:
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None


def linear_solver_info(name: str | None = None) -> dict:
    """The linear solver a run uses and the versions behind it, for the results file's attributes.

    Parameters
    ----------
    name : The backend asked for (a scene's ``compliance.linear_solver``); "auto" or None for the default.

    Returns
    -------
    ``{"linear_solver": ..., "requested": ..., "environment": $REFSIM_LINEAR_SOLVER or "", "available": [...],
    "scipy": ..., "pypardiso": ..., "mkl": ..., "scikit-sparse": ..., "superlu_ordering": ...}`` (versions are
    None when not installed).
    """
    chosen = default_linear_solver() if name in (None, "auto") else name
    return {
        "linear_solver": chosen,
        "requested": name or "auto",
        "environment": os.environ.get(ENVIRONMENT_VARIABLE, ""),
        "available": list(available_linear_solvers()),
        "superlu_ordering": DEFAULT_SUPERLU_ORDERING,
        "scipy": _version("scipy"),
        "pypardiso": _version("pypardiso"),
        "mkl": _version("mkl"),
        "scikit-sparse": _version("scikit-sparse"),
        "machine": platform.machine(),
    }
