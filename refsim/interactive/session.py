"""An interactive run: the scene's simulation stepped at its dt with the needle base pose given live,
written to a results file by the same writer as `refsim run`, with the applied trajectory and a replay scene
beside it.

The session owns the step; :class:`refsim.interactive.pacing.Pacer` decides when it is taken (at the wall
clock, or once per received pose). A session ends with :meth:`InteractiveSession.finish`: one last step (the
pose held) records the tissue (as the last step of `refsim run` does), the results file is closed, and the
trajectory CSV and the replay scene are written beside it.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import time as clock

import numpy as np

from refsim.interactive.pose import PoseTarget, exact_unit
from refsim.interactive.recording import AppliedTrajectory, replay_paths, write_replay_scene

__all__ = ["InteractiveSession", "StepReport", "start_pose"]

logger = logging.getLogger(__name__)

#: Wall-clock window of the real-time factor [s].
RATE_WINDOW = 1.0
#: Steps kept in :attr:`InteractiveSession.force_history`.
HISTORY_STEPS = 20_000


@dataclasses.dataclass(frozen=True)
class StepReport:
    """What a step sends back to the pose stream and shows in the window.

    Attributes
    ----------
    step, time : Step number and simulated time [s].
    force : Force of the tissue on the needle [N], (3,) (the haptic force).
    phase : approach, insertion or cutting.
    events : Names of the step's events (puncture, cut_start, ...).
    base, direction : The applied base pose [m], unit (3,).
    real_time_factor : Simulated over wall-clock time over the last second (nan before two steps).
    """

    step: int
    time: float
    force: np.ndarray
    phase: str
    events: tuple[str, ...]
    base: np.ndarray
    direction: np.ndarray
    real_time_factor: float

    def message(self) -> dict:
        """The step's line of the pose stream (JSON-ready)."""
        rate = self.real_time_factor
        return {
            "step": self.step,
            "time": self.time,
            "force": [float(value) for value in self.force],
            "phase": self.phase,
            "events": list(self.events),
            "base": [float(value) for value in self.base],
            "direction": [float(value) for value in self.direction],
            "rtf": None if not np.isfinite(rate) else round(float(rate), 4),
        }


def start_pose(scene) -> tuple[np.ndarray, np.ndarray]:
    """The base position [m] and unit direction of the scene's trajectory at t = 0 (an aimed insertion is
    resolved on the mesh); the direction's norm is exactly 1.0 (:func:`refsim.interactive.pose.exact_unit`).

    Raises
    ------
    ValueError
        A SceneError or MeshError naming the file and the defect.
    """
    from refsim.scene import SceneError
    from refsim.scene.trajectory import Trajectory, aimed

    spec = scene.trajectory
    if spec.entry is not None:
        from refsim.scene.build import build_mesh

        mesh = build_mesh(scene.mesh, scene.base_directory)
        trajectory = aimed(spec, mesh.rest_positions, mesh.boundary_faces, scene.needle.length).trajectory
    else:
        try:
            trajectory = Trajectory.from_spec(spec, scene.base_directory)
        except ValueError as error:
            raise SceneError(f"{scene.source}: trajectory.file: {error}") from None
    base, direction = trajectory.pose(0.0)
    return np.asarray(base, dtype=float), exact_unit(direction)


