"""The rigid needle's cut in the liver for several d_c: the cut's area (the laid triangles plus the strip
between the last layer and the crack tip, which the triangles lag by up to d_c), the largest lateral advance
of the crack tip from the path it started on (x and z, rest coordinates), the layers laid and the peak needle
force.

    PYTHONPATH=. python studies/liver/cut_area.py [d_c ...]      (default: 0.5e-3 1e-3 2e-3 m)

The needle is inserted along −y (refsim/scenes/liver_rigid.toml), so x and z are lateral to it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))


def cut_area(state) -> tuple[float, float]:
    """(area [m²], largest lateral advance of a crack-tip column from the path [m]) of ``state``'s cut: the
    laid triangles (rest coordinates) plus the strip between the last layer and the crack tip, over the
    columns that have been laid (a column added below the strip shares its upper neighbour's point until the
    next layer)."""
    strip, cut = state.cut_strip, state.cut
    corners = cut.rest_points[cut.triangles]
    laid = (
        0.5
        * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum()
    )
    last = strip.last_layer
    fresh = last < 0  # columns of a block added below the strip that have no point yet
    gap = np.linalg.norm((strip.front.rest_points - cut.rest_points[np.maximum(last, 0)])[:, [0, 2]], axis=1)
    pair = ~fresh[:-1] & ~fresh[1:]
    ahead = float((0.5 * (gap[1:] + gap[:-1]) * np.abs(np.diff(strip.depths)))[pair].sum())
    first = strip.rest_rear_edge(cut)
    advance = np.linalg.norm((strip.front.rest_points - first)[:, [0, 2]], axis=1)[~fresh]
    return float(laid) + ahead, float(advance.max()) if advance.size else 0.0


def main(argv=None) -> int:
    from refsim.scene import load_scene
    from refsim.simulation import Simulation

    spacings = [float(v) for v in (argv if argv is not None else sys.argv[1:])] or [0.5e-3, 1e-3, 2e-3]
    print("| d_c [mm] | cut area [mm²] | largest advance [mm] | layers | peak force [N] |")
    print("|---|---|---|---|---|")
    for d_c in spacings:
        simulation = Simulation(load_scene("liver_rigid", [f"cutting.point_spacing={d_c!r}"]))
        state = simulation.initial_state()
        area, peak = (0.0, 0.0), 0.0
        for _ in range(simulation.scene.time.step_count):
            state, record = simulation.step(state)
            peak = max(peak, float(np.linalg.norm(record.needle_force)))
            if state.cut_strip is not None and state.cut is not None:
                area = max(area, cut_area(state))
        layers = state.cut_strip.layers.shape[0] if state.cut_strip is not None else 0
        print(
            f"| {d_c * 1e3:g} | {area[0] * 1e6:.1f} | {area[1] * 1e3:.2f} | {layers} | {peak:.2f} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
