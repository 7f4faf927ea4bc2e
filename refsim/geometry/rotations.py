"""Batched rotations: Rodrigues' formula, its logarithm, and the polar decomposition.

All functions take and return stacks: rotation vectors of shape (k, 3) [rad] and rotation matrices of shape
(k, 3, 3), row-major, acting on column vectors (``y = R @ x``).
"""

from __future__ import annotations

import numpy as np

from refsim.kernel_cache import numba

__all__ = [
    "skew",
    "rotation_matrix",
    "rotation_vector",
    "polar_rotation",
    "polar_rotation_one",
    "needle_rest_frame",
]

# Below this angle [rad] the series expansions of sin(θ)/θ and (1 − cos θ)/θ² are used; their truncation error
# (θ⁴/120 and θ⁴/720) is then under 1e-18, below double round-off.
_SMALL_ANGLE = 1e-4


def skew(vectors: np.ndarray) -> np.ndarray:
    """Cross-product matrices.

    Parameters
    ----------
    vectors : Vectors, shape (k, 3).

    Returns
    -------
    Matrices S with ``S[i] @ y == np.cross(vectors[i], y)``, shape (k, 3, 3).
    """
    vectors = np.asarray(vectors, dtype=float)
    out = np.zeros(vectors.shape[:-1] + (3, 3))
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    out[..., 0, 1], out[..., 0, 2] = -z, y
    out[..., 1, 0], out[..., 1, 2] = z, -x
    out[..., 2, 0], out[..., 2, 1] = -y, x
    return out


