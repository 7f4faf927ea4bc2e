"""Compiled co-rotation and assembly (refsim.fem.assembly) and the compiled polar decomposition
(refsim.geometry.rotations) against their NumPy / SVD references."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.fem.tissue import TissueModel, TissueState
from refsim.geometry.rotations import polar_rotation, polar_rotation_one, rotation_matrix
from refsim.materials import HookeMaterial
from refsim.mesh.generators import box_mesh

EPS = np.finfo(float).eps
MATERIAL = HookeMaterial(youngs_modulus=5.0e5, poisson_ratio=0.4, density=1000.0)


def polar_rotation_svd(deformation_gradients: np.ndarray) -> np.ndarray:
    """Rotation factor R of the polar decomposition F = R U, with det R = +1, by batched SVD (the reference).

    F = P Σ Qᵀ, R = P diag(1, 1, det(P Qᵀ)) Qᵀ, so that inverted elements (det F < 0) still give a proper
    rotation (the closest one to F).

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


def _orthogonality(r: np.ndarray) -> float:
    return float(np.abs(r @ np.swapaxes(r, -1, -2) - np.eye(3)).max())


def test_polar_newton_equals_svd_on_random_gradients():
    rng = np.random.default_rng(0)
    f = np.eye(3) + 0.4 * rng.standard_normal((5000, 3, 3))
    f = f[np.linalg.det(f) > 0.0]
    newton, svd = polar_rotation(f), polar_rotation_svd(f)
    # R is a smooth function of F with condition ~ σ_max/(σ_i+σ_j) (Higham §8.1); here it is < 1e3, so a few
    # hundred ε bounds the difference of two backward-stable computations.
    sigma = np.linalg.svd(f, compute_uv=False)
    condition = sigma[:, 0] / (sigma[:, 1] + sigma[:, 2])
    assert np.all(np.abs(newton - svd).max(axis=(1, 2)) <= 50 * EPS * np.maximum(condition, 1.0))
    assert _orthogonality(newton) <= 8 * EPS
    np.testing.assert_allclose(np.linalg.det(newton), 1.0, rtol=0, atol=8 * EPS)


def test_polar_of_rotation_times_stretch():
    rng = np.random.default_rng(1)
    rotations = rotation_matrix(rng.standard_normal((200, 3)))
    q = rotation_matrix(rng.standard_normal((200, 3)))
    stretch = q @ (np.linspace(0.5, 2.0, 3) * np.swapaxes(q, 1, 2))  # SPD, eigenvalues 0.5, 1.25, 2
    out = polar_rotation(rotations @ stretch)
    np.testing.assert_allclose(out, rotations, rtol=0, atol=40 * EPS)


@pytest.mark.parametrize("flatness", [1e-4, 1e-8, 1e-12])
def test_polar_near_degenerate(flatness):
    # F = R diag(1, 1, s): as s → 0 the polar factor stays R (det F > 0), and the iteration must still
    # converge.
    rng = np.random.default_rng(2)
    rotations = rotation_matrix(rng.standard_normal((50, 3)))
    f = rotations @ np.diag([1.0, 0.7, flatness])
    out = polar_rotation(f)
    np.testing.assert_allclose(out, polar_rotation_svd(f), rtol=0, atol=1e-12)
    assert _orthogonality(out) <= 8 * EPS


def test_polar_inverted_and_singular_use_the_svd():
    rng = np.random.default_rng(3)
    f = np.eye(3) + 0.3 * rng.standard_normal((100, 3, 3))
    f[:, :, 0] *= -1.0  # inverted (det < 0)
    f = f[np.linalg.det(f) < 0.0]
    out = polar_rotation(f)
    np.testing.assert_allclose(out, polar_rotation_svd(f), rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.linalg.det(out), 1.0, atol=8 * EPS)
    singular = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    r = np.empty((3, 3))
    assert polar_rotation_one(singular, r) == -1  # the SVD fallback
    np.testing.assert_allclose(r, np.eye(3), atol=8 * EPS)


