"""Validation of ConstraintProblem: every bad input is a ValueError that says what is wrong."""

import numpy as np
import pytest

from refsim.solvers import LAW_NAMES, ConstraintProblem


def _base(**overrides):
    fields = dict(
        compliance=np.eye(4),
        free_gap=np.zeros(4),
        bilateral=[0, 1],
        shaft_friction=[2],
        shaft_pairs=[[0, 1]],
        shaft_friction_coefficient=[0.3],
        unilateral=[3],
    )
    fields.update(overrides)
    return ConstraintProblem(**fields)


def test_valid_problem_has_read_only_arrays_and_kinds():
    problem = _base(name="ok")
    assert problem.row_count == 4
    assert [LAW_NAMES[k] for k in problem.row_kinds()] == [
        "bilateral",
        "bilateral",
        "group_friction",
        "unilateral",
    ]
    assert problem.contacts.shape == (0, 3) and problem.box_rows.shape == (0,)
    with pytest.raises(ValueError):
        problem.compliance[0, 0] = 2.0
    np.testing.assert_allclose(problem.gap(np.ones(4)), np.ones(4))


def test_inputs_are_copied():
    compliance = np.eye(2)
    problem = ConstraintProblem(compliance=compliance, free_gap=[0.0, 1.0], unilateral=[0, 1])
    compliance[0, 0] = 5.0
    assert problem.compliance[0, 0] == 1.0


@pytest.mark.parametrize(
    ("overrides", "words"),
    [
        (dict(compliance=np.ones((4, 3))), "square"),
        (dict(compliance=np.ones(4)), "dimension"),
        (dict(free_gap=np.zeros(3)), "free_gap has shape"),
        (dict(free_gap=[0, np.nan, 0, 0]), "non-finite"),
        (dict(compliance=np.diag([1, 1, np.inf, 1])), "non-finite"),
        (dict(unilateral=[3, 1]), "row 1 is listed as bilateral and again as unilateral"),
        (dict(unilateral=[]), "belong to no kind"),
        (dict(unilateral=[4]), "outside [0, 4)"),
        (dict(unilateral=[3.5]), "integer"),
        (dict(shaft_friction_coefficient=[-0.1]), "negative coefficient"),
        # float64 arrays of the right shape (the rows' own, checked by min and max first) are still named
        (dict(shaft_friction_coefficient=np.array([-0.1])), "negative coefficient"),
        (dict(shaft_friction_coefficient=np.array([np.nan])), "non-finite"),
        (dict(shaft_friction_coefficient=np.array([np.inf])), "non-finite"),
        (dict(shaft_normal_preload=np.array([-np.inf])), "non-finite"),
        (dict(shaft_normal_preload=np.array([-1.0])), "negative value"),
        (dict(shaft_friction_coefficient=[0.1, 0.2]), "expected (1,)"),
        (dict(shaft_pairs=[[0, 3]], unilateral=[3]), "must be bilateral"),
        (dict(shaft_pairs=np.zeros((0, 2))), "one pair per row"),
    ],
)
def test_bad_problem_names_the_defect(overrides, words):
    with pytest.raises(ValueError, match="ConstraintProblem 'bad'") as info:
        _base(name="bad", **overrides)
    assert words in str(info.value)


def test_contact_and_box_validation():
    good = ConstraintProblem(
        compliance=np.eye(5),
        free_gap=np.zeros(5),
        contacts=[[0, 1, 2]],
        contact_friction=[0.5],
        box_rows=[3, 4],
        box_lower=[-1, -np.inf],
        box_upper=[1, np.inf],
    )
    assert good.box_lower[1] == -np.inf
    with pytest.raises(ValueError, match="negative coefficient"):
        ConstraintProblem(
            compliance=np.eye(3), free_gap=np.zeros(3), contacts=[[0, 1, 2]], contact_friction=[-0.5]
        )
    with pytest.raises(ValueError, match=r"contacts must have shape \(count, 3\)"):
        ConstraintProblem(
            compliance=np.eye(2), free_gap=np.zeros(2), contacts=[[0, 1]], contact_friction=[0.5]
        )
    with pytest.raises(ValueError, match="box_lower 1.0 > box_upper -1.0"):
        ConstraintProblem(
            compliance=np.eye(1), free_gap=np.zeros(1), box_rows=[0], box_lower=[1.0], box_upper=[-1.0]
        )
    with pytest.raises(ValueError, match="box_upper has shape"):
        ConstraintProblem(compliance=np.eye(1), free_gap=np.zeros(1), box_rows=[0], box_lower=[1.0])
    with pytest.raises(ValueError, match="listed as contact and again as contact"):
        ConstraintProblem(
            compliance=np.eye(3),
            free_gap=np.zeros(3),
            contacts=[[0, 1, 1]],
            contact_friction=[0.5],
            unilateral=[2],
        )


