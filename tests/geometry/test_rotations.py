"""Rotations: Rodrigues' formula and its logarithm against scipy, polar decomposition properties."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from refsim.geometry import polar_rotation, rotation_matrix, rotation_vector, skew


def _random_vectors(rng, count, angles):
    axes = rng.normal(size=(count, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return axes * angles[:, None]


def test_skew_is_the_cross_product():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, 50, 3))
    np.testing.assert_allclose(np.einsum("kij,kj->ki", skew(a), b), np.cross(a, b), atol=1e-15)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-6, 0.9e-4, 1.1e-4, 0.3, 2.0, np.pi - 1e-6])
def test_rotation_matrix_matches_scipy(angle):
    vectors = _random_vectors(np.random.default_rng(1), 40, np.full(40, angle))
    matrices = rotation_matrix(vectors)
    # Reference: scipy's quaternion-based Rotation.from_rotvec, accurate to round-off at every angle.
    np.testing.assert_allclose(matrices, Rotation.from_rotvec(vectors).as_matrix(), atol=4e-16)
    np.testing.assert_allclose(
        matrices @ np.swapaxes(matrices, 1, 2), np.broadcast_to(np.eye(3), (40, 3, 3)), atol=1e-15
    )


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-6, 0.9e-4, 1.1e-4, 0.3, 2.0, np.pi - 1e-2, np.pi - 1e-6])
def test_rotation_vector_inverts_rotation_matrix(angle):
    vectors = _random_vectors(np.random.default_rng(2), 40, np.full(40, angle))
    recovered = rotation_vector(Rotation.from_rotvec(vectors).as_matrix())
    # Near π the axis comes from R + Rᵀ; its error is eps / (1 − cos θ) ~ eps, the angle's eps / sin θ.
    tolerance = 4e-16 / max(np.sin(angle), 1e-3) + 4e-16 * angle
    np.testing.assert_allclose(recovered, vectors, atol=tolerance)


def test_polar_rotation_recovers_rotation_of_stretch():
    rng = np.random.default_rng(3)
    rotations = Rotation.random(30, random_state=4).as_matrix()
    factors = rng.normal(size=(30, 3, 3))
    stretches = factors @ np.swapaxes(factors, 1, 2) + 0.5 * np.eye(3)  # symmetric positive definite
    np.testing.assert_allclose(polar_rotation(rotations @ stretches), rotations, atol=1e-12)


def test_polar_rotation_of_inverted_gradient_is_proper_and_closest():
    rng = np.random.default_rng(5)
    gradients = rng.normal(size=(30, 3, 3))
    gradients[np.linalg.det(gradients) > 0] *= -1.0  # all inverted
    result = polar_rotation(gradients)
    np.testing.assert_allclose(np.linalg.det(result), 1.0, atol=1e-14)
    others = Rotation.random(200, random_state=6).as_matrix()
    best = np.linalg.norm(gradients - result, axis=(1, 2))
    trials = np.linalg.norm(gradients[:, None] - others[None], axis=(2, 3))
    assert np.all(best[:, None] <= trials + 1e-12)


def test_closest_rotation_is_the_svd_s_proper_rotation_to_its_conditioning():
    # Reference: R = P diag(1, 1, det(P Qᵀ)) Qᵀ for F = P Σ Qᵀ (the maximiser of tr(Rᵀ F) over SO(3), Kabsch /
    # Umeyama), computed by NumPy's SVD. R's sensitivity to a perturbation of F is 1 / (σ₂ + d σ₃) with
    # d = sign det F (the smallest sum of two singular values that a rotation mixes), so the two computations,
    # each within a few ε of their F, agree to 64 ε (σ₁ / (σ₂ + d σ₃)) at most: general, inverted and nearly
    # flat F, 3,000 each, and the degenerate ones (zero, flat, a reflection).
    from refsim.geometry.rotations import _closest_rotation

    EPS = np.finfo(float).eps

    def reference(f):
        u, _, vt = np.linalg.svd(f)
        if np.linalg.det(u @ vt) < 0.0:
            u[:, 2] *= -1.0
        return u @ vt

    rng = np.random.default_rng(7)
    out = np.empty((3, 3))
    for scale in (0.3, 1.0, 3.0):
        for index in range(3000):
            f = np.eye(3) + scale * rng.standard_normal((3, 3))
            if index % 2:
                f[:, 0] *= -1.0  # inverted
            sigma = np.linalg.svd(f, compute_uv=False)
            gap = sigma[1] + np.sign(np.linalg.det(f)) * sigma[2]
            _closest_rotation(f, out)
            assert np.abs(out - reference(f)).max() <= 64 * EPS * sigma[0] / gap
            assert np.abs(out @ out.T - np.eye(3)).max() <= 8 * EPS and np.linalg.det(out) > 0.0
    for f in (np.zeros((3, 3)), np.diag([1.0, 1.0, 0.0]), np.diag([2.0, 1.0, -0.5])):
        _closest_rotation(f, out)
        np.testing.assert_allclose(out, reference(f), rtol=0, atol=8 * EPS)
