"""Solver reports that cannot lie: the data residual, and Gauss-Seidel's divergence on an infeasible
problem."""

import numpy as np
import pytest

from refsim.solvers import ConstraintProblem, natural_residual, solve_gauss_seidel
from refsim.solvers.residual import data_residual, data_residual_by_kind, data_scales

from .conftest import planted_problem


def _infeasible():
    # δ = W λ + δ_free with W = ones: δ_1 − δ_2 = 2 for every λ, so both bilateral rows cannot vanish.
    return ConstraintProblem(compliance=np.ones((2, 2)), free_gap=[1.0, -1.0], bilateral=[0, 1], name="ones")


def test_data_residual_is_bounded_below_on_an_infeasible_problem():
    # Reference: for bilateral rows e = δ, and min ‖δ‖ subject to δ_1 − δ_2 = 2 is √2 (at δ = (1, −1)).
    # ρ = 1/W_ii = 1, so F_data = ‖δ_free‖ = √2 and the denominator is √2: the data residual is ≥ 1 for
    # every λ, while the natural residual ‖e‖ / max(‖δ_free‖, ‖λ‖, ‖δ‖) goes to 0 along λ = t (−1, 1).
    problem = _infeasible()
    weight, scale = data_scales(problem)
    np.testing.assert_array_equal(weight, [1.0, 1.0])
    assert scale == pytest.approx(np.sqrt(2.0))
    rng = np.random.default_rng(0)
    for t in (1.0, 1e3, 1e6, 1e9):
        direction = np.array([-1.0, 1.0]) * t
        assert data_residual(problem, direction) == pytest.approx(1.0)
        assert natural_residual(problem, direction) <= 1.0 / t
    for multipliers in rng.standard_normal((50, 2)) * 10.0 ** rng.uniform(-3, 9, (50, 1)):
        assert data_residual(problem, multipliers) >= 1.0 - 1e-12


@pytest.mark.parametrize("sweeps", [1000, 3_000_000])
def test_gauss_seidel_reports_divergence(sweeps):
    # issue 10: with 3e6 sweeps the λ-normalised residual falls below the tolerance (2.4e-7 < 1e-6), yet no
    # solution exists: the report must say diverged, not converged.
    multipliers, report = solve_gauss_seidel(_infeasible(), tolerance=1e-6, max_iterations=sweeps)
    assert not report.converged
    assert report.diverged
    assert "diverging" in report.message
    # after each sweep row 2 was solved last: δ = (2, 0), so ‖e‖ / √2 = √2
    assert report.data_residual == pytest.approx(np.sqrt(2.0))
    assert np.linalg.norm(multipliers) > report.iterations  # λ grows by 2 √2 per sweep


def test_converged_reports_meet_both_residuals():
    rng = np.random.default_rng(11)
    problem, _, _ = planted_problem(rng, bilateral=2, unilateral=3, contacts=2, shafts=2, box=3)
    multipliers, report = solve_gauss_seidel(problem, tolerance=1e-9, max_iterations=20_000)
    assert report.converged and not report.diverged
    assert report.residual <= 1e-9 and report.data_residual <= 1e-9
    assert report.data_residual == pytest.approx(data_residual(problem, multipliers))
    parts = data_residual_by_kind(problem, multipliers)
    assert np.sqrt(sum(v * v for v in parts.values())) == pytest.approx(report.data_residual, rel=1e-12)


def test_slow_but_convergent_is_not_called_divergent():
    # A well-posed problem stopped early: not converged, but neither diverged (λ does not grow without bound).
    rng = np.random.default_rng(2)
    problem, _, _ = planted_problem(rng, bilateral=6, unilateral=6, contacts=4, rank=10)
    _, report = solve_gauss_seidel(problem, tolerance=1e-14, max_iterations=40)
    assert not report.converged and not report.diverged


def test_strict_criterion_meets_both_residuals():
    rng = np.random.default_rng(4)
    problem, _, _ = planted_problem(rng, bilateral=3, unilateral=4, contacts=3, shafts=1, box=2, scale=1e-3)
    _, report = solve_gauss_seidel(problem, tolerance=1e-10, max_iterations=50_000, criterion="strict")
    assert report.converged and report.residual <= 1e-10 and report.data_residual <= 1e-10


def test_report_constructor_has_the_fields_and_defaults_of_the_dataclass():
    # SolverReport writes its instance dictionary in one call (a hand-written __init__): its keywords must be
    # the dataclass fields, in order, with the fields' defaults, and the result must behave as the frozen
    # dataclass
    import dataclasses
    import inspect

    from refsim.solvers import SolverReport

    parameters = inspect.signature(SolverReport.__init__).parameters
    fields = dataclasses.fields(SolverReport)
    assert list(parameters)[1:] == [f.name for f in fields]
    for f in fields:
        parameter = parameters[f.name]
        assert parameter.kind is inspect.Parameter.KEYWORD_ONLY
        if f.default is not dataclasses.MISSING:
            default, expected = parameter.default, f.default
            assert (default == expected) or (default != default and expected != expected), (
                f.name
            )  # NaN == NaN
        elif f.default_factory is not dataclasses.MISSING:
            assert parameter.default is None, f.name  # history: a new empty array per report
        else:
            assert parameter.default is inspect.Parameter.empty, f.name
    report = SolverReport(solver="s", iterations=2, residual=0.5, converged=False, seconds=1.0)
    other = SolverReport(solver="s", iterations=2, residual=0.5, converged=False, seconds=1.0)
    assert report.history.shape == (0,) and report.history is not other.history
    assert (
        np.isnan(report.increment)
        and np.isnan(report.asymmetry)
        and report.path == ""
        and not report.diverged
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        report.iterations = 3
    changed = dataclasses.replace(report, iterations=5, history=np.ones(2))
    assert changed.iterations == 5 and changed.solver == "s" and changed.history.tolist() == [1.0, 1.0]
    assert "iterations=2" in repr(report)
