"""Co-rotation and assembly of the tissue's step system, compiled (numba) into the fixed pattern of the free
DoFs.

One pass over the tets computes, per element, F = Ds Dm⁻¹, its polar rotation R (scaled Newton,
:func:`refsim.geometry.rotations.polar_rotation_one`), the local displacement u = Rᵀ x − X (centred, as in
:meth:`TissueModel.internal_forces`), the internal force R Kₑ u and the 10 distinct 3 × 3 blocks
s · R Kₑ_ab Rᵀ (a ≤ b) of the tangent (Kₑ is symmetric, so block (b, a) is block (a, b)ᵀ), and adds them
straight into

* the ``data`` of A_ff = (M/dt² + C/dt + K)_ff, a CSR matrix whose pattern is built once (free DoFs only, the
  fixed ones eliminated): either its **upper triangle** (what PARDISO reads, for a symmetric matrix; each
  block entry lands in at most one upper entry: 78 additions per tet) or the full matrix (what SuperLU,
  CHOLMOD and the fast strategies' products need: 144), through a precomputed slot of each block entry (−1
  when it has no place there);
* the ``data`` of the coupling A_fc (free rows, constrained columns), for prescribed displacements;
* the internal force vector.

Both storages hold the same numbers (the upper one is the full one's upper triangle, bit for bit). No Python
loop over elements; the result equals the NumPy/scikit-fem assembly of :class:`TissueModel` to round-off
(tests/fem/test_assembly.py).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from refsim.geometry.rotations import polar_rotation_one
from refsim.kernel_cache import numba

__all__ = ["FreePattern", "assemble_free_system", "deformation_gradient", "deformation_rotation"]


class FreePattern:
    """The fixed CSR patterns of A_ff and A_fc and the slot of every element entry in them.

    Parameters
    ----------
    pattern : The full stiffness pattern (CSR, dof_count × dof_count).
    scatter : Full-pattern index of each element entry, in the order (tet, a, b, i, j), shape
    (tet_count·144,).
    constrained_dofs : Sorted constrained DoFs, shape (c,).
    mass_matrix : M on the full pattern's DoFs (CSR; its entries must lie in the pattern).
    """

    def __init__(
        self, pattern: sp.csr_matrix, scatter: np.ndarray, constrained_dofs: np.ndarray, mass_matrix
    ) -> None:
        n = pattern.shape[0]
        self.dof_count = n
        self.constrained_dofs = np.asarray(constrained_dofs, dtype=np.int64)
        self.free_dofs = np.setdiff1d(np.arange(n), self.constrained_dofs)
        numbered = sp.csr_matrix(
            (np.arange(pattern.nnz, dtype=float), pattern.indices, pattern.indptr), shape=(n, n)
        )
        numbered.has_sorted_indices = True
        free_free = numbered[self.free_dofs][:, self.free_dofs].tocsr()
        free_free.sort_indices()
        free_fixed = numbered[self.free_dofs][:, self.constrained_dofs].tocsr()
        free_fixed.sort_indices()
        self.indptr, self.indices = free_free.indptr.copy(), free_free.indices.copy()
        self.coupling_indptr, self.coupling_indices = free_fixed.indptr.copy(), free_fixed.indices.copy()
        to_free = np.full(pattern.nnz, -1, dtype=np.int64)
        to_free[free_free.data.astype(np.int64)] = np.arange(free_free.nnz)
        to_coupling = np.full(pattern.nnz, -1, dtype=np.int64)
        to_coupling[free_fixed.data.astype(np.int64)] = np.arange(free_fixed.nnz)
        # One int32 slot per element entry (little memory traffic in the scatter): k ≥ 0 is entry k of A_ff,
        # k ≤ −2 entry −k − 2 of A_fc, −1 nothing (a constrained row).
        free_slot, coupling_slot = to_free[scatter], to_coupling[scatter]
        combined = np.where(free_slot >= 0, free_slot, np.where(coupling_slot >= 0, -coupling_slot - 2, -1))
        if max(free_free.nnz, free_fixed.nnz) >= 2**31 - 2:
            raise ValueError("the stiffness pattern is too large for int32 slots")
        self.slots = combined.reshape(-1, 144).astype(np.int32)
        self.nnz, self.coupling_nnz = free_free.nnz, free_fixed.nnz
        self._upper_pattern(combined.reshape(-1, 144))
        mass = sp.csr_matrix(mass_matrix)
        mass_ff = mass[self.free_dofs][:, self.free_dofs].tocsr()
        mass_ff.sort_indices()
        self.mass_data = self._on_pattern(mass_ff, self.indptr, self.indices)
        mass_fc = mass[self.free_dofs][:, self.constrained_dofs].tocsr()
        mass_fc.sort_indices()
        self.mass_coupling_data = self._on_pattern(mass_fc, self.coupling_indptr, self.coupling_indices)
        self.mass_upper_data = self.mass_data[self.upper_positions]

    def _upper_pattern(self, combined: np.ndarray) -> None:
        """The upper triangle of A_ff (its pattern, where its entries sit in the full data) and the slot of
        each of the 90 block entries (a ≤ b, i, j) of every tet in it.

        A block entry (a, b, i, j) is the value of the full entries (3n_a + i, 3n_b + j) and, for a < b,
        (3n_b + j, 3n_a + i): at most one of them is an upper entry of A_ff or an entry of A_fc (a tet's nodes
        are distinct, and a DoF is either free or constrained); that one is its slot (k ≥ 0 upper entry k,
        k ≤ −2 coupling entry −k − 2, −1 none)."""
        f = self.free_dofs.size
        rows = np.repeat(np.arange(f), np.diff(self.indptr))
        self.upper_positions = np.flatnonzero(self.indices >= rows)
        to_upper = np.full(self.nnz + 1, -1, dtype=np.int64)  # the last: "no free entry"
        to_upper[self.upper_positions] = np.arange(self.upper_positions.size)
        # the index dtype of the full pattern (SciPy's int32 for any pattern that fits): a CSR matrix made on
        # these arrays takes them as they are, with no copy at each step
        upper_indptr = np.zeros(f + 1, dtype=np.int64)
        np.cumsum(np.bincount(rows[self.upper_positions], minlength=f), out=upper_indptr[1:])
        self.upper_indptr = upper_indptr.astype(self.indptr.dtype)
        self.upper_indices = self.indices[self.upper_positions]
        self.upper_nnz = self.upper_positions.size
        direct, mirrored = _BLOCK_ENTRIES
        first = combined[:, direct]
        second = np.where(mirrored >= 0, combined[:, np.maximum(mirrored, 0)], -1)
        slots = np.full(first.shape, -1, dtype=np.int64)
        for candidate in (first, second):
            upper = to_upper[np.where(candidate >= 0, candidate, self.nnz)]
            target = np.where(upper >= 0, upper, np.where(candidate <= -2, candidate, -1))
            if np.any((slots != -1) & (target != -1)):
                raise ValueError("a block entry has two places in the upper storage")  # cannot happen
            slots = np.where(target != -1, target, slots)
        self.upper_slots = slots.astype(np.int32)

    @staticmethod
    def _on_pattern(matrix: sp.csr_matrix, indptr: np.ndarray, indices: np.ndarray) -> np.ndarray:
        """The entries of ``matrix`` in the order of the pattern (indptr, indices); zero where it has none."""
        shape = (indptr.size - 1, matrix.shape[1])
        holder = sp.csr_matrix((np.arange(indices.size, dtype=float) + 1.0, indices, indptr), shape=shape)
        out = np.zeros(indices.size)
        coo = matrix.tocoo()
        if coo.nnz == 0:
            return out
        picked = holder[coo.row, coo.col]
        positions = np.asarray(picked.todense() if sp.issparse(picked) else picked, dtype=float).ravel()
        if np.any((positions == 0.0) & (coo.data != 0.0)):
            raise ValueError("the mass matrix has entries outside the stiffness pattern")
        keep = positions > 0.0
        np.add.at(out, positions[keep].astype(np.int64) - 1, coo.data[keep])
        return out

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """A_ff as a CSR matrix on this pattern (no copy of ``data``)."""
        f = self.free_dofs.size
        out = sp.csr_matrix((data, self.indices, self.indptr), shape=(f, f), copy=False)
        out.has_sorted_indices = True
        return out

    def upper_matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """The upper triangle of A_ff (diagonal included) as a CSR matrix (no copy of ``data``)."""
        f = self.free_dofs.size
        out = sp.csr_matrix((data, self.upper_indices, self.upper_indptr), shape=(f, f), copy=False)
        out.has_sorted_indices = True
        return out

    def coupling(self, data: np.ndarray) -> sp.csr_matrix:
        """A_fc as a CSR matrix (free rows, constrained columns)."""
        out = sp.csr_matrix(
            (data, self.coupling_indices, self.coupling_indptr),
            shape=(self.free_dofs.size, self.constrained_dofs.size),
            copy=False,
        )
        out.has_sorted_indices = True
        return out


def _block_entries() -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """Where the 90 distinct block entries (a ≤ b, i, j), in the kernel's order, sit among a tet's 144 full
    entries (a, b, i, j) (index (4a + b)·9 + 3i + j): the direct one (a, b, i, j), its mirror (b, a, j, i) for
    a < b (−1 for a diagonal block, whose entries are each computed), and for each full entry the block entry
    that gives its value."""
    direct, mirrored, source = [], [], np.zeros(144, dtype=np.int64)
    for a in range(4):
        for b in range(a, 4):
            for i in range(3):
                for j in range(3):
                    source[(4 * a + b) * 9 + 3 * i + j] = len(direct)
                    if b != a:
                        source[(4 * b + a) * 9 + 3 * j + i] = len(direct)
                    direct.append((4 * a + b) * 9 + 3 * i + j)
                    mirrored.append((4 * b + a) * 9 + 3 * j + i if b != a else -1)
    return (np.array(direct), np.array(mirrored)), source


_BLOCK_ENTRIES, _FULL_SOURCE = _block_entries()
_UPPER_SOURCE = np.arange(90, dtype=np.int64)


@numba.njit(cache=True)
def deformation_gradient(positions, tets, rest_edges_inverse, e, f, ds):  # pragma: no cover - compiled
    """Tet ``e``'s deformation gradient F = Ds Dm⁻¹ into ``f`` (Ds = [x₁−x₀, x₂−x₀, x₃−x₀] into ``ds``): the
    co-rotation's first half in the assembly (:func:`assemble_free_system`) and in the fast mode's passes
    (:mod:`refsim.fem.corotated_matvec`)."""
    n0 = tets[e, 0]
    for c in range(3):
        for i in range(3):
            ds[i, c] = positions[tets[e, c + 1], i] - positions[n0, i]
    for i in range(3):
        for j in range(3):
            s = 0.0
            for k in range(3):
                s += ds[i, k] * rest_edges_inverse[e, k, j]
            f[i, j] = s


@numba.njit(cache=True)
def deformation_rotation(positions, tets, rest_edges_inverse, e, f, ds, r):  # pragma: no cover - compiled
    """Tet ``e``'s deformation gradient (:func:`deformation_gradient`) into ``f`` and its polar rotation
    (:func:`refsim.geometry.rotations.polar_rotation_one`) into ``r``."""
    deformation_gradient(positions, tets, rest_edges_inverse, e, f, ds)
    polar_rotation_one(f, r)


@numba.njit(cache=True)
def _assemble(
    positions,
    tets,
    rest_edges_inverse,
    centred_rest,
    stiffness,
    stiffness_factor,
    slots,
    source,
    data,
    coupling_data,
    forces,
    rotations,
):  # pragma: no cover - compiled
    tet_count = tets.shape[0]
    f = np.empty((3, 3))
    ds = np.empty((3, 3))
    r = np.empty((3, 3))
    x = np.empty((4, 3))
    u = np.empty(12)
    fl = np.empty(12)
    blocks = np.empty(90)
    entries = slots.shape[1]
    for e in range(tet_count):
        deformation_rotation(positions, tets, rest_edges_inverse, e, f, ds, r)
        for i in range(3):  # element by element: a slice assignment costs more than the copy here
            for j in range(3):
                rotations[e, i, j] = r[i, j]
        # centred element positions and u_a = Rᵀ x_a − X_a
        for i in range(3):
            mean = 0.25 * (
                positions[tets[e, 0], i]
                + positions[tets[e, 1], i]
                + positions[tets[e, 2], i]
                + positions[tets[e, 3], i]
            )
            for a in range(4):
                x[a, i] = positions[tets[e, a], i] - mean
        for a in range(4):
            for i in range(3):
                s = 0.0
                for k in range(3):
                    s += x[a, k] * r[k, i]
                u[3 * a + i] = s - centred_rest[e, a, i]
        for p in range(12):
            s = 0.0
            for q in range(12):
                s += stiffness[e, p, q] * u[q]
            fl[p] = s
        for a in range(4):
            node = tets[e, a]
            for i in range(3):
                s = 0.0
                for k in range(3):
                    s += r[i, k] * fl[3 * a + k]
                forces[3 * node + i] += s
        # the 10 distinct tangent blocks s · R K_ab Rᵀ (a ≤ b), entry (a, b, i, j) at blocks[9m + 3i + j]:
        # q = K_ab Rᵀ, q_ij = Σ_k K_ab,ik r_jk, then Σ_k r_ik q_kj, each sum in the order k = 0, 1, 2, written
        # out on scalars (R and q in registers: a tenth to a fifth less time than loops over small scratch
        # arrays, the same bits)
        r00, r01, r02 = r[0, 0], r[0, 1], r[0, 2]
        r10, r11, r12 = r[1, 0], r[1, 1], r[1, 2]
        r20, r21, r22 = r[2, 0], r[2, 1], r[2, 2]
        m = 0
        for a in range(4):
            for b in range(a, 4):
                row, column = 3 * a, 3 * b
                k00, k01, k02 = (
                    stiffness[e, row, column],
                    stiffness[e, row, column + 1],
                    stiffness[e, row, column + 2],
                )
                k10 = stiffness[e, row + 1, column]
                k11, k12 = stiffness[e, row + 1, column + 1], stiffness[e, row + 1, column + 2]
                k20 = stiffness[e, row + 2, column]
                k21, k22 = stiffness[e, row + 2, column + 1], stiffness[e, row + 2, column + 2]
                q00, q01, q02 = (
                    k00 * r00 + k01 * r01 + k02 * r02,
                    k00 * r10 + k01 * r11 + k02 * r12,
                    k00 * r20 + k01 * r21 + k02 * r22,
                )
                q10, q11, q12 = (
                    k10 * r00 + k11 * r01 + k12 * r02,
                    k10 * r10 + k11 * r11 + k12 * r12,
                    k10 * r20 + k11 * r21 + k12 * r22,
                )
                q20, q21, q22 = (
                    k20 * r00 + k21 * r01 + k22 * r02,
                    k20 * r10 + k21 * r11 + k22 * r12,
                    k20 * r20 + k21 * r21 + k22 * r22,
                )
                o = 9 * m
                blocks[o] = (r00 * q00 + r01 * q10 + r02 * q20) * stiffness_factor
                blocks[o + 1] = (r00 * q01 + r01 * q11 + r02 * q21) * stiffness_factor
                blocks[o + 2] = (r00 * q02 + r01 * q12 + r02 * q22) * stiffness_factor
                blocks[o + 3] = (r10 * q00 + r11 * q10 + r12 * q20) * stiffness_factor
                blocks[o + 4] = (r10 * q01 + r11 * q11 + r12 * q21) * stiffness_factor
                blocks[o + 5] = (r10 * q02 + r11 * q12 + r12 * q22) * stiffness_factor
                blocks[o + 6] = (r20 * q00 + r21 * q10 + r22 * q20) * stiffness_factor
                blocks[o + 7] = (r20 * q01 + r21 * q11 + r22 * q21) * stiffness_factor
                blocks[o + 8] = (r20 * q02 + r21 * q12 + r22 * q22) * stiffness_factor
                m += 1
        # into the slots: entry c of the storage's per-tet list takes block entry source[c]
        for c in range(entries):
            slot = slots[e, c]
            if slot >= 0:
                data[slot] += blocks[source[c]]
            elif slot <= -2:
                coupling_data[-slot - 2] += blocks[source[c]]


def assemble_free_system(
    pattern: FreePattern,
    positions: np.ndarray,
    tets: np.ndarray,
    rest_edges_inverse: np.ndarray,
    centred_rest: np.ndarray,
    stiffness: np.ndarray,
    mass_factor: float,
    stiffness_factor: float,
    *,
    upper: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rotations, internal forces and the data of A_ff and A_fc in one compiled pass.

    Parameters
    ----------
    pattern : The fixed patterns (:class:`FreePattern`).
    positions : Node positions [m], shape (node_count, 3).
    tets : Node indices, shape (tet_count, 4), int64.
    rest_edges_inverse : Dm⁻¹ per tet, shape (tet_count, 3, 3).
    centred_rest : Rest positions relative to each tet's centroid [m], shape (tet_count, 4, 3).
    stiffness : Kₑ [N/m], shape (tet_count, 12, 12), node-major local DoFs; C-contiguous (one tet's 144
        entries together: the kernel reads them tet by tet).
    mass_factor : 1/dt² + α/dt [1/s²].
    stiffness_factor : 1 + β/dt.
    upper : Assemble only the upper triangle of A_ff (:meth:`FreePattern.upper_matrix`'s data); the full
        matrix (:meth:`FreePattern.matrix`) by default.

    Returns
    -------
    A_ff data (pattern order, full or upper), A_fc data, internal forces [N] (dof_count,), rotations
    (tet_count, 3, 3).
    """
    if upper:
        data = mass_factor * pattern.mass_upper_data
        slots, source = pattern.upper_slots, _UPPER_SOURCE
    else:
        data = mass_factor * pattern.mass_data
        slots, source = pattern.slots, _FULL_SOURCE
    coupling = mass_factor * pattern.mass_coupling_data
    forces = np.zeros(pattern.dof_count)
    rotations = np.empty((tets.shape[0], 3, 3))
    _assemble(
        np.ascontiguousarray(positions, dtype=float),
        tets,
        rest_edges_inverse,
        centred_rest,
        np.ascontiguousarray(stiffness),
        float(stiffness_factor),
        slots,
        source,
        data,
        coupling,
        forces,
        rotations,
    )
    return data, coupling, forces, rotations
