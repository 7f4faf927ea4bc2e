"""Implicit Euler on the effective stiffness (refsim.fem.integration) through a step system and the exact
compliance strategy (refsim.fem.compliance), on small systems with closed forms."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from refsim.fem.compliance import Exact, StepSystem
from refsim.fem.integration import effective_stiffness


def spring_chain(
    count: int, stiffness: float = 100.0, mass: float = 0.5
) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Masses on a line joined by springs (free ends): M = m I, K the chain Laplacian times k."""
    laplacian = sp.diags(
        [-np.ones(count - 1), np.r_[1.0, 2.0 * np.ones(count - 2), 1.0], -np.ones(count - 1)], [-1, 0, 1]
    )
    return sp.csr_matrix(mass * sp.eye(count)), sp.csr_matrix(stiffness * laplacian)


def implicit_euler_step(
    mass,
    stiffness,
    dt,
    forces,
    velocities,
    *,
    rayleigh_mass=0.0,
    rayleigh_stiffness=0.0,
    constrained_dofs=None,
    prescribed=None,
):
    """One step's compliance: A = M/dt² + C/dt + K, rhs = f + (M/dt) v₀, through the exact strategy."""
    matrix = effective_stiffness(
        mass, stiffness, dt, rayleigh_mass=rayleigh_mass, rayleigh_stiffness=rayleigh_stiffness
    )
    rhs = np.asarray(forces, dtype=float) + (mass @ np.asarray(velocities, dtype=float)) / dt
    system = StepSystem.from_matrices(matrix, rhs, constrained_dofs, prescribed)
    return Exact().bind().step(system), matrix


def test_mass_spring_free_motion_matches_implicit_euler_recurrence():
    # One DoF, m ẍ = −k x − c ẋ, c = α m + β k. Implicit Euler on (x, v):
    # v₁ = (v₀ − dt k x₀ / m) / (1 + dt c/m + dt² k/m),  x₁ = x₀ + dt v₁   (linear, so one Newton
    # step is exact).
    m, k, alpha, beta, dt = 0.3, 50.0, 2.0, 0.01, 0.02
    c = alpha * m + beta * k
    mass, stiffness = sp.csr_matrix([[m]]), sp.csr_matrix([[k]])
    x, v = 0.1, -0.4
    for _ in range(25):
        step, _ = implicit_euler_step(
            mass, stiffness, dt, [-k * x], [v], rayleigh_mass=alpha, rayleigh_stiffness=beta
        )
        moved = step.free_displacement[0]
        v_expected = (v - dt * k * x / m) / (1.0 + dt * c / m + dt * dt * k / m)
        assert moved / dt == pytest.approx(v_expected, rel=1e-13)
        x, v = x + moved, moved / dt
    # Implicit Euler is dissipative: the amplitude decays.
    assert 0.5 * k * x * x + 0.5 * m * v * v < 0.5 * k * 0.1**2 + 0.5 * m * 0.4**2


def test_free_motion_of_a_chain_matches_dense_solve():
    mass, stiffness = spring_chain(5)
    dt, alpha, beta = 0.01, 1.5, 0.002
    rng = np.random.default_rng(0)
    forces, velocities = rng.standard_normal(5), rng.standard_normal(5)
    step, matrix = implicit_euler_step(
        mass, stiffness, dt, forces, velocities, rayleigh_mass=alpha, rayleigh_stiffness=beta
    )
    dense = (mass / dt**2 + (alpha * mass + beta * stiffness) / dt + stiffness).toarray()
    expected = np.linalg.solve(dense, forces + mass @ velocities / dt)
    np.testing.assert_allclose(step.free_displacement, expected, rtol=1e-12)
    np.testing.assert_allclose(matrix.toarray(), dense, rtol=1e-14)


