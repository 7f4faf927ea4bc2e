"""Convergence under refinement: observed order, Richardson extrapolation and Roache's grid convergence index.

Pure functions of a sequence of values f_i computed at refinement measures h_i (a spacing [m], or 1/cells).
Notation of Roache (1998) and Celik et al. (2008, "Procedure for estimation and reporting of uncertainty due
to discretization in CFD applications", J. Fluids Eng. 130, 078001): level 1 is the finest, 3 the coarsest,
r21 = h2/h1 > 1, r32 = h3/h2 > 1, ε21 = f2 − f1, ε32 = f3 − f2.

- Observed order, constant ratio r:  p = ln(ε32/ε21) / ln r.
- Any ratios (Celik's fixed point):  p = |ln|ε32/ε21| + q(p)| / ln r21,  q(p) = ln((r21^p − s)/(r32^p − s)),
  s = sign(ε32/ε21).
- Richardson extrapolation:          f_ext = f1 + (f1 − f2)/(r21^p − 1).
- Grid convergence index (fine):     GCI = Fs |e21| / (r21^p − 1), e21 = (f1 − f2)/f1, Fs = 1.25 (three
  levels); the uncertainty band of f1 is ± GCI |f1|.

A difference is an observation only above the round-off floor δ = ROUNDOFF · max(|f1|, |f2|, |f3|) (or a
floor the caller gives): with |ε21| ≤ δ the sequence has converged to round-off (f1, with δ as its
uncertainty, and no order: the quotient of a round-off difference is noise, and ln of it gives any order at
all); with |ε32| ≤ δ < |ε21| it is divergent. Otherwise it is oscillatory when ε21/ε32 < 0, divergent when no
positive order fits (for a constant ratio, |ε21| ≥ |ε32|), monotone otherwise; an order is reported for a
monotone sequence only (NaN otherwise, with the type saying why).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

__all__ = [
    "ROUNDOFF",
    "SAFETY_FACTOR",
    "ConvergenceResult",
    "convergence",
    "fitted_order",
    "grid_convergence_index",
    "observed_order",
    "richardson",
]

#: Roache's safety factor of the GCI for a three-level study.
SAFETY_FACTOR = 1.25

#: Relative round-off floor of a quantity computed by a run: differences below ROUNDOFF times the values'
#: magnitude are not resolved. A run accumulates the round-off of thousands of steps of float64
#: (ε = 2.2e-16), and quantities that are differences of positions (a stroke, a depth) lose a further factor
#: of position/difference to cancellation; 1e-12 is about 4500 ε.
ROUNDOFF = 1e-12


def roundoff_floor(values, scale: float | None = None) -> float:
    """The absolute round-off floor ROUNDOFF · (``scale`` or max |values|), in the values' unit."""
    magnitude = float(np.max(np.abs(values))) if scale is None else abs(float(scale))
    return ROUNDOFF * magnitude


@dataclass(frozen=True)
class ConvergenceResult:
    """Convergence of a quantity over the three finest levels of a sweep.

    Attributes
    ----------
    spacings : h1, h2, h3 (finest first), in the unit of the refinement measure.
    values : f1, f2, f3, in the quantity's unit.
    ratio_fine, ratio_coarse : r21 = h2/h1 and r32 = h3/h2 [-].
    kind : "monotone", "oscillatory", "divergent" or "converged" (|ε21| ≤ δ: f1 = f2 to round-off).
    order : Observed order p [-]; NaN unless monotone (not observable otherwise).
    extrapolated : Richardson-extrapolated value f_ext; f1 when converged; NaN otherwise.
    gci : Grid convergence index of the finest level, relative [-]; δ/|f1| when converged; NaN otherwise.
    uncertainty : GCI |f1|, the half-width of the uncertainty band of f1, in the quantity's unit; δ when
        converged.
    noise : The round-off floor δ used, in the quantity's unit.
    """

    spacings: tuple
    values: tuple
    ratio_fine: float
    ratio_coarse: float
    kind: str
    order: float
    extrapolated: float
    gci: float
    uncertainty: float
    noise: float = 0.0

    def as_dict(self) -> dict:
        """Plain data (for JSON and the study file)."""
        return asdict(self)


