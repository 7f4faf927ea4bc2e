"""What refsim's sparse SPD solvers share (:mod:`refsim.fem.linear`, :mod:`refsim.fem.pardiso`): their error,
the checks of a matrix and of a partial solve's right-hand side, and the copy of the values a factor was made
from (:class:`FactorisedValues`)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = ["FactorisedValues", "KeepsFactor", "LinearSolverError"]


class LinearSolverError(RuntimeError):
    """A linear solver is not available here or failed (the message names which and why)."""


def _check_square(matrix: sp.spmatrix) -> sp.csr_matrix:
    matrix = sp.csr_matrix(matrix)
    if matrix.shape[0] != matrix.shape[1] or matrix.shape[0] == 0:
        raise ValueError(f"matrix must be square and non-empty, got shape {matrix.shape}")
    matrix.sort_indices()
    return matrix


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


class KeepsFactor:
    """What a solver holding its values in ``self._values`` (:class:`FactorisedValues`) reports of them."""

    _values: FactorisedValues
    _pattern_key: tuple | None
    _pattern_arrays: tuple | None

    @property
    def factorisations(self) -> int:
        """Numeric factorisations made (a factorisation of the values held keeps the factor: not counted)."""
        return self._values.factorisations

    def _pattern(self, matrix: sp.spmatrix) -> tuple:
        """The key of ``matrix``'s sparsity pattern (size, non-zeros, digests of its index arrays), compared
        with ``self._pattern_key`` of the last analysis: taken from it, without the digests, when ``matrix``
        holds the very index arrays of last time (one FreePattern per run; SciPy hands out views of them, and
        they are held in ``self._pattern_arrays``, so that their memory cannot be recycled)."""
        last = self._pattern_arrays
        same = last is not None and _same_memory(last[0], matrix.indptr)
        if same and _same_memory(last[1], matrix.indices):
            key = self._pattern_key
        else:
            key = (matrix.shape[0], matrix.nnz, hash(matrix.indptr.tobytes()), hash(matrix.indices.tobytes()))
        self._pattern_arrays = (matrix.indptr, matrix.indices)
        return key


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
