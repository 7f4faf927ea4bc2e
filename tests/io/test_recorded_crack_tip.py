"""The results file's cut is the model's cut (issue 24, item 5): the written surface reaches the crack tip,
not only the last layer laid, and the step's counts are the written surface's."""

from __future__ import annotations

import numpy as np

from refsim.io import read_results
from refsim.io.driver import run_scene
from refsim.scene import load_scene

# cube_cut on 4³ cells: the needle inserted 17 mm, then moved sideways along +x at 10 mm/s; the run stops
# mid-stroke, where the crack tip has moved past the last layer.
TIMES = [0.0, 1.9, 2.0, 2.8]
BASES = [[0.00123, 0.00231, 0.422], [0.00123, 0.00231, 0.403], [0.00123, 0.00231, 0.403]]
BASES += [[0.00923, 0.00231, 0.403]]


def test_the_written_cut_reaches_the_crack_tip(tmp_path):
    scene = load_scene(
        "cube_cut",
        [
            "mesh.cells=[4, 4, 4]",
            f"trajectory.times={TIMES!r}",
            f"trajectory.base_positions={BASES!r}",
            "trajectory.directions=" + repr([[0, 0, -1]] * len(TIMES)),
            "time.duration=2.8",
        ],
    )
    last = {}
    d_c = scene.cutting.point_spacing
    for stop in (2.33, 2.37):  # two stops, so that one falls between two layers whatever the tear steps
        path = tmp_path / f"cut_{stop}.h5"
        steps = int(round(stop / scene.time.dt))
        run_scene(scene, path, steps=steps, handle_signals=False, on_step=lambda s, r: last.update(state=s))
        state = last["state"]
        strip, cut = state.cut_strip, state.cut
        assert strip is not None and cut.triangle_count
        tips, rear = strip.front.rest_points, strip.rest_rear_edge(cut)
        laid = cut.rest_points[strip.last_layer[strip.last_layer >= 0]]
        results = read_results(path)
        points, triangles = results.cut.at(int(results.step[-1]))
        corners = points[np.unique(triangles)]
        size = float(np.ptp(results.rest_positions, axis=0).max())
        # Reference: the crack tip and the rear edge (the strip's first layer), along the stroke (x), in rest
        # coordinates; the written surface spans them to round-off (the tip's own coordinates are written).
        assert abs(corners[:, 0].max() - tips[:, 0].max()) <= 1e-12 * size
        assert abs(corners[:, 0].min() - rear[:, 0].min()) <= 1e-12 * size
        # every crack-tip point is a written point
        distance = np.linalg.norm(tips[:, None, :] - corners[None, :, :], axis=2).min(axis=1)
        assert distance.max() <= 1e-12 * size
        # the counts of the step are the written surface's
        assert results.cut_point_count[-1] == points.shape[0]
        assert results.cut_triangle_count[-1] == triangles.shape[0]
        last[stop] = float(tips[:, 0].max() - laid[:, 0].max())
    # The test tells: at one of the stops at least, the crack tip was a tenth of d_c past the last layer.
    assert max(last[2.33], last[2.37]) > 0.1 * d_c, last
