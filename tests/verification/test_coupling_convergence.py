"""The needle's reaction in the paper's cube under refinement (issue 9, item 2), ring coupling.

A rigid needle inserted 40 mm (rows every 0.5 mm) into the clamped 100 mm cube, stuck, translated sideways or
along its axis: K = gᵀ(W + C)⁻¹g on 6, 12, 24 cells per axis (h = 16.7, 8.33, 4.17 mm;
:func:`refsim.verification.coupling_3d.cube_needle_stiffness`, C the sub-grid compliance of the rows).
Reference: none in closed form (a 3-D problem); the test asserts Roache's observed order of the three levels,
p = log2(ε₃₂/ε₂₁) ≥ 0.5 (a logarithmic drift, the bare line's in the limit, gives ε₃₂/ε₂₁ → 1, p → 0), and a
grid convergence index of the finest level below 5 %, and reports the Richardson value.

Both sub-grid models (``insertion.subgrid_line``): "infinite" (default; key "ring-infinite") and "finite"
("ring"). Measured (docs/coupling.md): the thin needle converges with both, except the finite model's axial
stiffness; the 8 mm needle does not on these meshes (they cross h = r). Those cases are strict expected
failures, so that a fix shows.

The 8 mm needle with h ≤ r on every level (the ring on the needle's surface) converges: in the clamped disc
slab against the closed forms (32, 64, 128 cells across) and in 3-D in a 40 mm clamped box (8, 16, 32
cells), both averaged over 8 centreline positions in the cell (the tests at the end).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from refsim.sweep.convergence import convergence, grid_convergence_index, observed_order, richardson
from refsim.verification import coupling, coupling_3d

pytestmark = pytest.mark.slow

SURFACE_CELLS_FINE = (32, 64, 128)  # levels of the plane-strain slab (h = 3.125, 1.5625, 0.78125 mm)
CUBE_CELLS = (6, 12, 24)  # cells per axis of the clamped 100 mm cube (h = 16.7, 8.33, 4.17 mm)


def _check(key):
    coarse, medium, fine = (coupling_3d.cube_needle_stiffness(n)[key] for n in CUBE_CELLS)
    order = observed_order(fine, medium, coarse, 2.0)
    print(f"\n{key}: K = {coarse:.1f}, {medium:.1f}, {fine:.1f} N/m, p = {order:.2f}")
    assert math.isfinite(order) and order >= 0.5
    extrapolated = richardson(fine, medium, 2.0, order)
    gci = grid_convergence_index(fine, medium, 2.0, order)
    print(f"Richardson {extrapolated:.1f} N/m, GCI {gci:.2%}")
    assert gci < 0.05


def _failing(reason):
    return pytest.mark.xfail(strict=True, reason=reason)


THIN, PAPER = coupling.NEEDLE_THIN, coupling.NEEDLE_PAPER
CROSSING = (
    "the ring is at ρ_c = h on 6 and 12 cells and at r on 24 (h < r): the sequence crosses h = r "
    "(with h < r on every level it converges: test_8mm_needle_in_a_clamped_box_…)"
)
CASES = [
    pytest.param(("ring-infinite", THIN, "lateral"), id="infinite-thin-lateral"),
    pytest.param(("ring-infinite", THIN, "axial"), id="infinite-thin-axial"),
    pytest.param(("ring", THIN, "lateral"), id="finite-thin-lateral"),
    pytest.param(
        ("ring", THIN, "axial"),
        id="finite-thin-axial",
        marks=_failing("K = 10781, 10590, 10417 N/m: ε₃₂/ε₂₁ = 1.1 (p = 0.15), 1.6 % per halving"),
    ),
    pytest.param(
        ("ring-infinite", PAPER, "lateral"),
        id="infinite-8mm-lateral",
        marks=_failing(f"K = 11949, 12163, 12023 N/m, not monotone: {CROSSING}"),
    ),
    pytest.param(
        ("ring", PAPER, "lateral"),
        id="finite-8mm-lateral",
        marks=_failing(f"K = 12706, 12564, 12252 N/m, ε₂₁ > ε₃₂: {CROSSING}"),
    ),
]


@pytest.mark.parametrize("key", CASES)
def test_needle_stiffness_converges_at_an_observed_order(key):
    _check(key)


# ------------------------------------------------------------ the 8 mm needle on its surface, 2-D (h ≤ r)
@pytest.mark.parametrize("kind", ["lateral", "axial"])
def test_8mm_needle_on_its_surface_converges_in_the_slab(kind):
    """The clamped disc slab (R = 50 mm) on 32, 64, 128 cells across (h = 3.1 … 0.78 mm < r = 8 mm), mean
    over 8 centreline positions. Reference: Baguelin et al. (1977) lateral, 2πG/ln(R/r) axial. The bare
    surface coupling (no sub-grid term) converges at the order of the calibrated cylinder K′(a_c = r + c h)
    (→ 1, within 15 %), its Richardson value equals the closed form within the GCI of the finest level, and
    the default model lies, at every position, inside that GCI band
    (refsim.verification.coupling.surface_coupling_results).
    """
    study = coupling.surface_coupling_study(kind, SURFACE_CELLS_FINE)
    result = study.convergence
    bare = ", ".join(f"{v:.5f}" for v in study.bare.mean(axis=1) / study.exact)
    print(
        f"\n{kind}: bare mean K′/K′_th = {bare}, "
        f"p = {result.order:.3f} (predicted {study.predicted_order:.3f}), Richardson "
        f"{result.extrapolated / study.exact:.5f}, GCI {result.gci:.2%}; model "
        f"{', '.join(f'{v:.5f}' for v in study.model.mean(axis=1) / study.exact)}"
    )
    assert result.kind == "monotone"
    for check in coupling.surface_coupling_results(study):
        assert check.passed, f"{check.name}: error {check.error:.3e} > tolerance {check.tolerance:.3e}"
    # The default has no observed order at one position, but its worst error over the positions (the
    # calibration's position spread) falls at every refinement, and stays below the bare coupling's best.
    worst = np.max(np.abs(study.model / study.exact - 1.0), axis=1)
    best_bare = np.min(np.abs(study.bare / study.exact - 1.0), axis=1)
    print(f"default's worst error over positions {', '.join(f'{w:.2%}' for w in worst)}")
    assert np.all(np.diff(worst) < 0.0)
    assert np.all(worst < best_bare)


# ------------------------------------------------ the 8 mm needle on its surface, 3-D (h ≤ r on every level)
@pytest.fixture(scope="module")
def box():
    return coupling_3d.box_surface_study()


@pytest.mark.parametrize("kind", ["lateral", "axial"])
def test_8mm_needle_in_a_clamped_box_converges_with_h_below_r(box, kind):
    """A rigid 8 mm needle inserted 20 mm at the centre of a 40 mm box (bottom and sides clamped), 8, 16, 32
    cells per axis (h = 5, 2.5, 1.25 mm < r), mean over 8 entry positions in the cell. Reference: no closed
    form (3-D); the bare surface coupling (no sub-grid term: its error is the ring's O(h) offset) must
    converge at an observed order (monotone, p ≥ 0.5), and its Richardson value ± its GCI (F_s 1.25) is the
    reference band.
    Both models ("infinite", the default, and "finite") must fall monotonically over the three levels and lie,
    at every position of the finest level, in that band. Their own observed order is printed, not asserted:
    on 8, 16, 32 cells it is 1.02 and 1.00 (lateral), but with the levels 12 and 24 added the default's
    successive differences are no power law (divergent on 12, 16, 24; docs/coupling.md): what is left after
    its sub-grid term is the calibration's position spread.
    """
    sizes = coupling_3d.BOX_SIZE / np.array(coupling_3d.BOX_CELLS)
    bare = convergence(sizes, box[("surface", kind)].mean(axis=1))
    levels = ", ".join(f"{v:.1f}" for v in bare.values[::-1])
    print(
        f"\n{kind}: surface K = {levels} N/m, p = {bare.order:.3f}, "
        f"Richardson {bare.extrapolated:.1f} ± {bare.uncertainty:.1f} N/m (GCI {bare.gci:.2%})"
    )
    assert bare.kind == "monotone" and bare.order >= 0.5
    for model in ("ring-infinite", "ring"):
        values = box[(model, kind)]
        result = convergence(sizes, values.mean(axis=1))
        levels = ", ".join(f"{v:.1f}" for v in result.values[::-1])
        print(
            f"{model}: K = {levels} N/m, p = {result.order:.3f}, "
            f"Richardson {result.extrapolated:.1f} (GCI {result.gci:.2%}); finest level over positions "
            f"{values[-1].min():.1f} … {values[-1].max():.1f}"
        )
        assert np.all(np.diff(values.mean(axis=1)) < 0.0)
        assert np.max(np.abs(values[-1] - bare.extrapolated)) <= bare.uncertainty
