"""The one compiled call of dense problems (refsim.solvers.newton._solve_dense_fresh: the set-up, W's
asymmetry and every Newton iteration in _dense_newton_fresh) answers a problem the same, bit for bit, whatever
is cached on it: a fresh copy, and a copy whose set-up caches (block_arrays, data_scales) were filled first,
as a Gauss–Seidel solve of the same problem fills them (the ground-truth workflow: solve_gauss_seidel, then
solve_exact on the same problem).

Reference: the solve of the fresh copy. The call recomputes the set-up by the same compiled operations, so no
tolerance: equality of the bytes of λ, of the history and of every report field but the wall-clock time.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from refsim.solvers import ConstraintProblem, solve_exact
from refsim.solvers.laws import block_arrays, friction_groups
from refsim.solvers.newton import SPARSE_ABOVE, solve_newton
from refsim.solvers.residual import data_scales, residuals

from .conftest import planted_problem

LAWS = {
    "contacts": dict(contacts=4),
    "mixed": dict(bilateral=2, unilateral=3, contacts=3, box=3),
    "lcp": dict(unilateral=6),
    "box": dict(box=5, bilateral=1),
    "shafts": dict(bilateral=1, shafts=3, contacts=2, shaft_preload=0.2),
    "groups": dict(bilateral=1, unilateral=2, shafts=4, box=1, shaft_preload=0.2),
}


def _with_group_form(problem: ConstraintProblem) -> ConstraintProblem:
    """The last half of the pair-form (shaft) rows written in the group form, each group also holding the
    first unilateral row (when there is one), and a plain bilateral row (when there is one) made an empty
    group: both forms in one problem, merged by the compiled set-up as by
    :func:`~refsim.solvers.laws.friction_groups`."""
    count = len(problem.shaft_friction)
    keep = count // 2
    extra = problem.unilateral[:1].tolist()
    members, offsets = [], [0]
    for pair in problem.shaft_pairs[keep:]:
        members += pair.tolist() + extra
        offsets.append(len(members))
    moved = problem.shaft_friction[keep:]
    plain = np.setdiff1d(problem.bilateral, problem.shaft_pairs.reshape(-1))
    group_rows = moved
    if plain.size:  # a plain bilateral row becomes an empty group: bound μ p
        group_rows = np.concatenate([moved, plain[:1]])
        offsets.append(len(members))
    bilateral = np.setdiff1d(problem.bilateral, group_rows)
    size = len(group_rows)
    return dataclasses.replace(
        problem,
        bilateral=bilateral,
        shaft_friction=problem.shaft_friction[:keep],
        shaft_pairs=problem.shaft_pairs[:keep],
        shaft_friction_coefficient=problem.shaft_friction_coefficient[:keep],
        shaft_normal_preload=problem.shaft_normal_preload[:keep],
        group_friction=group_rows,
        group_offsets=np.array(offsets),
        group_members=np.array(members, dtype=np.int64),
        group_friction_coefficient=np.full(size, 0.4),
        group_preload=np.linspace(0.0, 0.3, size),
    )


def _same(first, second) -> bool:
    """Equal values, NaN equal to NaN, arrays compared by dtype, shape and bytes."""
    if isinstance(first, np.ndarray) or isinstance(second, np.ndarray):
        first, second = np.asarray(first), np.asarray(second)
        return (
            first.dtype == second.dtype
            and first.shape == second.shape
            and first.tobytes() == second.tobytes()
        )
    if isinstance(first, float) and isinstance(second, float) and math.isnan(first) and math.isnan(second):
        return True
    return type(first) is type(second) and first == second


def _layered(problem: ConstraintProblem) -> ConstraintProblem:
    copy = dataclasses.replace(problem)
    block_arrays(copy)
    data_scales(copy)
    return copy


def _assert_identical(problem: ConstraintProblem, **options) -> None:
    fresh = dataclasses.replace(problem)
    lam_fresh, report_fresh = solve_exact(fresh, **options)
    layered = _layered(problem)
    lam_layered, report_layered = solve_exact(layered, **options)
    assert _same(lam_fresh, lam_layered)
    for field in dataclasses.fields(report_fresh):
        if field.name != "seconds":
            assert _same(getattr(report_fresh, field.name), getattr(report_layered, field.name)), field.name
    assert report_fresh.asymmetry == problem.asymmetry()


def _skewed(problem: ConstraintProblem, rng: np.random.Generator, amount: float) -> ConstraintProblem:
    """W made non-symmetric by ``amount`` (relative), the rest unchanged."""
    noise = rng.standard_normal(problem.compliance.shape)
    compliance = problem.compliance + amount * np.abs(problem.compliance).max() * (noise - noise.T)
    return dataclasses.replace(problem, compliance=compliance)


@pytest.mark.parametrize("laws", sorted(LAWS))
@pytest.mark.parametrize("skew", [0.0, 1e-4])
@pytest.mark.parametrize("method", ["auto", "newton"])
@pytest.mark.parametrize("start", ["cold", "warm"])
def test_fresh_path_is_bit_identical_to_the_layered_path(laws, skew, method, start):
    rng = np.random.default_rng(15)
    for rank_drop in (0, 2):
        problem, force, _ = planted_problem(rng, **LAWS[laws])
        if rank_drop:
            problem, force, _ = planted_problem(rng, rank=problem.row_count - rank_drop, **LAWS[laws])
        problem = _skewed(problem, rng, skew) if skew else problem
        if laws == "groups":
            problem = _with_group_form(problem)
        warm = force * (1.0 + 0.1 * rng.standard_normal(force.size)) if start == "warm" else None
        _assert_identical(problem, tolerance=1e-8, method=method, warm_start=warm)


@pytest.mark.parametrize("newton_iterations", [0, 1])
def test_fresh_path_that_does_not_converge_goes_on_as_the_layered_path(newton_iterations):
    # solve_exact answers from the compiled call's outcome only when it converged; otherwise its general code
    # (Gauss-Seidel chunks, Lemke, the cone route) takes over from the same Newton result: the same report
    rng = np.random.default_rng(16)
    unfinished = 0
    for laws in ("contacts", "mixed", "shafts"):
        problem, _, _ = planted_problem(rng, rank=None, **LAWS[laws])
        _assert_identical(problem, tolerance=1e-12, method="auto", newton_iterations=newton_iterations)
        _, report = solve_exact(
            dataclasses.replace(problem), tolerance=1e-12, method="auto", newton_iterations=newton_iterations
        )
        unfinished += report.path not in ("newton", "gauss_seidel", "gauss_seidel+newton")
    assert unfinished  # the case is exercised: some answers came from the code after Newton


def test_solve_exact_answers_small_fresh_problems_from_the_compiled_outcome(monkeypatch):
    # the converged fresh solve builds its report without solve_newton's layers (and without solve_newton)
    import refsim.solvers.exact as exact

    problem, _, _ = planted_problem(np.random.default_rng(6), contacts=3, unilateral=2)

    def forbidden(*args, **kwargs):
        raise AssertionError("solve_newton called on a small fresh problem")

    monkeypatch.setattr(exact, "solve_newton", forbidden)
    multipliers, report = solve_exact(dataclasses.replace(problem), tolerance=1e-8, method="auto")
    assert report.converged and report.solver == "exact/newton"
    assert report.residual <= 1e-8 and report.data_residual <= 1e-8
    assert (report.residual, report.data_residual) == residuals(problem, multipliers)


def test_fresh_path_is_taken_and_leaves_the_asymmetry_cached():
    problem, _, _ = planted_problem(np.random.default_rng(3), contacts=3, unilateral=2)
    fresh = dataclasses.replace(problem)
    result = solve_newton(fresh, tolerance=1e-8)
    assert result.converged
    assert "_block_arrays" not in fresh.__dict__  # the set-up ran inside the compiled call
    assert fresh.__dict__["_asymmetry"] == dataclasses.replace(problem).asymmetry()


def test_group_friction_takes_the_fresh_path():
    # the needle's problems (shaft rows: the pair form) and the group form, merged in compiled code
    for problem in (
        planted_problem(np.random.default_rng(4), bilateral=2, shafts=2, contacts=2)[0],
        _with_group_form(planted_problem(np.random.default_rng(4), unilateral=1, shafts=4)[0]),
    ):
        copy = dataclasses.replace(problem)
        assert solve_newton(copy, tolerance=1e-8).converged
        assert "_block_arrays" not in copy.__dict__ and "_asymmetry" in copy.__dict__


def test_large_dense_problems_take_the_one_call_and_sparse_ones_the_layered_path():
    # above 120 rows too, and with the set-up cached: one compiled entry point for every dense solve
    large, _, _ = planted_problem(np.random.default_rng(5), contacts=41)  # 123 rows
    for copy in (dataclasses.replace(large), _layered(large)):
        cached = "_block_arrays" in copy.__dict__
        solve_newton(copy, tolerance=1e-8, max_iterations=2)
        assert ("_block_arrays" in copy.__dict__) == cached  # the call did not set the problem up in Python
        assert "_asymmetry" in copy.__dict__
    _assert_identical(large, tolerance=1e-8, method="auto")
    # sparse storage (more than SPARSE_ABOVE rows, W diagonal): the layered path, set up in Python
    rows = SPARSE_ABOVE + 3
    sparse = ConstraintProblem(compliance=np.eye(rows), free_gap=-np.ones(rows), bilateral=np.arange(rows))
    result = solve_newton(sparse, tolerance=1e-8)
    assert result.storage == "sparse" and result.converged and "_block_arrays" in sparse.__dict__
    assert np.allclose(result.multipliers, 1.0, rtol=0.0, atol=1e-8)  # W λ + δ_free = 0: λ = 1


def test_friction_groups_merge_both_forms():
    # Reference: the law's statement (docs/solvers.md): pair-form rows first, members their two bilateral
    # rows; then the group-form rows with their offsets shifted by the pair members (2 per pair), an empty
    # group kept.
    problem = ConstraintProblem(
        compliance=np.eye(8),
        free_gap=np.ones(8),
        bilateral=[0, 1, 2, 3],
        unilateral=[4],
        shaft_friction=[5],
        shaft_pairs=[[0, 1]],
        shaft_friction_coefficient=[0.3],
        shaft_normal_preload=[0.1],
        group_friction=[6, 7],
        group_offsets=[0, 3, 3],
        group_members=[2, 3, 4],
        group_friction_coefficient=[0.4, 0.5],
        group_preload=[0.0, 0.2],
    )
    rows, offsets, members, coefficient, preload = friction_groups(problem)
    np.testing.assert_array_equal(rows, [5, 6, 7])
    np.testing.assert_array_equal(offsets, [0, 2, 5, 5])
    np.testing.assert_array_equal(members, [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(coefficient, [0.3, 0.4, 0.5])
    np.testing.assert_array_equal(preload, [0.1, 0.0, 0.2])
    assert rows.dtype == offsets.dtype == members.dtype == np.int64


def test_fresh_path_on_the_shared_problems(problems_root):
    """Every shared problem of dense storage (the floor study's 22 contact problems among them)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "studies" / "solvers" / "run.py"
    spec = importlib.util.spec_from_file_location("solver_study_run_fresh", path)
    run = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(run)
    problems = [p for _, p in run.external_problems(problems_root) if 0 < p.row_count <= SPARSE_ABOVE]
    assert len(problems) >= 22
    for problem in problems:
        for method in ("auto", "newton"):
            _assert_identical(problem, tolerance=1e-8, method=method)