def _check_ratio(name: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 1.0):
        raise ValueError(f"{name} = {value!r}: a refinement ratio must be a finite number > 1")
    return value


def observed_order(
    fine: float,
    medium: float,
    coarse: float,
    ratio: float,
    ratio_coarse: float | None = None,
    *,
    tolerance: float = 1e-12,
    max_iterations: int = 200,
    noise: float | None = None,
) -> float:
    """Observed order of convergence from three levels.

    Parameters
    ----------
    fine, medium, coarse : f1, f2, f3 (finest first).
    ratio : r21 = h2/h1 > 1.
    ratio_coarse : r32 = h3/h2 > 1; ``ratio`` when None (constant refinement ratio, closed form).
    tolerance : Stop the fixed point when p changes by less than this (any ratios).
    max_iterations : Fixed-point iterations allowed (any ratios).
    noise : Round-off floor δ of the differences (absolute); ROUNDOFF · max |f| when None.

    Returns
    -------
    p [-]; NaN when the sequence is oscillatory (ε21/ε32 < 0), divergent (no positive p), or a difference is
    at round-off (|ε21| ≤ δ or |ε32| ≤ δ: no order is observable).

    Raises
    ------
    ValueError
        For a ratio ≤ 1 or not finite, or non-finite values.
    """
    r21 = _check_ratio("ratio", ratio)
    r32 = r21 if ratio_coarse is None else _check_ratio("ratio_coarse", ratio_coarse)
    values = np.array([fine, medium, coarse], dtype=float)
    if not np.all(np.isfinite(values)):
        raise ValueError(f"values {values.tolist()}: expected finite numbers")
    floor = roundoff_floor(values) if noise is None else float(noise)
    e21, e32 = medium - fine, coarse - medium
    if abs(e21) <= floor or abs(e32) <= floor or e32 / e21 <= 0.0:  # at round-off, or oscillatory
        return float("nan")
    quotient = e32 / e21
    if r32 == r21:
        p = math.log(quotient) / math.log(r21)
        return p if p > 0.0 else float("nan")
    # p ln r21 = ln(ε32/ε21) + q(p), q(p) = ln((r21^p − 1)/(r32^p − 1)); a fixed point from p = 1.
    p = 1.0
    for _ in range(max_iterations):
        q = math.log((r21**p - 1.0) / (r32**p - 1.0))
        updated = (math.log(quotient) + q) / math.log(r21)
        if not (math.isfinite(updated) and updated > 0.0):
            return float("nan")  # divergent: no positive order fits
        if abs(updated - p) < tolerance:
            return updated
        p = updated
    return float("nan")


def richardson(fine: float, medium: float, ratio: float, order: float) -> float:
    """Richardson-extrapolated value f1 + (f1 − f2)/(r^p − 1) for fine f1, medium f2, ratio r = h2/h1, order
    p."""
    r = _check_ratio("ratio", ratio)
    return float(fine + (fine - medium) / (r**order - 1.0))


def grid_convergence_index(
    fine: float, medium: float, ratio: float, order: float, safety_factor: float = SAFETY_FACTOR
) -> float:
    """Roache's grid convergence index of the fine level, relative: Fs |(f1 − f2)/f1| / (r^p − 1) [-].

    Raises
    ------
    ValueError
        When f1 = 0 (a relative index is undefined; use the absolute difference instead).
    """
    r = _check_ratio("ratio", ratio)
    if fine == 0.0:
        raise ValueError("fine = 0: the relative GCI is undefined for a zero value")
    return float(safety_factor * abs((fine - medium) / fine) / (r**order - 1.0))


