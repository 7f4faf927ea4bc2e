"""A supernodal sparse Cholesky factorisation A = Pᵀ L Lᵀ P of our own (layer 2): symbolic analysis once per
pattern, a numeric factorisation per step made of compiled loops and dense BLAS / LAPACK calls.

The dense work (``dpotrf``, ``dtrsm``, ``dsyrk``) runs in the BLAS and LAPACK that SciPy ships
(scipy-openblas, whose kernels are chosen for the processor at run time): their addresses come from
``scipy.linalg.cython_blas`` / ``cython_lapack`` and are called from numba kernels by symbol name (so that the
kernels can be cached). Every argument of those Fortran routines is a pointer; the kernels pass the addresses
as machine integers (``intp``), which the C calling conventions of the platforms numba runs on pass like
pointers.

**Symbolic phase** (:class:`SymbolicFactor`, once per pattern): a fill-reducing ordering given by the caller
(PARDISO's METIS ordering, or SuperLU's minimum degree of A + Aᵀ: :func:`refsim.fem.linear`), the elimination
tree and its postorder, the column counts of L (row subtrees: the pattern of row k of L is the set of etree
nodes reached from A's entries of row k), fundamental supernodes merged with their parent when the explicit
zeros this adds stay few (relaxed amalgamation), each supernode's row structure, and the maps the numeric
phase scatters through: from A's stored upper-triangle entries to the supernodal blocks, and from each
supernode's update matrix to the rows of the supernodes it updates.

**Numeric phase** (:meth:`SymbolicFactor.factorise`): right-looking supernodal: for each supernode in order
(a topological order of the supernodal tree), ``dpotrf`` on its diagonal block, ``dtrsm`` on the rows below,
``dsyrk`` of those rows into a dense update matrix, scattered (subtracted) into the supernodes of its columns.
No allocation: L's values, the update workspace and the BLAS argument cells are allocated by the analysis.

**Solves**: forward and backward substitution by supernode columns; the forward half alone (Y = L⁻¹ P B, so
that Bᵀ A⁻¹ B = Yᵀ Y); and, for a set of marked positions, forward solves restricted to the supernodes on the
elimination-tree paths from those positions to the root (the only ones a unit load on them reaches), which
give the block (A⁻¹)[marked][:, marked] = Yᵀ Y and a solve of a right-hand side that is zero off the marked
positions (bit for bit the full solve: the skipped work is on zeros).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from refsim.kernel_cache import numba

__all__ = ["SymbolicFactor", "NotPositiveDefinite", "RELAXATION"]


class NotPositiveDefinite(ArithmeticError):
    """The numeric factorisation met a non-positive pivot (the matrix is not SPD to working precision)."""


def _bind_blas():
    """Register the addresses of SciPy's BLAS / LAPACK routines as symbols the kernels call by name."""
    import llvmlite.binding as llvm
    from numba import types
    from numba.extending import get_cython_function_address

    address = types.intp
    routines = {
        "dpotrf": ("scipy.linalg.cython_lapack", 5),
        "dtrsm": ("scipy.linalg.cython_blas", 11),
        "dsyrk": ("scipy.linalg.cython_blas", 10),
        "dgemm": ("scipy.linalg.cython_blas", 13),
    }
    functions = {}
    for name, (module, arguments) in routines.items():
        symbol = f"refsim_scipy_{name}"
        llvm.add_symbol(symbol, get_cython_function_address(module, name))
        functions[name] = types.ExternalFunction(symbol, types.void(*([address] * arguments)))
    return functions


_BLAS = _bind_blas()
_dpotrf, _dtrsm, _dsyrk, _dgemm = _BLAS["dpotrf"], _BLAS["dtrsm"], _BLAS["dsyrk"], _BLAS["dgemm"]

#: Relaxed amalgamation: a child supernode is merged into its parent when the merged supernode has at most
#: ``columns`` columns and its explicit zeros are at most ``fraction`` of its entries; (columns, fraction)
#: pairs, tried in order (CHOLMOD's defaults: 4 columns any, 16 columns 80 %, 48 columns 10 %, then 5 %).
RELAXATION = ((4, 1.0), (16, 0.8), (48, 0.1), (np.inf, 0.05))

