"""The law table (refsim.solvers.laws): one entry per law, the problem's fields taken from it, and every law's
kernels on hand-made problems with solutions worked out by hand."""

import dataclasses

import numpy as np
import pytest

from refsim.solvers import (
    LAW_NAMES,
    LAWS,
    ConstraintProblem,
    natural_map_error,
    natural_residual,
    solve_exact,
    solve_gauss_seidel,
)
from refsim.solvers.laws import LAW_FIELDS, block_arrays, problem_field_specs


def test_problem_fields_are_the_table_fields():
    names = [f.name for f in dataclasses.fields(ConstraintProblem)]
    assert names == [spec.name for spec in problem_field_specs()] + ["name"]
    assert LAW_NAMES == ("bilateral", "unilateral", "contact", "group_friction", "box")
    assert [law.code for law in LAWS] == list(range(len(LAWS)))
    # every law field has a unit, a dtype the schema knows and a role the validation knows
    for spec in LAW_FIELDS:
        assert spec.dtype in ("int64", "float64") and spec.unit
        assert spec.role in ("rows", "members", "offsets", "coefficient", "preload", "bound")
        if spec.role not in ("rows",):
            assert spec.per in [s.name for s in LAW_FIELDS if s.role == "rows"]


def _grouped_problem(preload=0.0):
    """W = I, so every row decouples except through the friction bounds. Rows:

    0 unilateral, δ_free = −1 → λ0 = 1 (δ0 = 0);
    1 group friction, group {0}, μ = 0.5, p: bound b1 = 0.5 (1 + p); δ_free = −2 → slip λ1 = b1 (δ1 = b1 − 2 <
    0); 2 group friction, group {0, 3, 4}, μ = 0.1: b2 = 0.1 √(1 + 9 + 16) = 0.5099; δ_free = 0.2 → stick
      λ2 = −0.2, δ2 = 0;
    3, 4 bilateral, δ_free = (−3, −4) → λ = (3, 4);
    5 group friction with an empty group, μ = 0.3, p = 2: b5 = 0.6; δ_free = 5 → slip λ5 = −0.6 (δ5 = 4.4 >
    0).
    """
    problem = ConstraintProblem(
        compliance=np.eye(6),
        free_gap=[-1.0, -2.0, 0.2, -3.0, -4.0, 5.0],
        unilateral=[0],
        bilateral=[3, 4],
        group_friction=[1, 2, 5],
        group_offsets=[0, 1, 4, 4],
        group_members=[0, 0, 3, 4],
        group_friction_coefficient=[0.5, 0.1, 0.3],
        group_preload=[preload, 0.0, 2.0],
        name="grouped",
    )
    solution = np.array([1.0, 0.5 * (1.0 + preload), -0.2, 3.0, 4.0, -0.6])
    return problem, solution


@pytest.mark.parametrize("preload", [0.0, 1.0])
def test_group_friction_solution_by_hand(preload):
    problem, solution = _grouped_problem(preload)
    np.testing.assert_allclose(
        problem.friction_bounds(solution), [0.5 * (1 + preload), 0.1 * np.sqrt(26), 0.6]
    )
    assert natural_residual(problem, solution) < 1e-15
    # moving any row off its law shows in its own error
    for row in range(6):
        moved = solution.copy()
        moved[row] += 0.1
        error, _ = natural_map_error(problem, moved)
        assert abs(error[row]) > 1e-3
    gs, report = solve_gauss_seidel(problem, tolerance=1e-14, max_iterations=50)
    assert report.converged
    np.testing.assert_allclose(gs, solution, atol=1e-13)
    exact, report = solve_exact(problem, tolerance=1e-12)
    assert report.converged, report.message
    np.testing.assert_allclose(exact, solution, atol=1e-9)


def test_pair_form_is_group_friction_with_pairs():
    # The same problem given as shaft rows (pairs) or as groups gives bit-identical Gauss-Seidel multipliers.
    rng = np.random.default_rng(3)
    factor = rng.standard_normal((7, 7))
    compliance = factor @ factor.T / 7 + 0.1 * np.eye(7)
    free_gap = rng.standard_normal(7)
    common = dict(compliance=compliance, free_gap=free_gap, bilateral=[0, 1, 2, 3], unilateral=[6])
    pairs = ConstraintProblem(
        **common,
        shaft_friction=[4, 5],
        shaft_pairs=[[0, 1], [2, 3]],
        shaft_friction_coefficient=[0.3, 0.6],
        shaft_normal_preload=[0.1, 0.0],
    )
    groups = ConstraintProblem(
        **common,
        group_friction=[4, 5],
        group_offsets=[0, 2, 4],
        group_members=[0, 1, 2, 3],
        group_friction_coefficient=[0.3, 0.6],
        group_preload=[0.1, 0.0],
    )
    for problem in (pairs, groups):
        assert LAW_NAMES[problem.row_kinds()[4]] == "group_friction"
    first, _ = solve_gauss_seidel(pairs, tolerance=1e-12, max_iterations=500)
    second, _ = solve_gauss_seidel(groups, tolerance=1e-12, max_iterations=500)
    np.testing.assert_array_equal(first, second)
    np.testing.assert_array_equal(pairs.friction_bounds(first), groups.friction_bounds(first))


