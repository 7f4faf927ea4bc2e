"""The recorded cut is the crack tip's swept region: a needle that cuts, then goes deeper while still pushing
sideways (a coarse cube), against the region its crack tip swept, tracked step by step from the crack tip
alone."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.cutting.metrics import surface_topology
from refsim.simulation import Simulation
from tests.simulation.cutting_cases import TOP, CuttingCase


class SweptRegion:
    """The region a strip's crack tip swept, from the crack tip alone: each pair of neighbouring columns
    sweeps the quad from where their tips were when the younger of the two appeared to where they are."""

    def __init__(self, tips: np.ndarray):
        self.first = tips.copy()
        self.start_a, self.start_b = tips[:-1].copy(), tips[1:].copy()

    def update(self, tips: np.ndarray) -> None:
        known = self.first.shape[0]
        if tips.shape[0] > known:  # columns added below the strip
            self.first = np.concatenate([self.first, tips[known:]])
            self.start_a = np.concatenate([self.start_a, tips[known - 1 : -1]])
            self.start_b = np.concatenate([self.start_b, tips[known:]])

    def area(self, tips: np.ndarray) -> float:
        quads = np.cross(tips[1:] - self.start_a, tips[:-1] - self.start_b)
        return float(0.5 * np.linalg.norm(quads, axis=1).sum())


@pytest.fixture(scope="module")
def plunge_run():
    # 4³ cells: insert 8 mm, then 3 mm sideways while going 4 mm deeper, then 3 mm more sideways.
    case = CuttingCase(depth=0.008, cells=4, stroke=(0.003, 0.0), plunge=0.004, turn=(0.003, 0.0))
    simulation = Simulation(case.scene())
    state = simulation.initial_state()
    region, extended = None, 0
    for _ in range(simulation.scene.time.step_count):
        state, _ = simulation.step(state)
        if state.cut_strip is None:
            assert region is None, "one strip: the needle stays in its cut"
            continue
        tips = state.cut_strip.front.rest_points
        if region is None:
            region = SweptRegion(tips)
        extended += tips.shape[0] > region.first.shape[0]
        region.update(tips)
    assert region is not None and extended >= 2  # several blocks added below the strip
    entry = np.array([case.entry[0], case.entry[1], TOP])
    return state, region, simulation.scene.cutting.point_spacing, entry, case.direction


def test_the_recorded_cut_reaches_as_deep_as_the_crack_tip_advanced(plunge_run):
    # Reference: the deepest crack-tip column that advanced more than d_c/10 from where it started. The
    # recorded surface's deepest point lies within d_c of it (columns every d_c; a column joins the surface
    # once it and a neighbour it can be joined to have moved).
    state, region, d_c, entry, direction = plunge_run
    tips = state.cut_strip.front.rest_points
    advanced = np.linalg.norm(tips - region.first, axis=1) > 0.1 * d_c
    swept_depth = float(((tips[advanced] - entry) @ direction).max())
    cut = state.cut
    recorded_depth = float(((cut.rest_points[np.unique(cut.triangles)] - entry) @ direction).max())
    assert swept_depth > 0.010  # the needle went 4 mm deeper than the 8 mm where the cut started
    assert recorded_depth >= swept_depth - d_c, (recorded_depth, swept_depth)


def test_the_recorded_area_is_the_swept_area(plunge_run):
    # The surface lags the crack tip by less than d_c per column (a layer is laid when one column is d_c
    # ahead, and then every column that moved is laid); a column added below the strip joins its upper
    # neighbour from the layer after that neighbour's first one laid after the addition (less than d_c by
    # d_c per block). So 0 ≤ swept − recorded ≤ d_c (L + n_blocks d_c), L the depth the columns span. The
    # recorded triangles split each swept quad in two: equal areas for planar quads; the quads here are planar
    # to the tissue's deformation over d_c, so the recorded area exceeds no quad's by more than 1e-3.
    state, region, d_c, _, _ = plunge_run
    cut = state.cut
    corners = cut.rest_points[cut.triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    recorded = float(0.5 * np.linalg.norm(normals, axis=1).sum())
    tips = state.cut_strip.front.rest_points
    swept = region.area(tips)
    depths = state.cut_strip.depths
    blocks = int(np.count_nonzero(np.diff(state.cut_strip.births) != 0))
    allowed = d_c * (float(depths[-1] - depths[0]) + blocks * d_c)
    assert swept - allowed <= recorded <= swept * (1 + 1e-3), (recorded, swept, allowed)


def test_the_recorded_cut_is_a_manifold_without_degenerate_triangles(plunge_run):
    state, _, d_c, _, _ = plunge_run
    cut = state.cut
    topology = surface_topology(cut.triangles, cut.point_count)
    assert topology.non_manifold_edges == 0 and topology.isolated_points == 0, topology
    edges = np.sort(cut.triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert counts.max() <= 2
    corners = cut.rest_points[cut.triangles]
    doubled = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    assert doubled.min() > 1e-6 * d_c**2
