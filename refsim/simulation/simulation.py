"""The time step loop (DESIGN.md, "One time step"): motion, free motion, detection, compliance, solve,
correction, events, record.

The scene and the models are static; a step takes a :class:`SimulationState` and returns a new one with the
:class:`~refsim.simulation.records.StepRecord` of what it did. Nothing the scene does not declare is computed: a
rigid needle has no beam solve, μ = 0 gives no friction rows, a scene without cutting never builds a cut.
"""

from __future__ import annotations

import logging
import time as clock
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from refsim.constraints import (
    BILATERAL,
    INSERTION,
    InsertionPath,
    PENETRATION,
    RowBlock,
    UNILATERAL,
    concatenate,
    empty_block,
    find_surface_contact,
    grow_path,
    insertion_block,
    penetration_block,
    points_beyond_tip,
)
from refsim.constraints.cut import cut_block, cut_criterion, front_border_points, resample_polyline, sweep_points
from refsim.fem.compliance import make_strategy
from refsim.fem.tissue import TissueState
from refsim.geometry import SurfaceProjector, TetLocator
from refsim.scene import Scene
from refsim.scene.build import SceneModels, build_models
from refsim.simulation.needle_body import FlexibleNeedle, NeedleState, RigidNeedle
from refsim.simulation.records import STAGES, Event, StepRecord
from refsim.solvers import ConstraintProblem, solve_exact, solve_gauss_seidel

__all__ = ["Simulation", "SimulationState", "SimulationError"]

logger = logging.getLogger(__name__)

APPROACH, INSERTION_PHASE, CUTTING_PHASE = "approach", "insertion", "cutting"


class SimulationError(RuntimeError):
    """The simulation reached a state it cannot continue from (non-finite values, a blown-up energy); the
    message names the step and what was detected."""


@dataclass(frozen=True)
class SimulationState:
    """Everything that changes during a run.

    Attributes
    ----------
    step : Steps done.
    time : Simulated time [s].
    phase : "approach" (tip outside), "insertion" or "cutting".
    tissue : Tissue positions [m] and velocities [m/s], each (n, 3).
    needle : Needle configuration.
    path : Insertion points (material points of the tissue).
    cut : The cut surface (None until the tissue is cut).
    """

    step: int
    time: float
    phase: str
    tissue: TissueState
    needle: NeedleState
    path: InsertionPath
    cut: object | None = None
    extras: dict = field(default_factory=dict)


class _StageTimer:
    def __init__(self) -> None:
        self.seconds = dict.fromkeys(STAGES, 0.0)
        self._last = clock.perf_counter()

    def lap(self, stage: str) -> None:
        now = clock.perf_counter()
        self.seconds[stage] += now - self._last
        self._last = now