def test_float64_box_bounds_may_be_infinite_but_not_nan():
    common = dict(compliance=np.eye(2), free_gap=np.zeros(2), box_rows=[0, 1])
    good = ConstraintProblem(box_lower=np.array([-np.inf, -1.0]), box_upper=np.array([np.inf, 2.0]), **common)
    np.testing.assert_array_equal(good.box_upper, [np.inf, 2.0])
    with pytest.raises(ValueError, match="box_lower has a non-finite value nan"):
        ConstraintProblem(box_lower=np.array([np.nan, -1.0]), box_upper=np.array([1.0, 1.0]), **common)


def test_multiplier_checks_and_asymmetry():
    problem = ConstraintProblem(compliance=[[1.0, 0.5], [0.0, 1.0]], free_gap=[0, 0], unilateral=[0, 1])
    assert problem.asymmetry() == pytest.approx(np.sqrt(0.5) / np.linalg.norm([[1, 0.5], [0, 1]]))
    with pytest.raises(ValueError, match=r"multipliers have shape \(3,\)"):
        problem.gap(np.zeros(3))
    with pytest.raises(ValueError, match="non-finite"):
        problem.gap([np.nan, 0.0])


def test_empty_problem():
    problem = ConstraintProblem(compliance=np.zeros((0, 0)), free_gap=np.zeros(0))
    assert problem.row_count == 0


def test_rows_checked_once_are_shared_and_values_still_checked():
    # Index fields equal to the last validated problem's skip their checks and share its read-only copies;
    # the values (coefficients, bounds) are checked every time, and other rows are checked again.
    rows = dict(
        bilateral=np.array([0, 1]),
        shaft_friction=np.array([2]),
        shaft_pairs=np.array([[0, 1]]),
        unilateral=np.array([3]),
        box_rows=np.zeros(0, dtype=np.int64),
    )
    first = ConstraintProblem(
        compliance=np.eye(4), free_gap=np.zeros(4), shaft_friction_coefficient=np.array([0.3]), **rows
    )
    second = ConstraintProblem(
        compliance=2.0 * np.eye(4), free_gap=np.ones(4), shaft_friction_coefficient=np.array([0.5]), **rows
    )
    assert second.bilateral is first.bilateral and not second.bilateral.flags.writeable
    assert second.shaft_friction_coefficient[0] == 0.5 and second.compliance[0, 0] == 2.0
    with pytest.raises(ValueError, match="shaft_friction_coefficient has a negative"):
        ConstraintProblem(
            compliance=np.eye(4), free_gap=np.zeros(4), shaft_friction_coefficient=np.array([-0.3]), **rows
        )
    with pytest.raises(ValueError, match="has shape"):
        two = np.array([0.3, 0.1])  # one coefficient per shaft row: one too many
        ConstraintProblem(compliance=np.eye(4), free_gap=np.zeros(4), shaft_friction_coefficient=two, **rows)
    clash = dict(rows, unilateral=np.array([1]))  # row 1 twice, row 3 in no law
    with pytest.raises(ValueError, match="listed as bilateral and again as unilateral"):
        ConstraintProblem(
            compliance=np.eye(4), free_gap=np.zeros(4), shaft_friction_coefficient=np.array([0.3]), **clash
        )
    third = ConstraintProblem(
        compliance=np.eye(4), free_gap=np.zeros(4), shaft_friction_coefficient=np.array([0.3]), **rows
    )
    assert third.bilateral is first.bilateral  # a failed problem is not remembered
    np.testing.assert_array_equal(third.row_kinds(), first.row_kinds())
