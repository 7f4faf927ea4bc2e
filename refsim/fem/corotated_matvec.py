"""The tissue's step system without a matrix: co-rotation, internal forces and A·v compiled (numba) per tet.

The fast compliance strategy (:class:`refsim.fem.compliance.Fast`) neither assembles nor factorises A = M/dt²
+ C/dt + K during a run: its free motion is conjugate gradients, which only needs products A v. One pass over
the tets (:func:`corotate`) computes per element F = Ds Dm⁻¹, its polar rotation R
(:func:`refsim.geometry.rotations.polar_rotation_one`, as :mod:`refsim.fem.assembly`) and the internal force;
a product (:func:`stiffness_product`) is another pass, and

    A v = (1/dt² + α/dt) M v + (1 + β/dt) K v        (Rayleigh C = α M + β K, refsim.fem.integration).

Neither reads the 12 × 12 element matrices. A P1 tet has constant shape-function gradients ∇φ_a (the rows of
Dm⁻¹, ∇φ_0 = −Σ of them) and its stiffness is Kₑ = V Bᵀ D B exactly (scikit-fem's one-point rule), so for
nodal vectors w_a

    Kₑ w = (V σ(ε) ∇φ_a)_a,   ε = sym(Σ_a w_a ⊗ ∇φ_a),   σ = λ tr ε I + 2μ ε,

and the co-rotated force R Kₑ (Rᵀ x − X) is V R σ ∇φ_a with ε = sym(Rᵀ F) − I (Σ_a X_a ⊗ ∇φ_a = I); the
product R Kₑ Rᵀ v the same with ε = sym(Rᵀ Σ_a v_a ⊗ ∇φ_a). That is about 100 multiply-adds and 10 numbers
read per tet instead of 144 and 144. Both equal the assembled system to round-off
(tests/fem/test_corotated_matvec.py).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from refsim.fem.assembly import deformation_rotation
from refsim.fem.compliance import StepSystem
from refsim.geometry.rotations import polar_rotation_one
from refsim.kernel_cache import numba

__all__ = [
    "Elements",
    "CorotatedOperator",
    "corotate",
    "corotate_with_nodes",
    "stiffness_product",
    "node_rotations",
    "matrix_free_step",
]


# A tet's 3 × 3 matrices go between the kernels below as 9-tuples of their entries, row by row (r: a
# rotation, h: a gradient Σ_a w_a ⊗ ∇φ_a, p: V r σ): kept in registers from the tet's positions to its
# forces, where (3, 3) scratch arrays went through memory (a store into one may alias the next array read).


@numba.njit(cache=True, inline="always")
def _first_piola(r, h, shift, volume, lame, shear):  # pragma: no cover - compiled
    # V r σ for the gradient h in the frame r: G = rᵀ h, ε = sym G − shift I, σ = λ tr ε I + 2μ ε
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
    h00, h01, h02, h10, h11, h12, h20, h21, h22 = h
    g00 = r00 * h00 + r10 * h10 + r20 * h20
    g01 = r00 * h01 + r10 * h11 + r20 * h21
    g02 = r00 * h02 + r10 * h12 + r20 * h22
    g10 = r01 * h00 + r11 * h10 + r21 * h20
    g11 = r01 * h01 + r11 * h11 + r21 * h21
    g12 = r01 * h02 + r11 * h12 + r21 * h22
    g20 = r02 * h00 + r12 * h10 + r22 * h20
    g21 = r02 * h01 + r12 * h11 + r22 * h21
    g22 = r02 * h02 + r12 * h12 + r22 * h22
    e00, e11, e22 = g00 - shift, g11 - shift, g22 - shift
    e01, e02, e12 = 0.5 * (g01 + g10), 0.5 * (g02 + g20), 0.5 * (g12 + g21)
    trace = lame * (e00 + e11 + e22)
    s00, s11, s22 = trace + 2.0 * shear * e00, trace + 2.0 * shear * e11, trace + 2.0 * shear * e22
    s01, s02, s12 = 2.0 * shear * e01, 2.0 * shear * e02, 2.0 * shear * e12
    return (
        volume * (r00 * s00 + r01 * s01 + r02 * s02),
        volume * (r00 * s01 + r01 * s11 + r02 * s12),
        volume * (r00 * s02 + r01 * s12 + r02 * s22),
        volume * (r10 * s00 + r11 * s01 + r12 * s02),
        volume * (r10 * s01 + r11 * s11 + r12 * s12),
        volume * (r10 * s02 + r11 * s12 + r12 * s22),
        volume * (r20 * s00 + r21 * s01 + r22 * s02),
        volume * (r20 * s01 + r21 * s11 + r22 * s12),
        volume * (r20 * s02 + r21 * s12 + r22 * s22),
    )


@numba.njit(cache=True, inline="always")
def _element_forces(
    out, c, tets, rest_edges_inverse, e, r, h, shift, volume, lame, shear
):  # pragma: no cover - compiled
    # P1 forces of the gradient h in the frame r, f_a = V r σ ∇φ_a (∇φ_a: row a of Dm⁻¹, a = 1..3; node 0
    # takes minus their sum), added into out[3 · node + i, c] node by node, each value to n0 right after it
    p00, p01, p02, p10, p11, p12, p20, p21, p22 = _first_piola(r, h, shift, volume, lame, shear)
    n0 = tets[e, 0]
    for a in range(3):
        node = tets[e, a + 1]
        d0, d1, d2 = rest_edges_inverse[e, a, 0], rest_edges_inverse[e, a, 1], rest_edges_inverse[e, a, 2]
        value = p00 * d0 + p01 * d1 + p02 * d2
        out[3 * node, c] += value
        out[3 * n0, c] -= value
        value = p10 * d0 + p11 * d1 + p12 * d2
        out[3 * node + 1, c] += value
        out[3 * n0 + 1, c] -= value
        value = p20 * d0 + p21 * d1 + p22 * d2
        out[3 * node + 2, c] += value
        out[3 * n0 + 2, c] -= value


@numba.njit(cache=True, inline="always")
def _gradient(rest_edges_inverse, e, start, w):  # pragma: no cover - compiled
    # Σ_a w_a ⊗ ∇φ_a = W Dm⁻¹ for the edge differences W = [w₁−w₀, w₂−w₀, w₃−w₀] (w: W's entries), each sum
    # from ``start``: 0.0 makes deformation_gradient's sums, −0.0 (the identity of addition) the products'
    w00, w01, w02, w10, w11, w12, w20, w21, w22 = w
    m00, m01, m02 = rest_edges_inverse[e, 0, 0], rest_edges_inverse[e, 0, 1], rest_edges_inverse[e, 0, 2]
    m10, m11, m12 = rest_edges_inverse[e, 1, 0], rest_edges_inverse[e, 1, 1], rest_edges_inverse[e, 1, 2]
    m20, m21, m22 = rest_edges_inverse[e, 2, 0], rest_edges_inverse[e, 2, 1], rest_edges_inverse[e, 2, 2]
    return (
        start + w00 * m00 + w01 * m10 + w02 * m20,
        start + w00 * m01 + w01 * m11 + w02 * m21,
        start + w00 * m02 + w01 * m12 + w02 * m22,
        start + w10 * m00 + w11 * m10 + w12 * m20,
        start + w10 * m01 + w11 * m11 + w12 * m21,
        start + w10 * m02 + w11 * m12 + w12 * m22,
        start + w20 * m00 + w21 * m10 + w22 * m20,
        start + w20 * m01 + w21 * m11 + w22 * m21,
        start + w20 * m02 + w21 * m12 + w22 * m22,
    )


@numba.njit(cache=True, inline="always")
def _entries(matrix):  # pragma: no cover - compiled
    # a (3, 3) array's entries, row by row
    return (
        matrix[0, 0], matrix[0, 1], matrix[0, 2],
        matrix[1, 0], matrix[1, 1], matrix[1, 2],
        matrix[2, 0], matrix[2, 1], matrix[2, 2],
    )  # fmt: skip


@numba.njit(cache=True, inline="always")
def _edges(vectors, c, n0, n1, n2, n3):  # pragma: no cover - compiled
    # W = [w₁−w₀, w₂−w₀, w₃−w₀] of the nodal vectors vectors[3 · node + i, c] (entries row by row)
    x0, y0, z0 = vectors[3 * n0, c], vectors[3 * n0 + 1, c], vectors[3 * n0 + 2, c]
    return (
        vectors[3 * n1, c] - x0, vectors[3 * n2, c] - x0, vectors[3 * n3, c] - x0,
        vectors[3 * n1 + 1, c] - y0, vectors[3 * n2 + 1, c] - y0, vectors[3 * n3 + 1, c] - y0,
        vectors[3 * n1 + 2, c] - z0, vectors[3 * n2 + 2, c] - z0, vectors[3 * n3 + 2, c] - z0,
    )  # fmt: skip


@numba.njit(cache=True, inline="always")
def _free_edges(vectors, positions, c, n0, n1, n2, n3):  # pragma: no cover - compiled
    # _edges of v given on the free DoFs (positions[d]: DoF d's row there, -1 on a constrained DoF, v = 0)
    x0 = _free(vectors, positions, 3 * n0, c)
    y0 = _free(vectors, positions, 3 * n0 + 1, c)
    z0 = _free(vectors, positions, 3 * n0 + 2, c)
    return (
        _free(vectors, positions, 3 * n1, c) - x0,
        _free(vectors, positions, 3 * n2, c) - x0,
        _free(vectors, positions, 3 * n3, c) - x0,
        _free(vectors, positions, 3 * n1 + 1, c) - y0,
        _free(vectors, positions, 3 * n2 + 1, c) - y0,
        _free(vectors, positions, 3 * n3 + 1, c) - y0,
        _free(vectors, positions, 3 * n1 + 2, c) - z0,
        _free(vectors, positions, 3 * n2 + 2, c) - z0,
        _free(vectors, positions, 3 * n3 + 2, c) - z0,
    )


@numba.njit(cache=True, inline="always")
def _free(vectors, positions, dof, c):  # pragma: no cover - compiled
    row = positions[dof]
    return vectors[row, c] if row >= 0 else 0.0


@numba.njit(cache=True)
def _corotate(
    positions, tets, rest_edges_inverse, volumes, lame, shear, forces, rotations
):  # pragma: no cover - compiled
    f = np.empty((3, 3))
    ds = np.empty((3, 3))
    r = np.empty((3, 3))
    for e in range(tets.shape[0]):
        deformation_rotation(positions, tets, rest_edges_inverse, e, f, ds, r)
        for i in range(3):  # element by element: a slice assignment costs more than the copy here
            for j in range(3):
                rotations[e, i, j] = r[i, j]
        # ε = sym(Rᵀ F) − I: the co-rotated strain of u = Rᵀ x − X (F = Σ_a x_a ⊗ ∇φ_a, I = Σ_a X_a ⊗ ∇φ_a)
        _element_forces(
            forces, 0, tets, rest_edges_inverse, e, _entries(r), _entries(f), 1.0, volumes[e], lame, shear
        )


@numba.njit(cache=True)
def _stiffness_product(
    vectors, tets, rest_edges_inverse, volumes, lame, shear, rotations, out
):  # pragma: no cover - compiled
    for e in range(tets.shape[0]):
        n0, n1, n2, n3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
        r = _entries(rotations[e])
        for c in range(vectors.shape[1]):
            # h = Σ_a v_a ⊗ ∇φ_a = Σ_a (v_a − v_0) ⊗ (Dm⁻¹ row a − 1)
            h = _gradient(rest_edges_inverse, e, -0.0, _edges(vectors, c, n0, n1, n2, n3))
            _element_forces(out, c, tets, rest_edges_inverse, e, r, h, 0.0, volumes[e], lame, shear)


@numba.njit(cache=True)
def _rotation(f, out):  # pragma: no cover - compiled
    # The rotation of F = R U into out (_rotation_of on F's entries).
    _rotation_of(_entries(f), out)


@numba.njit(cache=True)
def _rotation_of(f, out):  # pragma: no cover - compiled
    # The rotation of F = R U. F's polar factor is that of X₀ = F / s for any s > 0; with s = ‖F‖_F / √3 (1
    # for a rotation, λ for a rotation scaled by λ, the node rotations' sum divided by its count) a tet that
    # is not crushed has E₀ = X₀ᵀX₀ − I small, and then the Newton–Schulz iteration
    #     X ← X (3 I − XᵀX) / 2 = X (I − E / 2),   E_next = −¾ E² + ¼ E³
    # converges quadratically to R without a division (Higham, Functions of Matrices, §8.3: ‖I − X₀ᵀX₀‖₂ < 1
    # suffices; ‖E₀‖_F ≤ ½ is asked here: ‖E‖_F then falls as 0.22, 0.04, 1e-3, 1e-6, 1e-12, six updates at
    # most). It stops after the update that follows ‖E‖_F < 1e-8, whose E_next ≤ 1e-16: R to round-off, with
    # neither division nor square root per iteration (most tets of a simulation take 2–4). Anything else
    # (‖E₀‖_F > ½, or no convergence) takes the scaled Newton iteration
    # X ← ½ (γ X + γ⁻¹ X⁻ᵀ), stopped once ‖ΔX‖_F < 1e-8 (next error ≤ ½ ‖X⁻¹‖ ‖ΔX‖²), and what that does not
    # settle (det F ≤ 0, no convergence) goes to polar_rotation_one, which gives the SVD's rotation.
    a00, a01, a02, a10, a11, a12, a20, a21, a22 = f
    scale = a00 * a00 + a01 * a01 + a02 * a02 + a10 * a10 + a11 * a11 + a12 * a12
    scale += a20 * a20 + a21 * a21 + a22 * a22
    det = a00 * (a11 * a22 - a12 * a21) - a01 * (a10 * a22 - a12 * a20) + a02 * (a10 * a21 - a11 * a20)
    if not (det > 1e-14 * (scale * np.sqrt(scale))):
        _polar_of(f, out)
        return
    if _newton_schulz(a00, a01, a02, a10, a11, a12, a20, a21, a22, np.sqrt(3.0 / scale), out):
        return
    scaled = True
    for _ in range(30):
        c00, c01, c02 = a11 * a22 - a12 * a21, a12 * a20 - a10 * a22, a10 * a21 - a11 * a20
        c10, c11, c12 = a02 * a21 - a01 * a22, a00 * a22 - a02 * a20, a01 * a20 - a00 * a21
        c20, c21, c22 = a01 * a12 - a02 * a11, a02 * a10 - a00 * a12, a00 * a11 - a01 * a10
        det = a00 * c00 + a01 * c01 + a02 * c02
        if not (det > 0.0):
            break
        g, h = 0.5, 0.5 / det
        if scaled:
            norm = a00 * a00 + a01 * a01 + a02 * a02 + a10 * a10 + a11 * a11 + a12 * a12
            norm += a20 * a20 + a21 * a21 + a22 * a22
            inverse = c00 * c00 + c01 * c01 + c02 * c02 + c10 * c10 + c11 * c11 + c12 * c12
            inverse = (inverse + c20 * c20 + c21 * c21 + c22 * c22) / (det * det)
            gamma = np.sqrt(np.sqrt(inverse / norm))
            g, h = 0.5 * gamma, 0.5 / (gamma * det)
        b00, b01, b02 = g * a00 + h * c00, g * a01 + h * c01, g * a02 + h * c02
        b10, b11, b12 = g * a10 + h * c10, g * a11 + h * c11, g * a12 + h * c12
        b20, b21, b22 = g * a20 + h * c20, g * a21 + h * c21, g * a22 + h * c22
        change = (b00 - a00) ** 2 + (b01 - a01) ** 2 + (b02 - a02) ** 2 + (b10 - a10) ** 2
        change += (b11 - a11) ** 2 + (b12 - a12) ** 2 + (b20 - a20) ** 2 + (b21 - a21) ** 2
        change += (b22 - a22) ** 2
        a00, a01, a02, a10, a11, a12, a20, a21, a22 = b00, b01, b02, b10, b11, b12, b20, b21, b22
        if change < 1e-6:
            scaled = False
        if change < 1e-16:
            out[0, 0], out[0, 1], out[0, 2] = a00, a01, a02
            out[1, 0], out[1, 1], out[1, 2] = a10, a11, a12
            out[2, 0], out[2, 1], out[2, 2] = a20, a21, a22
            return
    _polar_of(f, out)


@numba.njit(cache=True)
def _polar_of(f, out):  # pragma: no cover - compiled
    # polar_rotation_one of F given by its entries (the cases _rotation_of leaves to it)
    matrix = np.empty((3, 3))
    matrix[0, 0], matrix[0, 1], matrix[0, 2], matrix[1, 0], matrix[1, 1], matrix[1, 2] = f[:6]
    matrix[2, 0], matrix[2, 1], matrix[2, 2] = f[6:]
    polar_rotation_one(matrix, out)


@numba.njit(cache=True, inline="always")
def _newton_schulz(a00, a01, a02, a10, a11, a12, a20, a21, a22, s, out):  # pragma: no cover - compiled
    # _rotation's Newton–Schulz iteration from X₀ = s F (F given by its entries, det F > 0): True with R in
    # out, or False (out untouched) when ‖X₀ᵀX₀ − I‖_F > ½ or it did not converge
    a00, a01, a02, a10, a11, a12, a20, a21, a22 = (
        s * a00,
        s * a01,
        s * a02,
        s * a10,
        s * a11,
        s * a12,
        s * a20,
        s * a21,
        s * a22,
    )
    for iteration in range(8):
        e00 = a00 * a00 + a10 * a10 + a20 * a20 - 1.0
        e11 = a01 * a01 + a11 * a11 + a21 * a21 - 1.0
        e22 = a02 * a02 + a12 * a12 + a22 * a22 - 1.0
        e01 = a00 * a01 + a10 * a11 + a20 * a21
        e02 = a00 * a02 + a10 * a12 + a20 * a22
        e12 = a01 * a02 + a11 * a12 + a21 * a22
        size = e00 * e00 + e11 * e11 + e22 * e22 + 2.0 * (e01 * e01 + e02 * e02 + e12 * e12)
        if iteration == 0 and not (size <= 0.25):
            return False
        m00, m11, m22 = 1.0 - 0.5 * e00, 1.0 - 0.5 * e11, 1.0 - 0.5 * e22
        m01, m02, m12 = -0.5 * e01, -0.5 * e02, -0.5 * e12
        b00 = a00 * m00 + a01 * m01 + a02 * m02
        b01 = a00 * m01 + a01 * m11 + a02 * m12
        b02 = a00 * m02 + a01 * m12 + a02 * m22
        b10 = a10 * m00 + a11 * m01 + a12 * m02
        b11 = a10 * m01 + a11 * m11 + a12 * m12
        b12 = a10 * m02 + a11 * m12 + a12 * m22
        b20 = a20 * m00 + a21 * m01 + a22 * m02
        b21 = a20 * m01 + a21 * m11 + a22 * m12
        b22 = a20 * m02 + a21 * m12 + a22 * m22
        a00, a01, a02, a10, a11, a12, a20, a21, a22 = b00, b01, b02, b10, b11, b12, b20, b21, b22
        if size < 1e-16:
            out[0, 0], out[0, 1], out[0, 2] = a00, a01, a02
            out[1, 0], out[1, 1], out[1, 2] = a10, a11, a12
            out[2, 0], out[2, 1], out[2, 2] = a20, a21, a22
            return True
    return False


@numba.njit(cache=True)
def _corotate_with_nodes(
    positions, tets, rest_edges_inverse, volumes, lame, shear, forces, rotations, node_rotations
):  # pragma: no cover - compiled
    # _corotate and _node_rotations in one pass over the tets (the same sums in the same order), each rotation
    # by _rotation (the nodes' from the sum of their tets' rotations): equal to them to round-off
    out = np.empty((3, 3))
    summed = np.zeros((node_rotations.shape[0], 3, 3))
    flat = positions.reshape(-1, 1)  # (3 · node_count, 1): the layout of _edges
    for e in range(tets.shape[0]):
        n0, n1, n2, n3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
        f = _gradient(rest_edges_inverse, e, 0.0, _edges(flat, 0, n0, n1, n2, n3))
        _rotation_of(f, out)
        r = _entries(out)
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
        rotations[e, 0, 0], rotations[e, 0, 1], rotations[e, 0, 2] = r00, r01, r02
        rotations[e, 1, 0], rotations[e, 1, 1], rotations[e, 1, 2] = r10, r11, r12
        rotations[e, 2, 0], rotations[e, 2, 1], rotations[e, 2, 2] = r20, r21, r22
        _element_forces(forces, 0, tets, rest_edges_inverse, e, r, f, 1.0, volumes[e], lame, shear)
        for a in range(4):
            node = tets[e, a]
            summed[node, 0, 0] += r00
            summed[node, 0, 1] += r01
            summed[node, 0, 2] += r02
            summed[node, 1, 0] += r10
            summed[node, 1, 1] += r11
            summed[node, 1, 2] += r12
            summed[node, 2, 0] += r20
            summed[node, 2, 1] += r21
            summed[node, 2, 2] += r22
    for node in range(node_rotations.shape[0]):
        _rotation(summed[node], node_rotations[node])


@numba.njit(cache=True)
def _free_product(
    vectors, positions, tets, rest_edges_inverse, volumes, lame, shear, rotations, masses, factors, full, out
):  # pragma: no cover - compiled
    # A_ff v for v on the free DoFs: positions[d] is DoF d's row among the free DoFs (-1: constrained, v = 0
    # there); full (dof_count, k) is scratch; masses the lumped mass per free DoF; factors (mass, stiffness).
    # The sums of stiffness_product and CorotatedOperator.full in their order (the same bits).
    full[:, :] = 0.0
    columns = vectors.shape[1]
    for e in range(tets.shape[0]):
        n0, n1, n2, n3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
        r = _entries(rotations[e])
        for c in range(columns):
            h = _gradient(rest_edges_inverse, e, -0.0, _free_edges(vectors, positions, c, n0, n1, n2, n3))
            _element_forces(full, c, tets, rest_edges_inverse, e, r, h, 0.0, volumes[e], lame, shear)
    for d in range(positions.shape[0]):
        row = positions[d]
        if row >= 0:
            for c in range(vectors.shape[1]):
                out[row, c] = full[d, c] * factors[1] + factors[0] * (masses[row] * vectors[row, c])


@numba.njit(cache=True)
def _node_rotations(tets, rotations, out):  # pragma: no cover - compiled
    summed = np.zeros((out.shape[0], 3, 3))
    for e in range(tets.shape[0]):
        for a in range(4):
            node = tets[e, a]
            for i in range(3):
                for j in range(3):
                    summed[node, i, j] += rotations[e, i, j]
    for node in range(out.shape[0]):
        polar_rotation_one(summed[node], out[node])


def node_rotations(tets: np.ndarray, rotations: np.ndarray, node_count: int) -> np.ndarray:
    """One rotation per node, the polar rotation of the sum of its tets' rotations (as
    :meth:`refsim.fem.tissue.TissueModel.node_rotations`), compiled; shape (node_count, 3, 3)."""
    out = np.empty((node_count, 3, 3))
    _node_rotations(tets, np.ascontiguousarray(rotations), out)
    return out


@dataclass(frozen=True, eq=False)
class Elements:
    """What the kernels read of a mesh of P1 tets with an isotropic Hooke material.

    Attributes
    ----------
    tets : Node indices, shape (tet_count, 4), int64.
    rest_edges_inverse : Dm⁻¹ per tet, Dm = [X1−X0, X2−X0, X3−X0], shape (tet_count, 3, 3): its row a is
        ∇φ_{a+1} (and ∇φ_0 = −Σ of the rows).
    volumes : Rest volumes [m³], shape (tet_count,).
    lame : λ [Pa].
    shear : μ [Pa].
    """

    tets: np.ndarray
    rest_edges_inverse: np.ndarray
    volumes: np.ndarray
    lame: float
    shear: float


def corotate(positions: np.ndarray, elements: Elements) -> tuple[np.ndarray, np.ndarray]:
    """Polar rotations and co-rotated internal forces of every tet, in one compiled pass.

    f_a = V R σ ∇φ_a with σ = λ tr ε I + 2μ ε, ε = sym(Rᵀ F) − I: the force R Kₑ (Rᵀ x − X) of the P1 element
    (Kₑ = V Bᵀ D B, the one-point rule being exact), without Kₑ.

    Parameters
    ----------
    positions : Node positions [m], shape (node_count, 3).
    elements : The tets and their material (:class:`Elements`).

    Returns
    -------
    Internal forces [N], shape (3 · node_count,), and rotations, shape (tet_count, 3, 3).
    """
    positions = np.ascontiguousarray(positions, dtype=float)
    forces = np.zeros((positions.size, 1))
    rotations = np.empty((elements.tets.shape[0], 3, 3))
    _corotate(
        positions,
        elements.tets,
        elements.rest_edges_inverse,
        elements.volumes,
        float(elements.lame),
        float(elements.shear),
        forces,
        rotations,
    )
    return forces[:, 0], rotations


def corotate_with_nodes(
    positions: np.ndarray, elements: Elements
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`corotate` and :func:`node_rotations` in one compiled pass over the tets, equal to the two calls
    to round-off (its polar rotation is :func:`_rotation`'s Newton–Schulz iteration, stopped once the next
    update is below round-off, where they take polar_rotation_one's scaled Newton iteration to 1e-15):
    internal forces (3 · node_count,), tet rotations (tet_count, 3, 3) and node rotations (node_count, 3, 3).
    """
    positions = np.ascontiguousarray(positions, dtype=float)
    forces = np.zeros((positions.size, 1))
    rotations = np.empty((elements.tets.shape[0], 3, 3))
    nodes = np.empty((positions.shape[0], 3, 3))
    _corotate_with_nodes(
        positions,
        elements.tets,
        elements.rest_edges_inverse,
        elements.volumes,
        float(elements.lame),
        float(elements.shear),
        forces,
        rotations,
        nodes,
    )
    return forces[:, 0], rotations, nodes


