"""Needle verification: cantilevers against closed forms and the elastica (refsim.verification.needle)."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.verification.needle import (
    CASES,
    case_cantilever_elastica,
    case_cantilever_small_load,
    case_rigid_motions,
    elastica_convergence,
    elastica_tip_displacement,
    needle_cantilever,
)
from refsim.verification.result import CaseResult


@pytest.mark.parametrize("element_count", [1, 4, 7])
def test_small_load_cantilever_is_exact_at_any_element_count(element_count):
    # Reference: δ = P L³/(3 E I) + P L/(κ G A) (Timoshenko; Przemieniecki's element is exact for a
    # point load).
    # δ/L = 1e-6 makes the geometric non-linearity 1e-12; tolerance 1e-8 (see the case's docstring).
    case = case_cantilever_small_load(element_count)
    assert case.passed, case


def test_small_load_cantilever_in_three_dimensions():
    # A tip force (0, Py, Pz) deflects the tip by (0, Py, Pz) · (L³/(3EI) + L/(κGA)) (linear, isotropic
    # section);
    # tolerance 1e-8 of δ as in the small-load case.
    length, radius, e, nu = 0.1, 4e-4, 1e11, 0.4
    area, inertia = np.pi * radius**2, np.pi * radius**4 / 4
    kappa, g = 6 * (1 + nu) / (7 + 6 * nu), e / (2 * (1 + nu))
    compliance = length**3 / (3 * e * inertia) + length / (kappa * g * area)
    force = np.array([0.0, 0.6, -0.8]) * 1e-6 * length / compliance
    result = needle_cantilever(
        force, length=length, radius=radius, youngs_modulus=e, poisson_ratio=nu, element_count=3
    )
    assert result.converged
    expected = force * compliance
    assert np.allclose(
        result.tip_displacement[1:], expected[1:], rtol=0, atol=1e-8 * np.linalg.norm(expected)
    )
    # Second order: the tip moves back by ∫ ½ y'² ds = (3/5) δ²/L for the cubic deflection (shear is 4e-5 of
    # δ here); 1 % tolerance.
    shortening = 0.6 * np.linalg.norm(expected) ** 2 / length
    assert result.tip_displacement[0] == pytest.approx(-shortening, rel=1e-2)


def test_axial_load_stretches_by_pl_over_ea():
    # Reference: u = P L/(E A) for an axial tip force; linear in the co-rotational model up to the Newton
    # tolerance.
    length, radius, e = 0.2, 1e-3, 2e11
    force = 10.0
    result = needle_cantilever(
        np.array([force, 0.0, 0.0]),
        length=length,
        radius=radius,
        youngs_modulus=e,
        poisson_ratio=0.3,
        element_count=5,
    )
    expected = force * length / (e * np.pi * radius**2)
    assert result.tip_displacement[0] == pytest.approx(expected, rel=1e-8)


def test_elastica_bvp_reproduces_bisshopp_drucker():
    # Reference: Bisshopp & Drucker, "Large deflection of cantilever beams", Q. Appl. Math. 3 (1945) 272,
    # table of the inextensible elastica under a tip load: P L²/(E I) = 1: δ/L = 0.30172, (L − x)/L = 0.05643;
    # 3: 0.60325, 0.25442; 10: 0.81061, 0.55500. The table has 5 decimals: tolerance 1e-5.
    table = {1.0: (0.30172, 0.05643), 3.0: (0.60325, 0.25442), 10.0: (0.81061, 0.55500)}
    for load, (deflection, shortening) in table.items():
        dx, dy = elastica_tip_displacement(load)
        assert -dy == pytest.approx(deflection, abs=1e-5)
        assert -dx == pytest.approx(shortening, abs=1e-5)


def test_shearable_elastica_reduces_to_timoshenko_at_small_load():
    # Reference: for k = P L²/(EI) → 0 the Reissner rod gives δ/L = k (1/3 + c_s); the non-linear correction
    # is O(k³) ≈ 1e-9 relative at k = 1e-4.
    k, shear = 1e-4, 0.02
    _, dy = elastica_tip_displacement(k, shear_compliance=shear, axial_compliance=0.01)
    assert -dy == pytest.approx(k * (1 / 3 + shear), rel=1e-7)


@pytest.mark.parametrize("load", [1.0, 10.0])
def test_large_load_cantilever_converges_to_the_elastica_at_second_order(load):
    # Reference: Reissner's elastica (BVP, scipy solve_bvp) with the needle's E A and κ G A. The two-node
    # co-rotational element converges at second order: fitted rate 2 ± 0.15 over n = 8, 16, 32, and the error
    # at n = 32 below 1e-3 L (measured ≈ 1e-4 L at P L²/EI = 10).
    data = elastica_convergence(load, (8, 16, 32))
    rate = -np.polyfit(np.log(data["element_counts"]), np.log(data["errors"]), 1)[0]
    assert rate == pytest.approx(2.0, abs=0.15)
    assert data["errors"][-1] < 1e-3
    # Newton with the consistent tangent: a handful of iterations per load step.
    assert np.all(data["newton_iterations"] <= 10 * max(1, int(np.ceil(load / 2))))


def test_elastica_cases_pass_with_derived_tolerance():
    # Tolerance: twice the Richardson estimate of the O(h²) discretisation error (see the case's docstring).
    cases = case_cantilever_elastica(load_parameters=(3.0,), element_count=16)
    assert len(cases) == 1 and all(case.passed for case in cases), cases


def test_rigid_motion_cases_pass():
    cases = case_rigid_motions()
    assert len(cases) == 2 and all(case.passed for case in cases), cases


def test_cases_registry_returns_case_results():
    assert len(CASES) == 3 and all(callable(case) for case in CASES)
    result = CASES[0]()
    assert isinstance(result, CaseResult)


def test_cantilever_rejects_bad_input():
    with pytest.raises(ValueError, match="tip_force"):
        needle_cantilever(
            [1.0, 2.0], length=0.1, radius=1e-3, youngs_modulus=1e11, poisson_ratio=0.3, element_count=4
        )
    with pytest.raises(ValueError, match="element_count"):
        needle_cantilever(
            [0.0, 1.0, 0.0], length=0.1, radius=1e-3, youngs_modulus=1e11, poisson_ratio=0.3, element_count=0
        )
    with pytest.raises(ValueError, match="load_steps"):
        needle_cantilever(
            [0.0, 1.0, 0.0],
            length=0.1,
            radius=1e-3,
            youngs_modulus=1e11,
            poisson_ratio=0.3,
            element_count=4,
            load_steps=0,
        )
