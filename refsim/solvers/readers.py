"""Readers of external problem files (Siconos ``.dat`` and FCLib ``.hdf5``) into :class:`ConstraintProblem`.

Formats as documented in ``shared/data/solver-problems/README.md`` (Siconos numerics test data and FCLib's
``fclib_local`` and ``fclib_global`` groups). Siconos' u = W r + q maps to δ = W λ + δ_free with the same
signs: Siconos' LCP rows are unilateral rows, equality rows bilateral, relay rows box rows, and 3-D friction
contacts are contacts (rows normal, tangent 1, tangent 2). Every error names the file and what was expected.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from refsim.solvers.problem import ConstraintProblem

__all__ = ["PROBLEM_KINDS", "condense_global", "read_fclib", "read_problem", "read_siconos"]

#: Problem kinds the readers understand (the folder names of the shared data set).
PROBLEM_KINDS = ("lcp", "mlcp", "relay", "fc3d", "gmp", "fclib")


class _Tokens:
    """Whitespace-separated tokens of a Siconos text file, read in order."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self.tokens = path.read_text(errors="replace").split()
        except OSError as error:
            raise ValueError(f"{path}: cannot read the file ({error})") from error
        self.position = 0

    def _next(self, what: str) -> str:
        if self.position >= len(self.tokens):
            raise ValueError(f"{self.path}: file ends while reading {what} (token {self.position})")
        token = self.tokens[self.position]
        self.position += 1
        return token

    def integer(self, what: str) -> int:
        token = self._next(what)
        try:
            return int(token)
        except ValueError:
            raise ValueError(
                f"{self.path}: expected an integer for {what} at token {self.position - 1}, got {token!r}"
            ) from None

    def integers(self, count: int, what: str) -> np.ndarray:
        return np.array([self.integer(what) for _ in range(count)], dtype=np.int64)

    def floats(self, count: int, what: str) -> np.ndarray:
        end = self.position + count
        if end > len(self.tokens):
            raise ValueError(
                f"{self.path}: file ends while reading {what} ({count} values expected, "
                f"{len(self.tokens) - self.position} left)"
            )
        try:
            values = np.array([float(t) for t in self.tokens[self.position : end]], dtype=np.float64)
        except ValueError as error:
            raise ValueError(f"{self.path}: bad number in {what}: {error}") from None
        self.position = end
        return values

    def matrix(self, what: str) -> np.ndarray:
        """A Siconos NumericsMatrix: dense (0) or sparse block (1)."""
        storage = self.integer(f"{what} storage type")
        rows = self.integer(f"{what} size0")
        cols = self.integer(f"{what} size1")
        if storage == 0:
            rows2 = self.integer(f"{what} dense size0")
            cols2 = self.integer(f"{what} dense size1")
            if (rows2, cols2) != (rows, cols):
                raise ValueError(f"{self.path}: {what} sizes disagree ({rows}x{cols} then {rows2}x{cols2})")
            return self.floats(rows * cols, f"{what} values").reshape(cols, rows).T.copy()
        if storage == 1:
            return self._block_matrix(rows, cols, what)
        raise ValueError(
            f"{self.path}: {what} storage type {storage} is not supported (0 dense, 1 sparse block)"
        )

    def _block_matrix(self, rows: int, cols: int, what: str) -> np.ndarray:
        self.integer(f"{what} nbblocks")
        block_rows = self.integer(f"{what} blocknumber0")
        block_cols = self.integer(f"{what} blocknumber1")
        row_ends = self.integers(block_rows, f"{what} row block sizes")
        col_ends = self.integers(block_cols, f"{what} column block sizes")
        filled1 = self.integer(f"{what} filled1")
        filled2 = self.integer(f"{what} filled2")
        row_pointers = self.integers(filled1, f"{what} index1_data")
        column_indices = self.integers(filled2, f"{what} index2_data")
        if row_ends[-1] != rows or col_ends[-1] != cols:
            raise ValueError(
                f"{self.path}: {what} block sizes end at {row_ends[-1]}x{col_ends[-1]}, "
                f"matrix is {rows}x{cols}"
            )
        row_starts = np.concatenate([[0], row_ends[:-1]])
        col_starts = np.concatenate([[0], col_ends[:-1]])
        dense = np.zeros((rows, cols))
        for block_row in range(block_rows):  # file parsing, not a hot path
            for entry in range(row_pointers[block_row], row_pointers[block_row + 1]):
                block_col = column_indices[entry]
                self.integer(f"{what} block number")
                height = row_ends[block_row] - row_starts[block_row]
                width = col_ends[block_col] - col_starts[block_col]
                values = self.floats(height * width, f"{what} block {entry}").reshape(width, height).T
                dense[
                    row_starts[block_row] : row_ends[block_row], col_starts[block_col] : col_ends[block_col]
                ] = values
        self.row_block_sizes = np.diff(np.concatenate([[0], row_ends]))
        return dense


