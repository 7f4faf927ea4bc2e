"""Compliance strategies (refsim.fem.compliance): exact against dense LAPACK, Dirichlet motion of fixed nodes,
refreshed, precomputed and fast against exact with errors derived or measured, the needle's step system."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from refsim.fem.compliance import (
    STRATEGIES,
    Exact,
    Fast,
    FreeMotionStart,
    Precomputed,
    Refreshed,
    StepSystem,
    make_strategy,
    pcg,
)
from refsim.fem.compliance.bodies import STRATEGY_CLASSES
from refsim.fem.integration import effective_stiffness
from refsim.fem.linear import available_linear_solvers
from refsim.fem.tissue import TissueModel, TissueState
from refsim.geometry.rotations import rotation_matrix
from refsim.materials import HookeMaterial
from refsim.mesh.generators import box_mesh
from tests.observed_order import assert_order

EPS = np.finfo(float).eps
MATERIAL = HookeMaterial(youngs_modulus=5.0e5, poisson_ratio=0.4, density=1000.0)
DT = 0.01


@pytest.fixture(scope="module")
def model() -> TissueModel:
    mesh = box_mesh(size=(0.1, 0.1, 0.1), cells=(3, 3, 3))
    rest = np.asarray(mesh.rest_positions, dtype=float)
    return TissueModel(
        rest,
        np.asarray(mesh.tets),
        MATERIAL,
        rayleigh_mass=1.0,
        rayleigh_stiffness=0.01,
        fixed_nodes=np.flatnonzero(rest[:, 2] < 1e-12),
        gravity=(0.0, 0.0, -9.81),
    )


def deformed(model: TissueModel, amplitude: float = 0.01, seed: int = 0) -> TissueState:
    rest = model.rest_positions
    positions = rest + amplitude * np.sin(20.0 * rest + seed)
    positions[model.fixed_nodes] = rest[model.fixed_nodes]
    velocities = 0.05 * np.cos(10.0 * rest + seed)
    velocities[model.fixed_nodes] = 0.0
    return TissueState(positions=positions, velocities=velocities)


def rows_on(model: TissueModel, count: int = 6, seed: int = 1) -> sp.csr_matrix:
    """Constraint-like rows: each couples the 12 DoFs of one tet (a point inside it) with a direction."""
    rng = np.random.default_rng(seed)
    tets = rng.choice(model.tet_count, count, replace=False)
    data, cols, rows = [], [], []
    for row, tet in enumerate(tets):
        weights = rng.dirichlet(np.ones(4))
        direction = rng.standard_normal(3)
        direction /= np.linalg.norm(direction)
        for node, weight in zip(model.tets[tet], weights, strict=True):
            rows += [row] * 3
            cols += list(3 * node + np.arange(3))
            data += list(weight * direction)
    return sp.csr_matrix((data, (rows, cols)), shape=(count, model.dof_count))


def dense_reference(model: TissueModel, state: TissueState, prescribed: np.ndarray | None = None):
    """Free motion and A⁻¹ of the reduced system by dense LAPACK (the reference)."""
    system = model.assemble_step(state, DT, fixed_displacements=prescribed)
    dense = system.matrix.toarray()
    inverse = np.linalg.inv(dense)
    return system, dense, inverse, system.expand(np.linalg.solve(dense, system.rhs), system.prescribed)


def test_exact_strategy_matches_dense_lapack_and_its_fast_forms(model):
    # The NumPy assembly on SuperLU/COLAMD and the compiled one (free_motion, default solver) against a dense
    # LAPACK solve of the same reduced system: κ(A)·ε relative (κ measured).
    state = deformed(model)
    system, dense, inverse, expected = dense_reference(model, state)
    kappa = np.linalg.cond(dense)
    tolerance = 10 * kappa * EPS
    step = Exact(linear_solver="superlu:COLAMD").bind().step(model.assemble_step(state, DT, compiled=False))
    scale = np.abs(expected).max()
    assert np.abs(step.free_displacement - expected).max() <= tolerance * scale
    positions, velocities, _ = model.free_motion(state, DT)
    moved = (positions - state.positions).ravel()
    assert np.abs(moved - expected).max() <= tolerance * scale
    # v = Δx/dt, and x₀ + Δx − x₀ is Δx to the round-off of the positions (ε max|x|).
    assert np.abs(velocities.ravel() - moved / DT).max() <= 2 * EPS * np.abs(positions).max() / DT
    jacobian = rows_on(model)
    w, responses = step.compliance(jacobian)
    full_inverse = system.expand(system.expand(inverse).T).T  # A⁻¹ on every DoF, zero on the fixed ones
    reference_w = jacobian @ full_inverse @ jacobian.T
    assert np.abs(w - reference_w).max() <= tolerance * np.abs(reference_w).max()
    np.testing.assert_array_equal(w, w.T)
    np.testing.assert_array_equal(responses[system.constrained_dofs], 0.0)
    # The fast forms agree with it to round-off.
    lam = np.random.default_rng(2).standard_normal(jacobian.shape[0])
    np.testing.assert_allclose(step.delassus(jacobian), w, rtol=0, atol=tolerance * np.abs(w).max())
    correction = step.correction(jacobian, lam)
    reference = responses @ lam
    assert np.abs(correction - reference).max() <= tolerance * np.abs(reference).max()


@pytest.mark.parametrize("solver", available_linear_solvers())
def test_exact_strategy_on_every_linear_solver_equals_a_dense_solve(model, solver):
    state = deformed(model)
    system, dense, inverse, free = dense_reference(model, state)
    step = Exact(linear_solver=solver).bind().step(system)
    kappa = np.linalg.cond(dense)
    bound = 10 * kappa * EPS  # backward-stable direct solve: relative forward error ≲ κ ε (Higham, ch. 7)
    assert np.abs(step.free_displacement - free).max() <= bound * np.abs(free).max()
    jacobian = rows_on(model)
    h = jacobian[:, system.free_dofs].toarray()
    w_reference = h @ inverse @ h.T
    assert np.abs(step.delassus(jacobian) - w_reference).max() <= bound * np.abs(w_reference).max()


def crowded_rows(model: TissueModel, count: int = 30, seed: int = 3) -> sp.csr_matrix:
    """More rows than DoFs touched: ``count`` points in two tets (as the paper's line rows in few tets)."""
    rng = np.random.default_rng(seed)
    tets = model.tets[rng.choice(model.tet_count, 2, replace=False)]
    data, cols, rows = [], [], []
    for row in range(count):
        nodes = tets[row % 2]
        weights = rng.dirichlet(np.ones(4))
        direction = rng.standard_normal(3)
        direction /= np.linalg.norm(direction)
        for node, weight in zip(nodes, weights, strict=True):
            rows += [row] * 3
            cols += list(3 * node + np.arange(3))
            data += list(weight * direction)
    return sp.csr_matrix((data, (rows, cols)), shape=(count, model.dof_count))


@pytest.mark.parametrize("layout", ["spread", "crowded"])
@pytest.mark.parametrize("solver", available_linear_solvers())
def test_exact_delassus_and_correction_for_few_or_many_rows(model, solver, layout):
    # Fewer rows than DoFs touched or more: with PARDISO W comes from the block of A⁻¹ on the DoFs touched
    # (a partial solve), otherwise from the rows' or the unit loads; W and A⁻¹Hᵀλ equal the dense solve to
    # κ(A)·ε.
    state = deformed(model)
    system, dense, inverse, _ = dense_reference(model, state)
    step = Exact(linear_solver=solver).bind().step(system)
    jacobian = rows_on(model, count=6) if layout == "spread" else crowded_rows(model)
    used = np.unique(jacobian.indices).size
    assert (jacobian.shape[0] < used) == (layout == "spread")
    bound = 10 * np.linalg.cond(dense) * EPS
    h = jacobian[:, system.free_dofs].toarray()
    w_reference = h @ inverse @ h.T
    assert np.abs(step.delassus(jacobian) - w_reference).max() <= bound * np.abs(w_reference).max()
    lam = np.random.default_rng(4).standard_normal(jacobian.shape[0])
    reference = system.expand(inverse @ (h.T @ lam))
    assert np.abs(step.correction(jacobian, lam) - reference).max() <= bound * np.abs(reference).max()


@pytest.mark.parametrize("solver", available_linear_solvers())
def test_an_exact_step_from_the_same_state_keeps_the_factor_and_its_bits(model, solver):
    # A tissue at rest (a needle above it) assembles the same matrix each step: the exact strategy's solver
    # keeps the factor of those values, and the step is the same, bit for bit, as one that factorised them.
    state = deformed(model)
    body = Exact(linear_solver=solver).bind()
    jacobian = rows_on(model)
    lam = np.linspace(-1.0, 1.0, jacobian.shape[0])
    steps = [body.step(model.assemble_step(state, 0.01)) for _ in range(2)]
    assert [step.report["refactorised"] for step in steps] == [True, False]
    fresh = Exact(linear_solver=solver).bind().step(model.assemble_step(state, 0.01))
    for step in (steps[1], fresh):
        np.testing.assert_array_equal(step.free_displacement, steps[0].free_displacement)
    np.testing.assert_array_equal(steps[1].delassus(jacobian), fresh.delassus(jacobian))
    np.testing.assert_array_equal(steps[1].correction(jacobian, lam), fresh.correction(jacobian, lam))
    moved = body.step(model.assemble_step(deformed(model, seed=4), 0.01))
    assert moved.report["refactorised"]


def test_exact_body_carries_its_partial_solve_marks_and_a_resumed_body_gives_the_same_bits(model):
    if "pardiso" not in available_linear_solvers():
        pytest.skip("partial solves need pardiso")
    from refsim.fem.compliance import PartialSolveMarks

    jacobian = rows_on(model, count=6)
    first, second = deformed(model, seed=0), deformed(model, seed=5)
    body = Exact(linear_solver="pardiso").bind()
    assert body.carried() is None  # nothing marked before any rows
    step = body.step(model.assemble_step(first, 0.01))
    step.delassus(jacobian)
    carried = body.carried()
    assert isinstance(carried, PartialSolveMarks)
    used = np.flatnonzero(np.isin(step.free_dofs, jacobian.indices))
    np.testing.assert_array_equal(carried.positions, used)  # exactly the DoFs the rows touch
    lam = np.linspace(-1.0, 1.0, jacobian.shape[0])

    def next_step(compliance):
        step = compliance.step(model.assemble_step(second, 0.01))
        return step.free_displacement, step.delassus(jacobian), step.correction(jacobian, lam)

    uninterrupted = next_step(body)
    resumed_body = Exact(linear_solver="pardiso").bind()
    resumed_body.resume(carried)
    for a, b in zip(uninterrupted, next_step(resumed_body), strict=True):
        np.testing.assert_array_equal(a, b)


def test_fixed_node_displacements_are_a_dirichlet_condition(model):
    state = deformed(model)
    drive = np.tile([1e-3, -2e-3, 5e-4], (model.fixed_nodes.size, 1))
    positions, _, step = model.free_motion(state, DT, fixed_displacements=drive)
    np.testing.assert_array_equal(positions[model.fixed_nodes], state.positions[model.fixed_nodes] + drive)
    # Reference: the full system A Δx = b with Δx_c given, solved densely on the free DoFs.
    full = model.assemble_step(state, DT)
    rotations = model.element_rotations(state.positions)
    from refsim.fem.integration import effective_stiffness

    a = effective_stiffness(
        model.mass_matrix, model.tangent_stiffness(rotations), DT, rayleigh_mass=1.0, rayleigh_stiffness=0.01
    ).toarray()
    free, fixed = full.free_dofs, full.constrained_dofs
    b = full.rhs - a[np.ix_(free, fixed)] @ drive.ravel()
    expected = np.linalg.solve(a[np.ix_(free, free)], b)
    kappa = np.linalg.cond(a[np.ix_(free, free)])
    displacement = (positions - state.positions).ravel()
    assert np.abs(displacement[free] - expected).max() <= 10 * kappa * EPS * np.abs(expected).max()
    # The drive moves the body: not the same as holding the nodes.
    held, _, _ = model.free_motion(state, DT)
    assert np.abs(held - positions)[~np.isin(np.arange(model.node_count), model.fixed_nodes)].max() > 1e-5


def test_refreshed_equals_exact_at_refresh_and_meets_its_tolerance_between(model):
    strategy = Refreshed(refresh_every=3, tolerance=1e-10, against_exact=True)
    body = strategy.bind()
    state = deformed(model, 0.0)
    jacobian = rows_on(model)
    for index in range(5):
        state = deformed(model, 0.004 * (index + 1), seed=index)
        system = model.assemble_step(state, DT)
        step = body.step(system)
        assert step.report["refactorised"] == (index % 3 == 0)
        _, dense, inverse, free = dense_reference(model, state)
        kappa = np.linalg.cond(dense)
        # PCG to a relative residual τ: ‖Δx − Δx*‖ ≤ κ τ ‖Δx*‖ (plus the direct solve's κ ε at a refresh).
        tau = strategy.tolerance if not step.report["refactorised"] else 10 * EPS
        assert np.linalg.norm(step.free_displacement - free) <= kappa * tau * np.linalg.norm(free) * 1.01
        h = jacobian[:, system.free_dofs].toarray()
        w_reference = h @ inverse @ h.T
        w = step.delassus(jacobian)
        assert (
            np.linalg.norm(w - w_reference) <= kappa * max(tau, 10 * EPS) * np.linalg.norm(w_reference) * 10
        )
        assert "compliance_error" in step.report and "free_motion_error" in step.report
    # Stale W: measured, not bounded: it differs from exact by more than the PCG-corrected one.
    stale = Refreshed(refresh_every=3, compliance_update="stale", against_exact=True).bind()
    stale.step(model.assemble_step(deformed(model, 0.0), DT))
    far = stale.step(model.assemble_step(deformed(model, 0.02, seed=4), DT))
    far.delassus(jacobian)
    assert far.report["compliance_error"] > 1e-8


def test_precomputed_is_exact_at_rest_and_under_a_rigid_rotation(model):
    # A₀ = M/dt² + C/dt + K₀; for a rigid rotation R of the whole body K = R K₀ Rᵀ and M (lumped, per-node
    # isotropic) = R M Rᵀ, so A⁻¹ = R A₀⁻¹ Rᵀ exactly: the rotated rest compliance is then the exact one.
    rotation = rotation_matrix(np.array([[0.3, -0.2, 0.5]]))[0]
    rest = model.rest_positions
    unfixed = TissueModel(
        rest, model.tets, MATERIAL, rayleigh_mass=1.0, rayleigh_stiffness=0.01, fixed_nodes=np.array([0])
    )
    jacobian = rows_on(unfixed)
    for positions in (rest, rest @ rotation.T):
        state = TissueState(positions=positions, velocities=np.zeros_like(rest))
        system = unfixed.assemble_step(state, DT)
        body = Precomputed(against_exact=True).bind()
        step = body.step(system)
        w = step.delassus(jacobian)
        kappa = np.linalg.cond(system.matrix.toarray())
        assert step.report["compliance_error"] <= 10 * kappa * EPS
        assert np.abs(w).max() > 0.0
    # Deformed: the precomputed W is off (measured), the free motion still meets the PCG tolerance.
    state = deformed(model, 0.02)
    step = Precomputed(against_exact=True).bind().step(model.assemble_step(state, DT))
    step.delassus(rows_on(model))
    assert step.report["compliance_error"] > 1e-6
    assert step.report["pcg_residual"] <= 1e-10


def warped_reference(model: TissueModel, state: TissueState, system: StepSystem) -> np.ndarray:
    """Ã⁻¹ = R A₀⁻¹ Rᵀ on the free DoFs, dense: the node rotations (TissueModel.node_rotations of the tets'
    polar rotations) and the rest matrix inverted by LAPACK."""
    rest_inverse = np.linalg.inv(system.rest_matrix().toarray())
    rotations = model.node_rotations(model.element_rotations(state.positions))
    groups = system.free_dofs.reshape(-1, 3)[:, 0] // 3
    blocks = sp.block_diag(list(rotations[groups])).toarray()
    return blocks @ rest_inverse @ blocks.T


def rest_epsilon(body) -> float:
    """The unit round-off of a fast body's rest factor (single precision where the solver has it)."""
    return float(np.finfo(np.float32 if body.rest_precision == "single" else np.float64).eps)


@pytest.mark.parametrize("precision", ["single", "double"])
def test_fast_w_and_correction_are_the_rotated_rest_compliance(model, precision):
    # W = H R C₀ Rᵀ Hᵀ and Δx = R C₀ Rᵀ Hᵀ λ from the C₀ node blocks, against the dense Ã⁻¹: κ(A₀) ε, ε the
    # rest factor's unit round-off (backward-stable solves, Higham ch. 7, 10).
    state = deformed(model, 0.02)
    jacobian = rows_on(model, 8)
    body = Fast(rest_precision=precision).bind()
    step = body.step(model.assemble_step(state, DT, matrix_free=True))
    reference_system = model.assemble_step(state, DT)
    warped = warped_reference(model, state, reference_system)
    h = jacobian[:, reference_system.free_dofs].toarray()
    kappa = np.linalg.cond(reference_system.rest_matrix().toarray())
    epsilon = rest_epsilon(body)
    expected = h @ warped @ h.T
    assert np.abs(step.delassus(jacobian) - expected).max() <= 10 * kappa * epsilon * np.abs(expected).max()
    lam = np.linspace(-1.0, 2.0, jacobian.shape[0])
    correction = reference_system.expand(warped @ (h.T @ lam))
    assert np.abs(step.correction(jacobian, lam) - correction).max() <= (
        10 * kappa * epsilon * np.abs(correction).max()
    )
    # one block per free node the rows touch (the fixed ones do not move)
    touched = np.setdiff1d(jacobian.indices // 3, model.fixed_nodes)
    assert step.report["rest_blocks_solved"] == touched.size


def test_fast_is_exact_under_a_rigid_rotation_and_bounded_when_deformed(model):
    # Rigid rotation R of the whole body: A = R A₀ Rᵀ exactly (see the precomputed test), so W is exact to
    # κ ε and the free motion to the PCG tolerance.
    rotation = rotation_matrix(np.array([[0.3, -0.2, 0.5]]))[0]
    rest = model.rest_positions
    unfixed = TissueModel(
        rest, model.tets, MATERIAL, rayleigh_mass=1.0, rayleigh_stiffness=0.01, fixed_nodes=np.array([0])
    )
    jacobian = rows_on(unfixed)
    state = TissueState(positions=rest @ rotation.T, velocities=np.zeros_like(rest))
    rigid = Fast(against_exact=True).bind()
    step = rigid.step(unfixed.assemble_step(state, DT))
    step.delassus(jacobian)
    kappa = np.linalg.cond(step.system.matrix.toarray())
    assert step.report["compliance_error"] <= 10 * kappa * rest_epsilon(rigid)
    # Deformed: A = Ã + E with Ã = R A₀ Rᵀ; A⁻¹ − Ã⁻¹ = A⁻¹ (Ã − A) Ã⁻¹ exactly, so
    # ‖W − W̃‖₂ ≤ ‖H‖₂² ‖A⁻¹‖₂ ‖Ã⁻¹‖₂ ‖A − Ã‖₂ (all computed densely here).
    state = deformed(model, 0.02)
    jacobian = rows_on(model)
    body = Fast(against_exact=True).bind()
    step = body.step(model.assemble_step(state, DT))
    w = step.delassus(jacobian)
    system, dense, inverse, expected_free = dense_reference(model, state)
    warped = warped_reference(model, state, system)
    h = jacobian[:, system.free_dofs].toarray()
    norm = np.linalg.norm
    bound = norm(h, 2) ** 2 * norm(inverse, 2) * norm(warped, 2) * norm(dense - np.linalg.inv(warped), 2)
    error = norm(w - h @ inverse @ h.T, 2)
    assert 0.0 < error <= bound
    # Free motion: relative residual ≤ tolerance, so the relative error ≤ κ(A) · tolerance.
    assert step.report["pcg_residual"] <= body.strategy.tolerance
    kappa = np.linalg.cond(dense)
    assert norm(step.free_displacement - expected_free) <= (
        kappa * body.strategy.tolerance * norm(expected_free)
    )


def test_fast_node_blocks_are_the_same_whatever_was_asked_before(model):
    # The C₀ blocks are a memo of the model: one (f, 3) solve per node whenever it is first needed, so W for
    # given rows has the same bits after other rows (a restarted run computes only the blocks it needs).
    state = deformed(model, 0.01)
    first, second = rows_on(model, 6, seed=1), rows_on(model, 6, seed=2)
    earlier = Fast().bind()
    earlier.step(model.assemble_step(state, DT, matrix_free=True)).delassus(first)
    later = earlier.step(model.assemble_step(state, DT, matrix_free=True)).delassus(second)
    fresh = Fast().bind().step(model.assemble_step(state, DT, matrix_free=True)).delassus(second)
    np.testing.assert_array_equal(later, fresh)
    # the correction sums the blocks in node order, not in the order they were solved: the same bits too
    lam = np.linspace(-1.0, 2.0, second.shape[0])
    fresh_step = Fast().bind().step(model.assemble_step(state, DT, matrix_free=True))
    later_step = earlier.step(model.assemble_step(state, DT, matrix_free=True))
    np.testing.assert_array_equal(later_step.correction(second, lam), fresh_step.correction(second, lam))


def test_fast_carried_start_is_one_richardson_step_from_the_last_free_motion(model):
    # The free motion's CG starts from x' + R C₀ Rᵀ (b − A' x') (FreeMotionStart: x' the last free
    # displacement, A' x' its image under the last operator). Carried from this very system's answer
    # (A x' = b to LAPACK's round-off), the start is that answer: the CG takes no iteration and its residual
    # is round-off (κ(A) ε, relative), far below the tolerance, whereas R C₀ Rᵀ b alone (a run's first step)
    # leaves the rotated rest compliance's error.
    state = deformed(model, 0.012)
    system, dense, _, expected = dense_reference(model, state)
    free = system.free_dofs
    answer = expected[free].copy()
    image = dense @ answer
    for array in (answer, image):
        array.setflags(write=False)
    kappa = np.linalg.cond(dense)
    carried = Fast().bind()
    carried.resume(FreeMotionStart(answer, image))
    step = carried.step(model.assemble_step(state, DT, matrix_free=True))
    first = Fast().bind().step(model.assemble_step(state, DT, matrix_free=True))
    assert step.report["pcg_carried_start"] and not first.report["pcg_carried_start"]
    assert step.report["pcg_iterations"] == 0
    assert step.report["pcg_start_residual"] <= 10 * kappa * EPS
    assert first.report["pcg_start_residual"] > 1e3 * step.report["pcg_start_residual"]
    # carried from rest (x' = 0, A' x' = 0), the start is R C₀ Rᵀ b: a run's first step, bit for bit
    rest = Fast().bind()
    rest.resume(FreeMotionStart(np.zeros_like(answer), np.zeros_like(image)))
    from_rest = rest.step(model.assemble_step(state, DT, matrix_free=True))
    np.testing.assert_array_equal(from_rest.free_displacement, first.free_displacement)
    # what the step carries on: its free displacement and A x = b − r, r the CG's last residual
    after = carried.carried()
    np.testing.assert_array_equal(after.displacement, step.free_displacement[free])
    relative = np.linalg.norm(after.load - dense @ after.displacement) / np.linalg.norm(after.load)
    assert relative <= 10 * kappa * EPS
    assert not after.displacement.flags.writeable and not after.load.flags.writeable


def test_fast_carried_start_meets_the_tolerance_from_another_state(model):
    # Carried from another state's free motion, the CG still stops at ‖b − A x‖ ≤ tol ‖b‖, so it is within
    # κ(A) tol of the dense answer (relative) like a run's first step, whatever the start; resumed from the
    # same carried start, a fresh body gives the same bits (a restarted run).
    first, second = deformed(model, 0.01), deformed(model, 0.012)
    previous = Fast().bind()
    previous.step(model.assemble_step(first, DT, matrix_free=True))
    start = previous.carried()
    carried = Fast().bind()
    carried.resume(start)
    carried_step = carried.step(model.assemble_step(second, DT, matrix_free=True))
    fresh_step = Fast().bind().step(model.assemble_step(second, DT, matrix_free=True))
    system, dense, _, expected = dense_reference(model, second)
    kappa = np.linalg.cond(dense)
    tolerance = carried.strategy.tolerance
    for step in (carried_step, fresh_step):
        assert step.report["pcg_residual"] <= tolerance
        assert np.linalg.norm(step.free_displacement - expected) <= kappa * tolerance * np.linalg.norm(
            expected
        )
    assert not np.array_equal(carried_step.free_displacement, fresh_step.free_displacement)
    again = Fast().bind()
    again.resume(start)
    repeated = again.step(model.assemble_step(second, DT, matrix_free=True))
    np.testing.assert_array_equal(repeated.free_displacement, carried_step.free_displacement)


def test_fast_is_a_strategy_of_the_scene_key():
    assert "fast" in STRATEGIES
    assert make_strategy("fast") == Fast()
    assert make_strategy("fast", against_exact=True).bind().matrix_free is False
    assert Fast().bind().matrix_free is True
    with pytest.raises(ValueError, match="tolerance"):
        Fast(tolerance=0.0)


def test_a_scene_tolerance_reaches_the_iterating_strategies_and_none_keeps_their_own():
    from refsim.scene import load_scene
    from refsim.simulation import Simulation

    for name in ("refreshed", "precomputed", "fast"):
        assert make_strategy(name, tolerance=3e-3).tolerance == 3e-3
        assert make_strategy(name).tolerance == STRATEGY_CLASSES[name].tolerance
    assert make_strategy("exact", tolerance=3e-3) == Exact()  # solves directly: nothing to stop
    scene = load_scene("cube", ['compliance.strategy="fast"', "compliance.tolerance=3e-3"])
    assert Simulation(scene).tissue_compliance.strategy.tolerance == 3e-3
    for bad in ("0.0", "1.0", "-1e-3"):
        with pytest.raises(ValueError, match="compliance.tolerance"):
            load_scene("cube", [f"compliance.tolerance={bad}"])


def test_the_fast_free_motion_stops_at_its_tolerance_whichever_it_is(model):
    # The relative residual ‖b − A x‖/‖b‖ of the free motion, computed again here from the assembled matrix
    # (the reference), is at most the tolerance (to round-off), and a looser tolerance takes no more work.
    state = deformed(model, 0.01)
    system, dense, _, _ = dense_reference(model, state)
    iterations = {}
    for tolerance in (1e-1, 1e-2, 1e-4, 1e-8):
        step = Fast(tolerance=tolerance).bind().step(model.assemble_step(state, DT, matrix_free=True))
        free = step.free_displacement[system.free_dofs]
        relative = np.linalg.norm(system.rhs - dense @ free) / np.linalg.norm(system.rhs)
        assert relative <= tolerance * (1 + 1e-6)
        iterations[tolerance] = step.report["pcg_iterations"]
    assert iterations[1e-1] <= iterations[1e-2] <= iterations[1e-4] <= iterations[1e-8]
    assert iterations[1e-8] > iterations[1e-1]  # the tolerance decides the work


def test_generic_step_system_serves_a_needle_like_body():
    # A chain with one end prescribed through StepSystem.from_matrices, against a dense solve of the full
    # system with the prescribed value substituted (the reference).
    count = 12
    laplacian = sp.diags([-np.ones(count - 1), 2.0 * np.ones(count), -np.ones(count - 1)], [-1, 0, 1]).tocsr()
    mass, stiffness = sp.identity(count, format="csr") * 0.1, 50.0 * laplacian
    matrix = effective_stiffness(mass, stiffness, DT)
    rng = np.random.default_rng(3)
    forces, velocities = rng.standard_normal(count), rng.standard_normal(count)
    rhs = forces + mass @ velocities / DT
    system = StepSystem.from_matrices(matrix, rhs, [0], np.array([0.01]))
    step = Exact(linear_solver="superlu:COLAMD").bind().step(system)
    dense = matrix.toarray()
    expected = np.zeros(count)
    expected[0] = 0.01
    expected[1:] = np.linalg.solve(dense[1:, 1:], rhs[1:] - dense[1:, 0] * 0.01)
    kappa = np.linalg.cond(dense[1:, 1:])
    assert np.abs(step.free_displacement - expected).max() <= 10 * kappa * EPS * np.abs(expected).max()
    rows = sp.csr_matrix(rng.standard_normal((3, count)))
    inverse = np.zeros((count, count))
    inverse[1:, 1:] = np.linalg.inv(dense[1:, 1:])
    reference = rows @ inverse @ rows.T
    assert np.abs(step.delassus(rows) - reference).max() <= 10 * kappa * EPS * np.abs(reference).max()


def test_pcg_solves_columns_to_their_tolerance():
    rng = np.random.default_rng(4)
    q, _ = np.linalg.qr(rng.standard_normal((30, 30)))
    a = q @ np.diag(np.linspace(1.0, 100.0, 30)) @ q.T
    b = rng.standard_normal((30, 4))
    x, iterations, residual = pcg(
        lambda v: a @ v, lambda r: r / np.diag(a)[:, None], b, tolerance=1e-12, max_iterations=100
    )
    assert residual <= 1e-12 and iterations <= 30 + 5  # CG terminates in ≤ n steps in exact arithmetic
    assert np.linalg.norm(a @ x - b, axis=0).max() <= 1e-12 * np.linalg.norm(b, axis=0).max() * 1.001


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"name": "quick"}, "compliance strategy"),
        ({"name": "refreshed", "refresh_every": 0}, "refresh_every"),
        ({"linear_solver": "umfpack"}, "linear solver"),
        ({"name": "refreshed_fast"}, "refreshed_first_order"),
        ({"name": "refreshed_stale", "w_update": "pcg"}, "W update"),
        ({"name": "refreshed", "w_update": "second_order"}, "compliance_update"),
    ],
)
def test_bad_strategy_values_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_strategy(**kwargs).bind()