def stiffness_product(vectors: np.ndarray, elements: Elements, rotations: np.ndarray) -> np.ndarray:
    """K v = Σₑ Rₑ Kₑ Rₑᵀ vₑ [N] for DoF vectors v [m] of shape (dof_count,) or (dof_count, k)."""
    vectors = np.asarray(vectors, dtype=float)
    single = vectors.ndim == 1
    block = np.ascontiguousarray(vectors[:, None] if single else vectors)
    out = np.zeros_like(block)
    _stiffness_product(
        block,
        elements.tets,
        elements.rest_edges_inverse,
        elements.volumes,
        float(elements.lame),
        float(elements.shear),
        rotations,
        out,
    )
    return out[:, 0] if single else out


_LAYOUT: list = [None, None, None]  # the last (mass matrix, free DoFs) and their layout (a one-entry memo)


def _layout(mass_matrix: sp.spmatrix, free_dofs: np.ndarray, dof_count: int) -> tuple:
    """What the operator of a model reads at every step, computed once per model: M as CSR, the lumped mass
    per free DoF (None when M is not diagonal: A_ff v then goes through :meth:`CorotatedOperator.full`), each
    DoF's row among the free DoFs (-1: constrained).

    Kept for the last (mass matrix, free DoFs) pair, by identity: both are the model's own arrays, held here
    (so no other object can take their identity) and never modified."""
    if _LAYOUT[0] is mass_matrix and _LAYOUT[1] is free_dofs:
        return _LAYOUT[2]
    mass = sp.csr_matrix(mass_matrix)
    diagonal = mass.nnz == dof_count and np.array_equal(mass.indices, np.arange(dof_count))
    diagonal = diagonal and np.array_equal(mass.indptr, np.arange(dof_count + 1))
    positions = np.full(dof_count, -1, dtype=np.int64)
    positions[free_dofs] = np.arange(free_dofs.size)
    layout = (mass, mass.data[free_dofs] if diagonal else None, positions)
    _LAYOUT[:] = [mass_matrix, free_dofs, layout]
    return layout