class InteractiveSession:
    """One interactive run of a scene, written to ``output``.

    Parameters
    ----------
    scene : The validated scene (its trajectory gives the start pose only).
    output : The results file (.h5); ``OUT.trajectory.csv`` and ``OUT.replay.toml`` are written beside it.
    overwrite : Replace existing files.
    max_speed : Largest base speed [m/s] (:class:`~refsim.interactive.pose.PoseTarget`).
    max_turn : Largest turning rate [rad/s].
    buffer_steps : Steps per written block of the results file.

    Raises
    ------
    RunInputError
        Bad input (the scene's models, the mesh, an output path), before any file is written.
    """

    def __init__(
        self,
        scene,
        output,
        *,
        overwrite: bool = False,
        max_speed: float = 0.05,
        max_turn: float = np.radians(30.0),
        buffer_steps: int | None = None,
    ) -> None:
        from refsim.io.driver import RunInputError, StepSink, check_output_path, check_results_path
        from refsim.io.filelock import WriterLockedError
        from refsim.io.writer import DEFAULT_BUFFER_STEPS, ResultWriter
        from refsim.scene.build import build_controls, build_models
        from refsim.scene.controls import Controls
        from refsim.scene.spec import TrajectorySpec
        from refsim.simulation import Simulation
        from refsim.simulation.summary import RunSummary

        if scene.instruments:
            names = ", ".join(spec.name for spec in scene.instruments)
            raise RunInputError(
                f"{scene.source}: refsim interactive steers one needle; this scene has [[instruments]] "
                f"({names}): run it with refsim run"
            )
        self.output = check_results_path(output, overwrite=overwrite, scene=scene)
        self.trajectory_path, self.replay_path = replay_paths(self.output)
        for path, what in ((self.trajectory_path, "trajectory file"), (self.replay_path, "replay scene")):
            check_output_path(path, overwrite=overwrite, what=what)
        try:
            base, direction = start_pose(scene)
            # The run's own scene holds the start pose (so the needle model, the writer's rest nodes and a
            # replay all start from the same bits); the poses after it come from the session.
            self.scene = dataclasses.replace(
                scene,
                trajectory=TrajectorySpec(
                    times=(0.0,),
                    base_positions=(tuple(base.tolist()),),
                    directions=(tuple(direction.tolist()),),
                ),
            )
            self.models = build_models(self.scene)
            boundary = build_controls(self.scene, self.models).boundary
        except (ValueError, OSError) as error:
            raise RunInputError(str(error)) from None
        self.source_scene = scene
        self.applied = AppliedTrajectory(base, direction)
        self.target = PoseTarget(
            base, direction, needle_length=scene.needle.length, max_speed=max_speed, max_turn=max_turn
        )
        self.simulation = Simulation(
            self.scene, self.models, Controls(trajectory=self.applied, boundary=boundary)
        )
        self.dt = self.scene.time.dt
        self.tissue_every = self.scene.output.tissue_every
        self.state = self.simulation.initial_state()
        self.summary = RunSummary(total_steps=None, output=str(self.output))
        try:
            self.output.parent.mkdir(parents=True, exist_ok=True)
            self.writer = ResultWriter(
                self.output,
                self.scene,
                self.models,
                overwrite=overwrite,
                buffer_steps=DEFAULT_BUFFER_STEPS if buffer_steps is None else buffer_steps,
            )
        except WriterLockedError as error:
            raise RunInputError(str(error)) from None
        except (FileExistsError, IsADirectoryError, NotADirectoryError, PermissionError, ValueError) as error:
            raise RunInputError(f"{self.output}: cannot create the results file: {error}") from None
        self._record_step = StepSink(self.writer, self.summary, self.models.mesh.rest_positions, total=0)
        self._wall = collections.deque()  # (wall clock [s], simulated time [s]) of the recent steps
        self.last_record = None
        #: (time [s], |force on the needle| [N]) of the recent steps (the window's live plot)
        self.force_history: collections.deque = collections.deque(maxlen=HISTORY_STEPS)
        self.finished = False
        self.status, self.stop_reason = "running", ""

    # ------------------------------------------------------------------ stepping

    @property
    def real_time_factor(self) -> float:
        """Simulated time over wall-clock time across the last :data:`RATE_WINDOW` seconds of steps."""
        if len(self._wall) < 2:
            return float("nan")
        (wall0, time0), (wall1, time1) = self._wall[0], self._wall[-1]
        return (time1 - time0) / (wall1 - wall0) if wall1 > wall0 else float("nan")

    def step(self, *, final: bool = False) -> StepReport:
        """One step at the pose the target allows (:meth:`PoseTarget.advance`); ``final`` records the
        tissue (the last step of a run). A numerical problem raises (the caller ends the session with
        :meth:`fail`)."""
        if self.finished:
            raise RuntimeError("the session is finished")
        time = self.state.time + self.dt
        base, direction = self.target.advance(self.dt)
        self.applied.append(time, base, direction)
        index = self.state.step + 1
        state, record = self.simulation.step(
            self.state, record_tissue=final or index % self.tissue_every == 0
        )
        self._record_step(state, record)
        self.state, self.last_record = state, record
        self.force_history.append((record.time, float(np.linalg.norm(record.needle_force))))
        now = clock.perf_counter()
        self._wall.append((now, record.time))
        while len(self._wall) > 2 and now - self._wall[0][0] > RATE_WINDOW:
            self._wall.popleft()
        return StepReport(
            step=record.step,
            time=record.time,
            force=np.asarray(record.needle_force, dtype=float),
            phase=str(record.phase),
            events=tuple(event.name for event in record.events),
            base=base,
            direction=direction,
            real_time_factor=self.real_time_factor,
        )

    # ------------------------------------------------------------------ ending

    def fail(self, error: BaseException) -> None:
        """End the session after a step failed: close the file (complete = False, the reason stored) and
        write the trajectory and replay of the completed steps."""
        text = str(error) or type(error).__name__
        reason = text if text.startswith("step ") else f"step {self.state.step + 1}: {text}"
        self._close(status="numerical", reason=reason)

    def finish(self) -> None:
        """End the session: a last step with the pose held records the tissue, then the files are written.
        A failure of that step ends the session as :meth:`fail` does."""
        if self.finished:
            return
        self.target.hold()
        try:
            self.step(final=True)
        except Exception as error:  # noqa: BLE001 - every failure must close the file and say why
            logger.debug("the final step failed", exc_info=True)
            self.fail(error)
            return
        self._close(status="complete", reason="")

    def _close(self, *, status: str, reason: str) -> None:
        """Close the files with a status of :data:`~refsim.simulation.summary.RUN_STATUSES` (its exit code
        is the summary's)."""
        if self.finished:
            return
        self.finished = True
        # the applied samples end at the last completed step (a failed step appended its pose)
        steps = self.state.step
        self.writer.close(complete=status == "complete", reason=reason)
        if self.writer.failure is not None and status != "write_failed":
            status = "write_failed"
            reason = f"{reason}; {self.writer.failure}" if reason else self.writer.failure
        applied = self.applied
        if applied.last_time > self.state.time:
            applied = _truncated(applied, self.state.time)
        applied.write_csv(self.trajectory_path)
        if steps > 0:
            write_replay_scene(self.scene, self.trajectory_path, steps, self.replay_path)
        self._store_applied(applied)
        self.status, self.stop_reason = status, reason
        self.summary.total_steps = steps
        self.summary.finish(status=status, stop_reason=reason, steps_written=self.writer.steps_completed)

    def _store_applied(self, applied: AppliedTrajectory) -> None:
        """Replace the results file's ``trajectory/samples`` (the start pose when the writer opened it) by the
        applied trajectory, and record the session's settings in the root attribute ``interactive``."""
        import h5py

        from refsim.io.schema import STATIC

        where = STATIC["trajectory/samples"].path
        try:
            with h5py.File(self.output, "r+") as handle:
                old = handle[where]
                attributes = dict(old.attrs)
                del handle[where]
                new = handle.create_dataset(where, data=applied.samples(), fletcher32=True)
                for key, value in attributes.items():
                    new.attrs[key] = value
                if self.replay_path.is_file():  # the scene that replays the file (the applied trajectory)
                    from refsim.scene import load_scene, scene_to_json

                    handle.attrs["scene"] = scene_to_json(load_scene(self.replay_path))
                handle.attrs["interactive"] = json.dumps(
                    {
                        "trajectory_csv": str(self.trajectory_path),
                        "replay_scene": str(self.replay_path),
                        "max_speed": self.target.max_speed,
                        "max_turn": self.target.max_turn,
                        "poses_received": self.target.received,
                        "poses_superseded": self.target.superseded,
                    }
                )
        except (OSError, ValueError) as error:
            logger.error("%s: cannot store the applied trajectory: %s", self.output, error)


def _truncated(applied: AppliedTrajectory, time: float) -> AppliedTrajectory:
    samples = applied.samples()
    kept = samples[samples[:, 0] <= time]
    out = AppliedTrajectory(kept[0, 1:4], kept[0, 4:7])
    for row in kept[1:]:
        out.append(row[0], row[1:4], row[4:7])
    return out