def test_every_strategy_variant_is_made_by_the_one_factory():
    from refsim.fem.compliance import STRATEGIES, STRATEGY_VARIANTS, W_UPDATES

    made = {variant: make_strategy(variant) for variant in STRATEGY_VARIANTS}
    assert {strategy.name for strategy in made.values()} == set(STRATEGIES)
    updates = [made[v].compliance_update for v in STRATEGY_VARIANTS if isinstance(made[v], Refreshed)]
    assert sorted(updates) == sorted(W_UPDATES)  # refreshed once with each update
    assert make_strategy("refreshed", w_update="stale") == make_strategy("refreshed_stale")


def test_needle_step_system_matches_a_dense_solve():
    # NeedleModel.assemble_step + Exact (the flexible needle's path, refsim.simulation.needle_body) against a
    # dense solve of A Δx = −f_int + (M/dt) v₀ with the base's six DoFs prescribed.
    from refsim.fem.needle import NeedleModel

    needle = NeedleModel(
        length=0.1, radius=5e-4, element_count=8, youngs_modulus=2e11, poisson_ratio=0.3, density=7850.0
    )
    positions, frames = needle.rest_state()
    rng = np.random.default_rng(5)
    velocities = 1e-3 * rng.standard_normal((needle.node_count, 6))
    increment = np.array([1e-4, 2e-4, 0.0, 0.0, 1e-3, -2e-3])
    mass = needle.mass_matrix()
    system = needle.assemble_step(
        positions, frames, velocities, DT, increment, rayleigh_mass=0.5, rayleigh_stiffness=1e-3, mass=mass
    )
    step = Exact(linear_solver="superlu:COLAMD").bind().step(system)
    matrix = effective_stiffness(
        mass, needle.tangent_stiffness(positions, frames), DT, rayleigh_mass=0.5, rayleigh_stiffness=1e-3
    ).toarray()
    rhs = -needle.internal_forces(positions, frames) + mass @ velocities.ravel() / DT
    base = np.asarray(needle.base_dofs)
    free = np.setdiff1d(np.arange(needle.dof_count), base)
    expected = np.zeros(needle.dof_count)
    expected[base] = increment
    expected[free] = np.linalg.solve(
        matrix[np.ix_(free, free)], rhs[free] - matrix[np.ix_(free, base)] @ increment
    )
    kappa = np.linalg.cond(matrix[np.ix_(free, free)])
    assert np.abs(step.free_displacement - expected).max() <= 10 * kappa * EPS * np.abs(expected).max()
    rows = sp.csr_matrix(rng.standard_normal((4, needle.dof_count)))
    inverse = np.zeros_like(matrix)
    inverse[np.ix_(free, free)] = np.linalg.inv(matrix[np.ix_(free, free)])
    reference = rows @ inverse @ rows.T
    w, responses = step.compliance(rows)
    assert np.abs(w - reference).max() <= 10 * kappa * EPS * np.abs(reference).max()
    np.testing.assert_array_equal(responses[base], 0.0)


