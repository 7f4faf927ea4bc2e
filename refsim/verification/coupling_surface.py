"""Coupling verification case of the paper's 8 mm needle coupled on its surface (h ≤ r on 16, 32, 64 cells):
an observed order, lateral and axial, at entry positions spread over the cell (a Halton sequence).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from refsim.constraints.coupling import (
    equivalent_radius,
)
from refsim.materials import HookeMaterial
from refsim.sweep.convergence import ConvergenceResult, convergence, observed_order
from refsim.verification.coupling_problems import (
    COUPLING_CELLS,
    NEEDLE_PAPER,
    ORDER_TOLERANCE,
    OUTER,
    PAPER_TISSUE,
    antiplane_stiffness,
    baguelin_stiffness,
    coupled_stiffness,
)
from refsim.verification.result import CaseResult

__all__ = [
    "SURFACE_POSITIONS",
    "SurfaceStudy",
    "surface_coupling_study",
    "cylinder_radius_of",
    "surface_offsets",
    "surface_coupling_results",
    "case_surface_coupling",
]


# ------------------------------------------------------- the 8 mm needle coupled on its surface (h ≤ r)
def _halton(index: int, base: int) -> float:
    value, scale = 0.0, 1.0
    while index > 0:
        scale /= base
        value += scale * (index % base)
        index //= base
    return value


#: Positions of the centreline in its cell (units of h) over which the surface coupling is averaged: the first
#: eight points of the Halton sequence in bases 2 and 3 (spread over the cell, none on its symmetry points).
SURFACE_POSITIONS = tuple((_halton(i, 2), _halton(i, 3)) for i in range(1, 9))


@dataclass(frozen=True)
class SurfaceStudy:
    """The 8 mm needle in the clamped disc slab with h ≤ r on every level (the ring on the needle's surface).

    Attributes
    ----------
    kind : "lateral" or "axial". needle_radius : r [m]. cells : Cells across, coarse to fine.
    exact : The closed form K′ [N/m²] (Baguelin et al. 1977, lateral; 2πG/ln(R/r), axial).
    bare : K′ [N/m²] of the bare surface coupling (no sub-grid compliance), shape (levels, positions).
    model : K′ [N/m²] of the model (ring with its sub-grid compliance, the default), same shape.
    convergence : Observed order, Richardson value and GCI of the position mean of ``bare``.
    predicted : K′ [N/m²] of a rigid cylinder of the calibrated equivalent radius a_c(ρ = r, h) (the table
        RING_EQUIVALENT_RADIUS), per level: what the bare surface coupling should give, before averaging.
    predicted_order : The observed order of ``predicted`` (→ 1 as h → 0).
    """

    kind: str
    needle_radius: float
    cells: tuple
    exact: float
    bare: np.ndarray
    model: np.ndarray
    convergence: ConvergenceResult
    predicted: np.ndarray
    predicted_order: float


def surface_coupling_study(
    kind: str,
    cells=COUPLING_CELLS,
    *,
    needle_radius: float = NEEDLE_PAPER,
    positions=SURFACE_POSITIONS,
    outer: float = OUTER,
    material: HookeMaterial = PAPER_TISSUE,
) -> SurfaceStudy:
    """K′ of a needle coupled on its surface (h ≤ r) in the clamped disc slab, with and without sub-grid term.

    Once h ≤ r the ring lies on the needle's surface (ρ_c = r) and behaves like a rigid cylinder of radius
    a_c ≈ r + 0.25 h: the bare surface coupling (C = 0) converges at order 1 to the closed form from above;
    the model's sub-grid term ln(a_c/r) removes that O(h) offset with the calibrated a_c, leaving the a_c's
    dependence on where the ring crosses the cells (not a smooth function of h). Each level is the mean over
    ``positions`` of the centreline in its cell (one factorisation per level and kind).

    Raises
    ------
    ValueError
        For a kind other than lateral/axial, fewer than three levels, or a level with h > r.
    """
    if kind not in ("lateral", "axial"):
        raise ValueError(f"kind = {kind!r}; valid: 'lateral', 'axial'")
    cells = tuple(int(n) for n in cells)
    sizes = np.array([2.0 * outer / n for n in cells])
    if len(cells) < 3 or np.any(sizes > needle_radius):
        raise ValueError(
            f"cells = {cells}: need three or more levels with h = 2R/cells ≤ r = {needle_radius} m "
            f"(h = {sizes.tolist()} m)"
        )
    closed_form = baguelin_stiffness if kind == "lateral" else antiplane_stiffness
    exact = closed_form(material, needle_radius, outer)
    values = {}
    for subgrid in (False, True):
        values[subgrid] = np.array(
            [
                [
                    coupled_stiffness(
                        kind,
                        "ring",
                        needle_radius=needle_radius,
                        outer=outer,
                        cells=n,
                        offset=tuple(o),
                        material=material,
                        surface_subgrid=subgrid,
                    )
                    for o in positions
                ]
                for n in cells
            ]
        )
    predicted = np.array(
        [closed_form(material, float(equivalent_radius(needle_radius, h, kind)), outer) for h in sizes]
    )
    result = convergence(sizes, values[False].mean(axis=1))
    predicted_order = observed_order(
        predicted[-1], predicted[-2], predicted[-3], sizes[-2] / sizes[-1], sizes[-3] / sizes[-2]
    )
    return SurfaceStudy(
        kind, needle_radius, cells, exact, values[False], values[True], result, predicted, predicted_order
    )


def cylinder_radius_of(
    kind: str, stiffness: float, outer: float = OUTER, material: HookeMaterial = PAPER_TISSUE
) -> float:
    """The radius a [m] of the rigid cylinder whose closed-form K′ (clamped at R) is ``stiffness`` [N/m²].

    Inverts :func:`baguelin_stiffness` (lateral, increasing in a; bisection) or :func:`antiplane_stiffness`
    (axial, a = R exp(−2πG/K′)). Used to read a coupling's stiffness as an equivalent radius.
    """
    from scipy.optimize import brentq

    if kind == "axial":
        return outer * math.exp(-2.0 * math.pi * material.shear_modulus / stiffness)
    if kind != "lateral":
        raise ValueError(f"kind = {kind!r}; valid: 'lateral', 'axial'")
    return float(
        brentq(
            lambda a: baguelin_stiffness(material, a, outer) - stiffness,
            1e-9 * outer,
            (1.0 - 1e-9) * outer,
            xtol=1e-15 * outer,
        )
    )


def surface_offsets(study: SurfaceStudy, outer: float = OUTER) -> tuple[np.ndarray, np.ndarray]:
    """The rings' measured offsets (a − r)/h per level and position, of the bare surface coupling and of the
    model (for the model, the residual offset after its sub-grid term), shape (levels, positions) each."""
    sizes = np.array([2.0 * outer / n for n in study.cells])[:, None]

    def offsets(values):
        radii = np.vectorize(lambda k: cylinder_radius_of(study.kind, k, outer))(values)
        return (radii - study.needle_radius) / sizes

    return offsets(study.bare), offsets(study.model)


def surface_coupling_results(study: SurfaceStudy) -> list[CaseResult]:
    """The three checks of a :class:`SurfaceStudy`.

    1. The Richardson value of the bare surface coupling against the closed form; tolerance the GCI of the
       finest level (Roache, F_s = 1.25, observed order).
    2. The observed order against the order of the calibrated cylinder K′(a_c(r, h)) (→ 1); tolerance 15 %
       (ORDER_TOLERANCE, the asymptotic range).
    3. The model (with the sub-grid term) on the finest level, at every position, inside the GCI band of that
       Richardson value: error max |K′_model − K′_ext| / K′_ext, tolerance GCI |K′_f| / K′_ext.
    """
    result = study.convergence
    r_mm, kind = study.needle_radius * 1e3, study.kind
    meshes = ", ".join(map(str, study.cells))
    where = f"{len(study.bare[0])} positions, {meshes} cells"
    formula = "K′ Baguelin et al. 1977" if kind == "lateral" else "K′_ax = 2πG/ln(R/r)"
    extrapolated = result.extrapolated
    band = result.uncertainty / extrapolated if result.kind == "monotone" else math.nan
    order_error = (
        abs(result.order - study.predicted_order) / study.predicted_order
        if result.kind == "monotone"
        else math.inf
    )
    spread = float(np.max(np.abs(study.model[-1] - extrapolated)) / extrapolated)
    return [
        CaseResult(
            name=f"needle r = {r_mm:g} mm on its surface, no sub-grid term, {kind}: Richardson ({where})",
            reference=f"{formula}; tolerance GCI of the finest level (F_s 1.25, observed order)",
            expected=study.exact,
            computed=extrapolated,
            error=abs(extrapolated - study.exact) / study.exact,
            tolerance=result.gci,
            unit="N/m²",
        ),
        CaseResult(
            name=f"needle r = {r_mm:g} mm on its surface, no sub-grid term, {kind}: observed order",
            reference=(
                "order of K′(a_c), a_c = r + c h from RING_EQUIVALENT_RADIUS (→ 1: the ring's O(h) offset); "
                "tol. 15 %"
            ),
            expected=study.predicted_order,
            computed=result.order,
            error=order_error,
            tolerance=ORDER_TOLERANCE,
        ),
        CaseResult(
            name=f"needle r = {r_mm:g} mm, ring coupling (default), {kind}: {study.cells[-1]} cells, every "
            "position in that GCI band",
            reference=(
                "the Richardson value above ± GCI |K′_f|; error max over positions |K′ − K′_ext| / K′_ext"
            ),
            expected=extrapolated,
            computed=float(study.model[-1].mean()),
            error=spread,
            tolerance=band,
            unit="N/m²",
        ),
    ]


def case_surface_coupling() -> list[CaseResult]:
    """The paper's 8 mm needle coupled on its surface (h ≤ r on 16, 32, 64 cells): an observed order, lateral
    and axial."""
    return [
        *surface_coupling_results(surface_coupling_study("lateral")),
        *surface_coupling_results(surface_coupling_study("axial")),
    ]