@pytest.fixture(scope="module")
def model() -> TissueModel:
    mesh = box_mesh(size=(0.1, 0.1, 0.1), cells=(4, 3, 2))
    rest = np.asarray(mesh.rest_positions, dtype=float)
    return TissueModel(
        rest,
        np.asarray(mesh.tets),
        MATERIAL,
        rayleigh_mass=0.7,
        rayleigh_stiffness=0.02,
        fixed_nodes=np.flatnonzero(rest[:, 0] < 1e-12),
        gravity=(0.0, -9.81, 0.0),
    )


def test_compiled_assembly_equals_numpy_assembly(model):
    rest = model.rest_positions
    rotation = rotation_matrix(np.array([[0.2, 0.9, -0.4]]))[0]
    positions = (rest + 0.004 * np.sin(30.0 * rest)) @ rotation.T + 0.3
    positions[model.fixed_nodes] = rest[model.fixed_nodes]
    state = TissueState(positions=positions, velocities=0.1 * np.cos(7.0 * rest))
    drive = np.tile([2e-4, -1e-4, 3e-4], (model.fixed_nodes.size, 1))
    numpy_path = model.assemble_step(state, 0.01, fixed_displacements=drive, compiled=False)
    compiled = model.assemble_step(state, 0.01, fixed_displacements=drive)
    np.testing.assert_array_equal(numpy_path.free_dofs, compiled.free_dofs)
    # Same sums in another order: entries equal to a few ε of the largest (each is a sum of ≤ 24 element
    # terms).
    a, b = numpy_path.matrix.toarray(), compiled.matrix.toarray()
    assert np.abs(a - b).max() <= 64 * EPS * np.abs(a).max()
    assert np.abs(numpy_path.rhs - compiled.rhs).max() <= 64 * EPS * np.abs(numpy_path.rhs).max()
    # The compiled pattern is the fixed one: no structural entry lost, the same at every step.
    assert compiled.matrix.nnz >= numpy_path.matrix.nnz
    again = model.assemble_step(TissueState(positions=rest, velocities=0 * rest), 0.01)
    np.testing.assert_array_equal(again.matrix.indices, compiled.matrix.indices)
    np.testing.assert_array_equal(again.matrix.indptr, compiled.matrix.indptr)


def test_upper_storage_is_the_full_matrix_upper_triangle_bit_for_bit(model):
    # The upper storage PARDISO reads holds the very numbers of the full assembly's upper triangle (each block
    # entry computed once and added in the same tet order), and A_fc and the right-hand side are unchanged.
    rest = model.rest_positions
    positions = rest + 0.003 * np.cos(40.0 * rest[:, [1, 2, 0]])
    positions[model.fixed_nodes] = rest[model.fixed_nodes]
    state = TissueState(positions=positions, velocities=0.2 * np.sin(9.0 * rest))
    drive = np.tile([1e-4, 2e-4, -3e-4], (model.fixed_nodes.size, 1))
    full = model.assemble_step(state, 0.01, fixed_displacements=drive)
    upper = model.assemble_step(state, 0.01, fixed_displacements=drive, upper_triangle=True)
    assert upper.upper_triangle and not full.upper_triangle
    rows, columns = upper.matrix.nonzero()
    assert np.all(columns >= rows)
    np.testing.assert_array_equal(upper.matrix.toarray(), np.triu(full.matrix.toarray()))
    np.testing.assert_array_equal(upper.rhs, full.rhs)
    mirrored = np.triu(full.matrix.toarray()) + np.triu(full.matrix.toarray(), 1).T
    np.testing.assert_array_equal(upper.full_matrix().toarray(), mirrored)
    assert full.full_matrix() is full.matrix
    # the full storage is symmetric to round-off (the diagonal blocks' two triangles are computed apart)
    dense = full.matrix.toarray()
    assert np.abs(dense - dense.T).max() <= 8 * EPS * np.abs(dense).max()
    with pytest.raises(ValueError, match="compiled"):
        model.assemble_step(state, 0.01, compiled=False, upper_triangle=True)