# Characters and scalars the BLAS calls read through pointers (cells of the factor's argument arrays).
_LOWER, _RIGHT, _TRANSPOSE, _NON_UNIT, _LEFT = (ord(c) for c in "LRTNL")


# ---------------------------------------------------------------------------------------------- symbolic


@numba.njit(cache=True)
def _elimination_tree(n, column_start, row_index):
    """Parent of each column in the elimination tree of a symmetric pattern given by its upper triangle in
    CSC (column j lists rows i < j); -1 at a root (Liu's algorithm with path compression)."""
    parent = np.full(n, -1, np.int64)
    ancestor = np.full(n, -1, np.int64)
    for j in range(n):
        for p in range(column_start[j], column_start[j + 1]):
            i = row_index[p]
            while i != -1 and i < j:
                following = ancestor[i]
                ancestor[i] = j
                if following == -1:
                    parent[i] = j
                    break
                i = following
    return parent


@numba.njit(cache=True)
def _postorder(parent):
    """A postorder of the forest ``parent`` (children in increasing order): order[k] is the k-th node."""
    n = parent.size
    head = np.full(n, -1, np.int64)
    following = np.full(n, -1, np.int64)
    for j in range(n - 1, -1, -1):
        if parent[j] != -1:
            following[j] = head[parent[j]]
            head[parent[j]] = j
    order = np.empty(n, np.int64)
    stack = np.empty(n, np.int64)
    k = 0
    for root in range(n):
        if parent[root] != -1:
            continue
        top = 0
        stack[0] = root
        while top >= 0:
            node = stack[top]
            child = head[node]
            if child == -1:
                top -= 1
                order[k] = node
                k += 1
            else:
                head[node] = following[child]
                top += 1
                stack[top] = child
    return order


@numba.njit(cache=True)
def _column_counts(n, column_start, row_index, parent):
    """nnz of each column of L, diagonal included: row k of L is the set of etree nodes reached by climbing
    from each i < k of column k of the upper pattern, stopping at nodes already reached for row k."""
    counts = np.ones(n, np.int64)
    flag = np.full(n, -1, np.int64)
    for k in range(n):
        flag[k] = k
        for p in range(column_start[k], column_start[k + 1]):
            i = row_index[p]
            while i != -1 and i < k and flag[i] != k:
                counts[i] += 1
                flag[i] = k
                i = parent[i]
    return counts


@numba.njit(cache=True)
def _fundamental_supernodes(parent, counts):
    """Supernode of each column: j + 1 joins j's supernode when it is j's parent, j is its only child and
    their columns of L have the same pattern below j + 1 (fundamental supernodes; columns postordered)."""
    n = parent.size
    children = np.zeros(n, np.int64)
    for j in range(n):
        if parent[j] != -1:
            children[parent[j]] += 1
    supernode = np.empty(n, np.int64)
    s = -1
    for j in range(n):
        if j > 0 and parent[j - 1] == j and children[j] == 1 and counts[j - 1] == counts[j] + 1:
            supernode[j] = s
        else:
            s += 1
            supernode[j] = s
    return supernode