def test_scene_keys_choose_the_strategy():
    from refsim.scene import load_scene
    from refsim.scene.loader import SceneError

    scene = load_scene(
        "cube",
        [
            'compliance.strategy="refreshed"',
            "compliance.refresh_every=5",
            'compliance.w_update="stale"',
            'compliance.linear_solver="superlu"',
        ],
    )
    spec = scene.compliance
    strategy = make_strategy(
        spec.strategy,
        refresh_every=spec.refresh_every,
        linear_solver=spec.linear_solver,
        w_update=spec.w_update,
    )
    assert (
        isinstance(strategy, Refreshed)
        and strategy.refresh_every == 5
        and strategy.compliance_update == "stale"
    )
    assert load_scene("cube").compliance.strategy == "exact"
    with pytest.raises(SceneError, match="refresh_every"):
        load_scene("cube", ["compliance.refresh_every=0"])
    with pytest.raises(SceneError, match="strategy"):
        load_scene("cube", ['compliance.strategy="quick"'])


def test_first_order_w_update_is_second_order_in_the_matrix_change(model):
    """A⁻¹ = A₀⁻¹ − A₀⁻¹ΔA A₀⁻¹ + O(‖A₀⁻¹ΔA‖²) (the Neumann series): the stale W errs by O(ΔA), the
    first-order corrected one by O(ΔA²). ΔA is a smooth function of the change of configuration h (the
    rotations move by O(h)), so the errors are power series in h: orders 1 and 2, each next term one power of
    h above (q = 1). Three levels h = 0.4, 0.2, 0.1 (r = 2); the band of the finest observed order is derived
    from them (tests/observed_order.py); the compliance errors are relative errors of order 1e-2 to 1e-4
    computed against exact solves (round-off ρ ≈ 1e-10 of them, negligible: ρ = 0)."""
    base = deformed(model, 0.01)
    direction = deformed(model, 0.01, seed=7).positions - base.positions
    jacobian = rows_on(model)
    sizes = np.array([0.4, 0.2, 0.1])
    errors = {"stale": [], "first_order": []}
    for update in errors:
        for h in sizes:
            body = Refreshed(refresh_every=100, compliance_update=update, against_exact=True).bind()
            body.step(model.assemble_step(base, DT))
            moved = TissueState(positions=base.positions + h * direction, velocities=base.velocities)
            step = body.step(model.assemble_step(moved, DT))
            step.delassus(jacobian)
            errors[update].append(step.report["compliance_error"])
    assert_order(errors["stale"], 2.0, order=1.0, next_exponent=1.0, what="stale W")
    assert_order(errors["first_order"], 2.0, order=2.0, next_exponent=1.0, what="first-order W update")
    assert np.all(np.array(errors["first_order"]) < np.array(errors["stale"]))
    # Its correction is a PCG solve on the current A: exact to the tolerance.
    lam = np.ones(jacobian.shape[0])
    correction = step.correction(jacobian, lam)
    _, dense, inverse, _ = dense_reference(model, moved)
    expected = step.system.expand(inverse @ (jacobian[:, step.system.free_dofs].T @ lam))
    kappa = np.linalg.cond(dense)
    assert np.linalg.norm(correction - expected) <= kappa * 1e-10 * np.linalg.norm(expected)


