"""Verification of the needle–tissue coupling (issue 9, item 7) and the calibration of its equivalent radius.

Plane-strain and antiplane problems on thin 3-D slabs of Kuhn-split tets (top and bottom on rollers), solved
with the rest stiffness of :class:`~refsim.fem.tissue.TissueModel` and the coupling rows as plain arrays:

- a rigid cylinder pushed laterally in a clamped annulus (hole resolved by the mesh), against Baguelin, Frank
  and Saïd (1977): K′ = 8πG(1−ν)(3−4ν) / [(3−4ν)² ln(R/a) − (R²−a²)/(R²+a²)];
- the same cylinder pushed axially, against the antiplane solution K′_ax = 2πG / ln(R/a);
- an interference fit: the contact pressure against Lamé with the outer surface clamped, and the pull-out
  force of the friction law (Gauss–Seidel and exact) against dF/dL = 2π a μ p;
- a needle coupled to a disc slab that does not resolve it, lateral and axial: the well-posed ring coupling
  (:mod:`refsim.constraints.coupling`) converges to the closed forms above, the paper's bare line does not
  (its compliance grows like ln(1/h) at the slope the line-load solution predicts);
- the calibration of the equivalent radius of a coupling ring (:func:`ring_equivalent_radius`) on a box with
  the exact line-load field on its sides.

Tolerances: a mesh sequence refined by 2 gives the observed order p and the Grid Convergence Index of the
finest mesh, GCI = F_s |K_f − K_m| / (2^p − 1) with F_s = 1.25 (Roache 1994); a case passes when the closed
form lies within the GCI (plus, for the coupling, the spread of the calibrated equivalent radius).

The problems and closed forms are in :mod:`refsim.verification.coupling_problems`, the cases per physics in
:mod:`~refsim.verification.coupling_annulus` (a resolved hole), :mod:`~refsim.verification.coupling_rings`
(an unresolved needle: rings, bare line, calibration) and :mod:`~refsim.verification.coupling_surface` (the
8 mm needle on its surface); this module lists the cases (``CASES``) and re-exports their names.
"""

from __future__ import annotations

from collections.abc import Callable

from refsim.verification.coupling_annulus import (  # noqa: F401 (re-exported)
    case_antiplane_axial,
    case_baguelin_lateral,
    case_interference_pullout,
    interference_pullout,
)
from refsim.verification.coupling_problems import (  # noqa: F401 (re-exported)
    CALIBRATION_OFFSETS,
    COARSEST_ANGULAR,
    COUPLING_CELLS,
    NEEDLE_PAPER,
    NEEDLE_THIN,
    ORDER_TOLERANCE,
    OUTER,
    PAPER_TISSUE,
    annulus_slab,
    annulus_stiffness,
    antiplane_stiffness,
    baguelin_stiffness,
    calibrate_rings,
    coupled_stiffness,
    disc_slab,
    grid_convergence,
    ring_equivalent_radius,
)
from refsim.verification.coupling_rings import (  # noqa: F401 (re-exported)
    _calibration_tolerance,
    bare_line_compliance_slope,
    case_bare_line_lateral,
    case_coupling_axial,
    case_coupling_lateral,
    case_ring_calibration,
)
from refsim.verification.coupling_surface import (  # noqa: F401 (re-exported)
    SURFACE_POSITIONS,
    SurfaceStudy,
    case_surface_coupling,
    cylinder_radius_of,
    surface_coupling_results,
    surface_coupling_study,
    surface_offsets,
)
from refsim.verification.result import CaseResult

__all__ = [
    "CASES",
    "baguelin_stiffness",
    "antiplane_stiffness",
    "grid_convergence",
    "annulus_slab",
    "disc_slab",
    "ring_equivalent_radius",
    "calibrate_rings",
    "annulus_stiffness",
    "coupled_stiffness",
    "case_baguelin_lateral",
    "case_antiplane_axial",
    "case_interference_pullout",
    "case_coupling_lateral",
    "case_coupling_axial",
    "case_bare_line_lateral",
    "case_ring_calibration",
    "case_surface_coupling",
    "SURFACE_POSITIONS",
    "SurfaceStudy",
    "surface_coupling_study",
    "surface_coupling_results",
    "surface_offsets",
    "cylinder_radius_of",
]


CASES: list[Callable[[], CaseResult | list[CaseResult]]] = [
    case_baguelin_lateral,
    case_antiplane_axial,
    case_interference_pullout,
    case_coupling_lateral,
    case_coupling_axial,
    case_bare_line_lateral,
    case_ring_calibration,
    case_surface_coupling,
]
