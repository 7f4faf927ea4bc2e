"""Compiled parts of the row builders (numba): the tissue Jacobian of interpolated points.

:func:`refsim.constraints.rows.point_rows` builds H_tissue for points interpolated from mesh nodes. Built as
a COO matrix, SciPy converts it to CSR keeping each row's entries in input order, sorts each row's columns
(``csr_sort_indices``, std::sort: not stable, so the order of equal columns is its own) and sums the equal
columns in the sorted order (``csr_sum_duplicates``). A ring-averaged row has 4 (q + 1) nodes, many shared,
so that order decides the last bits of H. Here the entries are made in one compiled pass, SciPy sorts only a
probe per distinct row pattern (its data the entries' positions, so its result is the permutation std::sort
applied: the sort compares columns only), and the compiled pass sums the duplicates in that order. The
result is the COO path's matrix bit for bit (``tests/constraints/test_rows.py``) without its many small
arrays.
"""

from __future__ import annotations

import numpy as np

from refsim.kernel_cache import numba

__all__ = ["row_entries", "summed_rows"]


@numba.njit(cache=True)
def row_entries(node_indices, weights, directions, sign):  # pragma: no cover - compiled
    """Columns (r, 3p) int32 and values (r, 3p) of rows ``sign · w_k · n`` on the DoFs 3 node + (0, 1, 2),
    in COO order (node by node, axis by axis); each row's pattern (an index into the distinct column
    patterns, a new one whenever a row's columns differ from the row before's), shape (r,); and the first row
    of each pattern, shape (u,)."""
    rows, per_point = node_indices.shape
    width = 3 * per_point
    columns = np.empty((rows, width), dtype=np.int32)
    values = np.empty((rows, width))
    pattern = np.empty(rows, dtype=np.int64)
    firsts = np.empty(rows, dtype=np.int64)
    patterns = 0
    for row in range(rows):
        for k in range(per_point):
            scaled = sign * weights[row, k]
            for axis in range(3):
                columns[row, 3 * k + axis] = 3 * node_indices[row, k] + axis
                values[row, 3 * k + axis] = scaled * directions[row, axis]
        same = row > 0
        if same:
            for slot in range(width):
                if columns[row, slot] != columns[row - 1, slot]:
                    same = False
                    break
        if same:
            pattern[row] = pattern[row - 1]
        else:
            pattern[row] = patterns
            firsts[patterns] = row
            patterns += 1
    return columns, values, pattern, firsts[:patterns].copy()


@numba.njit(cache=True)
def summed_rows(columns, values, order, pattern_slot):  # pragma: no cover - compiled
    """CSR arrays (data, indices, indptr) of the rows with equal columns summed in the order ``order``
    ((u, 3p) positions, one per distinct pattern; row i uses ``order[pattern_slot[i]]``), each sum left to
    right as csr_sum_duplicates does."""
    rows, width = columns.shape
    data = np.empty(rows * width)
    indices = np.empty(rows * width, dtype=np.int32)
    indptr = np.zeros(rows + 1, dtype=np.int32)
    count = 0
    for row in range(rows):
        permutation = order[pattern_slot[row]]
        slot = 0
        while slot < width:
            column = columns[row, permutation[slot]]
            total = values[row, permutation[slot]]
            slot += 1
            while slot < width and columns[row, permutation[slot]] == column:
                total += values[row, permutation[slot]]
                slot += 1
            indices[count] = column
            data[count] = total
            count += 1
        indptr[row + 1] = count
    return data[:count].copy(), indices[:count].copy(), indptr


@numba.njit(cache=True)
def basis_of(tangents):  # pragma: no cover - compiled
    """:func:`refsim.constraints.rows.orthonormal_basis` in one pass: the helper axis is the first world
    axis of smallest |t_i|, first = helper × t / ‖helper × t‖, second = t × first; each cross product's
    component is a₁b₂ − a₂b₁ (NumPy's order) and the norm sums its squares left to right (NumPy's reduction
    over three), so the bits are NumPy's."""
    count = tangents.shape[0]
    first = np.empty((count, 3))
    second = np.empty((count, 3))
    helper = np.zeros(3)
    for row in range(count):
        t = tangents[row]
        axis = 0
        smallest = abs(t[0])
        for candidate in range(1, 3):
            if abs(t[candidate]) < smallest:
                smallest = abs(t[candidate])
                axis = candidate
        helper[:] = 0.0
        helper[axis] = 1.0
        f0 = helper[1] * t[2] - helper[2] * t[1]
        f1 = helper[2] * t[0] - helper[0] * t[2]
        f2 = helper[0] * t[1] - helper[1] * t[0]
        norm = np.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
        f0, f1, f2 = f0 / norm, f1 / norm, f2 / norm
        first[row, 0], first[row, 1], first[row, 2] = f0, f1, f2
        second[row, 0] = t[1] * f2 - t[2] * f1
        second[row, 1] = t[2] * f0 - t[0] * f2
        second[row, 2] = t[0] * f1 - t[1] * f0
    return first, second
