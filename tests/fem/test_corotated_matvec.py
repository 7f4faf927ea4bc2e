"""The matrix-free step system (refsim.fem.corotated_matvec) against the assembled one of TissueModel."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.fem.corotated_matvec import (
    Elements,
    corotate,
    corotate_with_nodes,
    node_rotations,
    stiffness_product,
)
from refsim.fem.tissue import TissueModel, TissueState
from refsim.geometry.rotations import rotation_matrix
from refsim.materials import HookeMaterial
from refsim.mesh.generators import box_mesh

EPS = np.finfo(float).eps
DT = 0.01


@pytest.fixture(scope="module")
def model() -> TissueModel:
    mesh = box_mesh(size=(0.1, 0.08, 0.06), cells=(3, 3, 2))
    rest = np.asarray(mesh.rest_positions, dtype=float)
    return TissueModel(
        rest,
        np.asarray(mesh.tets),
        HookeMaterial(youngs_modulus=5.0e5, poisson_ratio=0.4, density=1000.0),
        rayleigh_mass=1.0,
        rayleigh_stiffness=0.01,
        fixed_nodes=np.flatnonzero(rest[:, 2] < 1e-12),
        gravity=(0.0, 0.0, -9.81),
    )


def elements(model: TissueModel) -> Elements:
    material = model.material
    return Elements(
        model.tets,
        model._rest_edges_inverse,
        model.element_volumes,
        material.lame_lambda,
        material.shear_modulus,
    )


def deformed(model: TissueModel) -> TissueState:
    rest = model.rest_positions
    positions = rest + 0.01 * np.sin(30.0 * rest)
    positions[model.fixed_nodes] = rest[model.fixed_nodes]
    return TissueState(positions=positions, velocities=0.05 * np.cos(10.0 * rest))


def roundoff_bound(model: TissueModel, magnitudes: np.ndarray) -> np.ndarray:
    """k ε |A| |v| per entry: both paths sum the same products of one node's tets in different orders; a sum
    of k products differs from the exact one by at most k ε Σ|terms| (Higham, Accuracy and Stability, §3.1),
    k = 12 local entries × 9 rotation products per tet of the busiest node."""
    tets_per_node = np.bincount(model.tets.ravel()).max()
    return 12 * 9 * tets_per_node * EPS * magnitudes


def test_operator_and_rhs_equal_the_assembled_system(model):
    state = deformed(model)
    drive = np.tile([2e-4, -1e-4, 3e-4], (model.fixed_nodes.size, 1))
    assembled = model.assemble_step(state, DT, fixed_displacements=drive)
    free = model.assemble_step(state, DT, fixed_displacements=drive, matrix_free=True)
    assert free.matrix is None
    np.testing.assert_array_equal(free.free_dofs, assembled.free_dofs)
    np.testing.assert_array_equal(free.prescribed, assembled.prescribed)
    vectors = np.random.default_rng(0).standard_normal((assembled.free_dofs.size, 3))
    expected = assembled.matrix @ vectors
    bound = roundoff_bound(model, abs(assembled.matrix) @ np.abs(vectors))
    assert np.all(np.abs(free.operator(vectors) - expected) <= bound)
    assert np.all(np.abs(free.product(vectors[:, 0]) - expected[:, 0]) <= bound[:, 0])
    # rhs = f_ext − f_int + (M/dt) v₀ − A_fc Δx_c: the same force terms and coupling, summed differently.
    scale = np.abs(assembled.rhs).max()
    assert np.abs(free.rhs - assembled.rhs).max() <= roundoff_bound(model, scale)
    np.testing.assert_allclose(free.group_rotations(), assembled.group_rotations(), rtol=0, atol=16 * EPS)


def test_the_matrix_free_step_builds_no_pattern_and_has_its_dofs():
    # A fresh model: the matrix-free step reads the free and constrained DoFs, never A's pattern; they are the
    # arrays the pattern has once it is built (and then the pattern's own).
    mesh = box_mesh(size=(0.1, 0.08, 0.06), cells=(2, 2, 2))
    rest = np.asarray(mesh.rest_positions, dtype=float)
    fresh = TissueModel(
        rest,
        np.asarray(mesh.tets),
        HookeMaterial(youngs_modulus=5.0e5, poisson_ratio=0.4, density=1000.0),
        fixed_nodes=np.flatnonzero(rest[:, 2] < 1e-12),
    )
    state = deformed(fresh)
    first = fresh.assemble_step(state, DT, matrix_free=True)
    assert not hasattr(fresh, "_free_pattern")
    second = fresh.assemble_step(state, DT, matrix_free=True)
    assert second.free_dofs is first.free_dofs  # computed once per model
    np.testing.assert_array_equal(second.rhs, first.rhs)
    pattern = fresh.free_pattern
    np.testing.assert_array_equal(first.free_dofs, pattern.free_dofs)
    np.testing.assert_array_equal(first.constrained_dofs, pattern.constrained_dofs)
    assert first.free_dofs.dtype == pattern.free_dofs.dtype == np.int64
    assert fresh.free_and_constrained_dofs[0] is pattern.free_dofs


def test_internal_forces_and_rotations_equal_the_element_stiffness_form(model):
    # f = R Kₑ (Rᵀx − X) with scikit-fem's Kₑ (TissueModel.internal_forces) against V R σ ∇φ.
    positions = deformed(model).positions
    forces, rotations = corotate(positions, elements(model))
    expected_rotations = model.element_rotations(positions)
    np.testing.assert_allclose(rotations, expected_rotations, rtol=0, atol=16 * EPS)
    expected = model.internal_forces(positions, expected_rotations).ravel()
    assert np.abs(forces - expected).max() <= roundoff_bound(model, np.abs(expected).max())


def test_a_rigid_motion_has_no_internal_force_and_a_rotated_stiffness(model):
    # Rigid rotation Q and translation: F = Q, R = Q, ε = 0 so f = 0; K(Q) v = Q K₀ Qᵀ v (co-rotation).
    rotation = rotation_matrix(np.array([[0.4, -0.3, 0.6]]))[0]
    rest = model.rest_positions
    forces, rotations = corotate(rest @ rotation.T + np.array([0.01, -0.02, 0.03]), elements(model))
    np.testing.assert_allclose(rotations, np.broadcast_to(rotation, rotations.shape), rtol=0, atol=16 * EPS)
    stiffness_scale = np.abs(model.rest_stiffness).max() * np.abs(rest).max()
    assert np.abs(forces).max() <= roundoff_bound(model, stiffness_scale)
    vectors = np.random.default_rng(1).standard_normal((model.node_count, 3))
    turned = stiffness_product((vectors @ rotation.T).ravel(), elements(model), rotations).reshape(-1, 3)
    expected = (model.rest_stiffness @ vectors.ravel()).reshape(-1, 3) @ rotation.T
    bound = roundoff_bound(model, (abs(model.rest_stiffness) @ np.abs(vectors.ravel())).max())
    assert np.abs(turned - expected).max() <= bound


def test_one_pass_corotation_equals_the_two_passes(model):
    # corotate_with_nodes: the tets' rotations and forces and the nodes' rotations in one pass, its polar
    # iteration stopped once the next Newton step is below round-off (‖ΔX‖ < 1e-8, next error ≈ ½‖ΔX‖²): the
    # rotations within a few ε of polar_rotation_one's, the forces within the product bound.
    positions = deformed(model).positions
    forces, rotations, nodes = corotate_with_nodes(positions, elements(model))
    expected_forces, expected_rotations = corotate(positions, elements(model))
    np.testing.assert_allclose(rotations, expected_rotations, rtol=0, atol=16 * EPS)
    expected_nodes = node_rotations(model.tets, expected_rotations, model.node_count)
    np.testing.assert_allclose(nodes, expected_nodes, rtol=0, atol=16 * EPS)
    assert np.abs(forces - expected_forces).max() <= roundoff_bound(model, np.abs(expected_forces).max())
    np.testing.assert_allclose(
        np.einsum("nij,nkj->nik", nodes, nodes),
        np.broadcast_to(np.eye(3), nodes.shape),
        rtol=0,
        atol=16 * EPS,
    )


@pytest.mark.parametrize(
    ("regime", "strain"),
    [("small strain", 1e-3), ("moderate strain", 0.1), ("large strain", 0.6), ("scaled rotation", 0.0)],
)
def test_the_fast_pass_polar_rotation_is_the_svd_rotation_in_every_regime(regime, strain):
    # Reference: the rotation of F = R U is P Qᵀ for F = P Σ Qᵀ (det F > 0; Higham, Functions of Matrices,
    # §8.1), here from LAPACK's SVD, and polar_rotation_one (the exact mode's, iterated to 1e-15).
    # _rotation takes the Newton–Schulz iteration from F / (‖F‖_F / √3) when ‖X₀ᵀX₀ − I‖_F ≤ ½ (small and
    # moderate strains, and a rotation scaled by any λ > 0: X₀ is then R), the scaled Newton iteration
    # otherwise, the SVD's rotation for det F ≤ 0: every answer orthogonal to a few ε (the iterations stop
    # once the next update is below round-off), within 16 ε·κ(F) of polar_rotation_one's and within 64 ε·κ(F)
    # of the SVD's (the SVD's own rotation is off by up to about 25 ε·κ(F): both iterations measured so on
    # 2,000 samples per strain).
    from refsim.fem.corotated_matvec import _rotation
    from refsim.geometry.rotations import polar_rotation_one

    rng = np.random.default_rng(7)
    rotations = rotation_matrix(rng.uniform(-np.pi, np.pi, (200, 3)))
    if regime == "scaled rotation":
        gradients = rng.uniform(0.05, 20.0, (200, 1, 1)) * rotations
    else:
        stretch = np.eye(3) + strain * rng.uniform(-1.0, 1.0, (200, 3, 3))
        stretch = 0.5 * (stretch + stretch.transpose(0, 2, 1))
        stretch = stretch[np.linalg.det(stretch) > 0.0][:100]
        gradients = rotations[: stretch.shape[0]] @ stretch
    out, reference = np.empty((3, 3)), np.empty((3, 3))
    for gradient in gradients:
        left, values, right = np.linalg.svd(gradient)
        expected = left @ right
        assert np.linalg.det(expected) > 0.0
        _rotation(np.ascontiguousarray(gradient), out)
        polar_rotation_one(np.ascontiguousarray(gradient), reference)
        np.testing.assert_allclose(out.T @ out, np.eye(3), rtol=0, atol=8 * EPS)
        condition = values[0] / values[-1]
        np.testing.assert_allclose(out, reference, rtol=0, atol=16 * EPS * condition)
        np.testing.assert_allclose(out, expected, rtol=0, atol=64 * EPS * condition)
    # An inverted tet (det F < 0): the closest proper rotation, P diag(1, 1, −1) Qᵀ.
    flipped = rotations[0] @ np.diag([1.2, 0.9, -0.8])
    _rotation(np.ascontiguousarray(flipped), out)
    np.testing.assert_allclose(out, rotations[0], rtol=0, atol=16 * EPS)