def _lcp(tokens: _Tokens, name: str) -> ConstraintProblem:
    n = tokens.integer("n")
    matrix = tokens.matrix("M")
    vector = tokens.floats(n, "q")
    return ConstraintProblem(compliance=matrix, free_gap=vector, unilateral=np.arange(n), name=name)


def _fc3d(tokens: _Tokens, name: str) -> ConstraintProblem:
    dimension = tokens.integer("d")
    if dimension != 3:
        raise ValueError(
            f"{tokens.path}: friction problems of dimension {dimension} are not supported (3 only)"
        )
    contact_count = tokens.integer("nc")
    matrix = tokens.matrix("W")
    vector = tokens.floats(3 * contact_count, "q")
    friction = tokens.floats(contact_count, "mu")
    return ConstraintProblem(
        compliance=matrix,
        free_gap=vector,
        contacts=np.arange(3 * contact_count).reshape(-1, 3),
        contact_friction=friction,
        name=name,
    )


def _mlcp(tokens: _Tokens, name: str) -> ConstraintProblem:
    tokens.integer("isStorageType1")
    tokens.integer("isStorageType2")
    equalities = tokens.integer("n")
    complementarities = tokens.integer("m")
    total = equalities + complementarities
    block_rows = [tokens.integer("blocksRows")]
    while block_rows[-1] != total:
        block_rows.append(tokens.integer("blocksRows"))
        if len(block_rows) > total + 1:
            raise ValueError(f"{tokens.path}: blocksRows never reaches n+m = {total}")
    tokens.integers(len(block_rows) - 1, "blocksIsComp")
    matrix = tokens.matrix("M")
    if matrix.shape != (total, total):
        raise ValueError(f"{tokens.path}: M has shape {matrix.shape}, expected ({total}, {total})")
    vector = tokens.floats(total, "q")
    return ConstraintProblem(
        compliance=matrix,
        free_gap=vector,
        bilateral=np.arange(equalities),
        unilateral=np.arange(equalities, total),
        name=name,
    )


def _relay(tokens: _Tokens, name: str) -> ConstraintProblem:
    n = tokens.integer("n")
    matrix = tokens.matrix("M")
    vector = tokens.floats(n, "q")
    lower = tokens.floats(n, "lb")
    upper = tokens.floats(n, "ub")
    return ConstraintProblem(
        compliance=matrix, free_gap=vector, box_rows=np.arange(n), box_lower=lower, box_upper=upper, name=name
    )


def _gmp(tokens: _Tokens, name: str) -> ConstraintProblem:
    matrix = tokens.matrix("M")
    sizes = getattr(tokens, "row_block_sizes", np.array([matrix.shape[0]]))
    vector = tokens.floats(matrix.shape[0], "q")
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    kinds: dict[str, list] = {"bilateral": [], "unilateral": [], "contacts": [], "friction": []}
    for start, size in zip(starts, sizes, strict=True):
        block_type = tokens.integer("problem type")
        rows = np.arange(start, start + size)
        if block_type == 0:
            kinds["unilateral"].append(rows)
        elif block_type == 2:
            kinds["bilateral"].append(rows)
        elif block_type == 4:
            if size != 3:
                raise ValueError(f"{tokens.path}: FC3D block of size {size}, expected 3")
            kinds["contacts"].append(rows)
            kinds["friction"].append(tokens.floats(1, "mu")[0])
        else:
            raise ValueError(
                f"{tokens.path}: generic mechanical block type {block_type} is not supported "
                "(0 LCP, 2 EQUALITY, 4 FC3D are)"
            )

    def stack(key):
        return np.concatenate(kinds[key]) if kinds[key] else np.zeros(0, dtype=np.int64)

    contacts = np.array(kinds["contacts"], dtype=np.int64).reshape(-1, 3)
    return ConstraintProblem(
        compliance=matrix,
        free_gap=vector,
        bilateral=stack("bilateral"),
        unilateral=stack("unilateral"),
        contacts=contacts,
        contact_friction=np.array(kinds["friction"]),
        name=name,
    )