@pytest.mark.parametrize(
    "strategy", [Exact(), Refreshed(refresh_every=2), Precomputed(), Fast()], ids=lambda s: s.name
)
def test_every_strategy_moves_prescribed_nodes_exactly(model, strategy):
    body = strategy.bind()
    state = deformed(model, 0.003)
    drive = np.tile([0.0, 5e-4, -2e-4], (model.fixed_nodes.size, 1))
    for _ in range(3):
        positions, _, step = model.free_motion(state, DT, fixed_displacements=drive, compliance=body)
        np.testing.assert_array_equal(
            positions[model.fixed_nodes], state.positions[model.fixed_nodes] + drive
        )
        _, dense, _, reference = dense_reference(model, state, drive)
        kappa = np.linalg.cond(dense)
        # Direct solve: κ ε; PCG: κ times the relative residual reached (1e-10 or the fast strategy's 1e-6).
        tau = max(step.report.get("pcg_residual", 0.0), 10 * EPS)
        assert np.linalg.norm(step.free_displacement - reference) <= kappa * tau * np.linalg.norm(reference)
        state = TissueState(positions=positions, velocities=(positions - state.positions) / DT)


def _dense_columns_numpy(matrix, columns):
    # the NumPy form of the compiled copy (scatter_columns) for a canonical CSR
    where = np.full(matrix.shape[1], -1, dtype=np.int64)
    where[columns] = np.arange(columns.size)
    out = np.zeros((matrix.shape[0], columns.size))
    column = where[matrix.indices]
    keep = column >= 0
    rows = np.repeat(np.arange(matrix.shape[0]), np.diff(matrix.indptr))
    out[rows[keep], column[keep]] = matrix.data[keep] + 0.0
    return out


