"""The recorded cut against the crack tip's swept region, for one scene.

    PYTHONPATH=. python studies/cutting/recorded_cut.py SCENE [key=value ...]

Runs the scene and, for each strip (each cut start), compares at the last step it exists:

- the laid surface (`state.cut`: the triangles the rows read) and the written one (what the results file
  holds: the laid surface and a layer at the crack tip, `refsim.cutting.strip.recorded_surface`): their areas
  and the deepest of their points, depth measured along the strip's first layer (the insertion path at the cut
  start) from its entry column, rest coordinates;
- the region the crack tip has swept: for each pair of neighbouring columns, the quad from where their crack
  tips were when the younger of the two was added (the path for the strip's own columns, the needle for those
  added below it) to where they are now; its area, and the deepest column whose crack tip advanced more than
  d_c/10 from where it started.

The laid area lags the swept one by what lies between the last layer and the crack tip (up to d_c per unit
depth); the written one is the swept region.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))


def triangle_area(cut, triangles) -> float:
    corners = cut.rest_points[triangles]
    return float(
        0.5
        * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum()
    )


class SweptRegion:
    """Where each column's crack tip started (tracked over the steps) and the region it has swept."""

    def __init__(self, step: int):
        self.since = step  # the strip's triangles are those laid from here on
        self.start_a = np.zeros((0, 3))  # pair j: column j's tip when the pair began
        self.start_b = np.zeros((0, 3))  # pair j: column j+1's tip when the pair began
        self.first = np.zeros((0, 3))  # column j's tip when it was added
        self.axis_origin = None
        self.axis = None

    def update(self, strip, cut) -> None:
        tips = strip.front.rest_points
        known = self.first.shape[0]
        if known == 0:
            path = cut.rest_points[strip.layers[0][strip.layers[0] >= 0]]
            self.axis_origin = path[0]
            self.axis = (path[-1] - path[0]) / np.linalg.norm(path[-1] - path[0])
            self.first = tips.copy()
            self.start_a, self.start_b = tips[:-1].copy(), tips[1:].copy()
            return
        if tips.shape[0] > known:
            self.first = np.concatenate([self.first, tips[known:]])
            self.start_a = np.concatenate([self.start_a, tips[known - 1 : -1]])
            self.start_b = np.concatenate([self.start_b, tips[known:]])

    def depth(self, points) -> np.ndarray:
        return (points - self.axis_origin) @ self.axis

    def measure(self, strip, cut, spacing: float, step: int) -> dict:
        from refsim.cutting.strip import recorded_surface

        tips = strip.front.rest_points
        swept = 0.5 * np.linalg.norm(np.cross(tips[1:] - self.start_a, tips[:-1] - self.start_b), axis=1)
        advance = np.linalg.norm(tips - self.first, axis=1)
        advanced = advance > 0.1 * spacing
        triangles = cut.triangles[cut.triangle_created_step >= self.since]
        used = np.unique(triangles)
        written = recorded_surface(cut, strip, step)
        written_triangles = written.triangles[written.triangle_created_step >= self.since]
        written_used = np.unique(written_triangles)
        return {
            "laid area [mm²]": triangle_area(cut, triangles) * 1e6,
            "written area [mm²]": triangle_area(written, written_triangles) * 1e6,
            "swept area [mm²]": float(swept.sum()) * 1e6,
            "laid depth [mm]": float(self.depth(cut.rest_points[used]).max()) * 1e3 if used.size else 0.0,
            "written depth [mm]": (
                float(self.depth(written.rest_points[written_used]).max()) * 1e3 if written_used.size else 0.0
            ),
            "swept depth [mm]": float(self.depth(tips[advanced]).max()) * 1e3 if advanced.any() else 0.0,
            "columns": int(tips.shape[0]),
            "columns advanced": int(advanced.sum()),
            "largest advance [mm]": float(advance.max()) * 1e3,
            "triangles": int(triangles.shape[0]),
        }


def main(argv=None) -> int:
    from refsim.cutting.metrics import surface_topology
    from refsim.scene import load_scene
    from refsim.simulation import Simulation

    argv = list(sys.argv[1:] if argv is None else argv)
    simulation = Simulation(load_scene(argv[0], argv[1:]))
    spacing = simulation.scene.cutting.point_spacing
    state = simulation.initial_state()
    region, result, strip_count = None, None, 0

    def report() -> None:
        topology = surface_topology(state.cut.triangles, state.cut.point_count)
        print(f"strip {strip_count} (last step {result['step']}), the whole surface {topology}")
        for key, value in result.items():
            print(f"  {key}: {value:.3f}" if isinstance(value, float) else f"  {key}: {value}")

    for _ in range(simulation.scene.time.step_count):
        state, _record = simulation.step(state)
        strip = state.cut_strip
        if strip is None or state.cut is None:
            if region is not None:
                report()
                region = None
            continue
        if region is None:
            region, strip_count = SweptRegion(state.step), strip_count + 1
        region.update(strip, state.cut)
        result = region.measure(strip, state.cut, spacing, state.step)
        result["step"] = state.step
    if region is not None:
        report()
    if result is None:
        print("no cut")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
