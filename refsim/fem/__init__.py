"""Finite element models (layer 2): co-rotational tetrahedra, co-rotational Timoshenko needle, implicit Euler,
compliance strategies and the sparse solvers behind them."""

from refsim.fem.compliance import (
    Exact,
    Fast,
    Precomputed,
    Refreshed,
    StepCompliance,
    StepSystem,
    make_strategy,
)
from refsim.fem.integration import effective_stiffness
from refsim.fem.linear import linear_solver_info
from refsim.fem.needle import NeedleModel, NeedleSection
from refsim.fem.threads import hot_path_threads, thread_settings
from refsim.fem.tissue import TissueModel, TissueState

__all__ = [
    "Exact",
    "Fast",
    "NeedleModel",
    "NeedleSection",
    "Precomputed",
    "Refreshed",
    "StepCompliance",
    "StepSystem",
    "TissueModel",
    "TissueState",
    "effective_stiffness",
    "hot_path_threads",
    "linear_solver_info",
    "make_strategy",
    "thread_settings",
]