def test_blocks_are_sorted_by_row_and_cover_every_row():
    problem, _ = _grouped_problem()
    kinds, rows, params, members = block_arrays(problem)
    np.testing.assert_array_equal(rows[:, 0], np.arange(6))
    np.testing.assert_array_equal(kinds, [1, 3, 3, 0, 0, 3])
    np.testing.assert_array_equal(members[rows[2, 1] : rows[2, 2]], [0, 3, 4])
    np.testing.assert_array_equal(params[5], [0.3, 2.0])


@pytest.mark.parametrize("seed", range(6))
def test_blocks_of_scattered_laws_are_sorted_by_their_first_row(seed):
    # Reference: each law's blocks written out from the problem's fields, then Python's sort by first row
    # (first rows are distinct); the compiled pass must give the same blocks, fields and all, in that order.
    rng = np.random.default_rng(seed)
    rows = rng.permutation(21)
    contacts, bilateral, unilateral = rows[:6].reshape(2, 3), rows[6:12], rows[12:16]
    box, group = rows[16:19], rows[19:21]
    problem = ConstraintProblem(
        compliance=np.eye(21),
        free_gap=np.ones(21),
        bilateral=bilateral,
        unilateral=unilateral,
        contacts=contacts,
        contact_friction=[0.3, 0.5],
        box_rows=box,
        box_lower=[-1.0, -2.0, -3.0],
        box_upper=[1.0, 2.0, 3.0],
        group_friction=group,
        group_offsets=[0, 2, 3],
        group_members=unilateral[:3],
        group_friction_coefficient=[0.4, 0.6],
        group_preload=[0.1, 0.2],
    )
    lower, upper, mu_c = [-1.0, -2.0, -3.0], [1.0, 2.0, 3.0], [0.3, 0.5]
    ends, mu_g, preload = [(0, 2), (2, 3)], [0.4, 0.6], [0.1, 0.2]
    expected = (
        [(row, 0, (row, 0, 0), (0.0, 0.0)) for row in bilateral]
        + [(row, 1, (row, 0, 0), (0.0, 0.0)) for row in unilateral]
        + [(box[k], 4, (box[k], 0, 0), (lower[k], upper[k])) for k in range(3)]
        + [(group[k], 3, (group[k], *ends[k]), (mu_g[k], preload[k])) for k in range(2)]
        + [(contacts[k, 0], 2, tuple(contacts[k]), (mu_c[k], 0.0)) for k in range(2)]
    )
    expected.sort(key=lambda block: block[0])
    kinds, blocks, params, members = block_arrays(problem)
    assert [LAW_NAMES[k] for k in kinds] == [LAW_NAMES[e[1]] for e in expected]
    np.testing.assert_array_equal(blocks, [e[2] for e in expected])
    np.testing.assert_array_equal(params, [e[3] for e in expected])
    np.testing.assert_array_equal(members, unilateral[:3])
    assert kinds.dtype == blocks.dtype == np.int64 and params.dtype == np.float64


@pytest.mark.parametrize(
    ("overrides", "words"),
    [
        (dict(group_offsets=[0, 1, 4]), "group_offsets has shape (3,), expected (4,)"),
        (dict(group_offsets=[0, 3, 1, 4]), "never decrease"),
        (dict(group_offsets=[0, 1, 4, 5]), "end at len(group_members) = 4"),
        (dict(group_members=[0, 1, 3, 4]), "holds row 1, a group friction row"),
        (dict(group_friction_coefficient=[0.5, -0.1, 0.3]), "negative coefficient -0.1"),
        (dict(group_preload=[0.0, np.inf, 0.0]), "non-finite"),
        (dict(group_preload=[0.0, 0.0]), "group_preload has shape (2,), expected (3,)"),
        (dict(group_members=[0, 0, 3, 9]), "group_members holds row 9, outside [0, 6)"),
    ],
)
def test_bad_groups_are_named(overrides, words):
    problem, _ = _grouped_problem()
    fields = {f.name: getattr(problem, f.name) for f in dataclasses.fields(problem)}
    fields.update(overrides)
    with pytest.raises(ValueError) as info:
        ConstraintProblem(**fields)
    assert words in str(info.value)
