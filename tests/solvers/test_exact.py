"""The exact solver: round-off residuals on planted and closed-form problems, honest failures."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from refsim.solvers import (
    ConstraintProblem,
    available_backends,
    natural_residual,
    solve_exact,
    solve_gauss_seidel,
)

FRICTIONLESS = [dict(bilateral=6), dict(unilateral=8), dict(box=6), dict(bilateral=3, unilateral=4, box=3)]
FRICTION = [dict(contacts=4), dict(shafts=3), dict(bilateral=2, unilateral=3, contacts=3, shafts=3, box=3)]


@pytest.mark.parametrize("backend", ["clarabel", "osqp"])
@pytest.mark.parametrize("rank", [None, "half"])
@pytest.mark.parametrize("kinds", FRICTIONLESS)
def test_frictionless_planted_to_round_off(planted, rng, kinds, rank, backend):
    # Target of issue 3: natural residual ≤ 1e-9 on every frictionless symmetric PSD problem, singular or not
    size = sum(kinds.values())
    problem, _, gap = planted(rng, rank=None if rank is None else size // 2, **kinds)
    for method in ("auto", "cone"):  # the Newton path first, and the cone route (the default)
        multipliers, report = solve_exact(problem, backend=backend, method=method)
        assert report.converged, report.message
        assert report.residual <= 1e-9
        assert report.residual == natural_residual(problem, multipliers)
        assert report.solver == ("exact/newton" if method == "auto" else f"exact/{backend}")
    # δ is unique at a solution of a convex QP even when λ is not (W singular): compare by δ
    assert np.linalg.norm(problem.gap(multipliers) - gap) <= 1e-7 * max(1.0, np.linalg.norm(gap))


@pytest.mark.parametrize("rank", [None, "half"])
@pytest.mark.parametrize("kinds", FRICTION)
def test_friction_planted(planted, rng, kinds, rank):
    size = (
        3 * kinds.get("contacts", 0)
        + 3 * kinds.get("shafts", 0)
        + sum(v for k, v in kinds.items() if k not in ("contacts", "shafts"))
    )
    problem, _, _ = planted(rng, rank=None if rank is None else size // 2, **kinds)
    multipliers, report = solve_exact(problem)
    assert report.converged, report.message
    assert report.residual <= 1e-9


@pytest.mark.parametrize("ratio", [0.5, 0.999, 1.001, 3.0])
def test_block_on_plane_stick_and_slip(ratio):
    # Reference: λ_n = g / w_n; stick λ_t = −p / w_t when |p| / w_t ≤ μ λ_n, else λ_t = −μ λ_n sign(p)
    w_n, w_t, gap_n, mu = 0.5, 2.0, 0.1, 0.4
    normal_force = gap_n / w_n
    push = ratio * mu * normal_force * w_t
    problem = ConstraintProblem(
        compliance=np.diag([w_n, w_t, w_t]),
        free_gap=[-gap_n, 0.0, push],
        contacts=[[0, 1, 2]],
        contact_friction=[mu],
    )
    multipliers, report = solve_exact(problem)
    assert report.converged, report.message
    tangent = -push / w_t if ratio <= 1 else -mu * normal_force
    np.testing.assert_allclose(multipliers, [normal_force, 0.0, tangent], atol=1e-10)


@pytest.mark.parametrize("ratio", [0.5, 2.0, -2.0])
def test_shaft_pair_stick_and_slip(ratio):
    # Reference: λ_b = a / w; λ_s = −p / ws inside μ ‖λ_b‖, else −μ ‖λ_b‖ sign(p)
    w = np.array([0.5, 0.25, 2.0])
    pair_gap = np.array([-0.3, 0.4])
    bound = 0.2 * np.linalg.norm(pair_gap / w[:2])
    push = ratio * bound * w[2]
    problem = ConstraintProblem(
        compliance=np.diag(w),
        free_gap=[*pair_gap, push],
        bilateral=[0, 1],
        shaft_friction=[2],
        shaft_pairs=[[0, 1]],
        shaft_friction_coefficient=[0.2],
    )
    multipliers, report = solve_exact(problem)
    assert report.converged, report.message
    expected = -push / w[2] if abs(ratio) <= 1 else -bound * np.sign(push)
    np.testing.assert_allclose(multipliers, [*(-pair_gap / w[:2]), expected], atol=1e-10)


def test_agrees_with_gauss_seidel_by_gap_on_singular_problem(planted, rng):
    # redundant rows (rank 4 of 8): λ differs between solvers, δ must not
    problem, _, _ = planted(rng, unilateral=8, rank=4)
    exact, report = solve_exact(problem)
    iterative, gs_report = solve_gauss_seidel(problem, tolerance=1e-10, max_iterations=100000)
    assert report.converged and gs_report.converged
    gap = problem.gap(exact)
    assert np.linalg.norm(problem.gap(iterative) - gap) <= 1e-7 * max(1.0, np.linalg.norm(gap))


def test_backends_agree(planted, rng):
    problem, _, _ = planted(rng, bilateral=2, unilateral=6, box=4, rank=7)
    gaps = [
        problem.gap(solve_exact(problem, backend=name, method="cone")[0]) for name in ("clarabel", "osqp")
    ]
    np.testing.assert_allclose(gaps[0], gaps[1], atol=1e-8)


def test_non_symmetric_compliance_is_solved_as_given():
    # Reference: W = [[1, 0.5], [0, 1]], δ_free = (−1, −1), both unilateral: both active gives
    # λ = W⁻¹ (1, 1) = (0.5, 1) ≥ 0, δ = 0, the (unique, W is a P-matrix) solution.
    problem = ConstraintProblem(
        compliance=[[1.0, 0.5], [0.0, 1.0]], free_gap=[-1, -1], unilateral=[0, 1], name="skew"
    )
    # "auto" takes Lemke's pivoting first on a non-symmetric LCP, "newton" the semismooth Newton: both as
    # given
    for method, path in (("auto", "lemke"), ("newton", "newton")):
        multipliers, report = solve_exact(problem, method=method)
        assert report.converged and report.path == path
        assert report.asymmetry == pytest.approx(problem.asymmetry()) and "non-symmetric" in report.message
        np.testing.assert_allclose(multipliers, [0.5, 1.0], atol=1e-12)
    # within round-off it is accepted and the residual is measured on W as given
    nearly = ConstraintProblem(
        compliance=[[1.0, 0.5 + 1e-12], [0.5, 1.0]], free_gap=[-1, -1], unilateral=[0, 1]
    )
    assert solve_exact(nearly)[1].converged


def test_bad_arguments():
    problem = ConstraintProblem(compliance=np.eye(2), free_gap=[-1, -1], unilateral=[0, 1])
    with pytest.raises(ValueError, match="not installed; available"):
        solve_exact(problem, backend="no-such-solver")
    with pytest.raises(ValueError, match="tolerance"):
        solve_exact(problem, tolerance=0.0)
    assert "clarabel" in available_backends() and "osqp" in available_backends()


def test_non_convergence_is_reported_with_best_answer(planted, rng):
    # one outer iteration cannot settle the friction bounds and no polish is allowed: not converged, but the
    # best multipliers are returned and the message says why
    problem, _, _ = planted(rng, contacts=4, friction=0.8)
    multipliers, report = solve_exact(problem, max_iterations=1, polish=False, method="cone")
    assert not report.converged
    assert "not converged" in report.message and "not settled" in report.message
    assert report.residual == natural_residual(problem, multipliers)


def test_infeasible_problem_reports_failure():
    # bilateral rows with a singular W and an inconsistent free gap: δ = W λ + δ_free = 0 has no solution
    problem = ConstraintProblem(compliance=np.ones((2, 2)), free_gap=[1.0, -1.0], bilateral=[0, 1])
    multipliers, report = solve_exact(problem)
    assert not report.converged and "not converged" in report.message
    assert np.all(np.isfinite(multipliers))


def test_empty_problem():
    multipliers, report = solve_exact(ConstraintProblem(compliance=np.zeros((0, 0)), free_gap=np.zeros(0)))
    assert multipliers.shape == (0,) and report.converged


@settings(
    max_examples=10, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(seed=st.integers(0, 10**6), rank_fraction=st.floats(0.3, 1.0), scale=st.sampled_from([1e-4, 1.0, 1e4]))
def test_property_exact_frictionless_round_off(planted, seed, rank_fraction, scale):
    rng = np.random.default_rng(seed)
    problem, _, _ = planted(
        rng, bilateral=2, unilateral=5, box=3, rank=max(1, int(10 * rank_fraction)), scale=scale
    )
    _, report = solve_exact(problem)
    assert report.residual <= 1e-9, report.message
