"""A recorded ConstraintProblem reads back equal, field by field (every field of the law table)."""

import dataclasses

import h5py
import numpy as np

from refsim.io import schema
from refsim.io.reader import read_problem_group
from refsim.io.writer import write_problem_group
from refsim.solvers import ConstraintProblem


def _every_field_problem():
    """A problem in which every field is non-empty and differs from its default."""
    n = 14
    rng = np.random.default_rng(5)
    factor = rng.standard_normal((n, n))
    return ConstraintProblem(
        compliance=factor @ factor.T,
        free_gap=rng.standard_normal(n),
        bilateral=[0, 1, 2],
        unilateral=[3],
        contacts=[[4, 5, 6]],
        contact_friction=[0.4],
        shaft_friction=[7],
        shaft_pairs=[[0, 1]],
        shaft_friction_coefficient=[0.2],
        shaft_normal_preload=[0.01],
        group_friction=[8, 9],
        group_offsets=[0, 3, 4],
        group_members=[2, 3, 4, 12],
        group_friction_coefficient=[0.3, 0.5],
        group_preload=[0.02, 0.0],
        box_rows=[10, 11, 12, 13],
        box_lower=[-1.0, -np.inf, 0.0, 0.5],
        box_upper=[1.0, 2.0, np.inf, 0.5],
        name="every field",
    )


def test_every_field_round_trips(tmp_path):
    problem = _every_field_problem()
    assert set(schema.PROBLEM_FIELDS) == {f.name for f in dataclasses.fields(problem)} - {"name"}
    with h5py.File(tmp_path / "problem.h5", "w") as handle:
        write_problem_group(handle.create_group("p"), problem)
    with h5py.File(tmp_path / "problem.h5", "r") as handle:
        rebuilt = read_problem_group(handle["p"])
        for spec in schema.PROBLEM_FIELDS.values():
            assert handle["p"][spec.name].attrs["units"] == spec.unit
    for field in dataclasses.fields(problem):
        original, read = getattr(problem, field.name), getattr(rebuilt, field.name)
        if isinstance(original, np.ndarray):
            assert read.dtype == original.dtype and read.shape == original.shape, field.name
            np.testing.assert_array_equal(read, original, err_msg=field.name)
        else:
            assert read == original, field.name
    # the defect of issue 8: the preload read back as 0.0
    assert rebuilt.shaft_normal_preload[0] == 0.01


def test_fields_missing_from_an_older_file_take_defaults(tmp_path):
    problem = ConstraintProblem(compliance=np.eye(2), free_gap=[1.0, -1.0], bilateral=[0], unilateral=[1])
    with h5py.File(tmp_path / "old.h5", "w") as handle:
        group = handle.create_group("p")
        write_problem_group(group, problem)
        for name in (
            "shaft_normal_preload",
            "group_friction",
            "group_offsets",
            "group_members",
            "group_friction_coefficient",
            "group_preload",
        ):
            del group[name]
    with h5py.File(tmp_path / "old.h5", "r") as handle:
        rebuilt = read_problem_group(handle["p"], default_name="old")
    np.testing.assert_array_equal(rebuilt.unilateral, [1])
    assert rebuilt.group_friction.shape == (0,) and rebuilt.name == "old"
