"""Local kernels of the co-rotational Timoshenko beam (refsim.fem.beam_element)."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.fem.beam_element import (
    LOCAL_REDUCED_DOFS,
    beam_element_forces,
    hermite_shapes,
    left_jacobian_inverse,
    local_deformations,
    timoshenko_stiffness,
)
from refsim.geometry.rotations import rotation_matrix, rotation_vector

EPS = np.finfo(float).eps

# A steel needle element: E = 200 GPa, ν = 0.3, r = 1 mm, l = 2 cm.
E, NU, RADIUS, LENGTH = 2e11, 0.3, 1e-3, 0.02
G = E / (2 * (1 + NU))
KAPPA = 6 * (1 + NU) / (7 + 6 * NU)  # Cowper (1966), solid circle
AREA, INERTIA, POLAR = np.pi * RADIUS**2, np.pi * RADIUS**4 / 4, np.pi * RADIUS**4 / 2
SECTION = dict(
    youngs_modulus=E,
    shear_modulus=G,
    area=AREA,
    second_moment=INERTIA,
    polar_moment=POLAR,
    shear_coefficient=KAPPA,
)


def _stiffness(length=LENGTH, **overrides):
    return timoshenko_stiffness(length, **{**SECTION, **overrides})


def test_stiffness_is_symmetric_with_six_rigid_modes():
    # A free beam element has exactly 6 rigid-body modes (3 translations, 3 rotations).
    k = _stiffness()
    assert np.allclose(k, k.T, rtol=0, atol=1e-12 * np.abs(k).max())
    eigenvalues = np.linalg.eigvalsh(k)
    assert np.sum(np.abs(eigenvalues) < 1e-9 * eigenvalues.max()) == 6
    assert eigenvalues.min() > -1e-9 * eigenvalues.max()


@pytest.mark.parametrize("plane", ["xy", "xz"])
def test_single_element_cantilever_is_exact(plane):
    # Reference: Timoshenko cantilever under tip load P, δ = P L³/(3EI) + P L/(κGA), tip rotation P L²/(2EI)
    # (Przemieniecki's element is the exact condensation of the continuum beam). Round-off tolerance.
    k = _stiffness(length=0.1)
    free = np.arange(6, 12)
    displacement_dof, rotation_dof = (7, 11) if plane == "xy" else (8, 10)
    load = np.zeros(6)
    load[displacement_dof - 6] = 1.0
    u = np.linalg.solve(k[np.ix_(free, free)], load)
    expected = 0.1**3 / (3 * E * INERTIA) + 0.1 / (KAPPA * G * AREA)
    assert u[displacement_dof - 6] == pytest.approx(expected, rel=1e-10)
    sign = 1.0 if plane == "xy" else -1.0  # v' = θz, w' = −θy
    assert sign * u[rotation_dof - 6] == pytest.approx(0.1**2 / (2 * E * INERTIA), rel=1e-10)


def _skfem_condensed_bending(length, cells):
    """Timoshenko bending energy ½∫EI θ'² + ½∫κGA (w' − θ)², P1 w and θ, one-point (reduced) shear quadrature,
    assembled with scikit-fem on a line mesh of ``cells`` cells and condensed onto (w₀, θ₀, w_L, θ_L)."""
    from skfem import Basis, BilinearForm, ElementLineP1, MeshLine, asm

    mesh = MeshLine(np.linspace(0.0, length, cells + 1))
    bending_basis = Basis(mesh, ElementLineP1())
    shear_basis = Basis(mesh, ElementLineP1(), quadrature=(np.array([[0.5]]), np.array([1.0])))

    @BilinearForm
    def gradients(u, v, _):
        return u.grad[0] * v.grad[0]

    @BilinearForm
    def value_gradient(u, v, _):  # trial u = θ, test v = w: ∫ θ w'
        return u * v.grad[0]

    @BilinearForm
    def values(u, v, _):
        return u * v

    kga, ei = KAPPA * G * AREA, E * INERTIA
    k_ww = kga * asm(gradients, shear_basis)
    k_wt = -kga * asm(value_gradient, shear_basis)
    k_tt = ei * asm(gradients, bending_basis) + kga * asm(values, shear_basis)
    full = np.block([[k_ww.toarray(), k_wt.toarray()], [k_wt.T.toarray(), k_tt.toarray()]])
    n = cells + 1
    ends = np.array([0, n, n - 1, 2 * n - 1])  # (w₀, θ₀, w_L, θ_L)
    inner = np.setdiff1d(np.arange(2 * n), ends)
    schur = full[np.ix_(ends, ends)] - full[np.ix_(ends, inner)] @ np.linalg.solve(
        full[np.ix_(inner, inner)], full[np.ix_(inner, ends)]
    )
    return schur


def test_bending_block_matches_refined_scikit_fem_assembly_at_second_order():
    # Reference: the closed form is the exact condensation of the Timoshenko beam energy; the P1 / reduced
    # integration assembly of the same energy converges to it at O(h²). Fitted rate must be 2 ± 0.1, and the
    # finest error must be below the second-order extrapolation of the coarsest. The Richardson extrapolation
    # (4 K₃₂ − K₁₆)/3 removes the h² term; its residual O(h⁴) ≈ (1/32)²·error₃₂ must be far below the shear
    # contribution (Timoshenko vs Euler–Bernoulli ≈ 3.5e-3 here), so a wrong Φ would fail.
    length = 0.05  # Φ = 12EI/(κGAL²) ≈ 0.01: shear matters but does not dominate
    exact = _stiffness(length=length)[np.ix_([1, 5, 7, 11], [1, 5, 7, 11])]
    scale = np.diag([1.0, length, 1.0, length])  # make entries dimensionally comparable
    cells = np.array([4, 8, 16, 32])
    euler_bernoulli = _stiffness(length=length, shear_coefficient=1e12)[np.ix_([1, 5, 7, 11], [1, 5, 7, 11])]

    def error(matrix):
        return np.abs(scale @ (matrix - exact) @ scale).max() / np.abs(scale @ exact @ scale).max()

    assembled = [_skfem_condensed_bending(length, count) for count in cells]
    errors = [error(matrix) for matrix in assembled]
    rate = -np.polyfit(np.log(cells), np.log(errors), 1)[0]
    assert rate == pytest.approx(2.0, abs=0.1)
    assert errors[-1] < 1.1 * errors[0] * (cells[0] / cells[-1]) ** 2
    shear_effect = error(euler_bernoulli)
    assert error((4 * assembled[-1] - assembled[-2]) / 3) < max(
        4 * errors[-1] / cells[-1], 1e-3 * shear_effect
    )


def _random_element(rng, m=5, rotation_scale=0.3):
    xa = rng.normal(size=(m, 3)) * 0.01
    base = rotation_matrix(rng.normal(size=(m, 3)))
    xb = xa + LENGTH * (1 + 0.01 * rng.normal(size=(m, 1))) * base[:, :, 0] + 1e-3 * rng.normal(size=(m, 3))
    qa = rotation_matrix(rotation_scale * rng.normal(size=(m, 3))) @ base
    qb = rotation_matrix(rotation_scale * rng.normal(size=(m, 3))) @ base
    return xa, xb, qa, qb


def _perturb(state, index, step):
    xa, xb, qa, qb = (a.copy() for a in state)
    axis = np.zeros((1, 3))
    axis[0, index % 3] = step
    if index < 3:
        xa += axis
    elif index < 6:
        qa = rotation_matrix(axis) @ qa
    elif index < 9:
        xb += axis
    else:
        qb = rotation_matrix(axis) @ qb
    return xa, xb, qa, qb


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-6, 1e-4, 0.3, 2.5])
def test_left_jacobian_inverse_matches_finite_differences(angle):
    # δθ = J_l(θ)⁻¹ ω for exp(θ) ← exp(ω) exp(θ); checked by central differences of the log map, including the
    # series branch and its boundary (1e-4). FD error O(h²) + ε/h ≈ 1e-10.
    rng = np.random.default_rng(1)
    axis = rng.normal(size=3)
    theta = angle * axis / np.linalg.norm(axis)
    inverse = left_jacobian_inverse(theta[None])[0]
    base = rotation_matrix(theta[None])
    h = 1e-6
    numeric = np.empty((3, 3))
    for j in range(3):
        step = np.zeros((1, 3))
        step[0, j] = h
        plus = rotation_vector(rotation_matrix(step) @ base)[0]
        minus = rotation_vector(rotation_matrix(-step) @ base)[0]
        numeric[:, j] = (plus - minus) / (2 * h)
    assert np.allclose(inverse, numeric, atol=1e-8)


@pytest.mark.parametrize("rotation_scale", [0.0, 1e-8, 0.3])
def test_local_deformation_jacobian_matches_finite_differences(rotation_scale):
    # B = ∂d/∂p with world-frame rotation increments; central differences, h = 1e-7 (relative FD error ~1e-7),
    # including nodal frames exactly equal to the chord frame (rotation_scale = 0, near-degenerate θ̄ = 0).
    rng = np.random.default_rng(2)
    state = _random_element(rng, rotation_scale=rotation_scale)
    rest = np.full(5, LENGTH)
    local = local_deformations(*state, rest)
    h = 1e-7
    for index in range(12):
        step = h * (LENGTH if index % 6 < 3 else 1.0)
        plus = local_deformations(*_perturb(state, index, step), rest)["deformations"]
        minus = local_deformations(*_perturb(state, index, -step), rest)["deformations"]
        numeric = (plus - minus) / (2 * step)
        assert np.allclose(
            local["jacobian"][:, :, index], numeric, atol=1e-6 / (1 if index % 6 >= 3 else LENGTH)
        )


def test_element_forces_are_the_energy_gradient_and_balance():
    # f = Bᵀ K₇ d must equal ∂U/∂p (central differences, relative error ~1e-7) and be self-equilibrated:
    # Σ forces = 0 and Σ (moments + x × forces) = 0 (round-off).
    rng = np.random.default_rng(3)
    state = _random_element(rng)
    rest = np.full(5, LENGTH)
    k7 = np.broadcast_to(_stiffness()[np.ix_(LOCAL_REDUCED_DOFS, LOCAL_REDUCED_DOFS)], (5, 7, 7))
    forces, _ = beam_element_forces(*state, rest, k7)
    scale = np.abs(forces).max()
    for index in range(12):
        step = 1e-7 * (LENGTH if index % 6 < 3 else 1.0)
        plus = beam_element_forces(*_perturb(state, index, step), rest, k7)[1]
        minus = beam_element_forces(*_perturb(state, index, -step), rest, k7)[1]
        assert np.allclose((plus - minus) / (2 * step), forces[:, index], atol=1e-6 * scale / LENGTH)
    xa, xb = state[0], state[1]
    assert np.abs(forces[:, 0:3] + forces[:, 6:9]).max() < 1e-9 * scale
    torque = forces[:, 3:6] + forces[:, 9:12] + np.cross(xa, forces[:, 0:3]) + np.cross(xb, forces[:, 6:9])
    assert np.abs(torque).max() < 1e-9 * scale * LENGTH


def test_hermite_shapes_end_values_and_slopes():
    # H_a(0) = H_a(1) = H_b(0) = H_b(1) = 0; H_a'(0) = 1, H_a'(1) = 0, H_b'(0) = 0, H_b'(1) = 1; derivatives
    # match central differences (exact for cubics up to round-off).
    shapes, slopes = hermite_shapes(np.array([0.0, 1.0]))
    assert np.allclose(shapes, 0.0, atol=0)
    assert np.allclose(slopes, [[1.0, 0.0], [0.0, 1.0]], atol=0)
    xi = np.linspace(0.05, 0.95, 7)
    h = 1e-5
    numeric = (hermite_shapes(xi + h)[0] - hermite_shapes(xi - h)[0]) / (2 * h)
    assert np.allclose(hermite_shapes(xi)[1], numeric, atol=1e-9)
