"""refsim.sweep.convergence on manufactured sequences whose order, limit and GCI are known in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest

from refsim.sweep import convergence, fitted_order, grid_convergence_index, observed_order, richardson
from refsim.sweep.convergence import ROUNDOFF


def _sequence(h, limit=2.0, constant=0.7, order=2.0, higher=0.0):
    h = np.asarray(h, dtype=float)
    return limit + constant * h**order + higher * h ** (order + 1)


@pytest.mark.parametrize("order", [1.0, 2.0, 1.5, 3.0])
def test_constant_ratio_recovers_order_and_limit(order):
    h = [0.1, 0.2, 0.4]
    f = _sequence(h, order=order)
    result = convergence(h, f)
    assert result.kind == "monotone"
    assert result.order == pytest.approx(order, rel=1e-10)
    assert result.extrapolated == pytest.approx(2.0, rel=1e-12)  # exact for f = f0 + C h^p
    assert result.ratio_fine == result.ratio_coarse == 2.0


def test_order_formula_of_roache():
    # p = ln((f3 - f2)/(f2 - f1)) / ln r, f1 finest
    f1, f2, f3, r = 1.01, 1.04, 1.16, 2.0
    assert observed_order(f1, f2, f3, r) == pytest.approx(math.log((f3 - f2) / (f2 - f1)) / math.log(r))


@pytest.mark.parametrize(
    ("h", "order"), [([0.1, 0.15, 0.3], 2.0), ([0.01, 0.013, 0.02], 1.3), ([0.2, 0.5, 0.6], 2.5)]
)
def test_general_ratios_recover_order(h, order):
    result = convergence(h, _sequence(h, order=order))
    assert result.ratio_fine != pytest.approx(result.ratio_coarse)
    assert result.order == pytest.approx(order, rel=1e-8)
    assert result.extrapolated == pytest.approx(2.0, rel=1e-10)


def test_levels_in_any_order_and_three_finest_used():
    h = [0.4, 0.05, 0.2, 0.1, 0.8]
    f = _sequence(h) + np.where(np.array(h) > 0.3, 5.0, 0.0)  # the coarse levels are wrong: ignored
    result = convergence(h, f)
    assert result.spacings == (0.05, 0.1, 0.2)
    assert result.order == pytest.approx(2.0)


def test_gci_is_roaches_formula():
    f1, f2, r, p = 1.01, 1.04, 2.0, 2.0
    expected = 1.25 * abs((f1 - f2) / f1) / (r**p - 1.0)
    assert grid_convergence_index(f1, f2, r, p) == pytest.approx(expected)
    result = convergence([0.1, 0.2, 0.4], [1.01, 1.04, 1.16])
    assert result.gci == pytest.approx(expected)
    assert result.uncertainty == pytest.approx(expected * 1.01)
    assert richardson(f1, f2, r, p) == pytest.approx(1.0)


def test_gci_band_contains_limit_with_higher_order_terms():
    # f = 2 + h^2 + 3 h^3: the observed order tends to 2 (off by about the relative size of the next term at
    # the coarsest level, 3 h3 = 0.3) and the band of the finest level holds the limit.
    h = np.array([0.025, 0.05, 0.1])
    result = convergence(h, _sequence(h, constant=1.0, higher=3.0))
    assert abs(result.order - 2.0) < 3.0 * h[-1]
    assert abs(result.values[0] - 2.0) <= result.uncertainty
    assert abs(result.extrapolated - 2.0) < abs(result.values[0] - 2.0)
    finer = convergence(h / 4, _sequence(h / 4, constant=1.0, higher=3.0))
    assert abs(finer.order - 2.0) < abs(result.order - 2.0)


def test_oscillatory_divergent_converged():
    assert convergence([1, 2, 4], [1.0, 1.1, 0.9]).kind == "oscillatory"
    assert math.isnan(convergence([1, 2, 4], [1.0, 1.1, 0.9]).order)
    assert convergence([1, 2, 4], [1.0, 1.5, 1.6]).kind == "divergent"
    assert convergence([1, 2.5, 3], [1.0, 1.5, 1.5001]).kind == "divergent"  # unequal ratios, no p > 0
    converged = convergence([1, 2, 4], [3.0, 3.0, 3.5])
    assert converged.kind == "converged" and converged.extrapolated == 3.0
    # its uncertainty is the round-off floor δ = ROUNDOFF · max |f| (here 3.5e-12), not zero
    assert converged.uncertainty == converged.noise == ROUNDOFF * 3.5
    assert converged.gci == pytest.approx(ROUNDOFF * 3.5 / 3.0, rel=1e-15)


def test_a_difference_at_round_off_gives_no_order():
    # f(h) = 1 + h² at h = 1/8, 1/4, 1/2 with the finest two levels made equal to within a few ulp: the order
    # from ln(ε32/ε21) would be ln(0.1875/4.4e-16)/ln 2 ≈ 48, a number of the round-off, not of the scheme.
    h = np.array([0.125, 0.25, 0.5])
    f = 1.0 + h**2
    f[0] = f[1] - 2.0 * np.spacing(f[1])
    assert math.isfinite(math.log((f[2] - f[1]) / (f[1] - f[0])) / math.log(2.0))  # the order it used to give
    result = convergence(h, f)
    assert result.kind == "converged" and math.isnan(result.order)
    assert result.extrapolated == f[0] and result.uncertainty == ROUNDOFF * f[2]
    assert math.isnan(observed_order(f[0], f[1], f[2], 2.0))
    # the same sequence with the floor set below the difference: an observation again (monotone, p ≈ 48)
    assert convergence(h, f, noise=0.0).kind == "monotone"
    # the coarse difference at round-off with the fine one not: no order either (divergent)
    g = np.array([1.0 + 1e-6, 1.0, 1.0 + 1e-14])
    assert convergence(h, g).kind == "divergent" and math.isnan(convergence(h, g).order)
    # the exact quadratic, well above the floor, still gives p = 2
    assert convergence(h, 1.0 + h**2).order == pytest.approx(2.0, abs=1e-12)
    with pytest.raises(ValueError, match="noise"):
        convergence(h, f, noise=-1.0)


def test_fitted_order_over_all_levels():
    h = np.array([0.01, 0.02, 0.04, 0.08, 0.16])
    slope, intercept = fitted_order(h, _sequence(h, constant=0.7, order=1.5), 2.0)
    assert slope == pytest.approx(1.5)
    assert math.exp(intercept) == pytest.approx(0.7)
    assert math.isnan(fitted_order(h, np.full(5, 2.0), 2.0)[0])


@pytest.mark.parametrize(
    ("spacings", "values", "message"),
    [
        ([0.1, 0.2], [1.0, 2.0], "three levels"),
        ([0.1, 0.1, 0.2], [1.0, 2.0, 3.0], "distinct"),
        ([0.1, -0.2, 0.3], [1.0, 2.0, 3.0], "positive"),
        ([0.1, 0.2, 0.3], [1.0, np.nan, 3.0], "finite"),
    ],
)
def test_bad_input_is_named(spacings, values, message):
    with pytest.raises(ValueError, match=message):
        convergence(spacings, values)


def test_bad_ratio_is_named():
    with pytest.raises(ValueError, match="ratio"):
        observed_order(1.0, 2.0, 3.0, 1.0)
    with pytest.raises(ValueError, match="zero value"):
        grid_convergence_index(0.0, 1.0, 2.0, 2.0)
