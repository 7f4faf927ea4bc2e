"""Compiled kernels of the beam needle's per-step work: the co-rotational element kinematics
(:func:`refsim.fem.beam_element.local_deformations`), the internal forces, and the centreline (points,
derivatives, Jacobian, closest points) of :class:`refsim.fem.needle.NeedleModel`.

The needle has a dozen elements and a step asks for a few query points at a time, so the NumPy expressions
these kernels replace cost their per-call overhead, not their arithmetic. Each kernel repeats the operations
of the NumPy expression it replaces in their order, so that it gives the same bits
(``tests/fem/test_needle_kernels.py`` holds each to its NumPy reference):

- an ``einsum`` whose summed index is the contiguous last axis of both operands (``"qi,qi->q"``,
  ``"qij,qj->qi"``, ``"mij,mj->mi"``) sums in two lanes, the even terms and the odd terms each from zero
  left to right, then the two lanes, then adds the result to the zeroed output (:func:`_lanes2`);
- an ``einsum`` whose summed index is not the contiguous one of both (``"mji,mjk->mik"``, ``"mij,mi->mj"``,
  ``"qk,qkj->qj"``, ``"mi,mi->m"`` on a column of the element frames) adds its products into the zeroed
  output left to right;
- a stacked 3 × 3 ``@`` goes to the BLAS ``dgemm`` of NumPy's OpenBLAS, which on processors with FMA sums
  with fused multiply-adds from zero (:data:`matmul_fused` probes which on first use; :func:`_dot3`);
- ``np.linalg.norm`` over a last axis of 3 sums the squares left to right; ``np.cross`` is the difference of
  two rounded products; ``np.trace`` sums left to right.

``np.arccos`` is NumPy's own vectorised implementation on this machine's processors (not libm's ``acos``:
the two differ in the last bit for about one argument in ten), so the kinematics kernel stops before it
and NumPy computes the angles between its two halves. Configurations the kernels do not cover (a relative
rotation within 1e-3 rad of π, invalid arc lengths, a degenerate element) go to the NumPy code, which gives
its result or raises its error.
"""

from __future__ import annotations

import functools

import numpy as np
from numba.core import types
from numba.extending import intrinsic

from refsim.kernel_cache import numba

__all__ = [
    "matmul_fused",
    "element_frames",
    "element_kinematics",
    "element_forces",
    "assemble_forces",
    "locate",
    "centreline",
    "project",
]

# The thresholds of the NumPy code (refsim.geometry.rotations, refsim.fem.beam_element), repeated here as
# literals the kernels compile in; tests/fem/test_needle_kernels.py checks that they agree.
_ROTATION_SMALL_ANGLE = 1e-4
_JACOBIAN_SMALL_ANGLE = 1e-4
_NEAR_PI = np.pi - 1e-3


@intrinsic
def _fma(typingctx, a, b, c):
    """a · b + c rounded once (LLVM's ``llvm.fma``: the processor's instruction, or libm's ``fma``)."""
    signature = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, arguments):
        return builder.fma(*arguments)

    return signature, codegen


