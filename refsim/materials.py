"""Material records (layer 1): isotropic Hooke materials in SI units, and the one definition of their limits.

:data:`MATERIAL_LIMITS` is the single source of the valid range of each material constant: the
:class:`HookeMaterial` record checks against it, the scene keys of the tissue and the needle take their range
from it (``refsim.scene.spec``), and the needle's cross-section (``refsim.fem.needle.NeedleSection``)
validates its material by building a :class:`HookeMaterial`. The upper bounds are physical (no solid is
stiffer than diamond, 1.2e12 Pa, or denser than osmium, 22.6e3 kg/m³) with a margin, so that an overflowing
value such as a density of 1e300 kg/m³ is refused before a run rather than found as inf forces in it.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

__all__ = ["HookeMaterial", "MATERIAL_LIMITS", "check_material_value"]

#: Valid range of each material constant: keyword arguments of ``refsim.scene.fields.spec`` (unit, low, high,
# : open ends). Young's modulus (0, 1e13] Pa; Poisson's ratio (−1, 0.5) (0.5, incompressible, has no finite
# first : Lamé parameter); density (0, 1e5] kg/m³.
MATERIAL_LIMITS = {
    "youngs_modulus": dict(unit="Pa", low=0.0, high=1e13, low_open=True),
    "poisson_ratio": dict(unit="-", low=-1.0, high=0.5, low_open=True, high_open=True),
    "density": dict(unit="kg/m^3", low=0.0, high=1e5, low_open=True),
}


def _describe(name: str) -> str:
    limits = MATERIAL_LIMITS[name]
    left = "(" if limits.get("low_open") else "["
    right = ")" if limits.get("high_open") else "]"
    return f"a finite number in {left}{limits['low']:g}, {limits['high']:g}{right} {limits['unit']}"


def check_material_value(name: str, value: object) -> float:
    """Check one material constant against :data:`MATERIAL_LIMITS`; return it as a float.

    Raises
    ------
    ValueError
        Naming the constant, the value and the valid range.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be {_describe(name)}, got {value!r} of type {type(value).__name__}")
    value = float(value)
    limits = MATERIAL_LIMITS[name]
    low, high = limits["low"], limits["high"]
    above_low = value > low if limits.get("low_open") else value >= low
    below_high = value < high if limits.get("high_open") else value <= high
    if not (math.isfinite(value) and above_low and below_high):
        raise ValueError(f"{name} must be {_describe(name)}, got {value!r}")
    return value


@dataclass(frozen=True, kw_only=True)
class HookeMaterial:
    """An isotropic linear elastic (Hooke) material.

    Attributes
    ----------
    youngs_modulus : Young's modulus E [Pa], in (0, 1e13].
    poisson_ratio : Poisson's ratio ν [-], in (−1, 0.5).
    density : Mass density ρ [kg/m³], in (0, 1e5].
    """

    youngs_modulus: float
    poisson_ratio: float
    density: float

    def __post_init__(self) -> None:
        for name in ("youngs_modulus", "poisson_ratio", "density"):
            check_material_value(name, getattr(self, name))

    @property
    def lame_lambda(self) -> float:
        """First Lamé parameter λ = E ν / ((1 + ν)(1 − 2ν)) [Pa]."""
        nu = self.poisson_ratio
        return self.youngs_modulus * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    @property
    def shear_modulus(self) -> float:
        """Shear modulus, the second Lamé parameter μ = E / (2 (1 + ν)) [Pa]."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))
