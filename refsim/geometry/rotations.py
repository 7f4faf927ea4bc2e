"""Batched rotations: Rodrigues' formula, its logarithm, and the polar decomposition.

All functions take and return stacks: rotation vectors of shape (k, 3) [rad] and rotation matrices of shape
(k, 3, 3), row-major, acting on column vectors (``y = R @ x``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["skew", "rotation_matrix", "rotation_vector", "polar_rotation", "needle_rest_frame"]

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
        # Near π the axial part vanishes; take the axis from the symmetric part R + Rᵀ = 2 cos θ I + 2(1−cos θ) a aᵀ.
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


def polar_rotation(deformation_gradients: np.ndarray) -> np.ndarray:
    """Rotation factor R of the polar decomposition F = R U, with det R = +1.

    Computed by batched SVD, F = P Σ Qᵀ, R = P diag(1, 1, det(P Qᵀ)) Qᵀ, so that inverted elements (det F < 0) still
    give a proper rotation (the closest one to F).

    Parameters
    ----------
    deformation_gradients : Matrices F, shape (k, 3, 3).

    Returns
    -------
    Rotation matrices, shape (k, 3, 3).
    """
    u, _, vt = np.linalg.svd(np.asarray(deformation_gradients, dtype=float))
    det = np.linalg.det(u @ vt)
    u[..., :, 2] *= det[..., None]
    return u @ vt


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