@numba.njit(cache=True)
def _supernode_rows(n, count, first, supernode, parent, column_start, row_index):
    """Row structure of each supernode (its own columns first, then the rows below in increasing order):
    the union of the pattern of A below its columns and of its children's rows below it. Returns (row_start,
    rows)."""
    capacity = 4 * n + 16
    rows = np.empty(capacity, np.int64)
    row_start = np.zeros(count + 1, np.int64)
    flag = np.full(n, -1, np.int64)
    # children of each supernode, as a linked list
    head = np.full(count, -1, np.int64)
    following = np.full(count, -1, np.int64)
    for s in range(count):
        last = first[s + 1] - 1
        if parent[last] != -1:
            p = supernode[parent[last]]
            following[s] = head[p]
            head[p] = s
    # the lower pattern of A by columns is the upper by rows: A's rows i > last in column j (j in s) are
    # the columns i > j of row j in the upper CSC's transpose; walk the upper CSC columns instead: column
    # i lists rows j < i, i.e. entries (i, j) of the lower triangle
    lower_start = np.zeros(n + 1, np.int64)
    for i in range(n):
        for p in range(column_start[i], column_start[i + 1]):
            j = row_index[p]
            if j < i:
                lower_start[j + 1] += 1
    for j in range(n):
        lower_start[j + 1] += lower_start[j]
    fill = lower_start[:-1].copy()
    lower_rows = np.empty(lower_start[n], np.int64)
    for i in range(n):
        for p in range(column_start[i], column_start[i + 1]):
            j = row_index[p]
            if j < i:
                lower_rows[fill[j]] = i
                fill[j] += 1
    position = 0
    for s in range(count):
        f, last = first[s], first[s + 1] - 1
        width = last - f + 1
        start = position
        needed = position + width
        for j in range(f, last + 1):
            needed += lower_start[j + 1] - lower_start[j]
        c = head[s]
        while c != -1:
            needed += row_start[c + 1] - row_start[c]
            c = following[c]
        if needed > capacity:
            capacity = max(2 * capacity, needed)
            grown = np.empty(capacity, np.int64)
            grown[:position] = rows[:position]
            rows = grown
        for j in range(f, last + 1):
            rows[position] = j
            flag[j] = s
            position += 1
        for j in range(f, last + 1):
            for p in range(lower_start[j], lower_start[j + 1]):
                i = lower_rows[p]
                if flag[i] != s:
                    flag[i] = s
                    rows[position] = i
                    position += 1
        c = head[s]
        while c != -1:
            for p in range(row_start[c], row_start[c + 1]):
                i = rows[p]
                if i > last and flag[i] != s:
                    flag[i] = s
                    rows[position] = i
                    position += 1
            c = following[c]
        rows[start + width : position] = np.sort(rows[start + width : position])
        row_start[s + 1] = position
    return row_start, rows[:position].copy()


@numba.njit(cache=True)
def _update_maps(count, first, supernode, row_start, rows, value_start):
    """For each supernode s, the groups of its rows below by the supernode t they fall in: (t, k0, k1, start)
    with rows below k0..k1-1 among t's columns, and relative[start + r - k0] the position in t's rows of s's
    row below r, for every r ≥ k0 (the rows an update column k in [k0, k1) touches)."""
    n = supernode.size
    local = np.full(n, -1, np.int64)
    group_start = np.zeros(count + 1, np.int64)
    groups = 0
    relative_size = 0
    for s in range(count):
        width = first[s + 1] - first[s]
        below = row_start[s] + width
        m = row_start[s + 1] - below
        k = 0
        while k < m:
            t = supernode[rows[below + k]]
            relative_size += m - k
            groups += 1
            while k < m and supernode[rows[below + k]] == t:
                k += 1
        group_start[s + 1] = groups
    group = np.empty((groups, 4), np.int64)
    relative = np.empty(relative_size, np.int64)
    g = 0
    r_at = 0
    for s in range(count):
        width = first[s + 1] - first[s]
        below = row_start[s] + width
        m = row_start[s + 1] - below
        k = 0
        while k < m:
            t = supernode[rows[below + k]]
            k0 = k
            while k < m and supernode[rows[below + k]] == t:
                k += 1
            for q in range(row_start[t], row_start[t + 1]):
                local[rows[q]] = q - row_start[t]
            group[g, 0] = t
            group[g, 1] = k0
            group[g, 2] = k
            group[g, 3] = r_at
            for r in range(k0, m):
                relative[r_at] = local[rows[below + r]]
                r_at += 1
            g += 1
    return group_start, group, relative


@numba.njit(cache=True)
def _value_map(n, indptr, indices, inverse, supernode, first, row_start, rows, value_start):
    """Where each stored entry of A (CSR, original numbering) goes in L's values: the entries with column ≥
    row (the upper triangle) at the position of their permuted lower-triangle twin; -1 for the others."""
    destination = np.full(indices.size, -1, np.int64)
    for i in range(n):
        for p in range(indptr[i], indptr[i + 1]):
            j = indices[p]
            if j < i:
                continue
            a, b = inverse[i], inverse[j]
            low, high = min(a, b), max(a, b)
            s = supernode[low]
            width = first[s + 1] - first[s]
            height = row_start[s + 1] - row_start[s]
            if high < first[s + 1]:
                where = high - first[s]
            else:
                below = rows[row_start[s] + width : row_start[s + 1]]
                where = width + np.searchsorted(below, high)
            destination[p] = value_start[s] + (low - first[s]) * height + where
    return destination


# ---------------------------------------------------------------------------------------------- numeric