def convergence(spacings, values, noise: float | None = None) -> ConvergenceResult:
    """Observed order, extrapolated value and GCI from the three finest levels of a sweep.

    Parameters
    ----------
    spacings : Refinement measure h of each level (any order), shape (L,), L ≥ 3, positive and distinct.
    values : Quantity at each level, shape (L,), finite.
    noise : Round-off floor δ (absolute, in the values' unit); ROUNDOFF · max(|f1|, |f2|, |f3|) when None.

    Raises
    ------
    ValueError
        For fewer than three levels, non-positive or repeated spacings, or non-finite values.
    """
    h = np.asarray(spacings, dtype=float)
    f = np.asarray(values, dtype=float)
    if h.ndim != 1 or h.shape != f.shape or h.size < 3:
        raise ValueError(
            f"need at least three levels with one value each, got spacings {h.shape}, values {f.shape}"
        )
    if not (np.all(np.isfinite(h)) and np.all(h > 0.0)):
        raise ValueError(f"spacings {h.tolist()}: expected finite positive numbers")
    if not np.all(np.isfinite(f)):
        raise ValueError(f"values {f.tolist()}: expected finite numbers")
    order_index = np.argsort(h)[:3]
    (h1, h2, h3), (f1, f2, f3) = h[order_index], f[order_index]
    if h1 == h2 or h2 == h3:
        raise ValueError(f"spacings {h.tolist()}: the three finest must be distinct")
    r21, r32 = h2 / h1, h3 / h2
    e21, e32 = f2 - f1, f3 - f2
    floor = roundoff_floor((f1, f2, f3)) if noise is None else float(noise)
    if not (math.isfinite(floor) and floor >= 0.0):
        raise ValueError(f"noise = {noise!r}: expected a finite number ≥ 0")
    nan = float("nan")
    order = extrapolated = gci = uncertainty = nan
    if abs(e21) <= floor:
        kind = "converged"
        extrapolated, uncertainty = float(f1), floor
        gci = floor / abs(f1) if f1 != 0.0 else nan
    elif abs(e32) <= floor or e21 / e32 < 0.0:
        kind = "oscillatory" if abs(e32) > floor else "divergent"
    else:
        order = observed_order(f1, f2, f3, r21, r32, noise=floor)
        kind = "monotone" if math.isfinite(order) else "divergent"
    if kind == "monotone":
        extrapolated = richardson(f1, f2, r21, order)
        if f1 != 0.0:
            gci = grid_convergence_index(f1, f2, r21, order)
            uncertainty = gci * abs(f1)
    return ConvergenceResult(
        spacings=(float(h1), float(h2), float(h3)),
        values=(float(f1), float(f2), float(f3)),
        ratio_fine=float(r21),
        ratio_coarse=float(r32),
        kind=kind,
        order=float(order),
        extrapolated=float(extrapolated),
        gci=float(gci),
        uncertainty=float(uncertainty),
        noise=float(floor),
    )


def fitted_order(spacings, values, limit: float) -> tuple[float, float]:
    """Least-squares slope and intercept of log|f − limit| against log h over every level (the fitted order).

    Parameters
    ----------
    spacings : h of each level, shape (L,), positive.
    values : f of each level, shape (L,).
    limit : The limit the values converge to (the exact value, or the Richardson-extrapolated one).

    Returns
    -------
    (slope, intercept): |f − limit| ≈ exp(intercept) h^slope. NaN when fewer than two levels differ from the
    limit.
    """
    h = np.asarray(spacings, dtype=float)
    error = np.abs(np.asarray(values, dtype=float) - float(limit))
    keep = (h > 0.0) & (error > 0.0) & np.isfinite(error)
    if np.count_nonzero(keep) < 2:
        return float("nan"), float("nan")
    slope, intercept = np.polyfit(np.log(h[keep]), np.log(error[keep]), 1)
    return float(slope), float(intercept)