def test_rows_restricted_to_their_dofs_are_scipys_numbers():
    # W and the correction read H on the DoFs it touches as a dense block: the entries copied into place for
    # a canonical CSR (one compiled pass), SciPy's column slicing otherwise (duplicates summed); both the bits
    # of H[:, used].toarray() and of the NumPy form, the sign of explicit zeros included (toarray sums into
    # zeros).
    from refsim.fem.compliance.system import _dense_columns

    rng = np.random.default_rng(3)
    for _ in range(20):
        matrix = sp.random(12, 40, density=0.25, format="csr", random_state=rng)
        matrix.data[::5] = -0.0
        columns = np.sort(rng.choice(40, 15, replace=False))
        expected = matrix[:, columns].toarray()
        got = _dense_columns(matrix, columns)
        np.testing.assert_array_equal(got, expected)
        np.testing.assert_array_equal(np.signbit(got), np.signbit(expected))
        np.testing.assert_array_equal(np.signbit(got), np.signbit(_dense_columns_numpy(matrix, columns)))
        np.testing.assert_array_equal(got, _dense_columns_numpy(matrix, columns))
        duplicated = sp.csr_matrix(
            (
                np.r_[matrix.data, 0.5],
                np.r_[matrix.indices, columns[0]],
                np.r_[matrix.indptr[:-1], matrix.nnz + 1],
            ),
            shape=matrix.shape,
        )
        assert not duplicated.has_canonical_format
        np.testing.assert_array_equal(_dense_columns(duplicated, columns), duplicated[:, columns].toarray())
