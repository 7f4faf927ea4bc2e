"""Cutting scenes over what users vary: entry point, needle tilt, stroke direction, mesh, d_i, d_c, needle,
solver. Built from the built-in cube_cut by overrides, short enough for the default suite (about 100
steps)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from refsim.constraints import BILATERAL, CUT_BORDER, CUT_SLIDE
from refsim.constraints.inserted import inserted_arc
from refsim.cutting.metrics import surface_topology
from refsim.geometry import TetLocator
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
    turn : A second lateral stroke after the first (an L-shaped path), like ``stroke`` [m]; (0, 0): none.
    plunge : How much deeper the needle goes along its axis during the (first) stroke [m].
    overrides : Further scene overrides.
    """

    entry: tuple[float, float] = (0.00123, 0.00231)
    tilt: float = 0.0
    stroke: tuple[float, float] = (0.005, 0.0)
    depth: float = 0.012
    cells: int = 6
    turn: tuple[float, float] = (0.0, 0.0)
    plunge: float = 0.0
    overrides: tuple[str, ...] = field(default_factory=tuple)

    @property
    def direction(self) -> np.ndarray:
        angle = np.radians(self.tilt)
        return np.array([np.sin(angle), 0.0, -np.cos(angle)])

    def lateral(self, stroke) -> np.ndarray:
        angle = np.radians(self.tilt)
        across = np.array([np.cos(angle), 0.0, np.sin(angle)])  # in the xz plane, normal to the needle
        return stroke[0] * across + stroke[1] * np.array([0.0, 1.0, 0.0])

    @property
    def stroke_vector(self) -> np.ndarray:
        return self.lateral(self.stroke)

    def scene_overrides(self) -> list[str]:
        d = self.direction
        entry = np.array([self.entry[0], self.entry[1], TOP])
        tip_start = entry - 0.002 * d
        speed = 0.02  # [m/s]
        t_insert = (0.002 + self.depth) / speed
        stroke = self.stroke_vector
        # (A hold when there is no stroke.)
        t_stroke = t_insert + max(float(np.linalg.norm(stroke + self.plunge * d)), 0.002) / speed
        base0 = tip_start - NEEDLE_LENGTH * d
        base1 = base0 + (0.002 + self.depth) * d
        base2 = base1 + stroke + self.plunge * d
        fmt = lambda v: "[" + ", ".join(f"{x:.9g}" for x in v) + "]"  # noqa: E731
        times, bases = [0.0, t_insert, t_stroke], [base0, base1, base2]
        turn = self.lateral(self.turn)
        if np.linalg.norm(turn) > 0.0:
            times.append(times[-1] + float(np.linalg.norm(turn)) / speed)
            bases.append(base2 + turn)
        times.append(times[-1] + 0.1)
        bases.append(bases[-1])
        duration = round(times[-1], 2)
        return [
            f"mesh.cells=[{self.cells}, {self.cells}, {self.cells}]",
            f"trajectory.times={fmt(times)}",
            f"trajectory.base_positions=[{', '.join(fmt(b) for b in bases)}]",
            f"trajectory.directions=[{', '.join([fmt(d)] * len(times))}]",
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
    # The largest distance normal to the cut of a needle sample in the tissue and in the cut (projecting
    # inside it or within d_c of its front) [m].
    needle_to_cut: float
    inserted: list = field(default_factory=list)  # inserted length after each step [m] (0 before puncture)
    cuts: dict = field(default_factory=dict)  # step -> cut surface after the step
    work: list = field(
        default_factory=list
    )  # (step, tissue energy [J], work of the needle on the tissue [J])
    # (step, largest distance normal to the cut of a needle sample in the tissue and in the cut [m], the
    # largest C λ of the step's sliding rows plus d_c times the largest rotation of a cut triangle's normal
    # over the step [m]) of each cutting step with such a sample.
    offsets: list = field(default_factory=list)
    # The cut block's spectrum at each step with cut rows (watch_cut_blocks).
    blocks: list = field(default_factory=list)

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
        advance = (strip.front.rest_points - strip.rest_rear_edge(cut)) @ self.cut_direction
        return float(advance.max())

    cut_direction: np.ndarray | None = None


@dataclass(frozen=True)
class CutBlockSpectrum:
    """The cut rows' block of one step's constraint problem (sliding, front and their friction rows): W +
    diag(C) as the solver gets it, C the rows' sub-grid compliance."""

    rows: int
    front_rows: int
    smallest: float  # smallest eigenvalue of W + diag(C) [m/N]
    largest: float  # largest eigenvalue of W + diag(C) [m/N]
    smallest_compliance: float  # min C over the rows [m/N]
    smallest_w: float  # smallest eigenvalue of W alone [m/N]


def watch_cut_blocks(simulation: Simulation) -> list:
    """Record the spectrum of the cut block of every problem ``simulation`` builds (a list it appends to)."""
    spectra = []
    build = simulation._problem

    def problem(rows, systems, *free):
        built = build(rows, systems, *free)
        cut = np.flatnonzero((rows.source == CUT_SLIDE) | (rows.source == CUT_BORDER))
        if built[0] is not None and cut.size:
            total = built[0].compliance[np.ix_(cut, cut)]
            diagonal = np.asarray(rows.compliance_diagonal, dtype=float)
            added = diagonal[cut] if diagonal.size else np.zeros(cut.size)
            eigen = np.linalg.eigvalsh(0.5 * (total + total.T))
            bare = np.linalg.eigvalsh(0.5 * (total + total.T) - np.diag(added))
            spectra.append(
                CutBlockSpectrum(
                    cut.size,
                    int(np.count_nonzero(rows.source == CUT_BORDER)),
                    float(eigen[0]),
                    float(eigen[-1]),
                    float(added.min()),
                    float(bare[0]),
                )
            )
        return built

    simulation._problem = problem
    return spectra


def _kink(cut, surface: np.ndarray) -> float:
    """The largest |n_a − n_b| between the vertex normals of two corners of a triangle (how much the normal
    the rows use varies over one triangle)."""
    corners = np.arange(cut.triangle_count).repeat(3)
    normals = cut.interpolated_normals(surface, corners, np.tile(np.eye(3), (cut.triangle_count, 1)))
    normals = normals.reshape(-1, 3, 3)
    return float(
        max(np.linalg.norm(normals[:, a] - normals[:, b], axis=1).max() for a, b in ((0, 1), (1, 2), (0, 2)))
    )


def run_case(case: CuttingCase) -> CuttingRun:
    """Run a case, measuring after each cutting step how far the needle's samples inside the cut are from
    it."""
    scene = case.scene()
    simulation = Simulation(scene)
    spectra = watch_cut_blocks(simulation)
    records, worst, direction = [], 0.0, None
    inserted, cuts, energies, work = [], {}, [], 0.0
    state = simulation.initial_state()
    tets = simulation.tets
    tissue = simulation.tissue
    spacing = scene.cutting.point_spacing
    offsets = []
    # The largest lateral sub-grid compliance of a sliding row [m/N] (refsim.simulation.detection).
    compliance = float(simulation.detector.cut_compliance[0].max())
    for _ in range(scene.time.step_count):
        previous_base = state.needle.base_position
        previous_positions, cut_before = state.tissue.positions, state.cut
        state, record = simulation.step(state)
        records.append(record)
        # Work of the needle on the tissue (a rigid needle translates with its base; the tissue receives −F).
        work += float(-record.needle_force @ (state.needle.base_position - previous_base))
        energy = tissue.strain_energy(state.tissue.positions) + tissue.kinetic_energy(state.tissue.velocities)
        energies.append((record.step, energy, work))
        needle = simulation.needle.geometry(state.needle)
        entry_arc = needle.length
        if state.path.point_count:
            if record.phase == "cutting":
                # Cutting: the needle's part inside the tissue (a tilted needle pushed sideways leaves its
                # entry point's projection above the tissue).
                entry_arc = inserted_arc(needle, TetLocator(state.tissue.positions, tets), spacing)
            else:
                entry = state.path.positions(state.tissue.positions, tets)[:1]
                entry_arc = float(needle.project(entry)[0][0])
        inserted.append(needle.length - entry_arc)
        if state.cut is not None:
            cuts[record.step] = state.cut
        if state.cut is not None and state.cut_direction is not None:
            direction = state.cut_direction
        if record.phase == "cutting" and state.cut is not None and state.cut.triangle_count:
            surface = state.cut.deformed_points(state.tissue.positions, tets)
            samples = needle.points(np.linspace(entry_arc, needle.length, 20))
            found = state.cut.closest_points(samples, surface)
            # Samples in the cut: projecting inside it, or beyond its front by less than one layer (d_c: the
            # crack tip is at the needle, the last layer up to d_c behind it); their distance normal to the
            # cut.
            normals = state.cut.interpolated_normals(surface, found.triangle, found.barycentric)
            offset = samples - found.closest
            across = np.einsum("ij,ij->i", offset, normals)
            in_plane = np.linalg.norm(offset - across[:, None] * normals, axis=1)
            near = found.inside | (in_plane <= spacing)
            if np.any(near) and cut_before is not None and cut_before.triangle_count:
                distance = float(np.abs(across[near]).max())
                worst = max(worst, distance)
                slide = (record.row_source == CUT_SLIDE) & (record.row_kind == BILATERAL)
                largest = float(np.abs(record.row_forces[slide]).max()) if np.any(slide) else 0.0
                # The rows are linearised with the normals of the step's start: the cut's rotation over the
                # step, times the sample's offset in the plane (≤ d_c), is what the linearisation may miss.
                shared = cut_before.triangle_count
                eye = np.tile(np.eye(3), (shared, 1))
                previous_normals = cut_before.interpolated_normals(
                    cut_before.deformed_points(previous_positions, tets), np.arange(shared).repeat(3), eye
                )
                turn = (
                    state.cut.interpolated_normals(surface, np.arange(shared).repeat(3), eye)
                    - previous_normals
                )
                rotation = float(np.linalg.norm(turn, axis=1).max()) if shared else 0.0
                # And a row holds its sample against the triangle its closest point was on at the step's
                # start, the measure takes the closest at the end: the angle between neighbouring triangles
                # (the cut's kinks), times the offset in the plane, is the difference.
                bound = compliance * largest + spacing * (rotation + _kink(state.cut, surface))
                offsets.append((record.step, distance, bound))
    run = CuttingRun(records, state, simulation, worst, inserted, cuts, energies, offsets, spectra)
    run.cut_direction = direction
    return run