_SICONOS = {"lcp": _lcp, "fc3d": _fc3d, "mlcp": _mlcp, "relay": _relay, "gmp": _gmp}


def read_siconos(path: str | Path, kind: str) -> ConstraintProblem:
    """Read a Siconos numerics ``.dat`` test problem.

    Parameters
    ----------
    path : File path.
    kind : One of ``"lcp"``, ``"mlcp"``, ``"relay"``, ``"fc3d"``, ``"gmp"`` (the format is not
        self-describing).

    Returns
    -------
    The problem, named after the file.
    """
    path = Path(path)
    if kind not in _SICONOS:
        raise ValueError(f"{path}: kind {kind!r} is not a Siconos kind; valid: {', '.join(_SICONOS)}")
    tokens = _Tokens(path)
    try:
        return _SICONOS[kind](tokens, path.stem)
    except ValueError as error:
        if str(path) in str(error):
            raise
        raise ValueError(f"{path}: {error}") from None


def _fclib_matrix(group, path: Path, name: str):
    """An FCLib matrix group (m, n, nz, p, i, x) as a scipy sparse matrix."""
    import scipy.sparse as sparse

    try:
        matrix_group = group[name]
        rows, cols = int(np.ravel(matrix_group["m"][()])[0]), int(np.ravel(matrix_group["n"][()])[0])
        storage = int(np.ravel(matrix_group["nz"][()])[0])
        pointers = np.ravel(matrix_group["p"][()])
        indices = np.ravel(matrix_group["i"][()])
        values = np.ravel(matrix_group["x"][()])
    except KeyError as error:
        raise ValueError(f"{path}: FCLib matrix {group.name}/{name} is incomplete ({error})") from None
    if storage == -1:
        return sparse.csc_matrix((values, indices, pointers), shape=(rows, cols))
    if storage == -2:
        return sparse.csr_matrix((values, indices, pointers), shape=(rows, cols))
    if storage >= 0:
        return sparse.coo_matrix(
            (values[:storage], (indices[:storage], pointers[:storage])), shape=(rows, cols)
        )
    raise ValueError(
        f"{path}: {group.name}/{name}/nz = {storage} is not a known storage (-2 CSR, -1 CSC, >= 0 triplet)"
    )


def condense_global(
    mass,
    contact_operator,
    force,
    contact_offset,
    friction,
    *,
    equality_operator=None,
    equality_offset=None,
    name: str = "",
) -> ConstraintProblem:
    """The local (condensed) problem of FCLib's global frictional contact problem.

    FCLib's global form: M v = H r + G λ + f, Gᵀ v + b = 0, u = Hᵀ v + w with the Coulomb law on (u, r) per
    contact. With B = [H G] and x = (r, λ), v = M⁻¹ (B x + f) and δ = Bᵀ M⁻¹ B x + Bᵀ M⁻¹ f + (w, b): the
    compliance W = Bᵀ M⁻¹ B, the free gap Bᵀ M⁻¹ f + (w, b); the contact rows come first (three per contact),
    then one bilateral row per column of G. M⁻¹ B is computed by a sparse LU of M.

    Parameters
    ----------
    mass : M, shape (n, n), symmetric positive definite (dense or scipy sparse).
    contact_operator : H, shape (n, 3 k).
    force : f, shape (n,).
    contact_offset : w, shape (3 k,).
    friction : μ, shape (k,).
    equality_operator : G, shape (n, p), or None.
    equality_offset : b, shape (p,), or None.
    name : Problem name.
    """
    import scipy.sparse as sparse
    import scipy.sparse.linalg as sparse_linalg

    mass = sparse.csc_matrix(mass)
    operator = sparse.csc_matrix(contact_operator)
    offset = np.asarray(contact_offset, dtype=float).reshape(-1)
    equality_count = 0
    if equality_operator is not None:
        equality = sparse.csc_matrix(equality_operator)
        equality_count = equality.shape[1]
        operator = sparse.hstack([operator, equality]).tocsc()
        offset = np.concatenate([offset, np.asarray(equality_offset, dtype=float).reshape(-1)])
    n = mass.shape[0]
    if mass.shape != (n, n) or operator.shape[0] != n:
        raise ValueError(
            f"{name or 'global problem'}: M has shape {mass.shape} and H {operator.shape}; expected "
            "M (n, n) and H with n rows"
        )
    try:
        factor = sparse_linalg.splu(mass)
    except RuntimeError as error:
        raise ValueError(f"{name or 'global problem'}: M cannot be factorised ({error})") from None
    solved = factor.solve(operator.toarray())
    compliance = operator.T @ solved
    free_gap = operator.T @ factor.solve(np.asarray(force, dtype=float)) + offset
    contact_rows = operator.shape[1] - equality_count
    return ConstraintProblem(
        compliance=np.asarray(compliance),
        free_gap=np.asarray(free_gap).reshape(-1),
        contacts=np.arange(contact_rows).reshape(-1, 3),
        contact_friction=np.asarray(friction, dtype=float),
        bilateral=np.arange(contact_rows, contact_rows + equality_count),
        name=name,
    )


