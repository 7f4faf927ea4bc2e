"""Finite element models (layer 2): co-rotational tetrahedra, co-rotational Timoshenko needle, implicit Euler."""

from refsim.fem.integration import ImplicitEulerSystem, effective_stiffness
from refsim.fem.needle import NeedleModel, NeedleSection
from refsim.fem.tissue import TissueModel, TissueState

__all__ = ["ImplicitEulerSystem", "NeedleModel", "NeedleSection", "TissueModel", "TissueState", "effective_stiffness"]
