"""The exact solver's Gauss–Seidel pre-sweeps (``method="auto"``,
:func:`refsim.solvers.newton_kernel._presweep`) and the compiled set-up
(:func:`refsim.solvers.laws.block_arrays`, :func:`refsim.solvers.residual.data_scales`).

The pre-sweeps must not change what the exact solver guarantees: every answer meets both residuals on the
problem as given, the report's residuals are those of the answer, and where the solution is unique the answer
is the one Newton alone gives (within the error bound of each answer). They must stop as soon as their rate
cannot reach the tolerance within their budget, so that they cost little where Gauss–Seidel is slow.
"""

import numpy as np
import pytest

from refsim.solvers import ConstraintProblem, data_residual, natural_map_error, natural_residual, solve_exact
from refsim.solvers.exact import _presweep_budget
from refsim.solvers.laws import BOX, CONTACT, GROUP_FRICTION, block_arrays, friction_groups
from refsim.solvers.newton import solve_newton
from refsim.solvers.residual import data_scales

from .conftest import planted_problem

LAWS = {
    "frictionless": dict(bilateral=3, unilateral=4, box=3),
    "contacts": dict(contacts=5),
    "group friction": dict(shafts=3, unilateral=2),
    "all": dict(bilateral=2, unilateral=3, contacts=3, shafts=2, box=3),
}


@pytest.mark.parametrize("laws", list(LAWS))
@pytest.mark.parametrize("rank", [None, 6])
@pytest.mark.parametrize("scale", [1e-4, 1.0])
@pytest.mark.parametrize("start", ["cold", "perturbed"])
def test_auto_answers_meet_the_tolerance_with_honest_reports(laws, rank, scale, start):
    # Matrix: every law, full rank and singular W (rank 6: non-unique λ, degenerate bounds), two force scales,
    # cold and warm starts. Reference: the residual definitions themselves (natural and data residual ≤ tol).
    rng = np.random.default_rng(21)
    problem, force, _ = planted_problem(rng, rank=rank, scale=scale, **LAWS[laws])
    warm = None if start == "cold" else force * (1.0 + 1e-2 * rng.standard_normal(problem.row_count))
    multipliers, report = solve_exact(problem, tolerance=1e-10, method="auto", warm_start=warm)
    assert report.converged, report.message
    assert report.path in ("gauss_seidel", "gauss_seidel+newton", "newton", "newton+gauss_seidel"), (
        report.path
    )
    assert report.residual == natural_residual(problem, multipliers) <= 1e-10
    assert report.data_residual == data_residual(problem, multipliers) <= 1e-10
    if report.path.startswith("gauss_seidel"):
        assert "Gauss-Seidel pre-sweep" in report.message


FRICTIONLESS = {
    "mixed": dict(bilateral=3, unilateral=4, box=3),
    "unilateral": dict(unilateral=10),
    "box": dict(box=8),
    "bilateral and box": dict(bilateral=4, box=4),
}


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("scale", [1e-4, 1.0, 1e3])
@pytest.mark.parametrize("laws", list(FRICTIONLESS))
def test_auto_and_newton_alone_give_the_same_unique_solution(seed, scale, laws):
    # Full-rank symmetric W without friction: λ* unique and ‖λ − λ*‖ ≤ (1 + ‖W‖₂) / σ_min(W) ‖e(λ)‖ (Mathias
    # and Pang 1990, strongly monotone; as in test_newton.py), so the two answers agree within the sum of the
    # bounds.
    rng = np.random.default_rng(100 + seed)
    problem, force, _ = planted_problem(rng, scale=scale, **FRICTIONLESS[laws])
    eigenvalues = np.linalg.eigvalsh(problem.compliance)
    bound = (1.0 + eigenvalues[-1]) / eigenvalues[0]
    auto, auto_report = solve_exact(problem, tolerance=1e-11, method="auto")
    alone, alone_report = solve_exact(problem, tolerance=1e-11, method="newton")
    assert auto_report.converged and alone_report.converged
    errors = [np.linalg.norm(natural_map_error(problem, answer)[0]) for answer in (auto, alone)]
    assert np.linalg.norm(auto - alone) <= bound * sum(errors) * (1 + 1e-6) + 1e-13 * np.linalg.norm(force)


def test_presweeps_stop_when_their_rate_cannot_reach_the_tolerance():
    # A bilateral chain with W = tridiag(-1, 2 + 1e-6, -1) (n = 60): Gauss-Seidel's rate is about cos²(π/61) ≈
    # 0.9973 per sweep, so reaching 1e-10 needs thousands of sweeps. The rule decides after the third sweep
    # (the first rate r₂/r₀): three sweeps, then Newton (one linear solve) finishes.
    n = 60
    compliance = (2.0 + 1e-6) * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1)
    problem = ConstraintProblem(
        compliance=compliance, free_gap=np.linspace(-1.0, 1.0, n), bilateral=np.arange(n)
    )
    result = solve_newton(problem, tolerance=1e-10, presweeps=_presweep_budget(n))
    assert result.presweeps == 3
    assert result.converged and result.iterations >= 1


