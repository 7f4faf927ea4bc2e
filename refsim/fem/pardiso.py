"""oneMKL PARDISO through ctypes (x86-64): its runtime library located and loaded once per process
(:func:`_pardiso_function`), and :class:`PardisoSolver`, real SPD (mtype 2), upper triangle, zero-based.
Phase 11 (analysis) once per pattern and set of partial-solve marks, phase 22 (numeric Cholesky) per step,
phase 33 (solve) per right-hand side block. Chosen and made through :mod:`refsim.fem.linear`."""

from __future__ import annotations

import ctypes
import importlib.metadata
import os
import platform
from functools import lru_cache

import numpy as np
import scipy.sparse as sp

from refsim.fem.linear_common import (
    FactorisedValues,
    KeepsFactor,
    LinearSolverError,
    _all_among,
    _check_square,
    _marked_rhs,
)

__all__ = ["MKL_RT_VARIABLE", "PardisoSolver"]


_ONE, _ZERO = ctypes.c_int32(1), ctypes.c_int32(0)
_MTYPE_SPD = ctypes.c_int32(2)  # PARDISO's matrix type: real symmetric positive definite
_UNUSED = np.zeros(1)  # what an unused array argument points to


class PardisoSolver(KeepsFactor):
    """oneMKL PARDISO, real symmetric positive definite: analysis once per pattern, numeric refactorisation
    per step.

    Parameters
    ----------
    ordering : PARDISO's fill-in reducing ordering, iparm[1]: 0 minimum degree, 2 METIS nested dissection.
    precision : "double", or "single" (iparm[27] = 1): the factor and the solves in float32, half the bytes a
        solve reads, each solution to about κ(A) · 6e-8 relative; the values given and the solutions returned
        are float64 either way.
    """

    name = "pardiso"
    storage = "upper"  # it reads A's upper triangle only: full storage or the upper triangle alone will do

    def __init__(self, ordering: int = 2, precision: str = "double") -> None:
        if precision not in ("double", "single"):
            raise ValueError(f"precision {precision!r}: expected 'double' or 'single'")
        self._pardiso = _pardiso_function()
        self.ordering = int(ordering)
        self.precision = precision
        self._dtype = np.float32 if precision == "single" else np.float64  # of the factor, loads, solutions
        self._pt = np.zeros(64, dtype=np.int64)
        self._iparm = np.zeros(64, dtype=np.int32)
        self._iparm[0] = 1  # we supply the parameters
        self._iparm[1] = self.ordering
        self._iparm[7] = 0  # no iterative refinement
        self._iparm[9] = 13  # pivot perturbation 1e-13 (not used for SPD)
        self._iparm[17] = -1  # report nnz(L)
        self._iparm[27] = 1 if precision == "single" else 0
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
        key = self._pattern(matrix)
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
            self._a = np.ascontiguousarray(matrix.data, dtype=self._dtype)
        else:
            self._a = np.ascontiguousarray(matrix.data[self._upper], dtype=self._dtype)
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
                np.zeros((self._n, count), dtype=self._dtype, order="F"),
                np.zeros((self._n, count), dtype=self._dtype, order="F"),
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
        return out[positions].astype(float, copy=False)

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
        b = np.ascontiguousarray(rhs, dtype=self._dtype)
        x = np.zeros(self._n, dtype=self._dtype)
        self._iparm[30] = 2
        try:
            self._call(33, b, x, 1)
        finally:
            self._iparm[30] = 0
        return x.astype(float, copy=False)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """A⁻¹ rhs for rhs of shape (n,) or (n, k)."""
        if not self._factorised:
            raise self._unfactorised()
        rhs = np.asarray(rhs, dtype=float)
        if rhs.shape[0] != self._n:
            raise ValueError(f"rhs has {rhs.shape[0]} rows, the matrix {self._n}")
        if rhs.ndim == 2 and rhs.shape[1] == 0:
            return np.zeros_like(rhs)
        b = np.asfortranarray(rhs, dtype=self._dtype)
        x = np.zeros_like(b, order="F")
        self._call(33, b, x, 1 if rhs.ndim == 1 else rhs.shape[1])
        return np.ascontiguousarray(x, dtype=float)

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
        b = np.asfortranarray(rhs, dtype=self._dtype)
        y = np.zeros_like(b, order="F")
        self._call(331, b, y, rhs.shape[1])
        return np.ascontiguousarray(y, dtype=float)

    @property
    def description(self) -> dict:
        return {
            "name": self.name,
            "ordering": {0: "minimum degree", 2: "METIS"}.get(self.ordering, self.ordering),
            "precision": self.precision,
        }


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