class CorotatedOperator:
    """v ↦ A v on the free DoFs, A = mass_factor · M + stiffness_factor · K(R) without assembling A.

    Parameters
    ----------
    dof_count : DoFs of the body.
    free_dofs : Free DoFs, sorted, shape (f,).
    elements : The tets and their material (:class:`Elements`).
    rotations : Element rotations, shape (tet_count, 3, 3).
    mass_matrix : M [kg] on every DoF, sparse (diagonal when lumped).
    mass_factor : 1/dt² + α/dt [1/s²].
    stiffness_factor : 1 + β/dt.
    """

    def __init__(
        self,
        dof_count: int,
        free_dofs: np.ndarray,
        elements: Elements,
        rotations: np.ndarray,
        mass_matrix: sp.spmatrix,
        mass_factor: float,
        stiffness_factor: float,
    ) -> None:
        self.dof_count = dof_count
        self.free_dofs = free_dofs
        self.elements = elements
        self.rotations = rotations
        self.mass_factor = float(mass_factor)
        self.stiffness_factor = float(stiffness_factor)
        self.mass, self._masses, self._positions = _layout(mass_matrix, free_dofs, dof_count)
        self._scratch = {}  # (dof_count, k) arrays of _free_product, by k
        self._factors = np.array([self.mass_factor, self.stiffness_factor])

    def full(self, vectors: np.ndarray) -> np.ndarray:
        """A v on every DoF for v on every DoF, shape (dof_count,) or (dof_count, k)."""
        out = stiffness_product(vectors, self.elements, self.rotations)
        out *= self.stiffness_factor
        out += self.mass_factor * (self.mass @ vectors)
        return out

    def __call__(self, vectors: np.ndarray) -> np.ndarray:
        """A_ff v for v on the free DoFs, shape (f,) or (f, k)."""
        vectors = np.asarray(vectors, dtype=float)
        if self._masses is None:
            full = np.zeros((self.dof_count,) + vectors.shape[1:])
            full[self.free_dofs] = vectors
            return self.full(full)[self.free_dofs]
        single = vectors.ndim == 1
        block = np.ascontiguousarray(vectors[:, None] if single else vectors)
        columns = block.shape[1]
        if columns not in self._scratch:
            self._scratch[columns] = np.empty((self.dof_count, columns))
        out = np.empty_like(block)
        elements = self.elements
        _free_product(
            block,
            self._positions,
            elements.tets,
            elements.rest_edges_inverse,
            elements.volumes,
            float(elements.lame),
            float(elements.shear),
            self.rotations,
            self._masses,
            self._factors,
            self._scratch[columns],
            out,
        )
        return out[:, 0] if single else out


