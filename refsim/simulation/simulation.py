"""The time step loop (DESIGN.md, "One time step"): it orders the stages and owns none of them.

- stage: motion; what: the controls at t + dt: needle base pose, tissue boundary displacements; owner:
  `refsim.scene.controls`
- stage: free_motion; what: each body's free motion (one Newton step of implicit Euler through its compliance
  strategy, or a kinematic pose), without constraint forces; owner: the bodies (`refsim.simulation.bodies`,
  `refsim.simulation.needle_body`; models in `refsim.fem`)
- stage: detection; what: rows of H from the free positions, by phase; owner: `refsim.simulation.detection`
  (builders in `refsim.constraints`)
- stage: compliance; what: W = Σ_b H_b A_b⁻¹ H_bᵀ over the bodies the rows touch and the constraint problem;
  owner: each body's `compliance`; `RowBlock.problem`
- stage: solve; what: Gauss–Seidel or the exact solver; owner: `refsim.solvers`
- stage: correction; what: x_b = x_b,free + A_b⁻¹ H_bᵀ λ for each body; a non-finite value stops the run;
  owner: each body's `correct`
- stage: events; what: puncture, insertion points, retraction, withdrawal, cut start, tears; owner:
  `refsim.simulation.events` (cut growth in `refsim.cutting.growth`)

The bodies (:class:`~refsim.simulation.bodies.Body`: the tissue, then the needle) are a tuple, ``bodies``; the
stages above loop over it. The scene, the models and the controls are static; a step takes a
:class:`SimulationState` and returns a new one with the :class:`~refsim.simulation.records.StepRecord` of what
it did. A step is a function of its state: a new simulation of the same scene continued from a state gives the
bits the uninterrupted run gives. Nothing the scene does not declare is computed: a rigid needle has no beam
solve, μ = 0 gives no friction rows, a scene without cutting never builds a cut.
"""

from __future__ import annotations

import logging
import time as clock
from collections.abc import Callable

import numpy as np

from refsim.constraints import (
    AXIAL_FRICTION,
    INSERTION,
    LATERAL_FIRST,
    LATERAL_SECOND,
    PENETRATION,
    ROLE_NAMES,
    SOURCE_NAMES,
    UNILATERAL,
    InsertionPath,
    RowBlock,
    StepGeometry,
)
from refsim.constraints.channel import stuck_points
from refsim.constraints.rows import gap_roundoff
from refsim.fem.compliance import make_strategy
from refsim.fem.threads import hot_path_threads
from refsim.scene import Scene
from refsim.scene.build import InstrumentModels, SceneModels, build_controls, build_models
from refsim.scene.controls import Controls
from refsim.simulation.bodies import Body, TissueBody
from refsim.simulation.detection import Detector
from refsim.simulation.events import EventRules
from refsim.simulation.instrument import Instrument
from refsim.simulation.margins import held_rows, problem_scale
from refsim.simulation.records import STAGES, InstrumentRecord, StepRecord, WithinStep
from refsim.simulation.state import Phase, SimulationState, evolved
from refsim.solvers import solve_exact, solve_gauss_seidel

__all__ = ["Simulation", "SimulationState", "SimulationError", "Phase"]

logger = logging.getLogger(__name__)

#: A shaft row that slipped by at most this fraction of d_i over a step is at rest (stuck): 1e-6 d_i is far
#: below any needle travel per step (10 mm/s × 1 ms = 20 d_i at d_i = 0.5 mm) and far above a stuck row's
#: solved slip (the solver's residual).
REST_SLIP = 1e-6

# Kept for code that imported the phase names from here.
APPROACH, INSERTION_PHASE, CUTTING_PHASE = Phase.APPROACH, Phase.INSERTION, Phase.CUTTING


