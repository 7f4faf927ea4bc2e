"""Modified Gauss–Seidel: planted problems, closed-form stick and slip, honest non-convergence."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from refsim.solvers import ConstraintProblem, natural_residual, solve_gauss_seidel

KINDS = [
    dict(bilateral=6),
    dict(unilateral=6),
    dict(contacts=4),
    dict(shafts=3),
    dict(box=6),
    dict(bilateral=2, unilateral=3, contacts=3, shafts=3, box=3),
]


@pytest.mark.parametrize("kinds", KINDS)
def test_planted_non_singular(planted, rng, kinds):
    problem, _, gap = planted(rng, friction=0.3, **kinds)
    multipliers, report = solve_gauss_seidel(problem, tolerance=1e-8, max_iterations=5000)
    assert report.converged, report.message
    assert report.residual <= 1e-8
    assert report.residual == pytest.approx(natural_residual(problem, multipliers))
    # the gap is unique at a solution (W positive definite here): δ within the residual's order
    assert np.linalg.norm(problem.gap(multipliers) - gap) <= 1e-5 * max(1.0, np.linalg.norm(gap))
    assert report.history.size == report.iterations
    assert report.history[-1] == pytest.approx(report.residual, rel=1e-6, abs=1e-14)


def block_on_plane(push, *, mass_compliance=2.0, normal_compliance=0.5, penetration=0.1, friction=0.4):
    """A point on a plane: W = diag(w_n, w_t, w_t), pressed by δ_free,n = −g and pushed by δ_free,t1 = p."""
    return ConstraintProblem(
        compliance=np.diag([normal_compliance, mass_compliance, mass_compliance]),
        free_gap=[-penetration, push, 0.0],
        contacts=[[0, 1, 2]],
        contact_friction=[friction],
    )


@pytest.mark.parametrize("ratio", [0.5, 0.99, 1.01, 3.0])
def test_block_on_plane_stick_and_slip(ratio):
    # Reference: λ_n = g / w_n; sticking needs |λ_t| = |p| / w_t ≤ μ λ_n, otherwise λ_t = −μ λ_n sign(p) and
    # the block slides by δ_t = p − w_t μ λ_n. ``ratio`` = required friction force / μ N.
    normal_force = 0.1 / 0.5
    push = ratio * 0.4 * normal_force * 2.0
    problem = block_on_plane(push)
    multipliers, report = solve_gauss_seidel(problem, tolerance=1e-12, max_iterations=100)
    assert report.converged, report.message
    expected_tangent = -push / 2.0 if ratio <= 1 else -0.4 * normal_force
    np.testing.assert_allclose(multipliers, [normal_force, expected_tangent, 0.0], atol=1e-12)
    slip = problem.gap(multipliers)[1]
    assert slip == pytest.approx(0.0 if ratio <= 1 else push - 2.0 * 0.4 * normal_force, abs=1e-12)


@pytest.mark.parametrize("ratio", [0.5, 2.0, -2.0])
def test_shaft_pair_stick_and_slip(ratio):
    # Reference: pair rows bilateral with W = diag(w1, w2, ws): λ_b = a / w, bound = μ ‖λ_b‖; the shaft row
    # sticks with λ_s = −p / ws when |p| / ws ≤ bound, else slips with λ_s = −bound sign(p).
    w = np.array([0.5, 0.25, 2.0])
    pair_gap = np.array([-0.3, 0.4])
    bound = 0.2 * np.linalg.norm(-pair_gap / w[:2])
    push = ratio * bound * w[2]
    problem = ConstraintProblem(
        compliance=np.diag(w),
        free_gap=[*pair_gap, push],
        bilateral=[0, 1],
        shaft_friction=[2],
        shaft_pairs=[[0, 1]],
        shaft_friction_coefficient=[0.2],
    )
    multipliers, report = solve_gauss_seidel(problem, tolerance=1e-13)
    assert report.converged
    expected = -push / w[2] if abs(ratio) <= 1 else -bound * np.sign(push)
    np.testing.assert_allclose(multipliers, [*(-pair_gap / w[:2]), expected], atol=1e-12)


def test_warm_start_at_solution_stops_after_one_sweep(planted, rng):
    problem, force, _ = planted(rng, unilateral=4, contacts=2)
    _, report = solve_gauss_seidel(problem, tolerance=1e-10, warm_start=force)
    assert report.converged and report.iterations == 1


def test_non_convergence_is_reported():
    # a 2-row bilateral problem with strong coupling converges slowly: 3 sweeps are not enough
    problem = ConstraintProblem(
        compliance=[[1.0, 0.999], [0.999, 1.0]], free_gap=[1.0, -1.0], bilateral=[0, 1]
    )
    multipliers, report = solve_gauss_seidel(problem, tolerance=1e-10, max_iterations=3)
    assert not report.converged and report.iterations == 3
    assert "not converged" in report.message
    assert report.residual == pytest.approx(natural_residual(problem, multipliers))


def test_zero_diagonal_rows_do_not_crash():
    # row 1 has W_11 = 0 (a row with no compliance): it cannot be solved alone; the solver must not divide
    # by zero, keeps λ_1 at its projection, and the residual says whether the rest was solved.
    problem = ConstraintProblem(
        compliance=np.diag([1.0, 0.0, 2.0]), free_gap=[-1.0, 0.5, -2.0], unilateral=[0, 1, 2]
    )
    multipliers, report = solve_gauss_seidel(problem, tolerance=1e-12)
    assert np.all(np.isfinite(multipliers))
    assert report.converged  # δ_1 = 0.5 ≥ 0 with λ_1 = 0 satisfies Signorini
    np.testing.assert_allclose(multipliers, [1.0, 0.0, 1.0])
    bad = ConstraintProblem(compliance=np.diag([1.0, 0.0]), free_gap=[-1.0, 0.5], bilateral=[0, 1])
    _, report = solve_gauss_seidel(bad, tolerance=1e-12, max_iterations=20)
    assert not report.converged and "zero diagonal" in report.message


def test_rows_of_no_compliance_take_the_bound_their_gap_pushes_them_to():
    # Reference: the law of a row whose W_ii (and so its whole row of W) is zero, λ = Π(λ − δ) with δ fixed:
    # a box row is at its upper bound when δ < 0 and at its lower one when δ > 0, a group friction row at the
    # bound opposing δ (a capped tip contact pressed on held tissue by a rigid needle; a friction row on
    # it). Gauss–Seidel's update λ − δ/W_ii has that limit as W_ii → 0+; the exact solver finds the same.
    from refsim.solvers import solve_exact

    problem = ConstraintProblem(
        compliance=np.diag([1.0, 0.0, 0.0, 0.0]),
        free_gap=[-1.0, -2e-4, 3e-4, 5e-5],
        unilateral=[0],
        box_rows=[1, 2],
        box_lower=[0.0, -0.25],
        box_upper=[0.8, 0.5],
        group_friction=[3],
        group_offsets=[0, 1],
        group_members=[0],
        group_friction_coefficient=[0.3],
        group_preload=[0.0],
    )
    multipliers, report = solve_gauss_seidel(problem, tolerance=1e-12)
    assert report.converged, report.message
    np.testing.assert_allclose(multipliers, [1.0, 0.8, -0.25, -0.3], rtol=0, atol=1e-12)
    exact, exact_report = solve_exact(problem, tolerance=1e-10)
    np.testing.assert_allclose(exact, multipliers, rtol=0, atol=1e-6)


def test_divergence_is_reported():
    # a non-monotone LCP (negative diagonal coupling) on which Gauss–Seidel blows up
    problem = ConstraintProblem(
        compliance=[[0.1, -0.1, -1.0], [-1.505, 0.5, 0.0], [0.0, -1.0, 0.0]],
        free_gap=[0.0, 0.495, 0.0],
        bilateral=[0, 1],
        unilateral=[2],
    )
    multipliers, report = solve_gauss_seidel(problem, max_iterations=2000)
    assert not report.converged
    assert "diverged" in report.message or report.residual > 1e-6


def test_increment_criterion_and_relaxation(planted, rng):
    problem, _, _ = planted(rng, unilateral=5, contacts=3)
    _, report = solve_gauss_seidel(problem, tolerance=1e-9, criterion="increment", max_iterations=5000)
    assert report.converged and report.increment < 1e-9 * (problem.row_count + 1)
    _, relaxed = solve_gauss_seidel(problem, tolerance=1e-8, relaxation=1.3, max_iterations=5000)
    assert relaxed.converged


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        (dict(tolerance=-1.0), "tolerance"),
        (dict(max_iterations=0), "max_iterations"),
        (dict(relaxation=2.0), "relaxation"),
        (dict(criterion="sofa"), "criterion"),
        (dict(warm_start=np.zeros(2)), "multipliers have shape"),
    ],
)
def test_bad_arguments(kwargs, words):
    problem = ConstraintProblem(compliance=np.eye(3), free_gap=np.zeros(3), unilateral=[0, 1, 2])
    with pytest.raises(ValueError, match=words):
        solve_gauss_seidel(problem, **kwargs)


def test_empty_problem():
    multipliers, report = solve_gauss_seidel(
        ConstraintProblem(compliance=np.zeros((0, 0)), free_gap=np.zeros(0))
    )
    assert multipliers.shape == (0,) and report.converged


@settings(
    max_examples=12, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(seed=st.integers(0, 10**6), friction=st.floats(0.0, 1.0))
def test_property_gauss_seidel_solves_positive_definite_problems(planted, seed, friction):
    problem, _, _ = planted(
        np.random.default_rng(seed), unilateral=3, contacts=2, shafts=2, box=2, friction=friction
    )
    _, report = solve_gauss_seidel(problem, tolerance=1e-7, max_iterations=20000)
    assert report.converged, report.message
