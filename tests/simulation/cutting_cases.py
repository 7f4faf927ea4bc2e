"""Cutting scenes over what users vary: entry point, needle tilt, stroke direction, mesh, d_i, d_c, needle,
solver. Built from the built-in cube_cut by overrides, short enough for the default suite (about 100 steps)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from refsim.cutting.metrics import surface_topology
from refsim.scene import load_scene
from refsim.simulation import Simulation

NEEDLE_LENGTH = 0.32  # cube_cut's needle [m]
TOP = 0.1  # the cube's top face [m]


@dataclass(frozen=True)
class CuttingCase:
    """One scene of the matrix.

    Attributes
    ----------
    entry : Where the needle enters the top face, (x, y) [m].
    tilt : Angle of the needle from the vertical, in the xz plane [deg].
    stroke : Lateral motion of the base, in the plane normal to the needle: (along x', along y) [m], x' the
        in-plane axis normal to the needle.
    depth : Inserted length [m].
    cells : Cells per axis.
    overrides : Further scene overrides.
    """

    entry: tuple[float, float] = (0.00123, 0.00231)
    tilt: float = 0.0
    stroke: tuple[float, float] = (0.005, 0.0)
    depth: float = 0.012
    cells: int = 6
    overrides: tuple[str, ...] = field(default_factory=tuple)

    @property
    def direction(self) -> np.ndarray:
        angle = np.radians(self.tilt)
        return np.array([np.sin(angle), 0.0, -np.cos(angle)])

    @property
    def stroke_vector(self) -> np.ndarray:
        angle = np.radians(self.tilt)
        across = np.array([np.cos(angle), 0.0, np.sin(angle)])  # in the xz plane, normal to the needle
        return self.stroke[0] * across + self.stroke[1] * np.array([0.0, 1.0, 0.0])

    def scene_overrides(self) -> list[str]:
        d = self.direction
        entry = np.array([self.entry[0], self.entry[1], TOP])
        tip_start = entry - 0.002 * d
        speed = 0.02  # [m/s]
        t_insert = (0.002 + self.depth) / speed
        stroke = self.stroke_vector
        t_stroke = t_insert + max(float(np.linalg.norm(stroke)), 0.002) / speed  # a hold when there is no stroke
        base0 = tip_start - NEEDLE_LENGTH * d
        base1 = base0 + (0.002 + self.depth) * d
        base2 = base1 + stroke
        fmt = lambda v: "[" + ", ".join(f"{x:.9g}" for x in v) + "]"  # noqa: E731
        times = [0.0, t_insert, t_stroke, t_stroke + 0.1]
        duration = round(times[-1], 2)
        return [
            f"mesh.cells=[{self.cells}, {self.cells}, {self.cells}]",
            f"trajectory.times={fmt(times)}",
            f"trajectory.base_positions=[{fmt(base0)}, {fmt(base1)}, {fmt(base2)}, {fmt(base2)}]",
            f"trajectory.directions=[{fmt(d)}, {fmt(d)}, {fmt(d)}, {fmt(d)}]",
            f"time.duration={duration}",
            "output.tissue_every=1000",
            *self.overrides,
        ]

    def scene(self):
        return load_scene("cube_cut", self.scene_overrides())


@dataclass
class CuttingRun:
    records: list
    state: object
    simulation: Simulation
    needle_to_cut: float  # the largest distance of a needle sample inside the cut from the cut surface [m]
    inserted: list = field(default_factory=list)  # inserted length after each step [m] (0 before puncture)
    cuts: dict = field(default_factory=dict)  # step -> cut surface after the step
    work: list = field(default_factory=list)  # (step, tissue energy [J], work of the needle on the tissue [J])

    @property
    def events(self) -> list[tuple[int, str]]:
        return [(r.step, e.name) for r in self.records for e in r.events]

    def count(self, name: str) -> int:
        return sum(1 for _, n in self.events if n == name)

    def first(self, name: str) -> int | None:
        steps = [s for s, n in self.events if n == name]
        return steps[0] if steps else None

    @property
    def topology(self):
        cut = self.state.cut
        return surface_topology(cut.triangles, cut.point_count)

    def extent(self) -> float:
        """How far the cut reaches beyond the path it started on, along ĉ in rest coordinates [m]: the largest
        advance of a crack-tip column from its first layer (the whole cloud's spread along ĉ when the strip is
        gone: the path itself is not straight in rest coordinates after a tilted insertion)."""
        cut, strip = self.state.cut, getattr(self.state, "cut_strip", None)
        if strip is None:
            return float(np.ptp(cut.rest_points @ self.cut_direction))
        advance = (strip.front.rest_points - cut.rest_points[strip.layers[0]]) @ self.cut_direction
        return float(advance.max())

    cut_direction: np.ndarray | None = None


def run_case(case: CuttingCase) -> CuttingRun:
    """Run a case, measuring after each cutting step how far the needle's samples inside the cut are from it."""
    scene = case.scene()
    simulation = Simulation(scene)
    records, worst, direction = [], 0.0, None
    inserted, cuts, energies, work = [], {}, [], 0.0
    state = simulation.initial_state()
    tets = simulation.tets
    tissue = simulation.tissue
    for _ in range(scene.time.step_count):
        previous_base = state.needle.base_position
        state, record = simulation.step(state)
        records.append(record)
        # Work of the needle on the tissue (a rigid needle translates with its base; the tissue receives −F).
        work += float(-record.needle_force @ (state.needle.base_position - previous_base))
        energy = tissue.strain_energy(state.tissue.positions) + tissue.kinetic_energy(state.tissue.velocities)
        energies.append((record.step, energy, work))
        needle = simulation.needle.geometry(state.needle)
        if state.path.point_count:
            entry = state.path.positions(state.tissue.positions, tets)[:1]
            inserted.append(needle.length - float(needle.project(entry)[0][0]))
        else:
            inserted.append(0.0)
        if state.cut is not None:
            cuts[record.step] = state.cut
        if state.cut is not None and state.cut_direction is not None:
            direction = state.cut_direction
        if record.phase == "cutting" and state.cut is not None and state.cut.triangle_count:
            needle = simulation.needle.geometry(state.needle)
            surface = state.cut.deformed_points(state.tissue.positions, tets)
            entry = state.path.positions(state.tissue.positions, tets)[:1]
            start = float(needle.project(entry)[0][0])
            samples = needle.points(np.linspace(start, needle.length, 20))
            found = state.cut.closest_points(samples, surface)
            if np.any(found.inside):
                worst = max(worst, float(np.linalg.norm(samples - found.closest, axis=1)[found.inside].max()))
    run = CuttingRun(records, state, simulation, worst, inserted, cuts, energies)
    run.cut_direction = direction
    return run
