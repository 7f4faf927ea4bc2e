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
