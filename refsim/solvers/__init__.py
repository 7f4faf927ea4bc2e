"""Constraint problems and their solvers (layer 0): Gauss–Seidel and an exact reference.

Knows nothing of needles or tissue: it takes a compliance W, a free gap δ_free and the rows of each law of the
table :data:`refsim.solvers.laws.LAWS`.
"""

from refsim.solvers.exact import available_backends, solve_exact
from refsim.solvers.gauss_seidel import solve_gauss_seidel
from refsim.solvers.laws import LAW_NAMES, LAWS, Law
from refsim.solvers.problem import ConstraintProblem
from refsim.solvers.readers import read_fclib, read_problem, read_siconos
from refsim.solvers.report import SolverReport
from refsim.solvers.residual import (
    data_residual,
    data_residual_by_kind,
    data_scales,
    natural_map_error,
    natural_residual,
    natural_residual_by_kind,
    project_friction_cone,
)

__all__ = [
    "LAWS",
    "LAW_NAMES",
    "Law",
    "ConstraintProblem",
    "SolverReport",
    "available_backends",
    "data_residual",
    "data_residual_by_kind",
    "data_scales",
    "natural_map_error",
    "natural_residual",
    "natural_residual_by_kind",
    "project_friction_cone",
    "read_fclib",
    "read_problem",
    "read_siconos",
    "solve_exact",
    "solve_gauss_seidel",
]