def matrix_free_step(
    *,
    dof_count: int,
    free_dofs: np.ndarray,
    constrained_dofs: np.ndarray,
    positions: np.ndarray,
    velocities: np.ndarray,
    elements: Elements,
    mass_matrix: sp.spmatrix,
    external_forces: np.ndarray,
    mass_factor: float,
    stiffness_factor: float,
    dt: float,
    prescribed: np.ndarray | None,
    rest_matrix: Callable[[], sp.csr_matrix],
) -> StepSystem:
    """The step system of :meth:`refsim.fem.tissue.TissueModel.assemble_step` with an operator instead of a
    matrix (``matrix`` None, ``operator`` v ↦ A_ff v).

    rhs = f_ext − f_int(x₀) + (M/dt) v₀ − A_fc Δx_c, the coupling applied through the operator on the
    prescribed increments; its ``group_rotations`` are :func:`node_rotations`.
    """
    forces, rotations, nodes = corotate_with_nodes(positions, elements)
    nodes.setflags(write=False)
    operator = CorotatedOperator(
        dof_count, free_dofs, elements, rotations, mass_matrix, mass_factor, stiffness_factor
    )
    rhs = np.asarray(external_forces, dtype=float).ravel() - forces
    rhs += (operator.mass @ np.asarray(velocities, dtype=float).ravel()) / dt
    reduced = rhs[free_dofs]
    if prescribed is not None and prescribed.size:
        increments = np.zeros(dof_count)
        increments[constrained_dofs] = prescribed
        reduced = reduced - operator.full(increments)[free_dofs]
    else:
        prescribed = np.zeros(constrained_dofs.size)
    return StepSystem(
        dof_count,
        free_dofs,
        constrained_dofs,
        None,
        reduced,
        prescribed,
        group_rotations=lambda: nodes,
        rest_matrix=rest_matrix,
        operator=operator,
    )