class SimulationError(RuntimeError):
    """The simulation reached a state it cannot continue from (non-finite values, a blown-up energy); the
    message names the step and what was detected."""


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

    def __init__(
        self, scene: Scene, models: SceneModels | None = None, controls: Controls | None = None
    ) -> None:
        self.scene = scene
        self.models = models if models is not None else build_models(scene)
        self.controls = controls if controls is not None else build_controls(scene, self.models)
        self.tets = np.asarray(self.models.mesh.tets)
        self.faces = np.asarray(self.models.mesh.boundary_faces)
        self.tissue = self.models.tissue
        self.dt = scene.time.dt
        spec = scene.compliance
        self.tissue_compliance = make_strategy(
            spec.strategy,
            refresh_every=spec.refresh_every,
            linear_solver=spec.linear_solver,
            tolerance=spec.tolerance,
            w_update=spec.w_update,
        ).bind()
        self.tissue_body = TissueBody(self.tissue, self.tissue_compliance)
        # what the strategy keeps for the run (the fast mode's rest factor) is made now, not in the first step
        self.tissue_body.prepare(self.dt)
        instrument_models = self.models.instruments or (
            InstrumentModels(
                "needle", scene.needle, self.models.needle, self.models.trajectory, scene.cutting.enabled
            ),
        )
        rest = self.models.mesh.rest_positions
        #: The scene's instruments, in order: each with its body, controls, detector and event rules.
        self.instruments: tuple[Instrument, ...] = tuple(
            Instrument(index, models, scene, self.tissue, self.faces, self.tets, rest)
            for index, models in enumerate(instrument_models)
        )
        #: Every body of the step, in the order W is summed: the tissue, then each instrument's needle.
        self.bodies: tuple[Body, ...] = (self.tissue_body, *(i.body for i in self.instruments))
        #: The instruments whose needle left its model's range in a step (warned once each: _warn_strained).
        self._strained: set[str] = set()
        #: Whether a constraint solve of this simulation did not converge yet (warned once: _warn_unsolved).
        self._unsolved = False

    @property
    def sole(self) -> Instrument:
        """The only instrument; a simulation of several raises (use ``instruments``)."""
        if len(self.instruments) != 1:
            names = ", ".join(instrument.name for instrument in self.instruments)
            raise AttributeError(
                f"the simulation has {len(self.instruments)} instruments ({names}): use instruments"
            )
        return self.instruments[0]

    @property
    def needle(self):
        """The only instrument's needle body (one-instrument simulations only)."""
        return self.sole.body

    @property
    def detector(self) -> Detector:
        """The only instrument's detector (one-instrument simulations only)."""
        return self.sole.detector

    @property
    def event_rules(self) -> EventRules:
        """The only instrument's event rules (one-instrument simulations only)."""
        return self.sole.event_rules

    # ------------------------------------------------------------------ state

    def initial_state(self) -> SimulationState:
        """Tissue at rest, each needle at its trajectory's first pose, tips outside."""
        control = self.controls.at(0.0)
        return SimulationState(
            step=0,
            time=0.0,
            tissue=self.tissue.rest_state(),
            instruments=tuple(instrument.initial_state(control) for instrument in self.instruments),
        )

    # ------------------------------------------------------------------ step

    def step(
        self, state: SimulationState, *, record_tissue: bool = False
    ) -> tuple[SimulationState, StepRecord]:
        """Advance one time step; return the new state and the record of the step.

        BLAS and OpenMP run on one thread inside the step (on 2 cores two OpenBLAS threads made one W
        computation 26 times slower); the caller's setting is restored after it."""
        with hot_path_threads(1):
            return self._step(state, record_tissue=record_tissue)

    def _step(self, state: SimulationState, *, record_tissue: bool) -> tuple[SimulationState, StepRecord]:
        """The stages in order, each timed (``StepRecord.stage_seconds``)."""
        timer = _StageTimer()
        step, time = state.step + 1, state.time + self.dt
        control = self.controls.at(time)
        timer.lap("motion")

        free, systems = self._free_motion(state, control)
        timer.lap("free_motion")

        # The step's solve; solved again from its start while an instrument's event gave way inside it (a
        # capped tip contact reaching f_p: its next solve has that instrument's rows after the event), or
        # after an event of STEP_SOLVED_AGAIN (one that changes what holds the needle: every instrument's
        # events of that solve stand; its next solve has their rows after them, with the tissue's cut and
        # channels as they left them).
        start, settled = state, {}
        while True:
            detections = self._detect(start, free)
            rows = RowBlock.concatenate([detection.rows for detection in detections])
            point_rows = self._point_rows(rows)
            timer.lap("detection")

            problem, responses = self._problem(rows, systems, free)
            timer.lap("compliance")

            multipliers, report = self._solve(problem, self._warm_start(start, rows, point_rows))
            timer.lap("solve")

            corrected = self._correct(start, free, systems, responses, multipliers)
            self._check_finite(step, corrected, multipliers)
            self._check_converged(step, corrected)
            timer.lap("correction")

            new_state = self._advanced(
                start, step, time, corrected, detections, rows, problem, multipliers, point_rows
            )
            new_state, parts = self._events(
                new_state, detections, rows, problem, multipliers, report, settled
            )
            timer.lap("events")

            unsettled = [part for part in parts if part.name not in settled]
            # Such an event is crossed inside the step: decided after it alone, the step would end with the
            # rows chosen at its start (the insertion rows' force above the cut's by the lateral load one step
            # adds; rows holding a needle already out of the tissue, a tip row on a tip out through a far
            # face). docs/cutting.md, "When an event takes effect".
            again = any(event.solves_step_again for part in unsettled for event in part.events)
            gave_way = {part.name: part for part in unsettled if again or part.within_step is not None}
            if not gave_way:
                break
            settled.update(gave_way)
            start = evolved(
                state,
                instruments=tuple(
                    evolved(new_state.instrument(own.name), needle=own.needle) if own.name in settled else own
                    for own in state.instruments
                ),
            )
            if again:
                start = evolved(
                    start, cut=new_state.cut, channels=new_state.channels, cracks=new_state.cracks
                )

        self._warn_strained(step, new_state)
        self._warn_unsolved(step, rows, problem, report)
        record = self._record(
            state, new_state, control, rows, problem, multipliers, report, parts, timer.seconds, record_tissue
        )
        return new_state, record

    def run(
        self,
        *,
        steps: int | None = None,
        on_step: Callable[[SimulationState, StepRecord], None] | None = None,
        state: SimulationState | None = None,
    ) -> SimulationState:
        """Run ``steps`` steps (the scene's duration by default), calling ``on_step`` after each.

        BLAS and OpenMP run on one thread for the whole loop, ``on_step`` included (one limit set for the run
        instead of one per step, as :meth:`step` does alone); the caller's setting is restored after it."""
        state = self.initial_state() if state is None else state
        total = self.scene.time.step_count if steps is None else steps
        every = self.scene.output.tissue_every
        with hot_path_threads(1):
            for index in range(1, total + 1):
                record_tissue = index % every == 0 or index == total
                state, record = self.step(state, record_tissue=record_tissue)
                if on_step is not None:
                    on_step(state, record)
        return state

    # ------------------------------------------------------------------ stages

    def _free_motion(self, state: SimulationState, control) -> tuple[dict, dict]:
        """Each body's free state and step system, by name: the tissue (from the carried factor state), then
        each instrument's needle at its own controls."""
        self.tissue_compliance.resume(state.tissue_factor)
        tissue = self.tissue_body
        free_tissue, tissue_system = tissue.free_motion(state.tissue, control, self.dt)
        free, systems = {tissue.name: free_tissue}, {tissue.name: tissue_system}
        for instrument in self.instruments:
            body = instrument.body
            own = state.instrument(instrument.name).needle
            free[body.name], systems[body.name] = body.free_motion(own, instrument.control(control), self.dt)
        return free, systems

    def _detect(self, state: SimulationState, free: dict) -> list:
        """Each instrument's detection (rows by its phase) on the step's geometry: the tissue and its needle
        at the start of the step and after free motion."""
        detections = []
        for instrument in self.instruments:
            body = instrument.body
            geometry = StepGeometry(
                mesh_tets=self.tets,
                tissue_previous=state.tissue.positions,
                tissue_free=free[self.tissue_body.name].positions,
                needle_previous=body.geometry(state.instrument(instrument.name).needle),
                needle_free=body.geometry(free[body.name]),
            )
            detections.append(instrument.detect(state, geometry))
        return detections

    def _advanced(
        self,
        state,
        step: int,
        time: float,
        corrected: dict,
        detections,
        rows,
        problem,
        multipliers,
        point_rows: tuple | None = None,
    ) -> SimulationState:
        """The state after the correction, before the events: each body's corrected state, each instrument's
        path with its rings and its points' multipliers, the tissue factor's carried state. ``point_rows``:
        :meth:`_point_rows` of ``rows`` (computed here when None)."""
        point_rows = self._point_rows(rows) if point_rows is None else point_rows
        instruments = []
        for instrument, detection in zip(self.instruments, detections, strict=True):
            own = state.instrument(instrument.name)
            path = own.path if detection.rings is None else own.path.with_rings(detection.rings)
            path = self._store_multipliers(
                path, rows, instrument.index, problem, multipliers, point_rows[instrument.index]
            )
            instruments.append(evolved(own, needle=corrected[instrument.body.name], path=path))
        return evolved(
            state,
            step=step,
            time=time,
            tissue=corrected[self.tissue_body.name],
            instruments=tuple(instruments),
            tissue_factor=self.tissue_compliance.carried(),
        )

    def _events(
        self, state: SimulationState, detections, rows, problem, multipliers, report, settled: dict
    ) -> tuple[SimulationState, list[InstrumentRecord]]:
        """Each instrument's events in order, on its own rows and multipliers, and its record. An instrument
        in ``settled`` (by name: its record from the solve in which an event gave way inside the step) has
        had its events: its record keeps their events, criteria and within-step state, with its end state
        from this solve."""
        parts = []
        scale = None if problem is None else problem_scale(problem, multipliers)  # one product by W per step
        for instrument, detection in zip(self.instruments, detections, strict=True):
            mine = rows.instruments == instrument.index
            earlier = settled.get(instrument.name)
            events, criteria, within = (), (), None
            if earlier is None:
                instrument.event_rules.margins.begin(
                    problem, rows, multipliers, report, own=mine, scale=scale
                )
                state, events = instrument.event_rules.apply(
                    state, instrument.name, detection, multipliers[mine]
                )
                criteria = instrument.event_rules.margins.taken()
                within = self._within_step(instrument, rows, multipliers, events)
            else:
                events, criteria, within = earlier.events, earlier.criteria, earlier.within_step
            own = state.instrument(instrument.name)
            parts.append(
                InstrumentRecord(
                    name=instrument.name,
                    phase=str(own.phase),
                    events=tuple(events),
                    base_position=own.needle.base_position,
                    needle_positions=own.needle.positions,
                    needle_frames=own.needle.frames,
                    needle_force=instrument.needle_force(rows, multipliers),
                    insertion_point_count=own.path.point_count,
                    needle_strain=instrument.body.element_strain(own.needle)[0],
                    criteria=criteria,
                    within_step=within,
                )
            )
        return state, parts

    @staticmethod
    def _within_step(instrument, rows, multipliers, events) -> WithinStep | None:
        """The instrument's state at a puncture through its capped tip contact (the contact gave way at f_p
        inside the step), or None: no puncture, or a plain contact, which holds the tip to the step's end."""
        if not any(event.name == "puncture" for event in events):
            return None
        mine = rows.instruments == instrument.index
        normal = np.flatnonzero(mine & (rows.source == PENETRATION) & (rows.kind == UNILATERAL))
        limits = rows.force_limit if rows.force_limit.size else np.full(rows.row_count, np.inf)
        if normal.size == 0 or not np.all(np.isfinite(limits[normal])):
            return None
        tip = mine & (rows.source == PENETRATION)
        return WithinStep(
            event="puncture",
            needle_force=instrument.needle_force(rows, multipliers),
            tip_force=(rows.directions[tip] * multipliers[tip, None]).sum(axis=0),
            point=np.array(rows.points[normal[0]]),
            normal_force=float(multipliers[normal].sum()),
        )

    def _record(
        self, state, new_state, control, rows, problem, multipliers, report, parts, seconds, record_tissue
    ) -> StepRecord:
        """What the step did: its rows and multipliers, each instrument's record, the stage times, the cut's
        size, the tissue when asked."""
        return StepRecord(
            step=new_state.step,
            time=new_state.time,
            tissue_positions=new_state.tissue.positions if record_tissue else None,
            row_kind=rows.kind,
            row_source=rows.source,
            row_points=rows.points,
            row_directions=rows.directions,
            row_forces=multipliers,
            solver=report,
            stage_seconds=seconds,
            problem=problem if self.scene.output.record_problems else None,
            cut_point_count=0 if new_state.cut is None else new_state.cut.point_count,
            cut_triangle_count=0 if new_state.cut is None else new_state.cut.triangle_count,
            triangulation_seconds=_triangulation_seconds(state.cut, new_state.cut),
            boundary_displacements=control.boundary_displacements if control.boundary_nodes.size else None,
            row_role=rows.roles,
            row_point=rows.points_of_rows,
            instruments=tuple(parts),
            row_instrument=rows.instruments,
        )

    def _problem(self, rows: RowBlock, systems: dict, free: dict | None = None):
        """The constraint problem of the rows, W = Σ_b H_b A_b⁻¹ H_bᵀ over the bodies with a Jacobian in
        them (in the order of ``bodies``), and each body's responses by name (None: no rows on it).
        ``free``: the bodies' free states the gaps were measured on, whose coordinates give the gaps'
        round-off (:func:`refsim.constraints.rows.gap_roundoff`; None: no round-off)."""
        responses = dict.fromkeys(body.name for body in self.bodies)
        if rows.row_count == 0:
            return None, responses
        compliance = None
        for body in self.bodies:
            jacobian = rows.jacobians.get(body.name)
            if jacobian is None:
                continue
            part, responses[body.name] = body.compliance(systems[body.name], jacobian)
            compliance = part if compliance is None else compliance + part
        if compliance is None:
            compliance = np.zeros((rows.row_count, rows.row_count))
        roundoff = 0.0 if free is None else gap_roundoff(*(own.positions for own in free.values()))
        return rows.problem(compliance, roundoff=roundoff), responses

    def _correct(self, state: SimulationState, free: dict, systems: dict, responses: dict, multipliers):
        """Each body's state after the constraint forces, by name: x_b = x_b,free + A_b⁻¹ H_bᵀ λ."""
        return {
            body.name: body.correct(
                systems[body.name],
                state.body_state(body.name),
                free[body.name],
                responses[body.name],
                multipliers,
                self.dt,
            )
            for body in self.bodies
        }

    def _solve(self, problem, warm_start):
        if problem is None:
            return np.zeros(0), None
        spec = self.scene.solver
        if spec.method == "exact":
            return solve_exact(
                problem,
                tolerance=spec.tolerance,
                backend=spec.backend,
                method=spec.exact_method,
                warm_start=warm_start,
            )
        return solve_gauss_seidel(
            problem,
            tolerance=spec.tolerance,
            max_iterations=spec.max_iterations,
            warm_start=warm_start,
            criterion=spec.criterion,
        )

    def _point_rows(self, rows: RowBlock) -> tuple:
        """Each instrument's insertion points' rows in ``rows`` (:func:`_point_rows`), by instrument index:
        read once per solve, by the warm start and by the storing of the multipliers."""
        return tuple(_point_rows(rows, instrument.index) for instrument in self.instruments)

    def _warm_start(
        self, state: SimulationState, rows: RowBlock, point_rows: tuple | None = None
    ) -> np.ndarray:
        """Last step's multipliers of each instrument's insertion points (they persist from step to step),
        zero elsewhere; read from the rows' instrument, role and point fields (``point_rows``:
        :meth:`_point_rows` of ``rows``, computed here when None)."""
        point_rows = self._point_rows(rows) if point_rows is None else point_rows
        warm = np.zeros(rows.row_count)
        for instrument in self.instruments:
            found, points, columns = point_rows[instrument.index]
            if found.size:
                warm[found] = state.instrument(instrument.name).path.multipliers[points, columns]
        return warm

    def _store_multipliers(
        self,
        path: InsertionPath,
        rows: RowBlock,
        index: int,
        problem,
        multipliers: np.ndarray,
        point_rows: tuple | None = None,
    ) -> InsertionPath:
        """Instrument ``index``'s path with each point's multipliers, stick state, stick anchor and annulus
        stretch after the solve, read from the rows' instrument, role and point fields (points without rows
        this step keep theirs; ``point_rows``: :func:`_point_rows` of the instrument, computed here when
        None)."""
        found, points, columns = _point_rows(rows, index) if point_rows is None else point_rows
        if found.size == 0:
            return path
        stored = np.array(path.multipliers, dtype=float, copy=True)
        stored[points] = 0.0  # (a point's every column, once per row: the same zeros)
        stored[points, columns] = multipliers[found]
        # (the path's own (p, 3) float array, updated: what with_multipliers would store, without its copy)
        path = path._with(multipliers=stored)
        if rows.shaft_rows.size == 0:
            return path
        # The instrument's shaft rows (row indices are unique: the mask selects them in shaft-row order).
        selected = (rows.source[rows.shaft_rows] == INSERTION) & (rows.instruments[rows.shaft_rows] == index)
        shaft = rows.shaft_rows[selected]
        if shaft.size == 0:
            return path
        # The stick state of each point for the next step's coefficient (μ_s when stuck, μ_d when slipping).
        pairs = rows.shaft_pairs[selected]
        bounds = rows.shaft_friction_coefficient[selected] * (
            np.linalg.norm(multipliers[pairs], axis=1) + rows.shaft_normal_preload[selected]
        )
        owners = rows.points_of_rows[shaft]
        # The needle surface's slip on the tissue over the step: the solved gap of each axial row.
        slips = problem.compliance[shaft] @ multipliers + problem.free_gap[shaft]
        stuck_now = stuck_points(
            multipliers[shaft], bounds, slips=slips, rest_slip=REST_SLIP * self.scene.insertion.spacing
        )
        stuck = np.array(path.stuck, dtype=bool, copy=True)
        stuck[owners] = stuck_now
        # A stuck point keeps its anchor; one that slipped gets it placed anew at the next step, from the
        # annulus' stretch −C λ (refsim.constraints.friction).
        added = rows.problem_compliance_diagonal()[shaft]
        anchors = np.array(path.anchors, dtype=float, copy=True)
        stretch = np.array(path.stretch, dtype=float, copy=True)
        anchors[owners] = np.where(stuck_now, rows.anchors[shaft], np.nan)
        stretch[owners] = -added * multipliers[shaft]
        # the path's own per-point arrays, updated: with_stuck and with_anchors' values, one copy of the path
        return path._with(stuck=stuck, anchors=anchors, stretch=stretch)

    def _check_converged(self, step, states: dict) -> None:
        """Stop where a body says its step diverged (a body's ``diverged(state)``: the flexible needle's)."""
        for body in self.bodies:
            diverged = getattr(body, "diverged", None)
            message = diverged(states[body.name]) if diverged is not None else None
            if message:
                raise SimulationError(f"step {step}: {message}; the run stops here")

    def _warn_strained(self, step: int, state: SimulationState) -> None:
        """Warn (logging), once per needle, where its step left the beam model's range without diverging (a
        body's ``strained(state)``: the flexible needle's element strain above
        ``refsim.simulation.needle_body.STRAIN_WARNING``); the value is recorded every step
        (``InstrumentRecord.needle_strain``)."""
        for instrument in self.instruments:
            strained = getattr(instrument.body, "strained", None)
            if strained is None or instrument.name in self._strained:
                continue
            message = strained(state.instrument(instrument.name).needle)
            if message:
                self._strained.add(instrument.name)
                logger.warning("step %d: %s", step, message)

    def _warn_unsolved(self, step: int, rows: RowBlock, problem, report) -> None:
        """Warn (logging), once per simulation, at the first step whose constraint solve did not converge,
        naming the rows no force can satisfy when there are some (:func:`held_rows`: a rigid needle driven
        into held tissue); the run goes on and its summary counts such steps."""
        if self._unsolved or problem is None or report is None or report.converged:
            return
        self._unsolved = True
        text = (
            f"step {step}: the constraint solve did not converge (natural residual {report.residual:.3g}, "
            f"tolerance {self.scene.solver.tolerance:g})"
        )
        held = held_rows(rows, problem)
        if held.any():
            owners = sorted({int(i) for i in rows.instruments[held]})
            names = ", ".join(
                repr(self.instruments[i].name) for i in owners if 0 <= i < len(self.instruments)
            )
            sources = ", ".join(sorted({SOURCE_NAMES[int(k)] for k in rows.source[held]}))
            depth = 1e3 * float(np.abs(problem.free_gap[held]).max())
            count = int(held.sum())
            rows_text = f"{count} row" if count == 1 else f"{count} rows"
            verb = "holds" if count == 1 else "hold"
            text += (
                f": {rows_text} of the needle {names or '(unknown)'} ({sources}) {verb} it against tissue "
                "that cannot move (compliance 0: a rigid needle and held tissue nodes only), with a gap of "
                f"up to {depth:.3g} mm that no force can close: the trajectory drives the needle into the "
                "tissue's fixed region (mesh.fixed_faces, mesh.fixed_box, mesh.fixed_nodes or the boundary "
                "motion's nodes). Those rows' forces, and this step's, are not a solution"
            )
        logger.warning(
            "%s; the run goes on, and its summary counts the steps whose solve did not converge", text
        )

    @staticmethod
    def _check_finite(step, states: dict, multipliers) -> None:
        checked = [(f"{name} positions", body_state.positions) for name, body_state in states.items()]
        for name, array in (*checked, ("constraint forces", multipliers)):
            if not np.all(np.isfinite(array)):
                raise SimulationError(f"step {step}: non-finite {name} detected; the run stops here")


def _triangulation_seconds(before, after) -> float:
    """Seconds of the triangulation done in this step (0 when the cut did not grow)."""
    if after is None or after is before or after.last_triangulation is None:
        return 0.0
    return float(after.last_triangulation.seconds)


#: Column of each insertion role in ``InsertionPath.multipliers`` (−1: not an insertion point's row).
_ROLE_COLUMN = np.full(len(ROLE_NAMES), -1, dtype=np.int64)
_ROLE_COLUMN[[LATERAL_FIRST, LATERAL_SECOND, AXIAL_FRICTION]] = (0, 1, 2)


def _point_rows(rows: RowBlock, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Instrument ``index``'s insertion points' rows: their indices, their points (into its path) and their
    columns in ``InsertionPath.multipliers``, shape (k,) each."""
    if rows.row_count == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, empty
    columns = _ROLE_COLUMN[rows.roles]
    points = rows.points_of_rows
    found = np.flatnonzero(
        (rows.source == INSERTION) & (points >= 0) & (columns >= 0) & (rows.instruments == index)
    )
    return found, points[found], columns[found]