@numba.njit(cache=True)
def _factorise(
    values, destination, lx, first, row_start, value_start, group_start, group, relative, work, cells
):
    """The numeric factorisation into ``lx``; returns -1, or the first column whose pivot is not positive.

    ``cells``: float64 cells the BLAS calls read their scalars through (int32 in the first ones, see
    :meth:`SymbolicFactor._cells`)."""
    lx[:] = 0.0
    for p in range(destination.size):
        d = destination[p]
        if d >= 0:
            lx[d] += values[p]
    ints = cells.view(np.int32)  # int32 cells 0..7, then characters, then the float64 cells 8 and 9
    base_int = cells.ctypes.data
    chars = base_int + 32  # bytes 32..39: 'L', 'R', 'T', 'N'
    lower, right, transpose, no = chars, chars + 1, chars + 2, chars + 3
    one, zero = base_int + 64, base_int + 72
    lx_address = lx.ctypes.data
    work_address = work.ctypes.data
    count = first.size - 1
    for s in range(count):
        width = first[s + 1] - first[s]
        height = row_start[s + 1] - row_start[s]
        m = height - width
        block = lx_address + 8 * value_start[s]
        ints[0] = width
        ints[1] = height
        ints[2] = m
        ints[3] = 0
        _dpotrf(lower, base_int, block, base_int + 4, base_int + 12)
        if ints[3] != 0:
            return first[s] + ints[3] - 1
        if m == 0:
            continue
        below = block + 8 * width
        _dtrsm(
            right, lower, transpose, no, base_int + 8, base_int, one, block, base_int + 4, below, base_int + 4
        )
        _dsyrk(lower, no, base_int + 8, base_int, one, below, base_int + 4, zero, work_address, base_int + 8)
        for g in range(group_start[s], group_start[s + 1]):
            t = group[g, 0]
            k0 = group[g, 1]
            k1 = group[g, 2]
            start = group[g, 3] - k0
            target_height = row_start[t + 1] - row_start[t]
            target = value_start[t]
            for k in range(k0, k1):
                column = target + relative[start + k] * target_height
                for r in range(k, m):
                    lx[column + relative[start + r]] -= work[r + k * m]
    return -1


@numba.njit(cache=True)
def _forward(lx, first, row_start, rows, value_start, order, index, y, work, cells):
    """y ← L⁻¹ y over the supernodes ``order`` (increasing; the others are skipped: their part of y must be
    zero), y of shape (u, k) C-ordered, row index[i] for column i of L (the identity for a whole solve, a
    compact numbering of the columns of ``order`` for a partial one). Per supernode: its own rows of y
    gathered into ``work`` (column-major, leading dimension its height), ``dtrsm`` on them, ``dgemm`` of the
    rows below, added back into y."""
    k = y.shape[1]
    ints = cells.view(np.int32)
    base_int = cells.ctypes.data
    chars = base_int + 32
    lower, left, no = chars, chars + 4, chars + 3
    one, zero = base_int + 64, base_int + 72
    lx_address = lx.ctypes.data
    work_address = work.ctypes.data
    ints[5] = k
    for q in range(order.size):
        s = order[q]
        f = first[s]
        width = first[s + 1] - f
        height = row_start[s + 1] - row_start[s]
        m = height - width
        block = lx_address + 8 * value_start[s]
        for c in range(k):
            for i in range(width):
                work[i + c * height] = y[index[f + i], c]
        ints[0] = width
        ints[1] = height
        ints[2] = m
        _dtrsm(
            left, lower, no, no, base_int, base_int + 20, one, block, base_int + 4, work_address, base_int + 4
        )
        for c in range(k):
            for i in range(width):
                y[index[f + i], c] = work[i + c * height]
        if m == 0:
            continue
        _dgemm(
            no,
            no,
            base_int + 8,
            base_int + 20,
            base_int,
            one,
            block + 8 * width,
            base_int + 4,
            work_address,
            base_int + 4,
            zero,
            work_address + 8 * width,
            base_int + 4,
        )
        start = row_start[s] + width
        for c in range(k):
            for i in range(m):
                y[index[rows[start + i]], c] -= work[width + i + c * height]


