"""Observed order of the P1 tissue under mesh refinement, measured by refsim.sweep.convergence (slow).

The problem is the verification suite's manufactured solution (refsim.verification.tissue: u = a sin kx sin ky
sin kz on the paper's cube and material, exact Dirichlet data, the body force −div σ(u)) on 4, 8, 16 cells per
axis. The quantities are the relative errors in the energy norm and in L², which converge to 0.

Reference: Céa's lemma with the P1 interpolation error gives ‖u − u_h‖_a = O(h), the Aubin–Nitsche duality
argument ‖u − u_h‖_L² = O(h²) (Ciarlet 1978, theorems 3.2.2 and 3.2.5). Here the order is the three-level
observed order p = ln(ε32/ε21)/ln r of refsim.sweep.convergence (differences between levels, not errors
against 0), so the test checks the sweep's estimator on a sequence whose order theory gives.

Tolerance: the three-level order deviates from the asymptotic one by the relative size of the next term of the
error expansion, O(k h) at the coarsest mesh (k h = π/8, 0.4, over two halvings about 0.1 of the rate, as the
verification suite takes): |p − 2| ≤ 0.2, |p − 1| ≤ 0.1. The Richardson value must then be near the limit 0
(within 10 % of the finest error: the leading term removed) and Roache's GCI band of the finest level must
contain it.

A pointwise displacement (the cube's centre) was measured too and is not asserted: its observed order climbs
from 0.7 (8, 12, 16 cells) to 1.7 (16, 24, 32), the pre-asymptotic approach to O(h² |ln h|) (Scott 1976); a
fine enough sequence costs minutes.
"""

from __future__ import annotations

import pytest

from refsim.sweep import convergence

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def errors():
    from refsim.verification.tissue import manufactured_solution_errors

    return [manufactured_solution_errors(cells) for cells in (4, 8, 16)]


@pytest.mark.parametrize(
    ("column", "order", "tolerance"), [(1, 1.0, 0.1), (2, 2.0, 0.2)], ids=["energy norm, O(h)", "L2, O(h^2)"]
)
def test_observed_order_of_p1_errors(errors, column, order, tolerance):
    result = convergence([row[0] for row in errors], [row[column] for row in errors])
    assert result.kind == "monotone"
    assert abs(result.order - order) <= tolerance, result
    assert abs(result.extrapolated) <= 0.1 * result.values[0], result
    assert result.values[0] <= result.uncertainty, result
