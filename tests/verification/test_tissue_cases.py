"""The tissue verification cases (refsim.verification.tissue): each states its reference and tolerance."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.verification import tissue
from refsim.verification.result import CaseResult
from tests.observed_order import assert_order


def _results(case) -> list[CaseResult]:
    result = case()
    return result if isinstance(result, list) else [result]


@pytest.mark.parametrize("case", tissue.CASES, ids=lambda case: case.__name__)
def test_case_passes(case):
    # References and derived tolerances are stated in each case's docstring and CaseResult.reference.
    for result in _results(case):
        assert isinstance(result, CaseResult)
        assert result.reference
        assert np.isfinite(result.computed)
        assert result.passed, f"{result.name}: error {result.error:.3e} > tolerance {result.tolerance:.3e}"


def test_convergence_errors_decrease_at_p1_rates():
    """Céa: ‖u − u_h‖_a = O(h); Aubin–Nitsche: ‖u − u_h‖_L² = O(h²) (P1 on a smooth manufactured solution).

    Three levels, 4, 8, 16 cells (r = 2). The band of each finest observed order is derived from the three
    levels (tests/observed_order.py): the next term of either error is taken one power of h above the
    leading one (q = 1; for the energy error the P1 interpolant's next term, for the L² one the duality
    argument's), and the errors, computed by degree-4 quadrature of smooth integrands, carry round-off far
    below the truncation term (ρ = 0)."""
    rows = np.array([tissue.manufactured_solution_errors(cells) for cells in (4, 8, 16)])
    np.testing.assert_allclose(rows[:-1, 0] / rows[1:, 0], 2.0, rtol=1e-12)  # h halves
    assert_order(rows[:, 1], 2.0, order=1.0, next_exponent=1.0, what="energy-norm error")
    assert_order(rows[:, 2], 2.0, order=2.0, next_exponent=1.0, what="L2 error")


def test_uniaxial_compression_detects_a_wrong_modulus(monkeypatch):
    # The case must be able to fail: with E doubled in the model (not in the closed form) the reaction is off.
    doubled = tissue.HookeMaterial(youngs_modulus=1.0e6, poisson_ratio=0.4, density=1000.0)
    original = tissue.TissueModel

    def model_with_doubled_modulus(rest, tets, material, **kwargs):
        return original(rest, tets, doubled, **kwargs)

    monkeypatch.setattr(tissue, "TissueModel", model_with_doubled_modulus)
    results = tissue.case_uniaxial_compression()
    assert not results[0].passed


@pytest.mark.slow
def test_convergence_rates_on_finer_meshes():
    # Same references as case 5 on 6, 12, 24 cells per axis (82,944 tets on the finest; 32 cells would take
    # minutes in the sparse LU).
    for result in tissue.case_convergence_manufactured(cells=(6, 12, 24)):
        assert result.passed, f"{result.name}: rate {result.computed:.4f}"
