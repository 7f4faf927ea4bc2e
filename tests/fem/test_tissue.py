"""Tests of the co-rotational tetrahedra (refsim.fem.tissue) and the Hooke material (refsim.materials)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.sparse as sp

from refsim.fem.compliance import Exact, Refreshed
from refsim.fem.linear import available_linear_solvers, make_linear_solver
from refsim.fem.tissue import TissueModel, TissueState, element_mass_matrices, element_stiffness_matrices
from refsim.geometry.rotations import rotation_matrix
from refsim.materials import HookeMaterial
from tests.observed_order import assert_order

EPS = np.finfo(float).eps
MATERIAL = HookeMaterial(youngs_modulus=5.0e5, poisson_ratio=0.4, density=1000.0)


def box(cells: int, size: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """A cube of cells³ hexahedra, 6 tets each: refsim.mesh.box_mesh, or a private Kuhn split if absent."""
    try:
        from refsim.mesh import box_mesh
    except ImportError:
        axis = np.linspace(0.0, size, cells + 1)
        grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
        index = np.arange(grid.shape[0]).reshape((cells + 1,) * 3)
        corners = np.stack(
            [
                index[i : i + cells, j : j + cells, k : k + cells].ravel()
                for i, j, k in itertools.product((0, 1), repeat=3)
            ],
            axis=1,
        )
        tets = []
        for permutation in itertools.permutations(range(3)):
            bits, path = 0, [0]
            for axis_index in permutation:
                bits |= 1 << (2 - axis_index)
                path.append(bits)
            tets.append(corners[:, path])
        return grid, np.concatenate(tets)
    mesh = box_mesh(size=(size, size, size), cells=(cells, cells, cells))
    return np.asarray(mesh.rest_positions, dtype=float), np.asarray(mesh.tets)


@pytest.fixture(scope="module")
def cube() -> TissueModel:
    rest, tets = box(2)
    return TissueModel(rest, tets, MATERIAL)


def closed_form_stiffness(element_positions: np.ndarray, material: HookeMaterial) -> np.ndarray:
    """Kₑ = V Bᵀ D B of a constant-strain tet (Zienkiewicz & Taylor, The Finite Element Method, vol. 1)."""
    edges = (element_positions[1:] - element_positions[0]).T
    inverse = np.linalg.inv(edges)
    volume = abs(np.linalg.det(edges)) / 6.0
    gradients = np.vstack([-inverse.sum(axis=0), inverse])  # row a: ∇N_a
    b = np.zeros((6, 12))
    for a, (gx, gy, gz) in enumerate(gradients):
        b[:, 3 * a : 3 * a + 3] = [[gx, 0, 0], [0, gy, 0], [0, 0, gz], [gy, gx, 0], [0, gz, gy], [gz, 0, gx]]
    lam, mu = material.lame_lambda, material.shear_modulus
    d = np.zeros((6, 6))
    d[:3, :3] = lam
    d[:3, :3] += 2.0 * mu * np.eye(3)
    d[3:, 3:] = mu * np.eye(3)
    return volume * b.T @ d @ b


# ------------------------------------------------------------------ material


def test_material_lame_parameters():
    # λ = E ν / ((1+ν)(1−2ν)), μ = E / (2(1+ν)); E = μ (3λ + 2μ)/(λ + μ) closes the loop.
    lam, mu = MATERIAL.lame_lambda, MATERIAL.shear_modulus
    assert mu * (3 * lam + 2 * mu) / (lam + mu) == pytest.approx(MATERIAL.youngs_modulus, rel=1e-14)
    assert lam / (2 * (lam + mu)) == pytest.approx(MATERIAL.poisson_ratio, rel=1e-14)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("youngs_modulus", 0.0),
        ("youngs_modulus", np.inf),
        ("poisson_ratio", 0.5),
        ("poisson_ratio", -1.0),
        ("density", -1.0),
        ("density", "1000"),
    ],
)
def test_material_rejects_bad_values(field, value):
    kwargs = {"youngs_modulus": 1e5, "poisson_ratio": 0.3, "density": 1000.0, field: value}
    with pytest.raises(ValueError, match=field):
        HookeMaterial(**kwargs)


# ------------------------------------------------------------------ element matrices


def test_element_stiffness_matches_closed_form_on_irregular_tets():
    rng = np.random.default_rng(1)
    rest = rng.uniform(-0.05, 0.05, size=(12, 3))
    tets = np.array(
        [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11], [3, 2, 1, 0]]
    )  # last one inverted orientation
    stiffness = element_stiffness_matrices(rest, tets, MATERIAL)
    for e, tet in enumerate(tets):
        expected = closed_form_stiffness(rest[tet], MATERIAL)
        np.testing.assert_allclose(stiffness[e], expected, rtol=0, atol=1e-12 * np.abs(expected).max())


def test_element_stiffness_null_space_is_rigid_motions(cube):
    stiffness = cube.element_stiffness[:5]
    np.testing.assert_allclose(stiffness, np.swapaxes(stiffness, 1, 2), atol=1e-12 * np.abs(stiffness).max())
    eigenvalues = np.linalg.eigvalsh(stiffness)
    scale = eigenvalues[:, -1:]
    assert np.all(np.abs(eigenvalues[:, :6]) < 1e-12 * scale)  # 3 translations + 3 infinitesimal rotations
    assert np.all(eigenvalues[:, 6:] > 1e-6 * scale)


def test_element_mass_closed_form_and_lumping():
    # Consistent P1 mass: ρ V (1 + δ_ab) / 20 (Zienkiewicz & Taylor); lumped: ρ V / 4 per node.
    rng = np.random.default_rng(2)
    rest = rng.uniform(0.0, 0.1, size=(4, 3))
    tets = np.array([[0, 1, 2, 3]])
    mass = element_mass_matrices(rest, tets, 1000.0)[0]
    volume = abs(np.linalg.det((rest[1:] - rest[0]).T)) / 6.0
    np.testing.assert_allclose(mass, 1000.0 * volume * (np.ones((4, 4)) + np.eye(4)) / 20.0, rtol=1e-13)
    lumped = TissueModel(rest, tets, MATERIAL)
    consistent = TissueModel(rest, tets, MATERIAL, lumped_mass=False)
    np.testing.assert_allclose(lumped.mass_matrix.diagonal(), np.full(12, 1000.0 * volume / 4.0), rtol=1e-13)
    np.testing.assert_allclose(
        np.asarray(consistent.mass_matrix.sum(axis=1)).ravel(), lumped.mass_matrix.diagonal(), rtol=1e-13
    )


def test_total_mass_and_gravity(cube):
    model = TissueModel(cube.rest_positions, cube.tets, MATERIAL, gravity=(0.0, 0.0, -9.81))
    assert model.nodal_masses.sum() == pytest.approx(1000.0 * 0.1**3, rel=1e-13)
    np.testing.assert_allclose(
        model.external_forces().sum(axis=0), [0.0, 0.0, -9.81 * model.nodal_masses.sum()], rtol=1e-13
    )


def test_node_order_within_tets_does_not_matter(cube):
    # The polar rotation and the scikit-fem DoF mapping must not depend on how each tet lists its nodes.
    rng = np.random.default_rng(3)
    permuted = np.array([tet[rng.permutation(4)] for tet in cube.tets])
    other = TissueModel(cube.rest_positions, permuted, MATERIAL)
    positions = cube.rest_positions + 0.01 * rng.standard_normal(cube.rest_positions.shape)
    forces = cube.internal_forces(positions, cube.element_rotations(positions))
    other_forces = other.internal_forces(positions, other.element_rotations(positions))
    np.testing.assert_allclose(other_forces, forces, atol=1e-12 * np.abs(forces).max())
    tangent = cube.tangent_stiffness(cube.element_rotations(positions))
    other_tangent = other.tangent_stiffness(other.element_rotations(positions))
    assert abs(tangent - other_tangent).max() < 1e-12 * abs(tangent).max()


# ------------------------------------------------------------------ co-rotation


def test_rest_tangent_is_the_linear_stiffness(cube):
    identity = np.broadcast_to(np.eye(3), (cube.tet_count, 3, 3))
    rotations = cube.element_rotations(cube.rest_positions)
    np.testing.assert_allclose(rotations, identity, atol=1e-14)
    difference = cube.tangent_stiffness(rotations) - cube.rest_stiffness
    assert abs(difference).max() < 1e-12 * abs(cube.rest_stiffness).max()


def test_tangent_matches_naive_assembly(cube):
    rng = np.random.default_rng(4)
    rotations = rotation_matrix(rng.standard_normal((cube.tet_count, 3)))
    blocks = np.zeros((cube.tet_count, 12, 12))
    for a in range(4):
        blocks[:, 3 * a : 3 * a + 3, 3 * a : 3 * a + 3] = rotations
    local = blocks @ cube.element_stiffness @ np.swapaxes(blocks, 1, 2)
    dofs = (3 * cube.tets[:, :, None] + np.arange(3)).reshape(-1, 12)
    rows = np.repeat(dofs, 12, axis=1).ravel()
    cols = np.tile(dofs, (1, 12)).ravel()
    naive = sp.coo_matrix((local.ravel(), (rows, cols)), shape=(cube.dof_count,) * 2).tocsr()
    tangent = cube.tangent_stiffness(rotations)
    assert abs(tangent - naive).max() < 1e-12 * abs(naive).max()
    again = cube.tangent_stiffness(rotations)
    assert np.array_equal(again.indices, tangent.indices) and np.array_equal(again.indptr, tangent.indptr)


def test_tangent_symmetric_positive_semidefinite(cube):
    rng = np.random.default_rng(5)
    positions = cube.rest_positions + 0.02 * rng.standard_normal(cube.rest_positions.shape)
    tangent = cube.tangent_stiffness(cube.element_rotations(positions)).toarray()
    scale = np.abs(tangent).max()
    np.testing.assert_allclose(tangent, tangent.T, atol=1e-13 * scale)
    eigenvalues = np.linalg.eigvalsh(tangent)
    assert eigenvalues[0] > -1e-12 * eigenvalues[-1]
    # Only the 3 translations are exact zero modes: each Rₑ Kₑ Rₑᵀ annihilates rotations of Rₑ X, which differ
    # from tet to tet once the body is deformed, so global rotations cost (little) energy. At rest
    # there are 6.
    assert np.sum(eigenvalues < 1e-10 * eigenvalues[-1]) == 3
    at_rest = np.linalg.eigvalsh(cube.rest_stiffness.toarray())
    assert np.sum(at_rest < 1e-10 * at_rest[-1]) == 6


@pytest.mark.parametrize("angle", [np.pi / 2, np.pi - 1e-3, 2.5])
def test_rigid_motions_give_zero_forces(cube, angle):
    rotation = rotation_matrix(np.array([[1.0, -2.0, 0.5]]) / np.sqrt(5.25) * angle)[0]
    positions = cube.rest_positions @ rotation.T + np.array([0.3, -1.0, 2.0])
    rotations = cube.element_rotations(positions)
    np.testing.assert_allclose(rotations, np.broadcast_to(rotation, rotations.shape), atol=1e-13)
    forces = cube.internal_forces(positions, rotations)
    # Round-off bound: Σ|K_ij| · 10 ε · (tet size), the local displacements being centred on each tet (see
    # refsim.verification.tissue.case_rigid_motions); the energy is quadratic in that error.
    element_size = 0.1 * np.sqrt(3) / 2
    noise = 10 * EPS * element_size
    stiffness_scale = abs(cube.rest_stiffness).sum(axis=1).max()
    assert np.abs(forces).max() < stiffness_scale * noise
    assert cube.strain_energy(positions) < cube.tet_count * stiffness_scale * noise**2


def test_global_rotation_covariance(cube):
    # f(Q x) = Q f(x) and K(Q x) = Q K(x) Qᵀ (block-wise) for any rotation Q: frame indifference.
    rng = np.random.default_rng(6)
    positions = cube.rest_positions + 0.01 * rng.standard_normal(cube.rest_positions.shape)
    q = rotation_matrix(np.array([[0.4, 1.1, -0.7]]))[0]
    forces = cube.internal_forces(positions, cube.element_rotations(positions))
    rotated = positions @ q.T
    rotated_forces = cube.internal_forces(rotated, cube.element_rotations(rotated))
    np.testing.assert_allclose(rotated_forces, forces @ q.T, atol=1e-11 * np.abs(forces).max())
    big_q = sp.block_diag([q] * cube.node_count)
    tangent = cube.tangent_stiffness(cube.element_rotations(positions))
    rotated_tangent = cube.tangent_stiffness(cube.element_rotations(rotated))
    assert abs(rotated_tangent - big_q @ tangent @ big_q.T).max() < 1e-11 * abs(tangent).max()


def test_internal_forces_balance_force_and_torque(cube):
    # Σ f = 0 (translation invariance) and Σ x × f = 0 (rotation invariance of the polar co-rotated energy).
    rng = np.random.default_rng(7)
    positions = cube.rest_positions + 0.02 * rng.standard_normal(cube.rest_positions.shape)
    forces = cube.internal_forces(positions, cube.element_rotations(positions))
    scale = np.abs(forces).max()
    np.testing.assert_allclose(forces.sum(axis=0), 0.0, atol=1e-12 * scale)
    np.testing.assert_allclose(np.cross(positions, forces).sum(axis=0), 0.0, atol=1e-12 * scale * 0.1)


def _tangent_mismatch(model: TissueModel, positions: np.ndarray, direction: np.ndarray, step: float) -> float:
    """‖K v − (f(x + h v) − f(x − h v)) / 2h‖ / ‖K v‖."""

    def forces(x):
        return model.internal_forces(x, model.element_rotations(x)).ravel()

    analytic = model.tangent_stiffness(model.element_rotations(positions)) @ direction.ravel()
    numeric = (forces(positions + step * direction) - forces(positions - step * direction)) / (2 * step)
    return float(np.linalg.norm(numeric - analytic) / np.linalg.norm(analytic))


def test_tangent_is_exact_at_rigid_configurations_and_approximate_otherwise(cube):
    """At a rigid configuration K is the exact tangent: the central difference (f(x + h v) − f(x − h v)) / 2h
    differs from K v by its truncation, C h² + D h⁴ (order 2, next term q = 2), plus its round-off, the
    positions' ε max|x| over the step h (relative to ‖K v‖). Away from it R K Rᵀ omits ∂R/∂x: the mismatch is
    O(strain) (order 1 in the strain's amplitude s, next term O(s²): q = 1) and does not vanish with h. Each
    order is asserted on three levels (r = 2) with the band derived from them (tests/observed_order.py)."""
    rng = np.random.default_rng(8)
    direction = rng.standard_normal(cube.rest_positions.shape)
    rotation = rotation_matrix(np.array([[np.pi / 2, 0.0, 0.0]]))[0]
    rigid = cube.rest_positions @ rotation.T
    steps = np.array([4e-5, 2e-5, 1e-5])
    mismatches = np.array([_tangent_mismatch(cube, rigid, direction, step) for step in steps])
    roundoff = np.finfo(float).eps * np.abs(rigid).max() / steps / mismatches
    assert mismatches[-1] < 1e-6
    assert_order(mismatches, 2.0, order=2.0, next_exponent=2.0, roundoff=roundoff, what="rigid tangent")
    shape = np.sin(30.0 * cube.rest_positions)
    amplitudes = np.array([0.002, 0.001, 0.0005])
    strained = np.array(
        [
            _tangent_mismatch(cube, (cube.rest_positions + amplitude * shape) @ rotation.T, direction, 1e-7)
            for amplitude in amplitudes
        ]
    )
    assert strained[-1] > 1e-4
    assert_order(strained, 2.0, order=1.0, next_exponent=1.0, what="strained tangent")


def test_forces_are_the_gradient_of_the_energy(cube):
    rng = np.random.default_rng(9)
    positions = (
        cube.rest_positions + 0.01 * rng.standard_normal(cube.rest_positions.shape)
    ) @ rotation_matrix(np.array([[0.3, 0.2, 1.4]]))[0].T
    direction = rng.standard_normal(positions.shape)
    step = 1e-7
    numeric = (
        cube.strain_energy(positions + step * direction) - cube.strain_energy(positions - step * direction)
    ) / (2 * step)
    analytic = np.sum(cube.internal_forces(positions, cube.element_rotations(positions)) * direction)
    assert numeric == pytest.approx(analytic, rel=1e-7)


# ------------------------------------------------------------------ time stepping


@pytest.mark.parametrize("rayleigh_mass", [0.0, 5.0])
def test_free_fall_step(cube, rayleigh_mass):
    # A free body under gravity translates rigidly (K annihilates translations), so one implicit Euler step
    # solves (1/dt² + α/dt) M Δx = M g + M v₀/dt: Δx = (g dt² + v₀ dt) / (1 + α dt).
    gravity = np.array([0.0, -3.0, -9.81])
    model = TissueModel(
        cube.rest_positions, cube.tets, MATERIAL, gravity=gravity, rayleigh_mass=rayleigh_mass
    )
    v0 = np.array([0.1, 0.2, -0.3])
    state = TissueState(positions=cube.rest_positions + 1.0, velocities=np.tile(v0, (cube.node_count, 1)))
    dt = 0.01
    positions, velocities, system = model.free_motion(state, dt)
    expected_step = (gravity * dt**2 + v0 * dt) / (1.0 + rayleigh_mass * dt)
    np.testing.assert_allclose(
        positions - state.positions, np.tile(expected_step, (cube.node_count, 1)), rtol=1e-9
    )
    np.testing.assert_allclose(velocities, (positions - state.positions) / dt, rtol=1e-12)
    assert system.dof_count == model.dof_count


def test_fixed_nodes_stay_and_can_be_driven(cube):
    bottom = np.flatnonzero(cube.rest_positions[:, 2] == 0.0)
    model = TissueModel(
        cube.rest_positions, cube.tets, MATERIAL, fixed_nodes=bottom, gravity=(0.0, 0.0, -9.81)
    )
    state = model.rest_state()
    positions, velocities, system = model.free_motion(state, 0.01)
    np.testing.assert_array_equal(positions[bottom], cube.rest_positions[bottom])
    np.testing.assert_array_equal(system.constrained_dofs, model.fixed_dofs)
    assert (positions - cube.rest_positions)[:, 2].min() < 0.0  # the rest sags
    drive = np.tile([0.0, 0.0, 1e-3], (bottom.size, 1))
    driven, _, _ = model.free_motion(state, 0.01, fixed_displacements=drive)
    np.testing.assert_allclose(driven[bottom], cube.rest_positions[bottom] + drive, rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="fixed_displacements"):
        model.free_motion(state, 0.01, fixed_displacements=np.zeros((1, 3)))


def test_step_system_compliance_symmetric_positive(cube):
    bottom = np.flatnonzero(cube.rest_positions[:, 2] == 0.0)
    model = TissueModel(
        cube.rest_positions,
        cube.tets,
        MATERIAL,
        fixed_nodes=bottom,
        rayleigh_mass=1.0,
        rayleigh_stiffness=0.01,
    )
    system = model.step_system(model.element_rotations(cube.rest_positions), 0.01)
    rng = np.random.default_rng(10)
    jacobian = rng.standard_normal((5, model.dof_count))
    compliance, _ = system.compliance(jacobian)
    assert np.all(np.linalg.eigvalsh(compliance) > 0.0)


def test_solve_static_under_gravity_balances_forces():
    rest, tets = box(3)
    bottom = np.flatnonzero(rest[:, 2] == 0.0)
    model = TissueModel(rest, tets, MATERIAL, fixed_nodes=bottom, gravity=(0.0, 0.0, -9.81))
    solution = model.solve_static(tolerance=1e-10)
    assert solution.converged
    internal = model.internal_forces(solution.positions, model.element_rotations(solution.positions))
    # The base carries the weight: the support reactions f_int − f_ext on the fixed nodes sum to −m g.
    reactions = internal[bottom] - model.external_forces()[bottom]
    np.testing.assert_allclose(
        reactions.sum(axis=0), [0.0, 0.0, 9.81 * model.nodal_masses.sum()], rtol=1e-8, atol=1e-9
    )


# ------------------------------------------------------------------ input errors


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"rayleigh_mass": -1.0}, "rayleigh_mass"),
        ({"rayleigh_stiffness": np.nan}, "rayleigh_stiffness"),
        ({"gravity": (0.0, 9.81)}, "gravity"),
        ({"fixed_nodes": [0, 10_000]}, "fixed_nodes"),
    ],
)
def test_bad_parameters_are_named(cube, kwargs, match):
    with pytest.raises(ValueError, match=match):
        TissueModel(cube.rest_positions, cube.tets, MATERIAL, **kwargs)


def test_bad_meshes_are_named(cube):
    with pytest.raises(ValueError, match="rest_positions"):
        TissueModel(cube.rest_positions[:, :2], cube.tets, MATERIAL)
    with pytest.raises(ValueError, match="outside"):
        TissueModel(cube.rest_positions, cube.tets + 1000, MATERIAL)
    flat = cube.rest_positions.copy()
    flat[:, 2] = 0.0
    with pytest.raises(ValueError, match="zero volume"):
        TissueModel(flat, cube.tets, MATERIAL)
    with pytest.raises(ValueError, match="integer"):
        TissueModel(cube.rest_positions, cube.tets.astype(float), MATERIAL)
    with pytest.raises(ValueError, match="positions must have shape"):
        cube.internal_forces(np.zeros((3, 3)), cube.element_rotations(cube.rest_positions))
    with pytest.raises(ValueError, match="velocities"):
        TissueState(positions=cube.rest_positions, velocities=np.zeros((2, 3)))


@pytest.mark.parametrize("solver", available_linear_solvers())
def test_free_motion_assembles_what_the_strategy_reads(cube, solver):
    # The exact strategy on PARDISO or the supernodal solver reads A's upper triangle only, so the free motion
    # assembles only that; the factor is the one of the full matrix (the same upper numbers): same bits.
    rest = cube.rest_positions
    state = TissueState(positions=rest + 1e-3 * np.sin(50.0 * rest), velocities=0.05 * np.cos(20.0 * rest))
    positions, _, step = cube.free_motion(state, 0.01, compliance=Exact(linear_solver=solver).bind())
    assert step.system.upper_triangle == (make_linear_solver(solver).storage == "upper")
    full = Exact(linear_solver=solver).bind().step(cube.assemble_step(state, 0.01))
    np.testing.assert_array_equal(
        positions, rest + 1e-3 * np.sin(50.0 * rest) + full.free_displacement.reshape(-1, 3)
    )
    # a strategy that multiplies by A (PCG) keeps the full storage, and refuses the upper triangle alone
    _, _, refreshed = cube.free_motion(state, 0.01, compliance=Refreshed(linear_solver=solver).bind())
    assert not refreshed.system.upper_triangle
    upper = cube.assemble_step(state, 0.01, upper_triangle=True)
    with pytest.raises(ValueError, match="upper triangle"):
        Refreshed(linear_solver=solver).bind().step(upper)