class Simulation:
    """A scene's simulation: build once, then step.

    Parameters
    ----------
    scene : The validated scene.
    models : Prebuilt models (built from the scene by default).
    """

    def __init__(self, scene: Scene, models: SceneModels | None = None) -> None:
        self.scene = scene
        self.models = models if models is not None else build_models(scene)
        self.tets = np.asarray(self.models.mesh.tets)
        self.faces = np.asarray(self.models.mesh.boundary_faces)
        self.tissue = self.models.tissue
        if scene.needle.rigid:
            self.needle = RigidNeedle(scene.needle.length, scene.needle.element_count)
        else:
            self.needle = FlexibleNeedle(
                self.models.needle,
                rayleigh_mass=scene.needle.rayleigh_mass,
                rayleigh_stiffness=scene.needle.rayleigh_stiffness,
            )
        self.dt = scene.time.dt
        spec = scene.compliance
        self.tissue_compliance = make_strategy(
            spec.strategy, refresh_every=spec.refresh_every, linear_solver=spec.linear_solver, w_update=spec.w_update
        ).bind()

    # ------------------------------------------------------------------ state

    def initial_state(self) -> SimulationState:
        """Tissue at rest, needle at the trajectory's first pose, tip outside."""
        base, direction = self.models.trajectory.pose(0.0)
        return SimulationState(
            step=0,
            time=0.0,
            phase=APPROACH,
            tissue=self.tissue.rest_state(),
            needle=self.needle.state_at(base, direction),
            path=InsertionPath.empty(),
        )

    # ------------------------------------------------------------------ step

    def step(self, state: SimulationState, *, record_tissue: bool = False) -> tuple[SimulationState, StepRecord]:
        """Advance one time step; return the new state and the record of the step."""
        scene, dt = self.scene, self.dt
        timer = _StageTimer()
        time = state.time + dt
        step = state.step + 1
        base, direction = self.models.trajectory.pose(time)
        timer.lap("motion")

        tissue_free, _, tissue_system = self.tissue.free_motion(state.tissue, dt, compliance=self.tissue_compliance)
        needle_free, needle_system = self.needle.free_motion(state.needle, base, direction, dt)
        timer.lap("free_motion")

        needle_free_geometry = self.needle.geometry(needle_free)
        needle_previous_geometry = self.needle.geometry(state.needle)
        rows, context = self._detect(state, tissue_free, needle_free_geometry, needle_previous_geometry)
        timer.lap("detection")

        problem, tissue_responses, needle_responses = self._problem(rows, tissue_system, needle_system)
        timer.lap("compliance")

        multipliers, report = self._solve(problem, self._warm_start(state, rows))
        timer.lap("solve")

        tissue_positions = tissue_free
        if tissue_responses is not None:
            tissue_positions = tissue_free + tissue_system.correction(tissue_responses, multipliers).reshape(-1, 3)
        tissue_state = TissueState(
            positions=tissue_positions, velocities=(tissue_positions - state.tissue.positions) / dt
        )
        needle_state = self.needle.correct(state.needle, needle_free, needle_system, needle_responses, multipliers, dt)
        self._check_finite(step, tissue_state, needle_state, multipliers)
        timer.lap("correction")

        new_state = replace(
            state,
            step=step,
            time=time,
            tissue=tissue_state,
            needle=needle_state,
            path=self._store_multipliers(state.path, rows, multipliers),
        )
        new_state, events = self._events(new_state, rows, multipliers, context)
        timer.lap("events")

        needle_force = (rows.directions * multipliers[:, None]).sum(axis=0) if rows.row_count else np.zeros(3)
        record = StepRecord(
            step=step,
            time=time,
            phase=new_state.phase,
            events=tuple(events),
            base_position=needle_state.base_position,
            needle_positions=needle_state.positions,
            needle_frames=needle_state.frames,
            tissue_positions=tissue_positions if record_tissue else None,
            row_kind=rows.kind,
            row_source=rows.source,
            row_points=rows.points,
            row_directions=rows.directions,
            row_forces=multipliers,
            needle_force=needle_force,
            insertion_point_count=new_state.path.point_count,
            solver=report,
            stage_seconds=timer.seconds,
            problem=problem if scene.output.record_problems else None,
            cut_point_count=0 if new_state.cut is None else new_state.cut.point_count,
            cut_triangle_count=0 if new_state.cut is None else new_state.cut.triangle_count,
            triangulation_seconds=_triangulation_seconds(state.cut, new_state.cut),
        )
        return new_state, record

    def run(
        self,
        *,
        steps: int | None = None,
        on_step: Callable[[SimulationState, StepRecord], None] | None = None,
        state: SimulationState | None = None,
    ) -> SimulationState:
        """Run ``steps`` steps (the scene's duration by default), calling ``on_step`` after each."""
        state = self.initial_state() if state is None else state
        total = self.scene.time.step_count if steps is None else steps
        every = self.scene.output.tissue_every
        for index in range(1, total + 1):
            record_tissue = index % every == 0 or index == total
            state, record = self.step(state, record_tissue=record_tissue)
            if on_step is not None:
                on_step(state, record)
        return state

    # ------------------------------------------------------------------ stages

    def _detect(self, state, tissue_free, needle_free, needle_previous) -> tuple[RowBlock, dict]:
        spec = self.scene.insertion
        dof_count = 3 * self.tissue.node_count
        blocks = []
        context: dict = {}
        if state.phase == APPROACH:
            projector = SurfaceProjector(tissue_free, self.faces)
            contact = find_surface_contact(projector, self.faces, needle_free.tip)
            context["contact"] = contact
            if contact.gap < spec.contact_distance:
                blocks.append(
                    penetration_block(
                        contact=contact,
                        tissue_free=tissue_free,
                        tissue_previous=state.tissue.positions,
                        needle_free=needle_free,
                        needle_previous=needle_previous,
                        friction_coefficient=spec.surface_friction_coefficient,
                        tissue_dof_count=dof_count,
                    )
                )
        elif state.path.point_count:
            blocks.append(
                insertion_block(
                    state.path,
                    mesh_tets=self.tets,
                    tissue_free=tissue_free,
                    tissue_previous=state.tissue.positions,
                    needle_free=needle_free,
                    needle_previous=needle_previous,
                    friction_coefficient=spec.shaft_friction_coefficient,
                    tissue_dof_count=dof_count,
                    normal_preload=spec.shaft_normal_force * spec.spacing,
                )
            )
        if state.phase == CUTTING_PHASE:
            entry = state.path.positions(state.tissue.positions, self.tets)[:1]
            entry_arc_length = float(needle_previous.project(entry)[0][0])
            offset = sum(block.row_count for block in blocks)
            block, info = cut_block(
                state.cut,
                mesh_tets=self.tets,
                tissue_free=tissue_free,
                needle_free=needle_free,
                entry_arc_length=entry_arc_length,
                spacing=self.scene.cutting.point_spacing,
                cut_direction=state.extras["cut_direction"],
                tissue_dof_count=dof_count,
            )
            if block is not None:
                blocks.append(block)
            context["border_points"] = info.border_point
            context["border_rows"] = offset + info.rows
        if not blocks:
            return empty_block(dof_count, self.needle.dof_count), context
        return concatenate(blocks), context

    def _problem(self, rows: RowBlock, tissue_system, needle_system):
        if rows.row_count == 0:
            return None, None, None
        compliance = tissue_system.delassus(rows.tissue_jacobian)
        tissue_responses = rows.tissue_jacobian  # the correction is tissue_system.correction(H, λ)
        needle_responses = None
        if rows.needle_jacobian is not None:
            needle_compliance, needle_responses = needle_system.compliance(rows.needle_jacobian)
            compliance = compliance + needle_compliance
        sets = rows.index_sets()
        problem = ConstraintProblem(
            compliance=compliance,
            free_gap=rows.free_gap,
            bilateral=sets["bilateral"],
            unilateral=sets["unilateral"],
            contacts=sets["contacts"],
            contact_friction=rows.contact_friction,
            shaft_friction=sets["shaft_rows"],
            shaft_pairs=rows.shaft_pairs,
            shaft_friction_coefficient=rows.shaft_friction_coefficient,
            shaft_normal_preload=rows.shaft_normal_preload,
        )
        return problem, tissue_responses, needle_responses

    def _solve(self, problem, warm_start):
        if problem is None:
            return np.zeros(0), None
        spec = self.scene.solver
        if spec.method == "exact":
            return solve_exact(problem, tolerance=spec.tolerance, backend=spec.backend)
        return solve_gauss_seidel(
            problem,
            tolerance=spec.tolerance,
            max_iterations=spec.max_iterations,
            warm_start=warm_start,
            criterion=spec.criterion,
        )

    @staticmethod
    def _insertion_rows(rows: RowBlock) -> np.ndarray:
        return np.flatnonzero(rows.source == INSERTION)

    def _warm_start(self, state: SimulationState, rows: RowBlock) -> np.ndarray:
        """Last step's multipliers of the insertion points (they persist from step to step), zero elsewhere."""
        warm = np.zeros(rows.row_count)
        insertion = self._insertion_rows(rows)
        if insertion.size and state.path.point_count:
            per_point = insertion.size // state.path.point_count
            warm[insertion] = state.path.multipliers[:, :per_point].ravel()
        return warm

    def _store_multipliers(self, path: InsertionPath, rows: RowBlock, multipliers: np.ndarray) -> InsertionPath:
        insertion = self._insertion_rows(rows)
        if insertion.size == 0 or path.point_count == 0:
            return path
        return path.with_multipliers(multipliers[insertion].reshape(path.point_count, -1))

    def _check_finite(self, step, tissue_state, needle_state, multipliers) -> None:
        for name, array in (
            ("tissue positions", tissue_state.positions),
            ("needle positions", needle_state.positions),
            ("constraint forces", multipliers),
        ):
            if not np.all(np.isfinite(array)):
                raise SimulationError(f"step {step}: non-finite {name} detected; the run stops here")

    def _events(self, state: SimulationState, rows: RowBlock, multipliers, context):
        spec = self.scene.insertion
        events: list[Event] = []
        needle = self.needle.geometry(state.needle)
        positions = state.tissue.positions
        if state.phase == APPROACH and rows.row_count:
            normal_rows = np.flatnonzero((rows.source == PENETRATION) & (rows.kind == UNILATERAL))
            normal_force = float(multipliers[normal_rows].sum())
            if normal_force >= spec.puncture_force:
                contact = context["contact"]
                entry = contact.barycentric @ positions[contact.nodes]
                tets, barycentric = self._locate(positions, entry[None, :], inward=contact.normal)
                if tets[0] >= 0:
                    path = InsertionPath.empty().appended(tets, barycentric, state.step)
                    state = replace(state, phase=INSERTION_PHASE, path=path)
                    events.append(Event("puncture", normal_force))
        if state.phase == INSERTION_PHASE and not events:
            # (Not in the step that punctures: the entry point is then at the tip, on either side by round-off.)
            state, more = self._insertion_events(state, rows, multipliers, needle)
            events.extend(more)
        elif state.phase == CUTTING_PHASE:
            state, more = self._tearing_events(state, rows, multipliers, context)
            events.extend(more)
        return state, events

    def _insertion_events(self, state, rows, multipliers, needle):
        spec = self.scene.insertion
        events: list[Event] = []
        positions = state.tissue.positions
        cutting = self.scene.cutting
        if cutting.enabled and rows.row_count:
            lateral = (rows.source == INSERTION) & (rows.kind == BILATERAL)
            force_on_needle = (rows.directions[lateral] * multipliers[lateral, None]).sum(axis=0)
            if cut_criterion(force_on_needle, state.path.point_count, cutting.cutting_force):
                mean_force = float(np.linalg.norm(force_on_needle)) / state.path.point_count
                state = self._start_cut(state, -force_on_needle / np.linalg.norm(force_on_needle))
                events.append(Event("cut_start", mean_force))
                return state, events
        locator = _LazyLocator(positions, self.tets)
        path, _ = grow_path(
            state.path,
            tip=needle.tip,
            tissue_positions=positions,
            mesh_tets=self.tets,
            locator=locator,
            spacing=spec.spacing,
            step=state.step,
        )
        beyond = points_beyond_tip(path, path.positions(positions, self.tets), needle)
        if np.any(beyond):
            path = path.subset(~beyond)
            events.append(Event("retraction"))
        state = replace(state, path=path)
        if path.point_count == 0:
            state = replace(state, phase=APPROACH)
            events.append(Event("withdrawal"))
        return state, events

    def _start_cut(self, state, direction):
        """The first cut surface: the path swept along the cut direction (module `refsim.constraints.cut`)."""
        from refsim.cutting import CutSurface, TriangulationParameters

        cutting = self.scene.cutting
        positions = state.tissue.positions
        path_points = resample_polyline(state.path.positions(positions, self.tets), cutting.point_spacing)
        cloud = sweep_points(path_points, direction, cutting.extent, cutting.point_spacing)
        parameters = TriangulationParameters.from_degrees(
            min_angle=cutting.min_angle, max_angle=cutting.max_angle, max_surface_angle=cutting.max_normal_angle
        )
        cut = self._grow_cut(CutSurface.empty(parameters), cloud, positions, state.step)
        extras = {**state.extras, "cut_direction": np.asarray(direction, dtype=float)}
        return replace(state, phase=CUTTING_PHASE, cut=cut, path=state.path.subset(np.array([0])), extras=extras)

    def _grow_cut(self, cut, points, positions, step):
        """Add deformed-state points to the cut, kept in rest coordinates (equation 4); drop those outside the
        tissue and those within d_c/2 of an existing point."""
        cutting = self.scene.cutting
        if cut.point_count:
            points = _far_from(points, cut.deformed_points(positions, self.tets), 0.5 * cutting.point_spacing)
        if len(points) == 0:
            return cut
        tets, barycentric = TetLocator(positions, self.tets).locate(points)
        inside = tets >= 0
        if not np.any(inside):
            return cut
        rest = np.einsum("pk,pkj->pj", barycentric[inside], self.models.mesh.rest_positions[self.tets[tets[inside]]])
        return cut.with_points(rest, tets[inside], barycentric[inside], step)

    def _grow_cut_rest(self, cut, rest_points, step):
        """Add rest-state points to the cut (those inside the tissue and farther than d_c/2 from every point)."""
        spacing = self.scene.cutting.point_spacing
        if cut.point_count and len(rest_points):
            rest_points = _far_from(rest_points, cut.rest_points, 0.5 * spacing)
        if len(rest_points) == 0:
            return cut
        tets, barycentric = self._rest_locator().locate(rest_points)
        inside = tets >= 0
        if not np.any(inside):
            return cut
        return cut.with_points(rest_points[inside], tets[inside], barycentric[inside], step)

    def _rest_locator(self):
        if getattr(self, "_rest_locator_cache", None) is None:
            self._rest_locator_cache = TetLocator(self.models.mesh.rest_positions, self.tets)
        return self._rest_locator_cache

    def _tearing_events(self, state, rows_block, multipliers, context):
        """Extend the cut when a border contact force reaches f_t (module `refsim.constraints.cut`)."""
        cutting = self.scene.cutting
        rows = context.get("border_rows", np.zeros(0, dtype=np.int64))
        if rows.size == 0:
            return state, []
        forces = multipliers[rows]
        strongest = int(np.argmax(forces))
        if forces[strongest] < cutting.tearing_force:
            return state, []
        positions = state.tissue.positions
        cut = state.cut
        surface = cut.deformed_points(positions, self.tets)
        outward = -rows_block.directions[rows[strongest]]  # against the contact's normal −n_c (deformed state)
        front, _ = front_border_points(cut, surface, state.extras["cut_direction"])
        needle = self.needle.geometry(state.needle)
        entry = state.path.positions(positions, self.tets)[:1]
        arc, _ = needle.project(surface[front])
        front = front[arc >= needle.project(entry)[0][0] - cutting.point_spacing]  # along the inserted length
        # Grow in rest coordinates, where the triangulation lives: the outward direction pulled back through each
        # front point's tet (F⁻¹ u), so that new points keep the rest-state spacing d_c.
        gradients = self.tissue.deformation_gradients(positions)[cut.tet_indices[front]]
        rest_outward = np.linalg.solve(gradients, np.broadcast_to(outward, (front.size, 3))[..., None])[..., 0]
        rest_outward /= np.linalg.norm(rest_outward, axis=1, keepdims=True)
        new_points = sweep_points(cut.rest_points[front], rest_outward, cutting.extent, cutting.point_spacing, first=1)
        grown = self._grow_cut_rest(cut, new_points, state.step)
        return replace(state, cut=grown), [Event("tear", float(forces[strongest]))]

    def _locate(self, positions, points, *, inward):
        """Tet and barycentric coordinates of points on or just under the surface."""
        locator = TetLocator(positions, self.tets)
        tets, barycentric = locator.locate(points)
        if np.any(tets < 0):
            # A point exactly on the surface may be reported outside by round-off: step inside by 1e-9 of the
            # mesh size, far below any physical length of the scene.
            size = float(np.ptp(positions, axis=0).max())
            retry = tets < 0
            nudged, nudged_bary = locator.locate(points[retry] - 1e-9 * size * inward)
            tets[retry], barycentric[retry] = nudged, nudged_bary
        return tets, barycentric


class _LazyLocator:
    """Builds the tet locator on first use (most steps add no insertion point)."""

    def __init__(self, positions, tets) -> None:
        self._positions, self._tets, self._locator = positions, tets, None

    def locate(self, points):
        if self._locator is None:
            self._locator = TetLocator(self._positions, self._tets)
        return self._locator.locate(points)


def _triangulation_seconds(before, after) -> float:
    """Seconds of the triangulation done in this step (0 when the cut did not grow)."""
    if after is None or after is before or after.last_triangulation is None:
        return 0.0
    return float(after.last_triangulation.seconds)


def _far_from(points: np.ndarray, existing: np.ndarray, distance: float) -> np.ndarray:
    """The points farther than ``distance`` [m] from every existing point (KD-tree), shape (k, 3)."""
    from scipy.spatial import cKDTree

    if len(points) == 0 or len(existing) == 0:
        return points
    nearest, _ = cKDTree(existing).query(points, k=1)
    return points[nearest > distance]
