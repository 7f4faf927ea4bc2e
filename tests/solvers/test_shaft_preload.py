"""Shaft friction with a normal preload: the bound of shaft row j is μ_j (‖(λ_b1, λ_b2)‖ + p_j).

References: the Coulomb law of a one-dimensional friction row with a given bound b (stick |λ| < b with δ = 0,
slip λ = −b sign(δ)); here b = μ (‖λ_pair‖ + p). Tolerances of the agreement tests are derived from the
solvers' tolerances and the conditioning of W (see :func:`_gap_agreement_bound`).
"""

import numpy as np
import pytest

from refsim.solvers import (
    ConstraintProblem,
    natural_map_error,
    natural_residual,
    natural_residual_by_kind,
    solve_exact,
    solve_gauss_seidel,
)

MU = 0.3


def _shaft_problem(**overrides):
    fields = dict(
        compliance=np.eye(3),
        free_gap=np.zeros(3),
        bilateral=[0, 1],
        shaft_friction=[2],
        shaft_pairs=[[0, 1]],
        shaft_friction_coefficient=[MU],
    )
    fields.update(overrides)
    return ConstraintProblem(**fields)


# ---------------------------------------------------------------------------------------------- validation
def test_preload_defaults_to_zeros_and_is_read_only():
    problem = _shaft_problem()
    np.testing.assert_array_equal(problem.shaft_normal_preload, [0.0])
    preloaded = _shaft_problem(shaft_normal_preload=[2.0])
    assert preloaded.shaft_normal_preload.dtype == np.float64
    with pytest.raises(ValueError):
        preloaded.shaft_normal_preload[0] = 1.0
    assert ConstraintProblem(
        compliance=np.eye(1), free_gap=[0.0], bilateral=[0]
    ).shaft_normal_preload.shape == (0,)


@pytest.mark.parametrize(
    "preload, words",
    [
        ([-1.0], "negative value"),
        ([np.nan], "non-finite"),
        ([np.inf], "non-finite"),
        ([1.0, 2.0], "expected (1,)"),
        ([[1.0]], "dimension"),
        (["a"], "numeric"),
    ],
)
def test_bad_preload_names_the_field(preload, words):
    with pytest.raises(ValueError) as error:
        _shaft_problem(shaft_normal_preload=preload)
    assert "shaft_normal_preload" in str(error.value) and words in str(error.value)


def test_shaft_bounds_helper():
    problem = _shaft_problem(shaft_normal_preload=[2.0])
    # μ (‖(3, 4)‖ + 2) = 0.3 × 7
    np.testing.assert_allclose(problem.shaft_bounds(np.array([3.0, 4.0, 0.0])), [MU * 7.0])


# ---------------------------------------------------------------------------------------------- residual
def test_residual_sees_the_preload(planted, rng):
    problem, force, _ = planted(rng, shafts=6, shaft_preload=2.0, friction=MU)
    assert natural_residual(problem, force) <= 1e-14
    # The same forces without the preload violate the law on every slipping row (they exceed μ ‖λ_pair‖).
    bare = ConstraintProblem(**{**_fields(problem), "shaft_normal_preload": np.zeros(6)})
    parts = natural_residual_by_kind(bare, force)
    assert parts["group_friction"] > 1e-3
    error, _ = natural_map_error(bare, force)
    slipping = np.abs(force[problem.shaft_friction]) >= problem.shaft_bounds(force) * (1 - 1e-12)
    assert slipping.sum() == 4  # rows 1, 2 of every 3 slip (planted_problem's pattern)
    assert np.all(np.abs(error[problem.shaft_friction[slipping]]) > 0.0)


def _fields(problem):
    names = (
        "compliance",
        "free_gap",
        "bilateral",
        "unilateral",
        "contacts",
        "contact_friction",
        "shaft_friction",
        "shaft_pairs",
        "shaft_friction_coefficient",
        "shaft_normal_preload",
        "box_rows",
        "box_lower",
        "box_upper",
        "name",
    )
    return {name: getattr(problem, name) for name in names}


# ---------------------------------------------------------------------------------------------- solvers
def _gap_agreement_bound(problem, first, second):
    """Bound on ‖δ₁ − δ₂‖ for two approximate solutions of a problem with W ≥ α I.

    For a strongly monotone problem the distance to the solution is bounded by the natural-map error:
    ‖λ − λ*‖ ≤ (1 + ‖W‖) / α ‖e(λ)‖ (Facchinei and Pang 2003, prop. 1.5.8; our shaft bounds depend on λ, so
    this holds only approximately, which the factor 10 covers), hence ‖δ − δ*‖ ≤ ‖W‖ ‖λ − λ*‖.
    """
    symmetric = 0.5 * (problem.compliance + problem.compliance.T)
    alpha = float(np.linalg.eigvalsh(symmetric)[0])
    norm = float(np.linalg.norm(problem.compliance, 2))
    errors = sum(float(np.linalg.norm(natural_map_error(problem, x)[0])) for x in (first, second))
    return 10.0 * norm * (1.0 + norm) / alpha * errors


