"""An observed order of convergence against its theoretical value, with a band derived from the measurements.

Reference (the asymptotic expansion behind Richardson extrapolation; Roache, "Quantification of uncertainty in
computational fluid dynamics", Annu. Rev. Fluid Mech. 29, 1997): an error that behaves like

    e(h) = C h^p (1 + D h^q + o(h^q))

measured on levels h_k = h_0 / r^k has the observed orders p_k = log(e_k / e_(k+1)) / log r = p + δ_k, with
δ_k = −log_r[(1 + D h_k^q) / (1 + D h_k^q r^−q)] ≈ −D h_k^q (1 − r^−q) / ln r: the pre-asymptotic deviation
shrinks by r^−q per level. From three levels, δ_(k+1) = (p_k − p_(k+1)) / (r^q − 1) to first order in D h^q,
so the finest observed order must lie within

    F_s |p_(m−2) − p_(m−1)| / (r^q − 1) + (ρ_(m−2) + ρ_(m−1)) / ln r

of p, with F_s = 1.25 (Roache's factor of safety for a three-level study, which covers the second-order
terms) and ρ_k each error's relative round-off bound (an error computed to ρ e changes log e by ρ). The
orders tested are integers, so the band must also stay below 1/2: a wider one could not tell p from p ± 1,
and a sequence that far from its asymptote asserts nothing.
"""

from __future__ import annotations

import numpy as np

#: Roache's factor of safety for a three-level (or more) convergence study.
SAFETY_FACTOR = 1.25


def observed_orders(errors, refinement: float) -> np.ndarray:
    """p_k = log(e_k / e_(k+1)) / log r of successive levels, coarse to fine."""
    errors = np.asarray(errors, dtype=float)
    return np.log(errors[:-1] / errors[1:]) / np.log(refinement)


def order_band(errors, refinement: float, next_exponent: float, roundoff=0.0) -> float:
    """The band of the finest observed order around the theoretical one (module docstring).

    Parameters
    ----------
    errors : The errors, coarse to fine, at least three levels.
    refinement : r, the ratio of successive level sizes (> 1).
    next_exponent : q, the exponent of the expansion's next term relative to the leading one.
    roundoff : Each error's relative round-off bound ρ (a scalar or one per level).
    """
    errors = np.asarray(errors, dtype=float)
    assert errors.size >= 3, "the band needs three levels"
    orders = observed_orders(errors, refinement)
    rho = np.broadcast_to(np.asarray(roundoff, dtype=float), errors.shape)
    truncation = SAFETY_FACTOR * abs(orders[-2] - orders[-1]) / (refinement**next_exponent - 1.0)
    return float(truncation + (rho[-2] + rho[-1]) / np.log(refinement))


def assert_order(
    errors, refinement: float, order: float, next_exponent: float, roundoff=0.0, what=""
) -> None:
    """Assert that ``errors`` (coarse to fine) converge at ``order``: the finest observed order within
    :func:`order_band` of it, and that band below 1/2."""
    orders = observed_orders(errors, refinement)
    band = order_band(errors, refinement, next_exponent, roundoff)
    detail = f"{what}: errors {np.asarray(errors)}, observed orders {orders}, band {band:.3g}"
    assert band < 0.5, f"{detail}: too far from the asymptote to tell order {order} from its neighbours"
    assert abs(orders[-1] - order) <= band, f"{detail}: the finest order is not {order}"
