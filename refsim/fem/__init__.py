"""Finite element models (layer 2): co-rotational tetrahedra, co-rotational Timoshenko needle, implicit Euler."""

from refsim.fem.integration import ImplicitEulerSystem, effective_stiffness

__all__ = ["ImplicitEulerSystem", "effective_stiffness"]