@pytest.mark.parametrize(
    "kinds", [dict(shafts=6), dict(bilateral=2, unilateral=3, contacts=2, shafts=6, box=2)]
)
@pytest.mark.parametrize("preload", [0.5, 5.0])
def test_planted_with_preload_both_solvers(planted, rng, kinds, preload):
    # Planted: stick rows inside μ (‖λ_b‖ + p), slip rows at it opposing δ_s (tests/solvers/conftest.py).
    problem, force, gap = planted(rng, friction=MU, shaft_preload=preload, **kinds)
    assert natural_residual(problem, force) <= 1e-14
    exact, report = solve_exact(problem)
    assert report.converged and report.residual <= 1e-9, report.message
    iterative, gs_report = solve_gauss_seidel(problem, tolerance=1e-10, max_iterations=20000)
    assert gs_report.converged, gs_report.message
    bound = _gap_agreement_bound(problem, exact, iterative)
    assert np.linalg.norm(problem.gap(exact) - problem.gap(iterative)) <= bound
    assert np.linalg.norm(problem.gap(exact) - gap) <= _gap_agreement_bound(problem, exact, force)
    # The slip states are those planted: |λ_s| at the bound exactly where the planted row slips.
    rows = problem.shaft_friction
    planted_slip = np.abs(force[rows]) >= problem.shaft_bounds(force) * (1 - 1e-12)
    for solution in (exact, iterative):
        at_bound = np.abs(solution[rows]) >= problem.shaft_bounds(solution) - 1e-6
        np.testing.assert_array_equal(at_bound, planted_slip)


@pytest.mark.parametrize("solver", ["gauss_seidel", "exact"])
@pytest.mark.parametrize("ratio", [0.5, 0.999, 1.001, 3.0, -3.0])
def test_zero_lateral_force_slips_at_mu_times_preload(solver, ratio):
    # Reference (closed form): W = diag(w_b1, w_b2, w_s), δ_free of the pair = 0 so λ_b = 0 and the bound is
    # b = μ p. A push a on the shaft row sticks with λ_s = −a / w_s when |a| / w_s ≤ μ p (δ_s = 0), else slips
    # with λ_s = −μ p sign(a) and δ_s = a − μ p w_s sign(a).
    w = np.array([0.5, 0.25, 2.0])
    preload = 1.5
    push = ratio * MU * preload * w[2]
    problem = ConstraintProblem(
        compliance=np.diag(w),
        free_gap=[0.0, 0.0, push],
        bilateral=[0, 1],
        shaft_friction=[2],
        shaft_pairs=[[0, 1]],
        shaft_friction_coefficient=[MU],
        shaft_normal_preload=[preload],
    )
    multipliers, report = _solve(solver, problem)
    assert report.converged, report.message
    sticks = abs(ratio) <= 1.0
    expected = -push / w[2] if sticks else -MU * preload * np.sign(push)
    np.testing.assert_allclose(multipliers, [0.0, 0.0, expected], atol=1e-10)
    slip = problem.gap(multipliers)[2]
    assert slip == pytest.approx(0.0 if sticks else push - MU * preload * w[2] * np.sign(push), abs=1e-10)
    # Without the preload (the paper's model) the same push slips freely: no force at all.
    bare = ConstraintProblem(**{**_fields(problem), "shaft_normal_preload": [0.0]})
    np.testing.assert_allclose(_solve(solver, bare)[0], 0.0, atol=1e-10)


@pytest.mark.parametrize("solver", ["gauss_seidel", "exact"])
def test_coupled_shaft_rows_all_slip_at_their_preload(solver, rng):
    # Reference (closed form): m shaft rows coupled through an SPD block W_ss, pair rows uncoupled with zero
    # free gap (λ_b = 0). A push a_j = c with c ≥ 2 ‖W_ss‖ μ max p makes every row slip: λ_s = −μ p (all at
    # the bound), δ_s = a − μ W_ss p > 0. A push with a smaller c of the opposite sign slips the other way.
    m = 5
    factor = rng.standard_normal((m, m))
    shaft_block = factor @ factor.T / m + 0.1 * np.eye(m)
    preload = rng.uniform(0.5, 2.0, m)
    compliance = np.zeros((3 * m, 3 * m))
    compliance[: 2 * m, : 2 * m] = np.diag(rng.uniform(0.5, 1.5, 2 * m))
    compliance[2 * m :, 2 * m :] = shaft_block
    push = 2.0 * np.linalg.norm(shaft_block, 2) * MU * preload.max()
    for sign in (1.0, -1.0):
        problem = ConstraintProblem(
            compliance=compliance,
            free_gap=np.concatenate([np.zeros(2 * m), np.full(m, sign * push)]),
            bilateral=np.arange(2 * m),
            shaft_friction=np.arange(2 * m, 3 * m),
            shaft_pairs=np.arange(2 * m).reshape(m, 2),
            shaft_friction_coefficient=np.full(m, MU),
            shaft_normal_preload=preload,
        )
        multipliers, report = _solve(solver, problem)
        assert report.converged, report.message
        np.testing.assert_allclose(multipliers[2 * m :], -sign * MU * preload, atol=1e-9)
        np.testing.assert_allclose(multipliers[: 2 * m], 0.0, atol=1e-9)
        # total axial force = μ Σ p: the straight-insertion picture of the needle
        assert -sign * multipliers[2 * m :].sum() == pytest.approx(MU * preload.sum(), rel=1e-9)


def _solve(solver, problem):
    if solver == "exact":
        return solve_exact(problem, tolerance=1e-12)
    return solve_gauss_seidel(problem, tolerance=1e-12, max_iterations=10000)
