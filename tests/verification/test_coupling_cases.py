"""The coupling verification cases (refsim.verification.coupling): each states its reference and tolerance."""

from __future__ import annotations

import math

import numpy as np
import pytest

from refsim.verification import coupling
from refsim.verification.result import CaseResult


@pytest.mark.parametrize("case", coupling.CASES, ids=lambda case: case.__name__)
def test_case_passes(case):
    for result in case():
        assert isinstance(result, CaseResult)
        assert result.reference
        assert np.isfinite(result.computed)
        assert result.passed, f"{result.name}: error {result.error:.3e} > tolerance {result.tolerance:.3e}"


def test_bare_line_fails_baguelin_where_the_ring_coupling_passes():
    # The paper's line: its error against K′(R, r) exceeds the ring coupling's derived tolerance on every
    # mesh, and its force keeps falling with h (1/ln h): no limit. The ring coupling's error is within
    # tolerance.
    exact = coupling.baguelin_stiffness(coupling.PAPER_TISSUE, coupling.NEEDLE_PAPER, coupling.OUTER)
    tolerance = coupling._calibration_tolerance("lateral", coupling.PAPER_TISSUE, exact) / exact
    bare = np.array(
        [
            coupling.coupled_stiffness(
                "lateral", "paper", needle_radius=coupling.NEEDLE_PAPER, outer=coupling.OUTER, cells=n
            )
            for n in coupling.COUPLING_CELLS
        ]
    )
    assert np.all(np.abs(bare - exact) / exact > 10 * tolerance)
    assert np.all(np.diff(bare) < 0.0)
    # The fitted slope of 1/K′ against ln h is the line-load theory's (case_bare_line_lateral), and the bare
    # line's equivalent radius c = a_eq/h from K′ = Baguelin(R, c h) is one constant over the meshes.
    sizes = 2 * coupling.OUTER / np.array(coupling.COUPLING_CELLS)
    nu, g = coupling.PAPER_TISSUE.poisson_ratio, coupling.PAPER_TISSUE.shear_modulus
    k = 3 - 4 * nu
    ratios = []
    for stiffness, h in zip(bare, sizes, strict=True):
        # Invert Baguelin for a: k² ln(R/a) − (R²−a²)/(R²+a²) = 8πG(1−ν)k / K′ (fixed point, a ≪ R).
        target = 8 * math.pi * g * (1 - nu) * k / stiffness
        a = 0.5 * h
        for _ in range(50):
            a = coupling.OUTER * math.exp(
                -(target + (coupling.OUTER**2 - a**2) / (coupling.OUTER**2 + a**2)) / k**2
            )
        ratios.append(a / h)
    assert max(ratios) / min(ratios) - 1 < 0.02


def test_grid_convergence_of_an_exact_sequence():
    # f_h = 1 + h²: order 2, Richardson value 1.
    values = 1 + np.array([1.0, 0.25, 0.0625])
    order, extrapolated, gci = coupling.grid_convergence(values)
    assert order == pytest.approx(2.0)
    assert extrapolated == pytest.approx(1.0)
    assert gci == pytest.approx(1.25 * (0.25 - 0.0625) / 3)
    assert math.isnan(coupling.grid_convergence(np.array([1.0, 2.0, 1.0]))[0])
