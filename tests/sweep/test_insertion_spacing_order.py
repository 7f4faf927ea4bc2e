"""Observed order of the shaft coupling under d_i refinement (slow).

The ring coupling (docs/coupling.md) ties the needle to the tissue by one row group every d_i along the
inserted shaft, each carrying the sub-grid compliance of a length d_i of annulus, (3 − 4ν) ln(a_c/r) / (8πG(1
− ν) d_i): the rows are a quadrature, with weight d_i per point, of the distributed coupling over the inserted
length L. The points sit at the entry, every d_i after it, and at the tip (grow_path), so the weights add up
to L + d_i: a rectangle rule with a full weight at each end where the trapezoidal rule has d_i/2. Its error is
first order, (d_i/2)(q(0) + q(L)) for the coupling load q per length at the ends, and the force on the needle,
linear in the coupling's perturbation, converges as O(d_i) (a midpoint or trapezoidal weighting would give
O(d_i²)).

The case: cube_cut with cutting off (the shaft is loaded sideways without the crack changing the problem),
inserted 17 mm, then moved 0.3 mm across its axis (t = 2.03 s); the quantity is the lateral force on the
needle (about 2.8 N); d_i = 0.5, 0.25, 0.125 mm (17 mm is about a multiple of each, so the tip point adds no
sawtooth). Over a matrix of mesh sizes and entry points.

Tolerance: the three-level order departs from 1 by 3β/ln 2 for an error a d + b d², β = b d/a at the finest
level. Measured (2026-12-01, 4 and 6 cells, d_i from 1 mm to 0.125 mm) p = 1.006 to 1.017; |p − 1| ≤ 0.1
allows β up to 0.02 and still tells the first order from the second. The sign of the error is not asserted
(at 0.3 mm of stroke the force falls as d_i is refined, at 0.1 mm it rises; measured on 4 and 6 cells).
Roache's GCI of the finest level (measured 0.11 to 0.18 %) must be below 1 %: d_i = 0.125 mm resolves the
coupling to that accuracy.
"""

from __future__ import annotations

import json

import pytest

from refsim.sweep import convergence

pytestmark = pytest.mark.slow

SPACINGS = (5e-4, 2.5e-4, 1.25e-4)
#: cube_cut's base positions moved sideways by (dx, dy) [m]: another entry point.
TRAJECTORY = [
    [0.00123, 0.00231, 0.422],
    [0.00123, 0.00231, 0.403],
    [0.00123, 0.00231, 0.403],
    [0.00923, 0.00231, 0.403],
    [0.00923, 0.00231, 0.403],
]


def _lateral_force(tmp_path, cells: int, shift: tuple, spacing: float) -> float:
    from refsim.io import read_results
    from refsim.io.driver import run_scene
    from refsim.scene import load_scene
    from refsim.sweep import quantity

    base = [[x + shift[0], y + shift[1], z] for x, y, z in TRAJECTORY]
    scene = load_scene(
        "cube_cut",
        [
            f"mesh.cells=[{cells}, {cells}, {cells}]",
            "cutting.enabled=false",
            "time.duration=2.03",
            "output.tissue_every=1000",
            f"trajectory.base_positions={json.dumps(base)}",
            f"insertion.spacing={spacing!r}",
        ],
    )
    path = tmp_path / f"c{cells}_{shift[0]}_{spacing}.h5"
    summary = run_scene(scene, path, handle_signals=False)
    assert summary.complete, summary
    results = read_results(path)
    assert results.events_named("puncture") and not results.events_named("cut_start")
    return quantity(results, "lateral_force@t=2.03")


@pytest.mark.parametrize(
    ("cells", "shift"),
    [(4, (0.0, 0.0)), (6, (0.0, 0.0)), (4, (-0.0113, 0.0071))],
    ids=["4 cells", "6 cells", "4 cells, other entry"],
)
def test_lateral_force_converges_at_first_order_in_d_i(tmp_path, cells, shift):
    forces = [_lateral_force(tmp_path, cells, shift, spacing) for spacing in SPACINGS]
    result = convergence(SPACINGS, forces)
    assert result.kind == "monotone", result
    assert abs(result.order - 1.0) <= 0.1, result
    assert result.gci < 0.01, (
        result
    )  # the finest level within 1 % of the limit: the rows resolve the coupling
