"""Sparse symmetric positive definite solvers: PARDISO, refsim's supernodal Cholesky, CHOLMOD or SuperLU
(layer 2).

Every body's effective stiffness A = M/dt² + C/dt + K keeps one sparsity pattern for a whole run (the free
DoFs of a fixed mesh), so a solver is made **for a pattern**: the symbolic analysis (fill-reducing ordering,
elimination tree) is done once, and each step only refactorises numerically.

Backends, in the order of :func:`default_linear_solver`:

``"pardiso"``
    Intel oneMKL PARDISO (x86-64 only), called through ctypes in oneMKL's runtime library ``mkl_rt``, which
    the ``mkl`` wheel installs (the ``pypardiso`` dependency brings it; refsim does not import pypardiso,
    whose import searches all of ``sys.prefix`` for the library: :mod:`refsim.fem.pardiso`): real SPD
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

import importlib.metadata
import os
import platform
from functools import lru_cache

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from refsim.fem.linear_common import (
    FactorisedValues,
    KeepsFactor,
    LinearSolverError,
    _all_among,
    _check_square,
    _marked_rhs,
)
from refsim.fem.pardiso import MKL_RT_VARIABLE, PardisoSolver, _pardiso_function

__all__ = [
    "LINEAR_SOLVERS",
    "ENVIRONMENT_VARIABLE",
    "LinearSolverError",
    "FactorisedValues",
    "MKL_RT_VARIABLE",
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


class SuperLUSolver(KeepsFactor):
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
    def description(self) -> dict:
        return {"name": self.name, "ordering": self.ordering}


SUPERNODAL_ORDERINGS = ("auto", "metis", "minimum-degree")


class SupernodalSolver(KeepsFactor):
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
        key = self._pattern(matrix)
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


def _construct(name: str, precision: str = "double"):
    if precision not in ("double", "single"):
        raise ValueError(f"precision {precision!r}: expected 'double' or 'single'")
    if name.startswith("superlu:"):
        return SuperLUSolver(name.split(":", 1)[1].upper())
    if name.startswith("supernodal:"):
        return SupernodalSolver(name.split(":", 1)[1].lower())
    if name == "pardiso":
        return PardisoSolver(precision=precision)
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


def make_linear_solver(name: str | None = None, *, precision: str = "double"):
    """A new solver instance of backend ``name`` ("auto" or None: :func:`default_linear_solver`).

    ``precision="single"``: a factor in float32 where the backend has one (PARDISO; the others factorise in
    double precision whatever is asked), for a factor used as a preconditioner or an approximation whose own
    error is far above float32's round-off (the fast mode's rest factor). Values and solutions are float64.

    ``"superlu:ORDERING"`` picks SuperLU's column ordering (e.g. ``superlu:COLAMD``, refsim's former choice).

    Raises
    ------
    LinearSolverError
        When the backend asked for does not work here (the message says why).
    """
    if name is None or name == "auto":
        name = default_linear_solver()
    return _construct(name, precision)


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
