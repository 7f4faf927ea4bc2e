"""Material records (layer 1): isotropic Hooke materials in SI units."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

__all__ = ["HookeMaterial"]


@dataclass(frozen=True, kw_only=True)
class HookeMaterial:
    """An isotropic linear elastic (Hooke) material.

    Attributes
    ----------
    youngs_modulus : Young's modulus E [Pa], finite and > 0.
    poisson_ratio : Poisson's ratio ν [-], in (−1, 0.5) (0.5, incompressible, has no finite first Lamé
    parameter). density : Mass density ρ [kg/m³], finite and > 0.
    """

    youngs_modulus: float
    poisson_ratio: float
    density: float

    def __post_init__(self) -> None:
        _check_number("youngs_modulus", self.youngs_modulus, "a finite number > 0 Pa")
        _check_number("poisson_ratio", self.poisson_ratio, "a number in (-1, 0.5)")
        _check_number("density", self.density, "a finite number > 0 kg/m^3")
        if not (math.isfinite(self.youngs_modulus) and self.youngs_modulus > 0.0):
            raise ValueError(f"youngs_modulus must be a finite number > 0 Pa, got {self.youngs_modulus!r}")
        if not -1.0 < self.poisson_ratio < 0.5:
            raise ValueError(f"poisson_ratio must lie in (-1, 0.5), got {self.poisson_ratio!r}")
        if not (math.isfinite(self.density) and self.density > 0.0):
            raise ValueError(f"density must be a finite number > 0 kg/m^3, got {self.density!r}")

    @property
    def lame_lambda(self) -> float:
        """First Lamé parameter λ = E ν / ((1 + ν)(1 − 2ν)) [Pa]."""
        nu = self.poisson_ratio
        return self.youngs_modulus * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    @property
    def shear_modulus(self) -> float:
        """Shear modulus, the second Lamé parameter μ = E / (2 (1 + ν)) [Pa]."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))

    @property
    def bulk_modulus(self) -> float:
        """Bulk modulus K = E / (3 (1 − 2ν)) [Pa]."""
        return self.youngs_modulus / (3.0 * (1.0 - 2.0 * self.poisson_ratio))

    @property
    def p_wave_modulus(self) -> float:
        """P-wave (constrained, oedometric) modulus λ + 2μ [Pa]: the stiffness of uniaxial strain."""
        return self.lame_lambda + 2.0 * self.shear_modulus


def _check_number(name: str, value: object, valid: str) -> None:
    """Raise a ValueError naming the field when ``value`` is not a real number (bool excluded)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be {valid}, got {value!r} of type {type(value).__name__}")