def read_fclib(path: str | Path) -> ConstraintProblem:
    """Read an FCLib HDF5 file (3-D frictional contact): the ``/fclib_local`` problem, or else the
    ``/fclib_global`` one condensed by :func:`condense_global`.

    Parameters
    ----------
    path : File path.

    Returns
    -------
    The problem (contacts, and bilateral rows for a global problem's G), named after the file.
    """
    import h5py

    path = Path(path)
    try:
        handle = h5py.File(path, "r")
    except OSError as error:
        raise ValueError(f"{path}: not a readable HDF5 file ({error})") from None
    with handle:
        kind = (
            "fclib_local" if "fclib_local" in handle else "fclib_global" if "fclib_global" in handle else None
        )
        if kind is None:
            raise ValueError(
                f"{path}: neither /fclib_local nor /fclib_global is in the file (groups: {', '.join(handle)})"
            )
        group = handle[kind]
        try:
            dimension = int(np.ravel(group["spacedim"][()])[0])
            vectors = group["vectors"]
            friction = np.ravel(vectors["mu"][()])
            if kind == "fclib_local":
                matrix = _fclib_matrix(group, path, "W")
                vector = np.ravel(vectors["q"][()])
            else:
                mass = _fclib_matrix(group, path, "M")
                contact_operator = _fclib_matrix(group, path, "H")
                force = np.ravel(vectors["f"][()])
                contact_offset = np.ravel(vectors["w"][()])
                equality = _fclib_matrix(group, path, "G") if "G" in group else None
                equality_offset = np.ravel(vectors["b"][()]) if equality is not None else None
        except KeyError as error:
            raise ValueError(f"{path}: not a readable FCLib {kind[6:]} problem ({error})") from None
    if dimension != 3:
        raise ValueError(f"{path}: spacedim {dimension} is not supported (3 only)")
    if kind == "fclib_global":
        return condense_global(
            mass,
            contact_operator,
            force,
            contact_offset,
            friction,
            equality_operator=equality,
            equality_offset=equality_offset,
            name=path.stem,
        )
    contact_count = friction.size
    return ConstraintProblem(
        compliance=matrix.toarray(),
        free_gap=vector,
        contacts=np.arange(3 * contact_count).reshape(-1, 3),
        contact_friction=friction,
        name=path.stem,
    )


def read_problem(path: str | Path, kind: str | None = None) -> ConstraintProblem:
    """Read any supported problem file; ``kind`` is inferred from the suffix or folder name when None.

    ``.hdf5`` files are read as FCLib; ``.dat`` files need their Siconos kind, inferred from the name of the
    folder holding them (lcp, mlcp, relay, fc3d, gmp) as in the shared data set.
    """
    path = Path(path)
    if kind is None:
        if path.suffix == ".hdf5":
            kind = "fclib"
        elif path.parent.name in _SICONOS:
            kind = path.parent.name
        else:
            raise ValueError(f"{path}: cannot infer the problem kind; pass kind= one of {PROBLEM_KINDS}")
    if kind == "fclib":
        return read_fclib(path)
    return read_siconos(path, kind)