def test_prescribed_dofs_are_eliminated():
    mass, stiffness = spring_chain(6)
    dt = 0.05
    rng = np.random.default_rng(1)
    forces, velocities = rng.standard_normal(6), rng.standard_normal(6)
    prescribed = np.array([0.01, -0.02])  # in the order of the sorted constrained DoFs: DoF 0, DoF 5
    step, matrix = implicit_euler_step(
        mass, stiffness, dt, forces, velocities, constrained_dofs=[5, 0], prescribed=prescribed
    )
    np.testing.assert_array_equal(step.constrained_dofs, [0, 5])
    np.testing.assert_array_equal(step.free_dofs, [1, 2, 3, 4])
    np.testing.assert_array_equal(step.free_displacement[[0, 5]], prescribed)
    # Reference: the full system's rows of the free DoFs hold with the prescribed values substituted.
    dense = matrix.toarray()
    residual = dense @ step.free_displacement - (forces + mass @ velocities / dt)
    np.testing.assert_allclose(residual[[1, 2, 3, 4]], 0.0, atol=1e-12 * np.abs(dense).max() * 0.02)
    # Fixed by default: zero on the constrained DoFs.
    fixed, _ = implicit_euler_step(mass, stiffness, dt, forces, velocities, constrained_dofs=[5, 0])
    np.testing.assert_array_equal(fixed.free_displacement[[0, 5]], 0.0)
    with pytest.raises(ValueError, match="prescribed"):
        implicit_euler_step(
            mass, stiffness, dt, forces, velocities, constrained_dofs=[5, 0], prescribed=np.zeros(3)
        )


def test_compliance_is_symmetric_positive_semidefinite_and_exact():
    mass, stiffness = spring_chain(8)
    step, matrix = implicit_euler_step(
        mass,
        stiffness,
        0.02,
        np.zeros(8),
        np.zeros(8),
        rayleigh_mass=0.5,
        rayleigh_stiffness=0.001,
        constrained_dofs=[0],
    )
    rng = np.random.default_rng(2)
    jacobian = rng.standard_normal((4, 8))
    jacobian[3] = jacobian[0] + jacobian[1]  # redundant row: W is singular, still PSD
    jacobian[2, 1:] = 0.0
    jacobian[2, 0] = 1.0  # a row on the constrained DoF only: zero compliance
    compliance, responses = step.compliance(jacobian)
    np.testing.assert_array_equal(compliance, compliance.T)
    eigenvalues = np.linalg.eigvalsh(compliance)
    assert eigenvalues[0] > -1e-14 * eigenvalues[-1]
    free = np.arange(1, 8)
    inverse = np.zeros((8, 8))
    inverse[np.ix_(free, free)] = np.linalg.inv(matrix.toarray()[np.ix_(free, free)])
    np.testing.assert_allclose(compliance, jacobian @ inverse @ jacobian.T, rtol=1e-11, atol=1e-16)
    np.testing.assert_allclose(responses, inverse @ jacobian.T, rtol=1e-11, atol=1e-16)
    np.testing.assert_allclose(compliance[2], 0.0, atol=0.0)
    np.testing.assert_array_equal(responses[0], 0.0)  # A⁻¹ is zero on the constrained DoF
    sparse = sp.csr_matrix(jacobian)
    np.testing.assert_allclose(step.delassus(sparse), compliance, rtol=1e-12, atol=1e-16)


def test_compliance_units_scale_with_dt():
    # W = H A⁻¹ Hᵀ with A = M/dt² + K: for a single mass with no spring W = dt²/m [m/N].
    step, _ = implicit_euler_step(sp.csr_matrix([[2.0]]), sp.csr_matrix([[0.0]]), 0.1, [0.0], [0.0])
    compliance, _ = step.compliance(np.array([[1.0]]))
    assert compliance[0, 0] == pytest.approx(0.01 / 2.0, rel=1e-14)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"dt": 0.0}, "dt"),
        ({"rayleigh_mass": -1.0}, "Rayleigh"),
        ({"constrained_dofs": [7]}, "constrained_dofs"),
        ({"constrained_dofs": [0, 1, 2]}, "every DoF"),
    ],
)
def test_bad_input_is_named(kwargs, match):
    mass, stiffness = spring_chain(3)
    arguments = {"dt": 0.01, **kwargs}
    dt = arguments.pop("dt")
    with pytest.raises(ValueError, match=match):
        implicit_euler_step(mass, stiffness, dt, np.zeros(3), np.zeros(3), **arguments)
