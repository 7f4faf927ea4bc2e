"""The natural-map residual: zero exactly at solutions, positive away from them, and the cone projection."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from refsim.solvers import (
    ConstraintProblem,
    natural_map_error,
    natural_residual,
    natural_residual_by_kind,
    project_friction_cone,
)

KINDS = [
    dict(bilateral=5),
    dict(unilateral=6),
    dict(contacts=3),
    dict(shafts=3),
    dict(box=6),
    dict(bilateral=2, unilateral=3, contacts=3, shafts=3, box=3),
]


@pytest.mark.parametrize("kinds", KINDS)
def test_residual_vanishes_at_planted_solution(planted, rng, kinds):
    problem, force, gap = planted(rng, rank=None, **kinds)
    np.testing.assert_allclose(problem.gap(force), gap, atol=1e-12)
    # δ_free = δ* − W λ* is exact to round-off, so e is of order eps · ‖W‖ ‖λ‖
    assert natural_residual(problem, force) < 1e-14


@pytest.mark.parametrize("kinds", KINDS)
def test_residual_detects_a_perturbation(planted, rng, kinds):
    problem, force, _ = planted(rng, **kinds)
    perturbed = force + 1e-3 * rng.standard_normal(force.size)
    assert natural_residual(problem, perturbed) > 1e-6


def test_by_kind_squares_sum_to_total(planted, rng):
    problem, force, _ = planted(rng, bilateral=2, unilateral=3, contacts=3, shafts=3, box=3)
    perturbed = force + 1e-2 * rng.standard_normal(force.size)
    parts = natural_residual_by_kind(problem, perturbed)
    assert set(parts) == {"bilateral", "unilateral", "contact", "group_friction", "box"}
    assert np.sqrt(sum(v * v for v in parts.values())) == pytest.approx(natural_residual(problem, perturbed))
    assert all(v > 0 for v in parts.values())


def test_hand_computed_values():
    # one unilateral row: W = 2, δ_free = −1; λ = 0 gives δ = −1, e = 0 − max(0, 0 + 1) = −1,
    # normalised by max(‖δ_free‖=1, ‖λ‖=0, ‖δ‖=1) = 1
    problem = ConstraintProblem(compliance=[[2.0]], free_gap=[-1.0], unilateral=[0])
    assert natural_residual(problem, [0.0]) == pytest.approx(1.0)
    assert natural_residual(problem, [0.5]) == 0.0
    # a contact sliding: W = I, δ_free = (−1, 2, 0), μ = 0.5: λ = (1, −0.5, 0) gives δ = (0, 1.5, 0)
    problem = ConstraintProblem(
        compliance=np.eye(3), free_gap=[-1.0, 2.0, 0.0], contacts=[[0, 1, 2]], contact_friction=[0.5]
    )
    assert natural_residual(problem, [1.0, -0.5, 0.0]) < 1e-16
    error, gap = natural_map_error(problem, [1.0, -0.5, 0.0])
    np.testing.assert_allclose(gap, [0.0, 1.5, 0.0])


def test_overflowing_multipliers_are_not_a_solution():
    problem = ConstraintProblem(compliance=[[1.0, 0.0], [0.0, 1.0]], free_gap=[1.0, 1.0], unilateral=[0, 1])
    assert natural_residual(problem, [1e154, 1e154]) > 0.5


@settings(max_examples=40, deadline=None, database=None)
@given(st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3), st.floats(0.0, 2.0))
def test_cone_projection_properties(point, mu):
    z = np.array(point)[None]
    p = project_friction_cone(z, [mu])[0]
    tol = 1e-9 * max(1.0, np.abs(z).max())
    # in the cone; idempotent; z − P(z) orthogonal to P(z) and in the polar cone (Moreau decomposition)
    assert np.linalg.norm(p[1:]) <= mu * p[0] + tol
    np.testing.assert_allclose(project_friction_cone(p[None], [mu])[0], p, atol=tol)
    r = z[0] - p
    assert abs(r @ p) <= tol * max(1.0, np.abs(z).max())
    assert mu * np.linalg.norm(r[1:]) <= -r[0] + tol


@settings(
    max_examples=15, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(seed=st.integers(0, 10**6), factor=st.floats(1e-4, 1e4))
def test_residual_invariant_to_problem_scale(planted, seed, factor):
    # λ ↦ c λ, δ_free ↦ c δ_free leaves the normalised residual unchanged (every law is 1-homogeneous)
    rng = np.random.default_rng(seed)
    problem, force, _ = planted(rng, unilateral=2, contacts=2, shafts=2, box=2)
    trial = force + 0.1 * rng.standard_normal(force.size)
    scaled = ConstraintProblem(
        compliance=problem.compliance,
        free_gap=factor * problem.free_gap,
        unilateral=problem.unilateral,
        contacts=problem.contacts,
        contact_friction=problem.contact_friction,
        bilateral=problem.bilateral,
        shaft_friction=problem.shaft_friction,
        shaft_pairs=problem.shaft_pairs,
        shaft_friction_coefficient=problem.shaft_friction_coefficient,
        box_rows=problem.box_rows,
        box_lower=factor * problem.box_lower,
        box_upper=factor * problem.box_upper,
    )
    assert natural_residual(scaled, factor * trial) == pytest.approx(
        natural_residual(problem, trial), rel=1e-9
    )