def test_presweeps_alone_answer_a_well_conditioned_problem():
    # Diagonally dominant W (Gauss-Seidel contracts by ~0.1 per sweep): the sweeps meet 1e-10 within the
    # budget and Newton takes no iteration; the answer is confirmed on a gap from scratch (the report's
    # residuals).
    rng = np.random.default_rng(5)
    n = 30
    coupling = 0.02 * rng.standard_normal((n, n))
    compliance = np.eye(n) + coupling @ coupling.T
    problem = ConstraintProblem(
        compliance=compliance, free_gap=rng.standard_normal(n), unilateral=np.arange(n)
    )
    multipliers, report = solve_exact(problem, tolerance=1e-10, method="auto")
    assert report.path == "gauss_seidel" and report.iterations == 0, report.message
    assert report.residual == natural_residual(problem, multipliers) <= 1e-10
    assert report.data_residual == data_residual(problem, multipliers) <= 1e-10


def test_newton_method_takes_no_presweeps():
    rng = np.random.default_rng(6)
    problem, _, _ = planted_problem(rng, unilateral=4, contacts=2)
    _, report = solve_exact(problem, tolerance=1e-10, method="newton")
    assert report.path == "newton" and "pre-sweep" not in report.message


@pytest.mark.parametrize("laws", list(LAWS))
def test_compiled_setup_matches_the_problem(laws):
    # Reference: the problem's own fields, read row by row (kinds from row_kinds(), parameters from the law
    # fields, ρ and F_data from their definitions in docs/solvers.md "A residual a diverging λ cannot
    # shrink").
    rng = np.random.default_rng(3)
    problem, _, _ = planted_problem(rng, shaft_preload=0.2, **LAWS[laws])
    kinds, rows, params, members = block_arrays(problem)
    assert np.all(np.diff(rows[:, 0]) > 0)
    row_kind = problem.row_kinds()
    np.testing.assert_array_equal(kinds, row_kind[rows[:, 0]])
    f_rows, offsets, f_members, mu, preload = friction_groups(problem)
    for b in range(kinds.size):
        if kinds[b] == BOX:
            index = int(np.flatnonzero(problem.box_rows == rows[b, 0])[0])
            assert tuple(params[b]) == (problem.box_lower[index], problem.box_upper[index])
        elif kinds[b] == GROUP_FRICTION:
            j = int(np.flatnonzero(f_rows == rows[b, 0])[0])
            np.testing.assert_array_equal(
                members[rows[b, 1] : rows[b, 2]], f_members[offsets[j] : offsets[j + 1]]
            )
            assert tuple(params[b]) == (mu[j], preload[j])
        elif kinds[b] == CONTACT:
            k = int(np.flatnonzero(problem.contacts[:, 0] == rows[b, 0])[0])
            np.testing.assert_array_equal(rows[b], problem.contacts[k])
            assert params[b, 0] == problem.contact_friction[k]
    weight, scale = data_scales(problem)
    diagonal = np.diag(problem.compliance).copy()
    diagonal[problem.contacts] = diagonal[problem.contacts].mean(axis=1)[:, None]
    np.testing.assert_allclose(weight, 1.0 / diagonal, rtol=1e-15)
    bounds = np.concatenate([problem.box_lower, problem.box_upper])
    expected = max(
        np.linalg.norm(weight * problem.free_gap),
        np.linalg.norm(bounds[np.isfinite(bounds)]),
        np.linalg.norm(mu * preload),
    )
    assert scale == pytest.approx(expected, rel=1e-14)


@pytest.mark.parametrize("laws", list(LAWS))
def test_python_path_presweeps_match_the_compiled_kernel(laws):
    # The Python iteration (a finite time limit selects it) runs the same compiled pre-sweeps: with no Newton
    # iteration allowed both return the swept point, which must be the same bits; then both converge.
    rng = np.random.default_rng(11)
    problem, _, _ = planted_problem(rng, **LAWS[laws])
    budget = _presweep_budget(problem.row_count)
    compiled = solve_newton(problem, tolerance=1e-10, presweeps=budget, max_iterations=0)
    python = solve_newton(problem, tolerance=1e-10, presweeps=budget, max_iterations=0, time_limit=60.0)
    assert compiled.storage == python.storage == "dense"
    assert compiled.presweeps == python.presweeps > 0
    np.testing.assert_array_equal(python.multipliers, compiled.multipliers)
    assert solve_newton(problem, tolerance=1e-10, presweeps=budget, time_limit=60.0).converged