def rotation_matrix(rotation_vectors: np.ndarray) -> np.ndarray:
    """Rotation matrices from rotation vectors (Rodrigues' formula), exact near zero.

    Parameters
    ----------
    rotation_vectors : Axis times angle [rad], shape (k, 3).

    Returns
    -------
    Rotation matrices, shape (k, 3, 3).
    """
    rotation_vectors = np.asarray(rotation_vectors, dtype=float)
    theta = np.linalg.norm(rotation_vectors, axis=-1)
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    theta2 = theta * theta
    a = np.where(small, 1.0 - theta2 / 6.0 + theta2 * theta2 / 120.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0 + theta2 * theta2 / 720.0, (1.0 - np.cos(safe)) / (safe * safe))
    k = skew(rotation_vectors)
    eye = np.broadcast_to(np.eye(3), k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def rotation_vector(matrices: np.ndarray) -> np.ndarray:
    """Rotation vectors (logarithm) of rotation matrices, valid for every angle in [0, π].

    Parameters
    ----------
    matrices : Rotation matrices, shape (k, 3, 3).

    Returns
    -------
    Axis times angle [rad], shape (k, 3), angle in [0, π].
    """
    matrices = np.asarray(matrices, dtype=float)
    trace = np.trace(matrices, axis1=-2, axis2=-1)
    cos_theta = np.clip(0.5 * (trace - 1.0), -1.0, 1.0)
    theta = np.arccos(cos_theta)
    axial = 0.5 * np.stack(
        [
            matrices[..., 2, 1] - matrices[..., 1, 2],
            matrices[..., 0, 2] - matrices[..., 2, 0],
            matrices[..., 1, 0] - matrices[..., 0, 1],
        ],
        axis=-1,
    )  # sin(θ) * axis
    sin_theta = np.sin(theta)
    small = theta < _SMALL_ANGLE
    near_pi = theta > np.pi - 1e-3
    factor = np.where(small, 1.0 + theta * theta / 6.0, theta / np.where(small, 1.0, sin_theta))
    out = factor[..., None] * axial
    if np.any(near_pi):
        # Near π the axial part vanishes; take the axis from the symmetric part R + Rᵀ = 2 cos θ I + 2(1−cos
        # θ) a aᵀ.
        sym = 0.5 * (matrices[near_pi] + np.swapaxes(matrices[near_pi], -1, -2))
        c = cos_theta[near_pi][..., None, None]
        aat = (sym - c * np.eye(3)) / (1.0 - c)
        column = np.argmax(np.diagonal(aat, axis1=-2, axis2=-1), axis=-1)
        axis = np.take_along_axis(aat, column[..., None, None].repeat(3, axis=-1), axis=-2)[..., 0, :]
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        # Choose the sign that agrees with the (small) axial part, when there is one.
        sign = np.where(np.einsum("...i,...i->...", axis, axial[near_pi]) < 0.0, -1.0, 1.0)
        out[near_pi] = (sign * theta[near_pi])[..., None] * axis
    return out


@numba.njit(cache=True, fastmath=False)
def _closest_rotation(f: np.ndarray, out: np.ndarray) -> None:
    """The proper rotation R maximising tr(Rᵀ F), into ``out``: R = P diag(1, 1, det(P Qᵀ)) Qᵀ for F = P Σ Qᵀ
    (the closest rotation to F in the Frobenius norm), computed without an SVD (numba's LAPACK wrappers take
    seconds to compile) as Horn's quaternion: tr(R(q)ᵀ F) = qᵀ K q for a unit quaternion q, K the symmetric
    4 × 4 matrix below, so q is K's eigenvector of largest eigenvalue (Horn, J. Opt. Soc. Am. A 4(4), 1987),
    found by cyclic Jacobi rotations (to round-off: the off-diagonal mass below 1e-32 of K's)."""
    k = np.empty((4, 4))
    k[0, 0] = f[0, 0] + f[1, 1] + f[2, 2]
    k[1, 1] = f[0, 0] - f[1, 1] - f[2, 2]
    k[2, 2] = -f[0, 0] + f[1, 1] - f[2, 2]
    k[3, 3] = -f[0, 0] - f[1, 1] + f[2, 2]
    k[0, 1] = k[1, 0] = f[2, 1] - f[1, 2]
    k[0, 2] = k[2, 0] = f[0, 2] - f[2, 0]
    k[0, 3] = k[3, 0] = f[1, 0] - f[0, 1]
    k[1, 2] = k[2, 1] = f[0, 1] + f[1, 0]
    k[1, 3] = k[3, 1] = f[0, 2] + f[2, 0]
    k[2, 3] = k[3, 2] = f[1, 2] + f[2, 1]
    v = np.eye(4)
    total = 0.0
    for i in range(4):
        for j in range(4):
            total += k[i, j] * k[i, j]
    for _ in range(50):
        off = 0.0
        for i in range(3):
            for j in range(i + 1, 4):
                off += k[i, j] * k[i, j]
        if off <= 1e-32 * total:
            break
        for p in range(3):
            for q in range(p + 1, 4):
                if k[p, q] == 0.0:
                    continue
                theta = (k[q, q] - k[p, p]) / (2.0 * k[p, q])
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
                c = 1.0 / np.sqrt(t * t + 1.0)
                sn = t * c
                for r in range(4):  # K ← K J (columns p, q)
                    kp, kq = k[r, p], k[r, q]
                    k[r, p], k[r, q] = c * kp - sn * kq, sn * kp + c * kq
                for r in range(4):  # K ← Jᵀ K (rows p, q)
                    kp, kq = k[p, r], k[q, r]
                    k[p, r], k[q, r] = c * kp - sn * kq, sn * kp + c * kq
                for r in range(4):  # V ← V J
                    vp, vq = v[r, p], v[r, q]
                    v[r, p], v[r, q] = c * vp - sn * vq, sn * vp + c * vq
    best = 0
    for i in range(1, 4):
        if k[i, i] > k[best, best]:
            best = i
    w, x, y, z = v[0, best], v[1, best], v[2, best], v[3, best]
    norm = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    out[0, 0] = w * w + x * x - y * y - z * z
    out[0, 1] = 2.0 * (x * y - w * z)
    out[0, 2] = 2.0 * (x * z + w * y)
    out[1, 0] = 2.0 * (x * y + w * z)
    out[1, 1] = w * w - x * x + y * y - z * z
    out[1, 2] = 2.0 * (y * z - w * x)
    out[2, 0] = 2.0 * (x * z - w * y)
    out[2, 1] = 2.0 * (y * z + w * x)
    out[2, 2] = w * w - x * x - y * y + z * z


@numba.njit(cache=True, fastmath=False)
def polar_rotation_one(f: np.ndarray, out: np.ndarray) -> int:
    """Rotation of the polar decomposition of one 3 × 3 matrix, into ``out``; returns the iterations (-1:
    SVD).

    Scaled Newton iteration X ← ½ (γ X + γ⁻¹ X⁻ᵀ), γ = (‖X⁻¹‖_F / ‖X‖_F)^½ (Higham, Functions of Matrices,
    §8.6), from X₀ = F; it converges quadratically to R when det F > 0. When det F ≤ 0 (an inverted or flat
    element) or without convergence in 30 iterations it takes the closest proper rotation
    (R = P diag(1, 1, det(P Qᵀ)) Qᵀ for F = P Σ Qᵀ; computed by :func:`_closest_rotation`, without LAPACK).
    """
    a00, a01, a02 = f[0, 0], f[0, 1], f[0, 2]
    a10, a11, a12 = f[1, 0], f[1, 1], f[1, 2]
    a20, a21, a22 = f[2, 0], f[2, 1], f[2, 2]
    det = a00 * (a11 * a22 - a12 * a21) - a01 * (a10 * a22 - a12 * a20) + a02 * (a10 * a21 - a11 * a20)
    scale = (
        a00 * a00
        + a01 * a01
        + a02 * a02
        + a10 * a10
        + a11 * a11
        + a12 * a12
        + a20 * a20
        + a21 * a21
        + a22 * a22
    )
    if not (det > 1e-14 * scale**1.5):
        _closest_rotation(f, out)
        return -1
    scaled = True
    for iteration in range(30):
        # cofactor matrix C: X⁻ᵀ = C / det
        c00 = a11 * a22 - a12 * a21
        c01 = a12 * a20 - a10 * a22
        c02 = a10 * a21 - a11 * a20
        c10 = a02 * a21 - a01 * a22
        c11 = a00 * a22 - a02 * a20
        c12 = a01 * a20 - a00 * a21
        c20 = a01 * a12 - a02 * a11
        c21 = a02 * a10 - a00 * a12
        c22 = a00 * a11 - a01 * a10
        det = a00 * c00 + a01 * c01 + a02 * c02
        norm = (
            a00 * a00
            + a01 * a01
            + a02 * a02
            + a10 * a10
            + a11 * a11
            + a12 * a12
            + a20 * a20
            + a21 * a21
            + a22 * a22
        )
        inverse_norm = (
            c00 * c00
            + c01 * c01
            + c02 * c02
            + c10 * c10
            + c11 * c11
            + c12 * c12
            + c20 * c20
            + c21 * c21
            + c22 * c22
        ) / (det * det)
        gamma = (inverse_norm / norm) ** 0.25 if scaled else 1.0
        g = 0.5 * gamma
        h = 0.5 / (gamma * det)
        b00, b01, b02 = g * a00 + h * c00, g * a01 + h * c01, g * a02 + h * c02
        b10, b11, b12 = g * a10 + h * c10, g * a11 + h * c11, g * a12 + h * c12
        b20, b21, b22 = g * a20 + h * c20, g * a21 + h * c21, g * a22 + h * c22
        change = (
            (b00 - a00) ** 2
            + (b01 - a01) ** 2
            + (b02 - a02) ** 2
            + (b10 - a10) ** 2
            + (b11 - a11) ** 2
            + (b12 - a12) ** 2
            + (b20 - a20) ** 2
            + (b21 - a21) ** 2
            + (b22 - a22) ** 2
        )
        a00, a01, a02, a10, a11, a12, a20, a21, a22 = b00, b01, b02, b10, b11, b12, b20, b21, b22
        if change < 1e-6:
            scaled = False  # near convergence the scaling only perturbs the quadratic rate
        if change < 1e-30:  # ‖ΔX‖_F < 1e-15: the next step is below round-off (quadratic convergence)
            out[0, 0], out[0, 1], out[0, 2] = a00, a01, a02
            out[1, 0], out[1, 1], out[1, 2] = a10, a11, a12
            out[2, 0], out[2, 1], out[2, 2] = a20, a21, a22
            return iteration + 1
    _closest_rotation(f, out)
    return -1


@numba.njit(cache=True)
def _polar_batch(f: np.ndarray, out: np.ndarray) -> None:
    for k in range(f.shape[0]):
        polar_rotation_one(f[k], out[k])


def polar_rotation(deformation_gradients: np.ndarray) -> np.ndarray:
    """Rotation factor R of the polar decomposition F = R U, with det R = +1 (compiled scaled Newton).

    See :func:`polar_rotation_one`: scaled Newton when det F > 0, the SVD (closest proper rotation) otherwise.
    Equal to the batched SVD's rotation to a few ε (tests/fem/test_assembly.py).

    Parameters
    ----------
    deformation_gradients : Matrices F, shape (k, 3, 3).

    Returns
    -------
    Rotation matrices, shape (k, 3, 3).
    """
    f = np.ascontiguousarray(deformation_gradients, dtype=float)
    if f.shape[-2:] != (3, 3):
        raise ValueError(f"deformation_gradients must have shape (k, 3, 3), got {f.shape}")
    flat = f.reshape(-1, 3, 3)
    out = np.empty_like(flat)
    _polar_batch(flat, out)
    return out.reshape(f.shape)


def needle_rest_frame(direction: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """The needle's rest material frame: columns (direction, e₁, direction × e₁), shape (3, 3).

    The one convention of both needles (the rigid one and the beam model). e₁ is the part of ``up`` normal to
    ``direction``, normalised; by default ``up`` is world z, or world y when the needle is within 25° of z.

    Parameters
    ----------
    direction : Needle direction from base to tip, shape (3,), non-zero (normalised here).
    up : Reference vector fixing the cross-section frame, shape (3,), not parallel to ``direction``.

    Raises
    ------
    ValueError
        When ``direction`` is zero or not finite, or ``up`` is parallel to it.
    """
    direction = np.asarray(direction, dtype=float)
    norm = np.linalg.norm(direction) if direction.shape == (3,) else 0.0
    if direction.shape != (3,) or not np.isfinite(norm) or norm <= 0.0:
        raise ValueError(f"direction must be a non-zero finite 3-vector, got {direction!r}")
    direction = direction / norm
    if up is None:
        up = np.array([0.0, 0.0, 1.0]) if abs(direction[2]) < np.cos(np.radians(25.0)) else np.eye(3)[1]
    up = np.asarray(up, dtype=float)
    if up.shape != (3,) or not np.all(np.isfinite(up)):
        raise ValueError(f"up must be a finite 3-vector, got {up!r}")
    normal = up - (up @ direction) * direction
    if np.linalg.norm(normal) <= 1e-6 * max(np.linalg.norm(up), 1e-300):
        raise ValueError(f"up {up!r} is parallel to direction {direction!r}: frame undefined")
    normal /= np.linalg.norm(normal)
    return np.stack([direction, normal, np.cross(direction, normal)], axis=-1)