@functools.cache
def matmul_fused() -> bool:
    """Whether NumPy's stacked 3 × 3 ``@`` sums with fused multiply-adds (OpenBLAS on a processor with FMA),
    probed once per process on numbers whose plain and fused sums differ."""
    a = np.array([[[1.0, 1.0 + 2.0**-30, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]] * 2)
    b = np.array([[[-1.0, 0.0, 0.0], [1.0 - 2.0**-30, 1.0, 0.0], [0.0, 0.0, 1.0]]] * 2)
    product = (a @ b)[0, 0, 0]  # −1 + (1 + u)(1 − u) = −u² fused; 0 when the product is rounded first
    return bool(product != 0.0)


@numba.njit(cache=True, error_model="numpy")
def _dot3(a0, a1, a2, b0, b1, b2, fused):
    """Σ a_k b_k as one row-by-column sum of NumPy's 3 × 3 ``@`` (see :func:`matmul_fused`)."""
    if fused:
        return _fma(a2, b2, _fma(a1, b1, _fma(a0, b0, 0.0)))
    return ((0.0 + a0 * b0) + a1 * b1) + a2 * b2


@numba.njit(cache=True, error_model="numpy")
def _lanes2(a0, a1, a2, b0, b1, b2):
    """``einsum`` over a contiguous axis of 3: (a₀b₀ + a₂b₂) + a₁b₁, added to zero."""
    even = (0.0 + a0 * b0) + a2 * b2
    odd = 0.0 + a1 * b1
    return 0.0 + (even + odd)


@numba.njit(cache=True, error_model="numpy")
def _norm3(x0, x1, x2):
    return np.sqrt((x0 * x0 + x1 * x1) + x2 * x2)


@numba.njit(cache=True, error_model="numpy")
def _frames_kernel(xa, xb, qa, qb, frames, lengths, mean):
    """Co-rotational element frames (`corotational_frames`); returns 1 if an element has zero length, 2 if a
    chord is parallel to its mean axis (after every element is done, as the NumPy checks), else 0."""
    m = xa.shape[0]
    zero = False
    parallel = False
    for e in range(m):
        c0 = xb[e, 0] - xa[e, 0]
        c1 = xb[e, 1] - xa[e, 1]
        c2 = xb[e, 2] - xa[e, 2]
        length = _norm3(c0, c1, c2)
        lengths[e] = length
        if length <= 0.0:
            zero = True
        e10, e11, e12 = c0 / length, c1 / length, c2 / length
        m0 = 0.5 * (qa[e, 0, 1] + qb[e, 0, 1])
        m1 = 0.5 * (qa[e, 1, 1] + qb[e, 1, 1])
        m2 = 0.5 * (qa[e, 2, 1] + qb[e, 2, 1])
        mean[e, 0], mean[e, 1], mean[e, 2] = m0, m1, m2
        e30 = e11 * m2 - e12 * m1
        e31 = e12 * m0 - e10 * m2
        e32 = e10 * m1 - e11 * m0
        norm3 = _norm3(e30, e31, e32)
        if norm3 <= 1e-12 * _norm3(m0, m1, m2):
            parallel = True
        e30, e31, e32 = e30 / norm3, e31 / norm3, e32 / norm3
        e20 = e31 * e12 - e32 * e11
        e21 = e32 * e10 - e30 * e12
        e22 = e30 * e11 - e31 * e10
        frames[e, 0, 0], frames[e, 0, 1], frames[e, 0, 2] = e10, e20, e30
        frames[e, 1, 0], frames[e, 1, 1], frames[e, 1, 2] = e11, e21, e31
        frames[e, 2, 0], frames[e, 2, 1], frames[e, 2, 2] = e12, e22, e32
    if zero:
        return 1
    if parallel:
        return 2
    return 0


@numba.njit(cache=True, error_model="numpy")
def _clipped_cosine(rel):
    """½ (trace − 1) clipped to [−1, 1] (NaN kept), as `rotation_vector`."""
    c = 0.5 * (((rel[0, 0] + rel[1, 1]) + rel[2, 2]) - 1.0)
    if c < -1.0:
        return -1.0
    if c > 1.0:
        return 1.0
    return c


@numba.njit(cache=True, error_model="numpy")
def _relative_kernel(frames, qa, qb, rel_a, rel_b, cos_a, cos_b):
    """R_eᵀ Q of both ends (``einsum("mji,mjk->mik")``) and the cosines of their angles (`rotation_vector`:
    ½ (trace − 1) clipped to [−1, 1])."""
    for e in range(frames.shape[0]):
        for i in range(3):
            for k in range(3):
                sa = 0.0
                sb = 0.0
                for j in range(3):
                    sa += frames[e, j, i] * qa[e, j, k]
                    sb += frames[e, j, i] * qb[e, j, k]
                rel_a[e, i, k] = sa
                rel_b[e, i, k] = sb
        cos_a[e] = _clipped_cosine(rel_a[e])
        cos_b[e] = _clipped_cosine(rel_b[e])


@numba.njit(cache=True, error_model="numpy")
def _rotation_vector_one(rel, theta, out):
    """`rotation_vector` of one matrix from its angle θ (arccos of its clipped cosine, from NumPy); False when
    θ is within 1e-3 of π (the NumPy code's other branch)."""
    a0 = 0.5 * (rel[2, 1] - rel[1, 2])
    a1 = 0.5 * (rel[0, 2] - rel[2, 0])
    a2 = 0.5 * (rel[1, 0] - rel[0, 1])
    sine = np.sin(theta)
    if theta < _ROTATION_SMALL_ANGLE:
        factor = 1.0 + theta * theta / 6.0
    else:
        factor = theta / sine
    out[0], out[1], out[2] = factor * a0, factor * a1, factor * a2
    return not (theta > _NEAR_PI)


@numba.njit(cache=True, error_model="numpy")
def _left_jacobian_inverse_one(t0, t1, t2, k, fused, out):
    """`left_jacobian_inverse` of one rotation vector: I − ½ K + c K², K = skew(θ) (into the scratch ``k``),
    K² as NumPy's stacked ``@``; (3, 3) into ``out``."""
    theta = _norm3(t0, t1, t2)
    if theta < _JACOBIAN_SMALL_ANGLE:
        coefficient = 1.0 / 12.0 + theta * theta / 720.0
    else:
        coefficient = 1.0 / (theta * theta) - (1.0 + np.cos(theta)) / ((2.0 * theta) * np.sin(theta))
    k[0, 0], k[0, 1], k[0, 2] = 0.0, -t2, t1
    k[1, 0], k[1, 1], k[1, 2] = t2, 0.0, -t0
    k[2, 0], k[2, 1], k[2, 2] = -t1, t0, 0.0
    for i in range(3):
        for j in range(3):
            kk = _dot3(k[i, 0], k[i, 1], k[i, 2], k[0, j], k[1, j], k[2, j], fused)
            identity = 1.0 if i == j else 0.0
            out[i, j] = (identity - 0.5 * k[i, j]) + coefficient * kk


@numba.njit(cache=True, error_model="numpy")
def _add_axis_spin(spin, e, offset, q, e30, e31, e32, twice):
    """spin[e, 0, offset:offset + 3] += (Q[:, 1] × e3) / (2 q₂), NumPy's cross and division."""
    s0, s1, s2 = q[e, 0, 1], q[e, 1, 1], q[e, 2, 1]
    spin[e, 0, offset] += (s1 * e32 - s2 * e31) / twice
    spin[e, 0, offset + 1] += (s2 * e30 - s0 * e32) / twice
    spin[e, 0, offset + 2] += (s0 * e31 - s1 * e30) / twice


@numba.njit(cache=True, error_model="numpy")
def _deformations_kernel(
    frames, lengths, mean, qa, qb, rel_a, rel_b, theta_a, theta_b, rest_lengths, fused, d, jac, spin
):
    """The rest of `local_deformations` once the angles are known: d, B and the spin Jacobian W (zeroed
    arrays in); returns False if a relative rotation is within 1e-3 rad of π."""
    m = frames.shape[0]
    rotation = np.empty(3)
    local = np.empty((3, 12))
    inverse = np.empty((3, 3))
    skew = np.empty((3, 3))
    for e in range(m):
        length = lengths[e]
        e10, e11, e12 = frames[e, 0, 0], frames[e, 1, 0], frames[e, 2, 0]
        e20, e21, e22 = frames[e, 0, 1], frames[e, 1, 1], frames[e, 2, 1]
        e30, e31, e32 = frames[e, 0, 2], frames[e, 1, 2], frames[e, 2, 2]
        m0, m1, m2 = mean[e, 0], mean[e, 1], mean[e, 2]
        # einsum("mi,mi->m") of the mean axes and a column of R_e (a strided operand): left to right
        q1 = ((0.0 + m0 * e10) + m1 * e11) + m2 * e12
        q2 = ((0.0 + m0 * e20) + m1 * e21) + m2 * e22
        spin[e, 1, 0], spin[e, 1, 1], spin[e, 1, 2] = e30 / length, e31 / length, e32 / length
        spin[e, 1, 6], spin[e, 1, 7], spin[e, 1, 8] = -e30 / length, -e31 / length, -e32 / length
        spin[e, 2, 0], spin[e, 2, 1], spin[e, 2, 2] = -e20 / length, -e21 / length, -e22 / length
        spin[e, 2, 6], spin[e, 2, 7], spin[e, 2, 8] = e20 / length, e21 / length, e22 / length
        ratio = q1 / q2
        for j in range(12):
            spin[e, 0, j] = ratio * spin[e, 1, j]
        twice = 2.0 * q2
        _add_axis_spin(spin, e, 3, qa, e30, e31, e32, twice)
        _add_axis_spin(spin, e, 9, qb, e30, e31, e32, twice)
        jac[e, 0, 0], jac[e, 0, 1], jac[e, 0, 2] = -e10, -e11, -e12
        jac[e, 0, 6], jac[e, 0, 7], jac[e, 0, 8] = e10, e11, e12
        d[e, 0] = length - rest_lengths[e]
        for end in range(2):
            if end == 0:
                ok = _rotation_vector_one(rel_a[e], theta_a[e], rotation)
                column = 3
            else:
                ok = _rotation_vector_one(rel_b[e], theta_b[e], rotation)
                column = 9
            if not ok:
                return False
            t0, t1, t2 = rotation[0], rotation[1], rotation[2]
            d[e, 1 + 3 * end], d[e, 2 + 3 * end], d[e, 3 + 3 * end] = t0, t1, t2
            for r in range(3):
                for j in range(12):
                    local[r, j] = -spin[e, r, j]
                for c in range(3):
                    local[r, column + c] += frames[e, c, r]
            _left_jacobian_inverse_one(t0, t1, t2, skew, fused, inverse)
            for i in range(3):
                for j in range(12):
                    jac[e, 1 + 3 * end + i, j] = _dot3(
                        inverse[i, 0],
                        inverse[i, 1],
                        inverse[i, 2],
                        local[0, j],
                        local[1, j],
                        local[2, j],
                        fused,
                    )
    return True


def element_frames(xa, xb, qa, qb):
    """`corotational_frames` compiled: (frames, chord lengths, mean axes, status) with status 0 (valid),
    1 (an element of zero length) or 2 (a chord parallel to its mean axis)."""
    m = xa.shape[0]
    frames = np.empty((m, 3, 3))
    lengths = np.empty(m)
    mean = np.empty((m, 3))
    status = _frames_kernel(
        np.ascontiguousarray(xa, dtype=float),
        np.ascontiguousarray(xb, dtype=float),
        np.ascontiguousarray(qa, dtype=float),
        np.ascontiguousarray(qb, dtype=float),
        frames,
        lengths,
        mean,
    )
    return frames, lengths, mean, status


def element_kinematics(xa, xb, qa, qb, rest_lengths):
    """`local_deformations` compiled: its dictionary, or None where the NumPy code must answer (a degenerate
    element, whose error it raises, or a relative rotation near π)."""
    xa = np.ascontiguousarray(xa, dtype=float)
    xb = np.ascontiguousarray(xb, dtype=float)
    qa = np.ascontiguousarray(qa, dtype=float)
    qb = np.ascontiguousarray(qb, dtype=float)
    frames, lengths, mean, status = element_frames(xa, xb, qa, qb)
    if status:
        return None
    m = lengths.size
    rel_a, rel_b = np.empty((m, 3, 3)), np.empty((m, 3, 3))
    cos_a, cos_b = np.empty(m), np.empty(m)
    _relative_kernel(frames, qa, qb, rel_a, rel_b, cos_a, cos_b)
    theta_a, theta_b = np.arccos(cos_a), np.arccos(cos_b)  # NumPy's arccos: see the module docstring
    d = np.zeros((m, 7))
    jac = np.zeros((m, 7, 12))
    spin = np.zeros((m, 3, 12))
    rest = np.ascontiguousarray(np.broadcast_to(np.asarray(rest_lengths, dtype=float), (m,)))
    if not _deformations_kernel(
        frames, lengths, mean, qa, qb, rel_a, rel_b, theta_a, theta_b, rest, matmul_fused(), d, jac, spin
    ):
        return None
    return {
        "deformations": d,
        "jacobian": jac,
        "element_frames": frames,
        "chord_lengths": lengths,
        "spin_jacobian": spin,
    }


@numba.njit(cache=True, error_model="numpy")
def _forces_kernel(d, jac, stiffness, forces, energies):
    """f = Bᵀ K₇ d (``einsum("mij,mj->mi")`` then ``einsum("mij,mi->mj")``) and ½ dᵀ K₇ d per element."""
    m = d.shape[0]
    local = np.empty(7)
    for e in range(m):
        for i in range(7):
            even = 0.0
            odd = 0.0
            for j in range(7):
                if j % 2 == 0:
                    even += stiffness[e, i, j] * d[e, j]
                else:
                    odd += stiffness[e, i, j] * d[e, j]
            local[i] = 0.0 + (even + odd)
        for j in range(12):
            total = 0.0
            for i in range(7):
                total += jac[e, i, j] * local[i]
            forces[e, j] = total
        even = 0.0
        odd = 0.0
        for i in range(7):
            if i % 2 == 0:
                even += d[e, i] * local[i]
            else:
                odd += d[e, i] * local[i]
        energies[e] = 0.5 * (0.0 + (even + odd))


def element_forces(kinematics, reduced_stiffness):
    """`beam_element_forces` from the element kinematics: (forces (m, 12), energies (m,))."""
    d = kinematics["deformations"]
    m = d.shape[0]
    forces = np.empty((m, 12))
    energies = np.empty(m)
    _forces_kernel(d, kinematics["jacobian"], reduced_stiffness, forces, energies)
    return forces, energies


@numba.njit(cache=True, error_model="numpy")
def _assemble_forces_kernel(forces, total):
    """``np.bincount`` of the element forces on their DoFs (6 e + k), in element order, into zeros."""
    for e in range(forces.shape[0]):
        for k in range(12):
            total[6 * e + k] += forces[e, k]


def assemble_forces(forces, dof_count):
    """The element forces summed on the DoFs (6 e + k) as a bincount, in element order, shape (dof_count,)."""
    total = np.zeros(dof_count)
    _assemble_forces_kernel(forces, total)
    return total


@numba.njit(cache=True, error_model="numpy")
def _clip(x, low, high):
    """``np.clip`` of one float: NaN kept, else max then min as NumPy's (``a > b ? a : b``, so −0 → +0)."""
    if np.isnan(x):
        return x
    x = x if x > low else low
    return x if x < high else high


@numba.njit(cache=True, error_model="numpy")
def _locate_one(s, length, element_length, last):
    """`NeedleModel._locate` of one valid arc length: (element, ξ)."""
    clipped = _clip(s, 0.0, length)
    scaled = clipped / element_length
    element = min(np.int64(np.floor(scaled)), last)
    return element, scaled - element


@numba.njit(cache=True, error_model="numpy")
def _locate_kernel(s, length, element_length, last, elements, xi):
    """`NeedleModel._locate` on valid arc lengths; False (nothing written to trust) if one is not."""
    slack = 1e-9 * length
    for i in range(s.size):
        value = s[i]
        if not (np.isfinite(value) and value >= -slack and value <= length + slack):
            return False
    for i in range(s.size):
        elements[i], xi[i] = _locate_one(s[i], length, element_length, last)
    return True


def locate(arc_lengths, length, element_length, element_count):
    """Element and local coordinate of each arc length (1-D float array), or None if one lies outside
    [0, length] (by more than 1e-9 length) or is not finite."""
    elements = np.empty(arc_lengths.size, dtype=np.int64)
    xi = np.empty(arc_lengths.size)
    if not _locate_kernel(arc_lengths, length, element_length, element_count - 1, elements, xi):
        return None
    return elements, xi


@numba.njit(cache=True, error_model="numpy")
def _point_one(positions, d, rot, e, x, l0, point, derivative, offset):
    """Centreline point, dp/ds and the rotated deflection (offset) at element e, local coordinate x."""
    h0 = x * ((1.0 - x) * (1.0 - x))
    h1 = -(x * x) * (1.0 - x)
    g0 = (1.0 - x) * (1.0 - 3.0 * x)
    g1 = x * (3.0 * x - 2.0)
    v = l0 * (0.0 + ((0.0 + h0 * d[e, 3]) + (0.0 + h1 * d[e, 6])))
    w = -l0 * (0.0 + ((0.0 + h0 * d[e, 2]) + (0.0 + h1 * d[e, 5])))
    dv = l0 * (0.0 + ((0.0 + g0 * d[e, 3]) + (0.0 + g1 * d[e, 6])))
    dw = -l0 * (0.0 + ((0.0 + g0 * d[e, 2]) + (0.0 + g1 * d[e, 5])))
    for i in range(3):
        chord = positions[e + 1, i] - positions[e, i]
        off = _lanes2(rot[e, i, 0], rot[e, i, 1], rot[e, i, 2], 0.0, v, w)
        offset[i] = off
        point[i] = (positions[e, i] + x * chord) + off
        derivative[i] = (chord + _lanes2(rot[e, i, 0], rot[e, i, 1], rot[e, i, 2], 0.0, dv, dw)) / l0


@numba.njit(cache=True, error_model="numpy")
def _centreline_kernel(
    positions, d, rot, b, spin, elements, xi, l0, jacobian, fused, points, derivatives, jac
):
    """`NeedleModel._centreline` at located points: points, derivatives and (``jacobian``) J, zeroed in."""
    offset = np.empty(3)
    left = np.empty((3, 3))
    rows = np.zeros((3, 12))
    for q in range(elements.size):
        e = elements[q]
        x = xi[q]
        _point_one(positions, d, rot, e, x, l0, points[q], derivatives[q], offset)
        if not jacobian:
            continue
        h0 = x * ((1.0 - x) * (1.0 - x))
        h1 = -(x * x) * (1.0 - x)
        for i in range(3):
            jac[q, i, i] = 1.0 - x
            jac[q, i, 6 + i] = x
        # skew(offset) @ rot, then @ spin (NumPy's stacked @, left to right)
        o0, o1, o2 = offset[0], offset[1], offset[2]
        for j in range(3):
            r0, r1, r2 = rot[e, 0, j], rot[e, 1, j], rot[e, 2, j]
            left[0, j] = _dot3(0.0, -o2, o1, r0, r1, r2, fused)
            left[1, j] = _dot3(o2, 0.0, -o0, r0, r1, r2, fused)
            left[2, j] = _dot3(-o1, o0, 0.0, r0, r1, r2, fused)
        for i in range(3):
            for j in range(12):
                jac[q, i, j] -= _dot3(
                    left[i, 0], left[i, 1], left[i, 2], spin[e, 0, j], spin[e, 1, j], spin[e, 2, j], fused
                )
        for j in range(12):
            rows[1, j] = l0 * ((0.0 + h0 * b[e, 3, j]) + h1 * b[e, 6, j])
            rows[2, j] = -l0 * ((0.0 + h0 * b[e, 2, j]) + h1 * b[e, 5, j])
        for i in range(3):
            for j in range(12):
                jac[q, i, j] += _dot3(
                    rot[e, i, 0], rot[e, i, 1], rot[e, i, 2], rows[0, j], rows[1, j], rows[2, j], fused
                )


def centreline(positions, kinematics, elements, xi, element_length, *, jacobian):
    """Points, dp/ds and (``jacobian``) J of the centreline at located points (`NeedleModel._centreline`)."""
    q = elements.size
    points = np.empty((q, 3))
    derivatives = np.empty((q, 3))
    jac = np.zeros((q, 3, 12) if jacobian else (0, 3, 12))
    _centreline_kernel(
        positions,
        kinematics["deformations"],
        kinematics["element_frames"],
        kinematics["jacobian"],
        kinematics["spin_jacobian"],
        elements,
        xi,
        element_length,
        jacobian,
        matmul_fused(),
        points,
        derivatives,
        jac,
    )
    return points, derivatives, jac


@numba.njit(cache=True, error_model="numpy")
def _valid_arc(value, length):
    slack = 1e-9 * length
    return np.isfinite(value) and value >= -slack and value <= length + slack


@numba.njit(cache=True, error_model="numpy")
def _project_kernel(
    positions,
    d,
    rot,
    samples,
    polyline,
    points,
    length,
    l0,
    last,
    iterations,
    arc_out,
    closest_out,
    distance_out,
):
    """`NeedleModel.project_on_centreline`: the polyline search, then Gauss–Newton on the curve; False if an
    arc length it would evaluate is invalid (the NumPy code then raises its error)."""
    count = polyline.shape[0] - 1
    segments = np.empty((count, 3))
    squared = np.empty(count)
    for s in range(count):
        for i in range(3):
            segments[s, i] = polyline[s + 1, i] - polyline[s, i]
        squared[s] = _lanes2(
            segments[s, 0], segments[s, 1], segments[s, 2], segments[s, 0], segments[s, 1], segments[s, 2]
        )
    closest = np.empty(3)
    tangent = np.empty(3)
    trial_point = np.empty(3)
    trial_tangent = np.empty(3)
    offset = np.empty(3)
    for q in range(points.shape[0]):
        p0, p1, p2 = points[q, 0], points[q, 1], points[q, 2]
        best = -1
        best_value = 0.0
        best_t = 0.0
        for s in range(count):
            r0, r1, r2 = p0 - polyline[s, 0], p1 - polyline[s, 1], p2 - polyline[s, 2]
            g0, g1, g2 = segments[s, 0], segments[s, 1], segments[s, 2]
            t = _clip(_lanes2(r0, r1, r2, g0, g1, g2) / squared[s], 0.0, 1.0)
            h0, h1, h2 = r0 - t * g0, r1 - t * g1, r2 - t * g2
            value = _lanes2(h0, h1, h2, h0, h1, h2)
            # np.argmin: the first minimum, or the first NaN
            if best < 0 or (not np.isnan(best_value) and (np.isnan(value) or value < best_value)):
                best, best_value, best_t = s, value, t
        arc = samples[best] + best_t * (samples[best + 1] - samples[best])
        if not _valid_arc(arc, length):
            return False
        element, x = _locate_one(arc, length, l0, last)
        _point_one(positions, d, rot, element, x, l0, closest, tangent, offset)
        distance = _norm3(p0 - closest[0], p1 - closest[1], p2 - closest[2])
        for _ in range(iterations):
            c0, c1, c2 = p0 - closest[0], p1 - closest[1], p2 - closest[2]
            t0, t1, t2 = tangent[0], tangent[1], tangent[2]
            step = _lanes2(c0, c1, c2, t0, t1, t2) / _lanes2(t0, t1, t2, t0, t1, t2)
            trial = _clip(arc + step, 0.0, length)
            if not _valid_arc(trial, length):
                return False
            element, x = _locate_one(trial, length, l0, last)
            _point_one(positions, d, rot, element, x, l0, trial_point, trial_tangent, offset)
            trial_distance = _norm3(p0 - trial_point[0], p1 - trial_point[1], p2 - trial_point[2])
            if trial_distance < distance:
                arc = trial
                closest[:] = trial_point
                tangent[:] = trial_tangent
                distance = trial_distance
        arc_out[q] = arc
        closest_out[q] = closest
        distance_out[q] = distance
    return True


def project(
    positions, kinematics, samples, polyline, points, length, element_length, element_count, iterations
):
    """`NeedleModel.project_on_centreline` on its polyline: (arc lengths, closest points, distances), or None
    where the NumPy code must answer (an invalid arc length: it raises)."""
    q = points.shape[0]
    arc = np.empty(q)
    closest = np.empty((q, 3))
    distance = np.empty(q)
    ok = _project_kernel(
        positions,
        kinematics["deformations"],
        kinematics["element_frames"],
        samples,
        polyline,
        points,
        length,
        element_length,
        element_count - 1,
        iterations,
        arc,
        closest,
        distance,
    )
    return (arc, closest, distance) if ok else None


@numba.njit(cache=True, error_model="numpy")
def _corotated_kernel(rotations, stiffness, scatter, fused, data):
    """`NeedleModel.tangent_stiffness` ("corotated"): R_e K_e R_eᵀ per element, R_e = diag(R, R, R, R), as
    NumPy's two stacked 12 × 12 ``@`` (every term of each sum, zeros included), then ``np.bincount`` of the
    element matrices into the CSR data through ``scatter``."""
    block = np.zeros((12, 12))
    left = np.empty((12, 12))
    index = 0
    for e in range(rotations.shape[0]):
        for b in range(4):
            for i in range(3):
                for j in range(3):
                    block[3 * b + i, 3 * b + j] = rotations[e, i, j]
        for i in range(12):
            for j in range(12):
                total = 0.0
                for k in range(12):
                    if fused:
                        total = _fma(block[i, k], stiffness[k, j], total)
                    else:
                        total = total + block[i, k] * stiffness[k, j]
                left[i, j] = total
        for i in range(12):
            for j in range(12):
                total = 0.0
                for k in range(12):
                    if fused:
                        total = _fma(left[i, k], block[j, k], total)
                    else:
                        total = total + left[i, k] * block[j, k]
                data[scatter[index]] += total
                index += 1


def corotated_stiffness_data(rotations, stiffness, scatter, size):
    """The CSR data of the assembled co-rotated tangent (see `_corotated_kernel`), shape (size,)."""
    data = np.zeros(size)
    _corotated_kernel(rotations, stiffness, scatter, matmul_fused(), data)
    return data


@numba.njit(cache=True, error_model="numpy")
def _increment_kernel(positions, frames, delta, fused, new_positions, new_frames):
    """`NeedleModel.apply_increment`: x + Δu and `rotation_matrix`(Δθ) @ Q per node (Rodrigues' formula with
    its series below 1e-4 rad, k @ k and the product as NumPy's stacked ``@``)."""
    rotation = np.empty((3, 3))
    k = np.empty((3, 3))
    for n in range(positions.shape[0]):
        for i in range(3):
            new_positions[n, i] = positions[n, i] + delta[6 * n + i]
        t0, t1, t2 = delta[6 * n + 3], delta[6 * n + 4], delta[6 * n + 5]
        theta = _norm3(t0, t1, t2)
        theta2 = theta * theta
        if theta < _ROTATION_SMALL_ANGLE:
            a = (1.0 - theta2 / 6.0) + theta2 * theta2 / 120.0
            b = (0.5 - theta2 / 24.0) + theta2 * theta2 / 720.0
        else:
            a = np.sin(theta) / theta
            b = (1.0 - np.cos(theta)) / (theta * theta)
        k[0, 0], k[0, 1], k[0, 2] = 0.0, -t2, t1
        k[1, 0], k[1, 1], k[1, 2] = t2, 0.0, -t0
        k[2, 0], k[2, 1], k[2, 2] = -t1, t0, 0.0
        for i in range(3):
            for j in range(3):
                kk = _dot3(k[i, 0], k[i, 1], k[i, 2], k[0, j], k[1, j], k[2, j], fused)
                identity = 1.0 if i == j else 0.0
                rotation[i, j] = (identity + a * k[i, j]) + b * kk
        for i in range(3):
            for j in range(3):
                new_frames[n, i, j] = _dot3(
                    rotation[i, 0],
                    rotation[i, 1],
                    rotation[i, 2],
                    frames[n, 0, j],
                    frames[n, 1, j],
                    frames[n, 2, j],
                    fused,
                )


def apply_increment(positions, frames, delta):
    """New positions and frames after a DoF increment (see `_increment_kernel`)."""
    new_positions = np.empty(positions.shape)
    new_frames = np.empty(frames.shape)
    _increment_kernel(positions, frames, delta, matmul_fused(), new_positions, new_frames)
    return new_positions, new_frames