@numba.njit(cache=True)
def _backward(lx, first, row_start, rows, value_start, y, work, cells):
    """y ← L⁻ᵀ y, y of shape (n, k) C-ordered, in the factor's order: per supernode (last first) its rows
    gathered into ``work``, ``dgemm`` of the rows below (transposed) subtracted from its own, ``dtrsm``
    (transposed), its own rows written back."""
    k = y.shape[1]
    ints = cells.view(np.int32)
    base_int = cells.ctypes.data
    chars = base_int + 32
    lower, left, transpose, no = chars, chars + 4, chars + 2, chars + 3
    one, minus_one = base_int + 64, base_int + 56
    lx_address = lx.ctypes.data
    work_address = work.ctypes.data
    ints[5] = k
    for s in range(first.size - 2, -1, -1):
        f = first[s]
        width = first[s + 1] - f
        height = row_start[s + 1] - row_start[s]
        m = height - width
        block = lx_address + 8 * value_start[s]
        start = row_start[s]
        for c in range(k):
            for i in range(height):
                work[i + c * height] = y[rows[start + i], c]
        ints[0] = width
        ints[1] = height
        ints[2] = m
        if m > 0:
            _dgemm(
                transpose,
                no,
                base_int,
                base_int + 20,
                base_int + 8,
                minus_one,
                block + 8 * width,
                base_int + 4,
                work_address + 8 * width,
                base_int + 4,
                one,
                work_address,
                base_int + 4,
            )
        _dtrsm(
            left,
            lower,
            transpose,
            no,
            base_int,
            base_int + 20,
            one,
            block,
            base_int + 4,
            work_address,
            base_int + 4,
        )
        for c in range(k):
            for i in range(width):
                y[f + i, c] = work[i + c * height]


