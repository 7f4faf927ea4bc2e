"""Leaving a cut backwards with part of the needle still in it (issue 24): intact tissue grips the needle only
where it is intact.

cube_cut on 4³ cells: the needle is inserted 17 mm at x = 1.23 mm, cuts 8 mm along +x, then swings back:
its surface crossing returns to 1 mm ahead of the line it entered along (inside its own cut) while it tilts
so that its tip goes 4 mm behind that line (into intact tissue). Reference: the cut spans x from the entry
line to the crack tip at about 9.2 mm, and an insertion point is a material point of intact tissue gripping
the needle, so after the needle leaves its cut no insertion point may lie inside the cut's span (beyond the
entry line by more than the cut's own spacing, d_c); the part of the needle still in the cut slides in it
(the old cut's sliding rows).
"""

from __future__ import annotations

import numpy as np
import pytest

from refsim.scene import load_scene
from refsim.simulation import Simulation

NEEDLE_LENGTH = 0.32
TOP = 0.1
ENTRY_X, Y = 0.00123, 0.00231
DEPTH = 0.017


def _pose(surface_x: float, tilt: float) -> tuple[list[float], list[float]]:
    """Base position and direction of the needle crossing the top face at (surface_x, Y) with its tip DEPTH
    below it, tilted by ``tilt`` [rad] towards −x in the x–z plane."""
    direction = np.array([-np.sin(tilt), 0.0, -np.cos(tilt)])
    inserted = DEPTH / np.cos(tilt)
    base = np.array([surface_x, Y, TOP]) - (NEEDLE_LENGTH - inserted) * direction
    return [float(v) for v in base], [float(v) for v in direction]


@pytest.mark.parametrize("solver", ["gauss_seidel", pytest.param("exact", marks=pytest.mark.slow)], ids=str)
def test_insertion_points_after_leaving_a_cut_lie_outside_it(solver):
    d_c = 0.001
    tilt = float(np.arctan2(0.005, DEPTH))  # tip 5 mm behind the surface crossing
    poses = [
        ([ENTRY_X, Y, TOP + 0.002 + NEEDLE_LENGTH], [0.0, 0.0, -1.0]),
        _pose(ENTRY_X, 0.0),
        _pose(ENTRY_X, 0.0),
        _pose(0.00923, 0.0),
        _pose(0.00923, 0.0),
        _pose(ENTRY_X + d_c, tilt),
        _pose(ENTRY_X + d_c, tilt),
    ]
    times = [0.0, 1.9, 2.0, 2.8, 3.0, 4.0, 4.2]
    fmt = lambda v: "[" + ", ".join(repr(x) for x in v) + "]"  # noqa: E731
    scene = load_scene(
        "cube_cut",
        [
            "mesh.cells=[4, 4, 4]",
            f"cutting.point_spacing={d_c}",
            f"trajectory.times={times!r}",
            "trajectory.base_positions=[" + ", ".join(fmt(p[0]) for p in poses) + "]",
            "trajectory.directions=[" + ", ".join(fmt(p[1]) for p in poses) + "]",
            f"time.duration={times[-1]}",
            *(('solver.method="exact"',) if solver == "exact" else ()),
        ],
    )
    simulation = Simulation(scene)
    left = []

    def watch(state, record):
        if any(event.name == "leave_cut" for event in record.events):
            left.append(state)

    simulation.run(on_step=watch)
    assert len(left) == 1
    state = left[0]
    points = state.path.positions(state.tissue.positions, simulation.tets)
    # The entry point (index 0) marks the inserted length and is kept wherever it is; every other point
    # grips intact tissue: behind the entry line, not in the cut's span.
    assert state.path.point_count >= 2
    assert np.all(points[1:, 0] <= ENTRY_X + d_c), points[:, 0]
