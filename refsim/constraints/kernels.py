"""Compiled parts of the row builders (numba): the tissue Jacobian of interpolated points.

:func:`refsim.constraints.rows.point_rows` builds H_tissue for points interpolated from mesh nodes. Built as
a COO matrix, SciPy converts it to CSR keeping each row's entries in input order, sorts each row's columns
(``csr_sort_indices``, std::sort: not stable, so the order of equal columns is its own) and sums the equal
columns in the sorted order (``csr_sum_duplicates``). A ring-averaged row has 4 (q + 1) nodes, many shared,
so that order decides the last bits of H. Here the entries are made in one compiled pass, SciPy sorts only a
probe per distinct row pattern (its data the entries' positions, so its result is the permutation std::sort
applied: the sort compares columns only). What is summed with what, in which order, and the CSR structure
are then a function of the rows' nodes alone (:func:`summation_plan`), kept while the nodes repeat (an
insertion point's ring, the tip's tets); each call makes the entries and sums them by that plan in one
compiled pass (:func:`planned_rows`). The result is the COO path's matrix bit for bit
(``tests/constraints/test_rows.py``) without its many small arrays.
"""

from __future__ import annotations

import numpy as np

from refsim.kernel_cache import numba

__all__ = ["row_entries", "summation_plan", "planned_rows", "basis_of"]


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


@numba.njit(cache=True)
def summation_plan(columns, order, pattern_slot):  # pragma: no cover - compiled
    """How SciPy's conversion sums the entries of rows with these columns (sorted by ``order``, one
    permutation per distinct pattern, equal columns summed in that order), without the values: for each
    entry in summation order its weight (an index into ``weights.ravel()``, (r, p)) and its direction
    component (an index into ``directions.ravel()``, (r, 3)), shapes (r · 3p,) each; the start of each sum
    among them, shape (nnz + 1,); and the CSR ``indices`` (nnz,) and ``indptr`` (r + 1,), int32. A function
    of the columns alone (the entries' pattern), so it serves every call whose rows have those columns
    (:func:`planned_rows`)."""
    rows, width = columns.shape
    per_point = width // 3
    weight_at = np.empty(rows * width, dtype=np.int64)
    direction_at = np.empty(rows * width, dtype=np.int64)
    starts = np.empty(rows * width + 1, dtype=np.int64)
    indices = np.empty(rows * width, dtype=np.int32)
    indptr = np.zeros(rows + 1, dtype=np.int32)
    count = 0
    at = 0
    for row in range(rows):
        permutation = order[pattern_slot[row]]
        slot = 0
        while slot < width:
            column = columns[row, permutation[slot]]
            starts[count] = at
            while slot < width and columns[row, permutation[slot]] == column:
                entry = permutation[slot]  # COO order: node k = entry // 3, component entry % 3
                weight_at[at] = row * per_point + entry // 3
                direction_at[at] = row * 3 + entry % 3
                at += 1
                slot += 1
            indices[count] = column
            count += 1
        indptr[row + 1] = count
    starts[count] = at
    return weight_at, direction_at, starts[: count + 1].copy(), indices[:count].copy(), indptr


@numba.njit(cache=True)
def planned_rows(weights, directions, sign, weight_at, direction_at, starts):  # pragma: no cover - compiled
    """The CSR ``data`` of the rows by a :func:`summation_plan`: each entry ``(sign · w_k) · n_a`` made as
    :func:`row_entries` makes it, the entries of each sum added left to right in the plan's order (the
    operations of SciPy's ``csr_sum_duplicates`` on those entries, in its order: the same bits)."""
    flat_weights = weights.ravel()
    flat_directions = directions.ravel()
    count = starts.size - 1
    data = np.empty(count)
    for entry in range(count):
        first = starts[entry]
        total = (sign * flat_weights[weight_at[first]]) * flat_directions[direction_at[first]]
        for at in range(first + 1, starts[entry + 1]):
            total += (sign * flat_weights[weight_at[at]]) * flat_directions[direction_at[at]]
        data[entry] = total
    return data


@numba.njit(cache=True)
def interpolated_points(weights, positions, nodes):  # pragma: no cover - compiled
    """Σ_k w_ik x_(nodes_ik), shape (q, 3): ``np.einsum("qk,qkj->qj", weights, positions[nodes])`` without
    the gathered (q, k, 3) array. einsum sums each output's k products left to right into a zeroed output
    (its reduction loop: the products accumulated from 0, then added to the output's 0), and so does this
    pass: the same bits (``tests/constraints/test_rows.py``)."""
    count, per_point = weights.shape
    out = np.empty((count, 3))
    for row in range(count):
        for axis in range(3):
            total = 0.0
            for k in range(per_point):
                total += weights[row, k] * positions[nodes[row, k], axis]
            out[row, axis] = 0.0 + total
    return out