class SymbolicFactor:
    """The analysis of one pattern and the factor's storage; :meth:`factorise` fills L for new values.

    Parameters
    ----------
    matrix : A (CSR, sorted indices, square): its upper triangle is read (column ≥ row); full storage or the
        upper triangle alone.
    permutation : The fill-reducing ordering: ``permutation[k]`` is the original index of the k-th pivot.
    relaxation : (columns, zero fraction) pairs of the relaxed amalgamation (:data:`RELAXATION`); () for
        fundamental supernodes only.
    """

    def __init__(self, matrix: sp.csr_matrix, permutation: np.ndarray, relaxation=RELAXATION) -> None:
        n = matrix.shape[0]
        permutation = np.asarray(permutation, dtype=np.int64)
        if permutation.shape != (n,) or not np.array_equal(np.sort(permutation), np.arange(n)):
            raise ValueError(f"permutation must be a permutation of 0..{n - 1}")
        pattern = self._upper_pattern(matrix, permutation)
        parent = _elimination_tree(n, pattern.indptr, pattern.indices)
        post = _postorder(parent)
        permutation = permutation[post]
        pattern = self._upper_pattern(matrix, permutation)
        parent = _elimination_tree(n, pattern.indptr, pattern.indices)
        counts = _column_counts(n, pattern.indptr, pattern.indices, parent)
        supernode = _fundamental_supernodes(parent, counts)
        first = np.concatenate([[0], np.flatnonzero(np.diff(supernode)) + 1, [n]]).astype(np.int64)
        row_start, rows = _supernode_rows(
            n, first.size - 1, first, supernode, parent, pattern.indptr, pattern.indices
        )
        for columns_limit, fraction in relaxation:
            first, supernode = self._amalgamate(first, supernode, parent, row_start, columns_limit, fraction)
            row_start, rows = _supernode_rows(
                n, first.size - 1, first, supernode, parent, pattern.indptr, pattern.indices
            )
        self.n = n
        self.permutation = permutation
        self.inverse = np.empty(n, np.int64)
        self.inverse[permutation] = np.arange(n)
        self.parent = parent
        self.column_counts = counts
        self.first = first
        self.supernode = supernode
        self.row_start = row_start
        self.rows = rows
        widths = np.diff(first)
        heights = np.diff(row_start)
        self.value_start = np.concatenate([[0], np.cumsum(widths * heights)]).astype(np.int64)
        self.group_start, self.group, self.relative = _update_maps(
            first.size - 1, first, supernode, row_start, rows, self.value_start
        )
        self.destination = _value_map(
            n,
            matrix.indptr.astype(np.int64),
            matrix.indices.astype(np.int64),
            self.inverse,
            supernode,
            first,
            row_start,
            rows,
            self.value_start,
        )
        below = heights - widths
        self.values = np.zeros(self.value_start[-1])
        self._work = np.zeros(max(int((below**2).max(initial=0)), 1))
        self._cells = np.zeros(10)
        self._cells.view(np.uint8)[32:37] = [_LOWER, _RIGHT, _TRANSPOSE, _NON_UNIT, _LEFT]
        self._cells[7], self._cells[8], self._cells[9] = -1.0, 1.0, 0.0
        self._all = np.arange(first.size - 1, dtype=np.int64)
        self._identity = np.arange(n, dtype=np.int64)
        self._height = int(heights.max(initial=1))
        self._solve_work = np.empty(self._height)
        self.factorised = False

    @staticmethod
    def _upper_pattern(matrix: sp.csr_matrix, permutation: np.ndarray) -> sp.csc_matrix:
        """The permuted symmetric pattern's upper triangle (column j: rows i ≤ j), CSC, sorted."""
        n = matrix.shape[0]
        inverse = np.empty(n, np.int64)
        inverse[permutation] = np.arange(n)
        coo = matrix.tocoo()
        a, b = inverse[coo.row], inverse[coo.col]
        low, high = np.minimum(a, b), np.maximum(a, b)
        pattern = sp.csc_matrix((np.ones(low.size), (low, high)), shape=(n, n))
        pattern.sum_duplicates()
        pattern.sort_indices()
        return pattern

    @staticmethod
    def _amalgamate(first, supernode, parent, row_start, columns_limit, fraction):
        """One pass of relaxed amalgamation (:data:`RELAXATION`) over contiguous child-parent pairs."""
        return _amalgamate(first, supernode, parent, row_start, columns_limit, fraction)

    @property
    def nnz(self) -> int:
        """Entries stored in L (its supernodal lower trapezoids, explicit zeros of amalgamation included)."""
        widths = np.diff(self.first)
        heights = np.diff(self.row_start)
        return int(np.sum(widths * heights - widths * (widths - 1) // 2))

    def factorise(self, data: np.ndarray) -> None:
        """L for A's values ``data`` (the CSR data of the analysed matrix, in its order)."""
        failed = _factorise(
            np.asarray(data, dtype=float),
            self.destination,
            self.values,
            self.first,
            self.row_start,
            self.value_start,
            self.group_start,
            self.group,
            self.relative,
            self._work,
            self._cells,
        )
        self.factorised = failed < 0
        if failed >= 0:
            raise NotPositiveDefinite(
                f"non-positive pivot at column {int(self.permutation[failed])}: "
                "the matrix is not positive definite"
            )

    def _workspace(self, columns: int) -> np.ndarray:
        """The solves' per-supernode workspace for ``columns`` right-hand sides."""
        if self._solve_work.size < self._height * columns:
            self._solve_work = np.empty(self._height * columns)
        return self._solve_work

    def solve(self, rhs: np.ndarray, supernodes: np.ndarray | None = None) -> np.ndarray:
        """A⁻¹ rhs, rhs of shape (n,) or (n, k); ``supernodes``: those the forward substitution visits (the
        etree paths of rhs's non-zeros, :meth:`paths`), all by default."""
        y = np.ascontiguousarray(rhs[self.permutation], dtype=float).reshape(self.n, -1)
        work = self._workspace(y.shape[1])
        order = self._all if supernodes is None else supernodes
        _forward(
            self.values,
            self.first,
            self.row_start,
            self.rows,
            self.value_start,
            order,
            self._identity,
            y,
            work,
            self._cells,
        )
        _backward(self.values, self.first, self.row_start, self.rows, self.value_start, y, work, self._cells)
        out = np.empty_like(y)
        out[self.permutation] = y
        return out.reshape(rhs.shape)

    def forward(self, rhs: np.ndarray) -> np.ndarray:
        """Y = L⁻¹ P rhs (rows in the factor's order), rhs of shape (n, k): Yᵀ Y = rhsᵀ A⁻¹ rhs."""
        y = np.ascontiguousarray(rhs[self.permutation], dtype=float)
        work = self._workspace(y.shape[1])
        _forward(
            self.values,
            self.first,
            self.row_start,
            self.rows,
            self.value_start,
            self._all,
            self._identity,
            y,
            work,
            self._cells,
        )
        return y

    def inverse_block(self, positions: np.ndarray, paths) -> np.ndarray:
        """(A⁻¹)[positions][:, positions] = Yᵀ Y, Y = L⁻¹ P E on the columns of ``paths`` (:meth:`paths` of a
        superset of ``positions``), the only rows of Y that are not zero."""
        supernodes, compact, columns = paths
        y = np.zeros((columns, positions.size))
        y[compact[self.inverse[positions]], np.arange(positions.size)] = 1.0
        work = self._workspace(positions.size)
        _forward(
            self.values,
            self.first,
            self.row_start,
            self.rows,
            self.value_start,
            supernodes,
            compact,
            y,
            work,
            self._cells,
        )
        return y.T @ y

    def paths(self, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """The supernodes on the elimination-tree paths from ``positions`` (original numbering) to the roots,
        increasing, and the compact numbering of their columns: (supernodes, compact (n,) with -1 off them,
        number of columns)."""
        count = self.first.size - 1
        on = np.zeros(count, bool)
        parent_of = self._supernode_parent()
        start = np.unique(self.supernode[self.inverse[np.asarray(positions, dtype=np.int64)]])
        _mark_paths(start, parent_of, on)
        supernodes = np.flatnonzero(on)
        columns = np.flatnonzero(on[self.supernode])  # their columns, increasing
        compact = np.full(self.n, -1, np.int64)
        compact[columns] = np.arange(columns.size)
        return supernodes, compact, columns.size

    def _supernode_parent(self) -> np.ndarray:
        last = self.first[1:] - 1
        parent = self.parent[last]
        return np.where(parent >= 0, self.supernode[np.maximum(parent, 0)], -1)


@numba.njit(cache=True)
def _mark_paths(start, parent_of, on):
    for q in range(start.size):
        s = start[q]
        while s != -1 and not on[s]:
            on[s] = True
            s = parent_of[s]


def _amalgamate(first, supernode, parent, row_start, columns_limit, fraction):
    """Merge each supernode into its parent when the parent's columns follow its own and the merge keeps the
    explicit zeros within ``fraction`` of the entries and the width within ``columns_limit``; returns the new
    (first, supernode)."""
    count = first.size - 1
    last = first[1:] - 1
    parent_of = np.where(parent[last] >= 0, supernode[np.maximum(parent[last], 0)], -1)
    widths = np.diff(first).astype(np.int64)
    heights = np.diff(row_start).astype(np.int64)
    target = _merge(parent_of, widths, heights, float(columns_limit), float(fraction))
    kept = np.unique(target)
    renumber = np.full(count, -1, np.int64)
    renumber[kept] = np.arange(kept.size)
    new_supernode = renumber[target[supernode]]
    new_first = np.concatenate([[0], np.flatnonzero(np.diff(new_supernode)) + 1, [first[-1]]]).astype(
        np.int64
    )
    return new_first, new_supernode


@numba.njit(cache=True)
def _merge(parent_of, widths, heights, columns_limit, fraction):
    """Target supernode of each supernode after relaxed merges of a child into its parent p, the child being
    the supernode just before p's (merged) first supernode, i.e. columns contiguous."""
    count = parent_of.size
    target = np.arange(count)
    width = widths.copy()
    height = heights.copy()
    zeros = np.zeros(count)
    leftmost = np.arange(count)  # the first original supernode of p's merged range
    for p in range(count):
        while True:
            s = leftmost[p] - 1
            if s < 0 or parent_of[s] != p or target[s] != s:
                break
            merged_width = width[s] + width[p]
            merged_height = height[p] + width[s]
            total = merged_width * merged_height - merged_width * (merged_width - 1) // 2
            held_s = width[s] * height[s] - width[s] * (width[s] - 1) // 2
            held_p = width[p] * height[p] - width[p] * (width[p] - 1) // 2
            new_zeros = total - (held_s - zeros[s]) - (held_p - zeros[p])
            if merged_width > columns_limit or new_zeros > fraction * total:
                break
            target[s] = p
            width[p] = merged_width
            height[p] = merged_height
            zeros[p] = new_zeros
            leftmost[p] = leftmost[s]
    # targets of targets (a merged child's own merged children)
    for s in range(count - 1, -1, -1):
        t = target[s]
        if t != s:
            target[s] = target[t]
    return target
