"""The bodies of the time step behind one protocol (refsim.simulation.bodies.Body): the tissue, the rigid
(kinematic) needle and the flexible needle.

Reference equations (docs/architecture.md, "Conventions"): each deformable body b has, at a step, the
effective stiffness A_b = M/dt² + C/dt + K on its free DoFs (fixed and prescribed DoFs eliminated); rows with
Jacobians H_b give the compliance W = Σ_b H_b A_b⁻¹ H_bᵀ and, with multipliers λ, the correction
x_b = x_b,free + A_b⁻¹ H_bᵀ λ. The references below invert A_b densely (LAPACK); the tolerance is the
round-off of the sparse factorisation against it, 10 κ(A_b) ε relative, κ measured.
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest
import scipy.sparse as sp

from refsim.constraints import BILATERAL, NEEDLE, TISSUE, RowBlock
from refsim.simulation import FlexibleNeedle, RigidNeedle, Simulation
from refsim.simulation.bodies import Body, TissueBody

EPS = np.finfo(float).eps
COARSE = "mesh.cells=[3, 3, 3]"
ROWS = 5


@pytest.fixture(scope="module")
def flexible():
    from tests.conftest import cube_scene

    return Simulation(cube_scene(COARSE, "needle.rigid=false"))


@pytest.fixture(scope="module")
def rigid():
    from tests.conftest import cube_scene

    return Simulation(cube_scene(COARSE))


def free_motion(simulation: Simulation):
    """The initial state, each body's free state and step system by name, after one step's free motion."""
    state = simulation.initial_state()
    control = simulation.controls.at(simulation.dt)
    free, systems = {}, {}
    for body in simulation.bodies:
        free[body.name], systems[body.name] = body.free_motion(
            getattr(state, body.name), control, simulation.dt
        )
    return state, free, systems


def random_rows(dof_count: int, seed: int) -> sp.csr_matrix:
    """ROWS rows, each on 6 random DoFs (some of them may be fixed or prescribed)."""
    rng = np.random.default_rng(seed)
    columns = np.stack([rng.choice(dof_count, 6, replace=False) for _ in range(ROWS)])
    values = rng.standard_normal(columns.shape)
    rows = np.repeat(np.arange(ROWS), 6)
    return sp.csr_matrix((values.ravel(), (rows, columns.ravel())), shape=(ROWS, dof_count))


def block(jacobians: dict) -> RowBlock:
    return RowBlock(
        jacobians=jacobians,
        free_gap=np.zeros(ROWS),
        kind=np.full(ROWS, BILATERAL, dtype=np.int8),
        source=np.zeros(ROWS, dtype=np.int8),
        points=np.zeros((ROWS, 3)),
        directions=np.tile([0.0, 0.0, 1.0], (ROWS, 1)),
    )


def dense_inverse(step) -> tuple[np.ndarray, float]:
    """A⁻¹ on every DoF of the body (zero on the constrained ones) by LAPACK, and κ(A) on the free DoFs."""
    system = step.system
    matrix = system.full_matrix().toarray()
    inverse = np.zeros((system.dof_count, system.dof_count))
    inverse[np.ix_(system.free_dofs, system.free_dofs)] = np.linalg.inv(matrix)
    return inverse, float(np.linalg.cond(matrix))


def test_every_body_satisfies_the_one_protocol(flexible, rigid):
    bodies = (*flexible.bodies, *rigid.bodies)
    assert {type(body) for body in bodies} == {TissueBody, FlexibleNeedle, RigidNeedle}
    for simulation in (flexible, rigid):
        names = [body.name for body in simulation.bodies]
        assert names == [TISSUE, NEEDLE]  # the tissue first: W is summed in this order
    for body in bodies:
        assert isinstance(body, Body)
    # The same signature for each operation, whatever the body.
    for operation in ("free_motion", "compliance", "correct"):
        signatures = {tuple(inspect.signature(getattr(body, operation)).parameters) for body in bodies}
        assert len(signatures) == 1, (operation, signatures)
    assert rigid.needle.dof_count is None
    assert flexible.needle.dof_count == 6 * flexible.models.needle.node_count
    assert flexible.tissue_body.dof_count == flexible.tissue.dof_count


def test_compliance_is_the_sum_over_the_bodies(flexible):
    # W = H_t A_t⁻¹ H_tᵀ + H_n A_n⁻¹ H_nᵀ, each A_b inverted densely.
    _, _, systems = free_motion(flexible)
    jacobians = {
        TISSUE: random_rows(flexible.tissue_body.dof_count, seed=1),
        NEEDLE: random_rows(flexible.needle.dof_count, seed=2),
    }
    problem, responses = flexible._problem(block(jacobians), systems)
    expected = np.zeros((ROWS, ROWS))
    tolerance = 0.0
    for name, jacobian in jacobians.items():
        inverse, kappa = dense_inverse(systems[name])
        part = jacobian @ inverse @ jacobian.T
        expected += part
        tolerance += 10 * kappa * EPS * np.abs(part).max()
    assert np.abs(problem.compliance - expected).max() <= tolerance
    assert set(responses) == {TISSUE, NEEDLE}
    assert all(value is not None for value in responses.values())


def test_a_kinematic_body_adds_nothing(rigid):
    # A rigid needle: no DoFs, no Jacobian in a row block, W is the tissue's alone, its correction its free
    # state.
    state, free, systems = free_motion(rigid)
    assert systems[NEEDLE] is None
    tissue_rows = random_rows(rigid.tissue_body.dof_count, seed=3)
    rows = block({TISSUE: tissue_rows, NEEDLE: None})
    assert set(rows.jacobians) == {TISSUE}
    problem, responses = rigid._problem(rows, systems)
    alone, _ = rigid.tissue_body.compliance(systems[TISSUE], tissue_rows)
    np.testing.assert_array_equal(problem.compliance, alone)
    assert responses[NEEDLE] is None
    zero, nothing = rigid.needle.compliance(None, sp.csr_matrix((ROWS, 0)))
    np.testing.assert_array_equal(zero, np.zeros((ROWS, ROWS)))
    assert nothing is None
    multipliers = np.ones(ROWS)
    corrected = rigid.needle.correct(None, state.needle, free[NEEDLE], None, multipliers, rigid.dt)
    assert corrected is free[NEEDLE]


def test_correction_is_the_free_state_plus_the_response_to_the_forces(flexible):
    # x_b = x_b,free + A_b⁻¹ H_bᵀ λ, against a dense solve; velocities over the whole step.
    state, free, systems = free_motion(flexible)
    dt = flexible.dt
    jacobians = {
        TISSUE: random_rows(flexible.tissue_body.dof_count, seed=4),
        NEEDLE: random_rows(flexible.needle.dof_count, seed=5),
    }
    _, responses = flexible._problem(block(jacobians), systems)
    multipliers = np.random.default_rng(6).standard_normal(ROWS)
    corrected = flexible._correct(state, free, systems, responses, multipliers)

    inverse, kappa = dense_inverse(systems[TISSUE])
    expected = (inverse @ (jacobians[TISSUE].T @ multipliers)).reshape(-1, 3)
    tissue = corrected[TISSUE]
    moved = tissue.positions - free[TISSUE].positions
    # Round-off: of the factorisation (10 κ ε relative) and of adding to positions (ε max|x| per entry).
    scale = np.abs(free[TISSUE].positions).max()
    assert np.abs(moved - expected).max() <= 10 * kappa * EPS * np.abs(expected).max() + 2 * EPS * scale
    np.testing.assert_array_equal(tissue.velocities, (tissue.positions - state.tissue.positions) / dt)

    inverse, kappa = dense_inverse(systems[NEEDLE])
    delta = (inverse @ (jacobians[NEEDLE].T @ multipliers)).reshape(-1, 6)
    needle = corrected[NEEDLE]
    moved = needle.positions - free[NEEDLE].positions
    scale = np.abs(free[NEEDLE].positions).max()
    assert np.abs(moved - delta[:, :3]).max() <= 10 * kappa * EPS * np.abs(delta).max() + 2 * EPS * scale
    velocity_change = needle.velocities - free[NEEDLE].velocities
    speed = np.abs(free[NEEDLE].velocities).max()
    assert np.abs(velocity_change - delta / dt).max() <= (
        10 * kappa * EPS * np.abs(delta).max() / dt + 2 * EPS * speed
    )
    # Nothing moves on the prescribed base DoFs.
    np.testing.assert_array_equal(needle.positions[0], free[NEEDLE].positions[0])


def test_a_non_finite_body_state_stops_the_run_naming_the_body(rigid):
    from dataclasses import replace

    from refsim.simulation import SimulationError

    state, free, _ = free_motion(rigid)
    positions = free[NEEDLE].positions.copy()
    positions[-1, 2] = np.nan
    states = {TISSUE: free[TISSUE], NEEDLE: replace(free[NEEDLE], positions=positions)}
    with pytest.raises(SimulationError, match="step 3: non-finite needle positions"):
        rigid._check_finite(3, states, np.zeros(2))
    rigid._check_finite(3, free, np.zeros(2))  # finite: nothing raised
    with pytest.raises(SimulationError, match="non-finite constraint forces"):
        rigid._check_finite(3, free, np.array([0.0, np.inf]))


def test_a_diverged_flexible_needle_stops_the_run_naming_it(flexible):
    # Reference: a steel needle yields below 1 % of axial strain, so an element's chord 20 % off its rest
    # length is a step whose one Newton step diverged (DIVERGED_STRAIN = 10 %), and 5 % is not stopped.
    from dataclasses import replace

    from refsim.simulation import SimulationError

    _, free, _ = free_motion(flexible)
    flexible._check_converged(3, free)  # as it is: nothing raised
    for stretch, stops in ((0.2, True), (0.05, False)):
        positions = free[NEEDLE].positions.copy()
        positions[-1] += stretch * (positions[-1] - positions[-2])  # the last element's chord by `stretch`
        states = {**free, NEEDLE: replace(free[NEEDLE], positions=positions)}
        if stops:
            with pytest.raises(SimulationError, match=r"step 3: the needle 'needle' diverged: its element"):
                flexible._check_converged(3, states)
        else:
            flexible._check_converged(3, states)


def test_a_strained_flexible_needle_is_measured_and_warned_once(flexible, caplog):
    # Reference: the chord strain |‖x_{e+1} − x_e‖ / ℓ_e − 1| of a stretched element is the stretch itself;
    # between STRAIN_WARNING (1 %, beyond steel's yield strain) and DIVERGED_STRAIN (10 %) the run goes on
    # with one warning per needle; below 1 % nothing is said; a rigid needle's strain is 0.
    from dataclasses import replace

    from refsim.simulation.needle_body import DIVERGED_STRAIN, STRAIN_WARNING

    body = flexible.needle
    _, free, _ = free_motion(flexible)
    assert body.element_strain(free[NEEDLE])[0] < 1e-6
    assert RigidNeedle(0.1, 4).element_strain(free[NEEDLE]) == (0.0, 0)
    for stretch, warned in ((0.5 * STRAIN_WARNING, False), (0.05, True), (2.0 * DIVERGED_STRAIN, False)):
        positions = free[NEEDLE].positions.copy()
        positions[-1] += stretch * (positions[-1] - positions[-2])  # the last element's chord by `stretch`
        state = replace(free[NEEDLE], positions=positions)
        strain, element = body.element_strain(state)
        assert strain == pytest.approx(stretch, rel=1e-6) and element == positions.shape[0] - 2
        message = body.strained(state)
        assert (message is not None) == warned  # above DIVERGED_STRAIN, diverged() speaks instead
        if warned:
            assert "smaller time.dt" in message and "steps/needle_strain" in message
    positions = free[NEEDLE].positions.copy()
    positions[-1] += 0.05 * (positions[-1] - positions[-2])
    stretched = replace(free[NEEDLE], positions=positions)
    world = flexible.initial_state()
    world = replace(world, instruments=(replace(world.instruments[0], needle=stretched),))
    flexible._strained.clear()  # the module's simulation: warned by no other test
    with caplog.at_level("WARNING", logger="refsim.simulation.simulation"):
        flexible._warn_strained(7, world)
        flexible._warn_strained(8, world)
    warnings = [r.getMessage() for r in caplog.records if "off its rest length" in r.getMessage()]
    assert len(warnings) == 1 and warnings[0].startswith("step 7: the element")


def test_a_rigid_needles_frames_follow_its_direction():
    # The nodes' frames are kept for the last direction: each pose gets the rest frame of its own direction,
    # as a fresh array of its own.
    from refsim.geometry import needle_rest_frame

    needle = RigidNeedle(0.1, 4)
    base = np.zeros(3)
    along_z = needle.state_at(base, np.array([0.0, 0.0, -1.0]))
    tilted_direction = np.array([0.6, 0.0, -0.8])
    tilted = needle.state_at(base, tilted_direction)
    again = needle.state_at(base + 1e-3, tilted_direction)
    poses = ((along_z, [0.0, 0.0, -1.0]), (tilted, tilted_direction), (again, tilted_direction))
    for state, direction in poses:
        expected = needle_rest_frame(np.asarray(direction))
        assert state.frames.shape == (5, 3, 3)
        np.testing.assert_array_equal(state.frames, np.broadcast_to(expected, (5, 3, 3)))
    assert again.frames is not tilted.frames and again.frames.flags.writeable
    again.frames[0] = 0.0  # a caller's copy: the next pose is not touched
    np.testing.assert_array_equal(needle.state_at(base, tilted_direction).frames, tilted.frames)
    with pytest.raises(ValueError):
        needle.state_at(base, np.zeros(3))
