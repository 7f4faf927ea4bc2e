"""Coupling verification cases on a hole the mesh resolves: a rigid cylinder pushed laterally in a clamped
annulus against Baguelin, Frank and Saïd (1977), axially against the antiplane solution, and an interference
fit (Lamé pressure, pull-out force of the friction law). Tolerances: the observed order and the Grid
Convergence Index of a mesh sequence refined by 2
(:func:`~refsim.verification.coupling_problems.grid_convergence`).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import scipy.sparse as sp

from refsim.constraints.channel import interference_pressure
from refsim.fem.tissue import TissueModel
from refsim.materials import HookeMaterial
from refsim.solvers import ConstraintProblem, solve_exact, solve_gauss_seidel
from refsim.verification.coupling_problems import (
    COARSEST_ANGULAR,
    NEEDLE_PAPER,
    OUTER,
    PAPER_TISSUE,
    SlabResponse,
    annulus_slab,
    annulus_stiffness,
    antiplane_stiffness,
    baguelin_stiffness,
    grid_convergence,
    order_result,
    slab_dofs,
)
from refsim.verification.result import CaseResult

__all__ = [
    "case_baguelin_lateral",
    "case_antiplane_axial",
    "interference_pullout",
    "case_interference_pullout",
]


def _annulus_case(kind: str, exact: float, label: str, reference: str, inner: float) -> list[CaseResult]:
    angular = (COARSEST_ANGULAR, 2 * COARSEST_ANGULAR, 4 * COARSEST_ANGULAR)
    values = np.array([annulus_stiffness(kind, inner, OUTER, n) for n in angular])
    order, _, gci = grid_convergence(values)
    meshes = ", ".join(map(str, angular))
    return [
        CaseResult(
            name=f"{label} (a = {inner * 1e3:g} mm, R = {OUTER * 1e3:g} mm; {meshes} cells around)",
            reference=f"{reference}; tolerance GCI (F_s 1.25, observed order)",
            expected=exact,
            computed=float(values[-1]),
            error=abs(values[-1] - exact) / exact,
            tolerance=gci / values[-1],
            unit="N/m²",
        ),
        order_result(
            f"{label}: observed order ({meshes} cells around)",
            "compliance error O(h²) (P1, smooth solution): fitted p = log2 of successive differences",
            order,
        ),
    ]


def case_baguelin_lateral(inner: float = 4.0e-3) -> list[CaseResult]:
    """A rigid cylinder (bilateral rows on the hole nodes) pushed laterally in a clamped annulus, plane
    strain."""
    return _annulus_case(
        "lateral",
        baguelin_stiffness(PAPER_TISSUE, inner, OUTER),
        "rigid cylinder, lateral, clamped annulus",
        "K′ = 8πG(1−ν)(3−4ν)/[(3−4ν)² ln(R/a) − (R²−a²)/(R²+a²)] (Baguelin, Frank, Saïd 1977)",
        inner,
    )


def case_antiplane_axial(inner: float = 4.0e-3) -> list[CaseResult]:
    """The same cylinder pushed along its axis (antiplane shear)."""
    return _annulus_case(
        "axial",
        antiplane_stiffness(PAPER_TISSUE, inner, OUTER),
        "rigid cylinder, axial, clamped annulus",
        "K′_ax = 2πG / ln(R/a) (antiplane shear)",
        inner,
    )


@functools.lru_cache(maxsize=16)
def interference_pullout(
    angular: int,
    *,
    inner: float = NEEDLE_PAPER,
    interference: float = 0.1e-3,
    friction_coefficient: float = 0.2,
    layers: int = 2,
    material: HookeMaterial = PAPER_TISSUE,
):
    """Interference fit on a clamped annulus slab, then the cylinder pulled along its axis until it slips.

    The slab is periodic in z (top nodes identified with bottom nodes), so every level of the hole is the same
    (plane strain for the fit, antiplane for the pull, no end effect). Rows per hole node: radial and
    tangential bilateral rows (the channel of radius a − δ_r opened to a) and an axial shaft-friction row
    bounded by μ ‖(λ_r, λ_θ)‖. The pull is 100 times the largest stick displacement, so every node slips.

    Returns
    -------
    (pressure [Pa] from the radial multipliers, ((solver, pull-out force per unit length [N/m]), …))
    """
    radial = max(2, round(angular * math.log(OUTER / inner) / (2.0 * math.pi)))
    height = layers * 2.0 * math.pi * inner / angular
    positions, tets, rho = annulus_slab(inner, OUTER, radial, angular, layers, height)
    model = TissueModel(positions, tets, material)
    tol = 1e-9 * OUTER
    z = positions[:, 2]
    top = z > height - tol
    # Identify each top node with the bottom node below it.
    key = np.round(positions[:, :2] / tol).astype(np.int64)
    bottom = np.flatnonzero(z < tol)
    lookup = {tuple(k): n for k, n in zip(key[bottom], bottom, strict=False)}
    identify = np.arange(positions.shape[0])
    identify[top] = [lookup[tuple(k)] for k in key[top]]
    hole = np.flatnonzero((rho < inner + tol) & ~top)
    rim = np.flatnonzero(rho > OUTER - tol)
    fixed = slab_dofs(rim, [0, 1, 2])
    radial_dir = np.column_stack([positions[hole, 0], positions[hole, 1], np.zeros(hole.size)]) / inner
    tangential_dir = np.column_stack([-radial_dir[:, 1], radial_dir[:, 0], np.zeros(hole.size)])
    count = hole.size
    nodes = np.concatenate([hole, hole, hole])
    directions = np.concatenate([radial_dir, tangential_dir, np.tile([0.0, 0.0, 1.0], (count, 1))])
    row_count = nodes.size
    columns = 3 * nodes[:, None] + np.arange(3)
    rows = sp.csr_matrix(
        (directions.ravel(), (np.repeat(np.arange(row_count), 3), columns.ravel())),
        shape=(row_count, model.dof_count),
    )
    compliance = SlabResponse(model, fixed, np.zeros(model.dof_count), rows, identify).compliance
    free_gap = np.concatenate([np.full(count, interference), np.zeros(2 * count)])
    normal = np.linalg.solve(compliance[: 2 * count, : 2 * count], -free_gap[: 2 * count])
    pressure = float(-normal[:count].sum()) / (2.0 * math.pi * inner * height)
    axial_rows = np.arange(2 * count, 3 * count)
    bound = friction_coefficient * np.hypot(normal[:count], normal[count:])
    pull = 100.0 * float(np.abs(compliance[np.ix_(axial_rows, axial_rows)]).sum(axis=1).max() * bound.max())
    free_gap[axial_rows] = pull
    problem = ConstraintProblem(
        compliance=0.5 * (compliance + compliance.T),
        free_gap=free_gap,
        bilateral=np.arange(2 * count),
        shaft_friction=axial_rows,
        shaft_pairs=np.stack([np.arange(count), count + np.arange(count)], axis=1),
        shaft_friction_coefficient=np.full(count, friction_coefficient),
        name="interference pull-out",
    )
    forces = []
    for label, solve in (("gauss_seidel", solve_gauss_seidel), ("exact", solve_exact)):
        multipliers, _ = solve(problem, tolerance=1e-10)
        forces.append((label, float(np.abs(multipliers[axial_rows]).sum()) / height))
    return pressure, tuple(forces)


def case_interference_pullout(coarsest: int = 24) -> list[CaseResult]:
    """Interference fit: contact pressure against Lamé (clamped outer surface), then pull-out against 2π a μ
    p."""
    material, inner, interference, mu = PAPER_TISSUE, NEEDLE_PAPER, 0.1e-3, 0.2
    exact = interference_pressure(
        shear_modulus=material.shear_modulus,
        poisson_ratio=material.poisson_ratio,
        radius=inner,
        interference=interference,
        outer_radius=OUTER,
    )
    angular = (coarsest, 2 * coarsest, 4 * coarsest)
    runs = [
        interference_pullout(n, inner=inner, interference=interference, friction_coefficient=mu)
        for n in angular
    ]
    pressures = np.array([p for p, _ in runs])
    order, _, gci = grid_convergence(pressures)
    relative_gci = gci / pressures[-1]
    meshes = ", ".join(map(str, angular))
    results = [
        CaseResult(
            name=f"interference fit δ_r = {interference * 1e3:g} mm, a = {inner * 1e3:g} mm: pressure "
            f"({meshes} around)",
            reference="Lamé, plane strain, u_r(R) = 0: p = B(2(λ+G)/R² + 2G/a²), B = δ_r/(1/a − a/R²); tol. "
            "GCI",
            expected=exact,
            computed=float(pressures[-1]),
            error=abs(pressures[-1] - exact) / exact,
            tolerance=relative_gci,
            unit="Pa",
        ),
        order_result(
            f"interference fit pressure: observed order ({meshes} around)",
            "compliance error O(h²) (P1, smooth solution): fitted p = log2 of successive differences",
            order,
        ),
    ]
    expected_pull = 2.0 * math.pi * inner * mu * exact
    for solver, force in runs[-1][1]:
        # The law gives μ Σ‖λ_normal‖ exactly at full slip; the error is the pressure's, plus the solver's
        # tolerance.
        results.append(
            CaseResult(
                name=f"pull-out at full slip, μ = {mu:g}, {solver} ({angular[-1]} around)",
                reference="dF/dL = 2π a μ p (p from Lamé); tolerance: the pressure's GCI + 1e-6 (solver)",
                expected=expected_pull,
                computed=force,
                error=abs(force - expected_pull) / expected_pull,
                tolerance=relative_gci + 1e-6,
                unit="N/m",
            )
        )
    return results
