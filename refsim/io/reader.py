"""Reading a results file written by :class:`refsim.io.ResultWriter` (layout in :mod:`refsim.io.schema`).

The reader trusts the root attribute ``steps_completed`` once it is checked (an integer from 0 to the length
of ``steps/step``): per-step datasets are cut to that many steps, so a file left by an interrupted run
(``complete = False``) reads like a shorter complete one. Damage is named, never read as data: a file shorter
than HDF5's superblock says (truncated: a copy or a transfer cut short) gives its two sizes, and a chunk whose
Fletcher-32 checksum does not match (a bit flip on the disk or in a copy) gives the dataset.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from refsim.cutting.laws import CUTTING_LAWS
from refsim.io import schema
from refsim.simulation.margins import CriterionSeries, EventMargin, assess

__all__ = [
    "CutHistory",
    "RecordedEvent",
    "ResultsError",
    "Results",
    "StepConstraints",
    "read_problem_group",
    "read_problems",
    "read_results",
    "results_status",
]


class ResultsError(ValueError):
    """A file that cannot be read as refsim results; the message names the file and the problem."""


class RecordedEvent(NamedTuple):
    """An event of the run: step, time [s], name, the value that triggered it (NaN when none) and its unit
    ("N", or "N/m" for the energy law's cut_start; refsim.io.schema.EVENT_VALUE_DATASETS)."""

    step: int
    time: float
    name: str
    force: float
    unit: str = "N"


class StepConstraints(NamedTuple):
    """Constraint rows of one step.

    kind : Row kind codes (names in ``Results.kind_names``), shape (r,).
    source : Row source codes (names in ``Results.source_names``), shape (r,).
    points : Tissue-side points [m], shape (r, 3).
    directions : Unit row directions, shape (r, 3).
    forces : Multipliers λ [N], shape (r,).
    """

    kind: np.ndarray
    source: np.ndarray
    points: np.ndarray
    directions: np.ndarray
    forces: np.ndarray


@dataclass(frozen=True)
class CutHistory:
    """The cut surface history: every point and triangle with the step that created it.

    Attributes
    ----------
    points : Points in rest coordinates [m], shape (p, 3).
    point_step : Creation step of each point, shape (p,).
    triangles : Triangles (point indices), shape (t, 3).
    triangle_step : Creation step of each triangle, shape (t,).
    tet_indices : Tissue tet of each point, shape (p,), or None when the file does not hold them.
    barycentric : Barycentric coordinates of each point in its tet, shape (p, 4), or None.
    """

    points: np.ndarray
    point_step: np.ndarray
    triangles: np.ndarray
    triangle_step: np.ndarray
    tet_indices: np.ndarray | None = None
    barycentric: np.ndarray | None = None

    def at(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        """Rest-state points [m] (p_s, 3) and triangles (t_s, 3) that existed after ``step``.

        Points are created before the triangles that use them and never removed, so the points of step s are a
        prefix of the history and the triangles index it directly.
        """
        point_count = int(np.count_nonzero(self.point_step <= step))
        triangles = self.triangles[self.triangle_step <= step]
        return self.points[:point_count], triangles


@dataclass(frozen=True)
class Results:
    """A run read from its results file. Per-step arrays have one entry per completed step.

    Attributes
    ----------
    path : The file.
    attributes : Root attributes (schema_version, refsim_version, git_commit, created, scene_name, ...).
    scene : The scene as a dict (decoded from the JSON root attribute).
    complete : False when the run was interrupted.
    rest_positions : Tissue rest positions [m], (n, 3). tets : (m, 4). faces : boundary triangles, (f, 3).
    fixed_nodes : Clamped tissue nodes, (c,). needle_rest_nodes : Needle nodes at t = 0 [m], (k, 3).
    step : Step indices, (s,). time : [s], (s,).
    quantities : The first instrument's step quantities, by name: one per row of
        :data:`refsim.io.schema.INSTRUMENT_STEP_QUANTITIES`, (s,) + its shape, each also an attribute of
        its name: phase (codes into ``phase_names``), (s,); base_position [m], (s, 3); needle_positions
        [m], (s, k, 3); needle_frames (s, k, 3, 3); needle_force, the force of the tissue on the needle [N],
        (s, 3), at the end of each step; insertion_point_count (s,); the state at a within-step event
        (the puncture's give-way), NaN in the other steps and in files of schema version 1:
        event_needle_force [N] (s, 3), event_tip_force [N] (s, 3), event_point [m] (s, 3).
        :attr:`profile_force` is the force profile (the give-way where a step has one).
    cut_point_count, cut_triangle_count : (s,). triangulation_seconds : [s], (s,).
    stage_seconds : Seconds of each stage, name -> (s,).
    solver : Solver report arrays: iterations (s,) (-1 no solve), residual (s,) (NaN), converged (s,) int8
        (1, 0, -1 no solve), seconds [s], increment [m], name, message.
    tissue_steps : Steps whose tissue positions were recorded, (t,). tissue_times : [s], (t,).
    tissue_positions : [m], (t, n, 3).
    constraint_offsets : (s + 1,); the rows of the i-th step are offsets[i]:offsets[i + 1].
    constraint_kind, constraint_source : (R,). constraint_points, constraint_directions : (R, 3).
    constraint_forces : [N], (R,).
    kind_names, source_names, phase_names, stage_names : Names of the codes.
    events : Events in order of occurrence.
    criteria : The criteria the events compared, every step (``refsim.simulation.margins.CriterionSeries``;
        empty for files written before ``criteria/``); :meth:`event_margins` reads each event's margin.
    cut : The cut surface history, or None when the run cut nothing.
    boundary_nodes : Nodes a boundary motion moves, (b,) (empty: none).
    boundary_displacement : Their prescribed displacement from rest after each step [m], (s, b, 3).
    trajectory_samples : The base trajectory the run used: t [s], x, y, z [m], dx, dy, dz, (w, 7).
    instrument_names : The instruments, in the scene's order (one-needle files: ("needle",)). The needle
        fields above (needle_rest_nodes, the step quantities, events, criteria, trajectory_samples) are the
        first instrument's; :meth:`instrument`
        gives each one's view, :attr:`instruments` all of them.
    constraint_instrument : The instrument of each row, index into ``instrument_names``, (R,).
    further : Each further instrument's needle fields, by name (read through :meth:`instrument`).
    """

    path: Path
    attributes: dict
    scene: dict
    complete: bool
    rest_positions: np.ndarray
    tets: np.ndarray
    faces: np.ndarray
    fixed_nodes: np.ndarray
    needle_rest_nodes: np.ndarray
    step: np.ndarray
    time: np.ndarray
    cut_point_count: np.ndarray
    cut_triangle_count: np.ndarray
    triangulation_seconds: np.ndarray
    stage_seconds: dict
    solver: dict
    tissue_steps: np.ndarray
    tissue_times: np.ndarray
    tissue_positions: np.ndarray
    constraint_offsets: np.ndarray
    constraint_kind: np.ndarray
    constraint_source: np.ndarray
    constraint_points: np.ndarray
    constraint_directions: np.ndarray
    constraint_forces: np.ndarray
    kind_names: tuple
    source_names: tuple
    phase_names: tuple
    stage_names: tuple
    events: tuple = ()
    criteria: CriterionSeries | None = None
    cut: CutHistory | None = None
    problem_steps: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    boundary_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    boundary_displacement: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3)))
    trajectory_samples: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    instrument_names: tuple = ("needle",)
    constraint_instrument: np.ndarray | None = None
    further: dict = field(default_factory=dict)
    quantities: dict = field(default_factory=dict)

    def __getattr__(self, name: str):
        # called only for names that are not fields: the step quantities by name (results.needle_force)
        quantities = self.__dict__.get("quantities")
        if quantities is not None and name in quantities:
            return quantities[name]
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def instrument(self, name: str) -> Results:
        """The run seen from one instrument: its needle fields in place of the first one's (tissue,
        solver, constraints and cut are the run's), and only it in ``instrument_names``."""
        if name not in self.instrument_names:
            raise KeyError(
                f"{self.path}: no instrument {name!r} (instruments: {', '.join(self.instrument_names)})"
            )
        own = self.further.get(name, {})
        return replace(self, instrument_names=(name,), further={}, **own)

    @property
    def instruments(self) -> tuple[Results, ...]:
        """Every instrument's view (:meth:`instrument`), in order."""
        return tuple(self.instrument(name) for name in self.instrument_names)

    # ------------------------------------------------------------------ sizes

    @property
    def step_count(self) -> int:
        """Number of completed steps in the file."""
        return int(self.step.shape[0])

    @property
    def stop_reason(self) -> str:
        """Why the run stopped early ("" for a complete run; files written before the attribute existed:
        "")."""
        return str(self.attributes.get("stop_reason", ""))

    @property
    def scene_name(self) -> str:
        """The scene's name."""
        return str(self.attributes.get("scene_name", ""))

    @property
    def phase_name(self) -> np.ndarray:
        """Phase of each step as strings, (s,)."""
        return np.asarray(self.phase_names, dtype=object)[self.phase]

    # ------------------------------------------------------------------ lookups

    def index_of(self, step: int) -> int:
        """Position of ``step`` in the per-step arrays.

        Raises
        ------
        ResultsError (a ValueError)
            When the file holds no such step (naming the range it holds).
        """
        where = np.flatnonzero(self.step == int(step))
        if where.size == 0:
            held = f"{self.step[0]}..{self.step[-1]}" if self.step_count else "none"
            raise ResultsError(f"{self.path}: no step {step} in the file (steps held: {held})")
        return int(where[0])

    def constraints_at(self, step: int) -> StepConstraints:
        """The constraint rows of ``step`` (a step number, as in ``self.step``)."""
        index = self.index_of(step)
        rows = slice(int(self.constraint_offsets[index]), int(self.constraint_offsets[index + 1]))
        return StepConstraints(
            self.constraint_kind[rows],
            self.constraint_source[rows],
            self.constraint_points[rows],
            self.constraint_directions[rows],
            self.constraint_forces[rows],
        )

    def nearest_tissue_step(self, step: int) -> int:
        """The recorded tissue step nearest to ``step`` (the earlier one on a tie).

        Raises
        ------
        LookupError
            When no tissue state was recorded.
        """
        if self.tissue_steps.size == 0:
            raise LookupError(f"{self.path}: no tissue positions recorded")
        return int(self.tissue_steps[np.argmin(np.abs(self.tissue_steps - int(step)))])

    def tissue_positions_at(self, step: int) -> np.ndarray:
        """Tissue positions [m] (n, 3) of the recorded step nearest to ``step``; rest positions for step 0."""
        if int(step) <= 0:
            return self.rest_positions
        nearest = self.nearest_tissue_step(step)
        return self.tissue_positions[int(np.flatnonzero(self.tissue_steps == nearest)[0])]

    def event_margins(self) -> list[EventMargin]:
        """The margin of each event with a criterion (its criterion at the event step and the step before,
        how many steps it could move, the knife-edge flag; ``refsim.simulation.margins.assess``)."""
        if self.criteria is None:
            return []
        return assess([(event.step, event.name) for event in self.events], self.criteria)

    def events_named(self, name: str) -> list[RecordedEvent]:
        """The events called ``name`` (e.g. "puncture", "tear")."""
        return [event for event in self.events if event.name == name]

    # ------------------------------------------------------------------ derived quantities

    def needle_axis(self, *, at: str = "base") -> np.ndarray:
        """Unit needle direction per step, (s, 3): the first segment ("base") or the last segment ("tip"),
        pointing from the base towards the tip."""
        if at not in ("base", "tip"):
            raise ValueError(f"at = {at!r}: expected 'base' or 'tip'")
        nodes = self.needle_positions
        segment = nodes[:, 1] - nodes[:, 0] if at == "base" else nodes[:, -1] - nodes[:, -2]
        return segment / np.linalg.norm(segment, axis=1, keepdims=True)

    @property
    def profile_force(self) -> np.ndarray:
        """The force of the tissue on the needle as its profile is read [N], (s, 3): in a step with a
        within-step event (the puncture's give-way of the tip contact at f_p), the force at the event
        (``event_needle_force``, the profile's peak); in every other step, the end-of-step force
        (``needle_force``). A file of schema version 1 has no event quantities: its ``needle_force`` is
        read, which at its puncture steps is the give-way's (that version solved the step once)."""
        event = self.event_needle_force
        return np.where(np.isfinite(event).all(axis=1)[:, None], event, self.needle_force)

    def puncture_point(self) -> np.ndarray | None:
        """Where the needle entered the tissue [m], (3,): the tip contact's surface point at the first
        puncture (the closest surface point to the tip when the contact gave way: ``event_point``, or the
        tissue-side point of the step's penetration row when the step records no within-step event), or
        None when the needle never punctured."""
        punctures = self.events_named("puncture")
        if not punctures:
            return None
        point = self.event_point[self.index_of(punctures[0].step)]
        if np.all(np.isfinite(point)):
            return point.copy()
        rows = self.constraints_at(punctures[0].step)
        if "penetration" in self.source_names:
            penetration = rows.source == self.source_names.index("penetration")
            if np.any(penetration):
                return rows.points[np.flatnonzero(penetration)[0]].copy()
        return self.needle_positions[self.index_of(punctures[0].step), -1].copy()

    def tip_depth(self) -> np.ndarray:
        """Depth of the tip along the needle from the puncture point [m], (s,): (tip − puncture point) · tip
        direction; negative before the tip reaches it, NaN everywhere when the needle never punctured."""
        entry = self.puncture_point()
        if entry is None:
            return np.full(self.step_count, np.nan)
        tip = self.needle_positions[:, -1]
        return np.einsum("ij,ij->i", tip - entry, self.needle_axis(at="tip"))

    def axial_lateral_force(self, force: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """A force on the needle per step, (s, 3) (by default the force profile, :attr:`profile_force`: the
        give-way in a puncture step), split along the base segment's axis t at the step's end [N]: the axial
        component F·t (negative when the tissue resists insertion), (s,), and the lateral norm
        ‖F − (F·t) t‖, (s,)."""
        axis = self.needle_axis(at="base")
        force = self.profile_force if force is None else np.asarray(force)
        axial = np.einsum("ij,ij->i", force, axis)
        lateral = np.linalg.norm(force - axial[:, None] * axis, axis=1)
        return axial, lateral


# ---------------------------------------------------------------------- opening


def _open(path) -> tuple:
    import h5py

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such results file")
    if path.is_dir():
        raise ResultsError(f"{path}: is a directory, not a results file")
    try:
        handle = h5py.File(path, "r")
    except OSError as error:
        raise ResultsError(_open_failure(path, error)) from None
    attributes = {key: _plain(value) for key, value in handle.attrs.items()}
    if attributes.get("format") != schema.FORMAT_NAME:
        handle.close()
        raise ResultsError(
            f"{path}: an HDF5 file, but not a refsim results file (root attribute 'format' is "
            f"{attributes.get('format')!r}, expected {schema.FORMAT_NAME!r})"
        )
    version = attributes.get("schema_version")
    if version not in schema.SUPPORTED_SCHEMA_VERSIONS:
        handle.close()
        raise ResultsError(
            f"{path}: results schema version {version!r} is not supported by this refsim (supported: "
            f"{', '.join(map(str, schema.SUPPORTED_SCHEMA_VERSIONS))}); use the refsim version that wrote it "
            f"({attributes.get('refsim_version', 'unknown')})"
        )
    return path, handle, attributes


def _open_failure(path: Path, error: OSError) -> str:
    """Why h5py could not open ``path``, in words: truncated (with the sizes), not HDF5, or HDF5's reason."""
    import re

    text = str(error)
    truncated = re.search(r"truncated file: eof = (\d+).*stored_eof = (\d+)", text)
    if truncated:
        size, expected = int(truncated.group(1)), int(truncated.group(2))
        return (
            f"{path}: the file is truncated: {size} bytes of the {expected} its HDF5 superblock announces "
            f"({expected - size} missing at the end, e.g. a copy or a transfer cut short); HDF5 cannot open "
            "it, so no step can be recovered from this copy: copy the whole file again from where the run "
            "wrote it, or run the scene again"
        )
    if "unable to lock file" in text:  # a run is writing it (HDF5's lock), not damage
        try:
            holder = path.with_name(f".{path.name}.lock").read_text(encoding="ascii").strip()
        except (OSError, UnicodeDecodeError):
            holder = ""
        who = f"process {holder}" if holder.isdigit() else "another process"
        return (
            f"{path}: {who} is writing this file (a run in progress holds its HDF5 lock); read it once that "
            "run ends (Ctrl-C or SIGTERM stops a run and keeps every completed step)"
        )
    with path.open("rb") as stream:
        head = stream.read(8)
    if head != b"\x89HDF\r\n\x1a\n":
        return f"{path}: not an HDF5 file (no HDF5 signature at its start), so not a refsim results file"
    return f"{path}: an HDF5 file that HDF5 cannot open, damaged ({text})"


def _plain(value):
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.generic):
        return value.item()
    return value


def _names(dataset) -> tuple[str, ...]:
    return tuple(_plain(name) for name in dataset.attrs.get("names", ()))


def _read(handle, path: str, count: int | None = None) -> np.ndarray:
    dataset = handle[path]
    try:
        data = dataset[()] if count is None else dataset[:count]
    except OSError as error:  # HDF5: "filter returned failure during read" (Fletcher-32), a bad chunk
        raise ResultsError(
            f"{handle.filename}: dataset {path!r} is damaged: {_read_failure(error)}; the file cannot be "
            "trusted (copy it again from where the run wrote it, or run the scene again)"
        ) from None
    if dataset.dtype.kind == "O":
        data = np.array([_plain(item) for item in np.ravel(data)], dtype=object).reshape(np.shape(data))
    return data


def _read_failure(error: OSError) -> str:
    text = str(error)
    if "filter" in text.lower() or "checksum" in text.lower():
        return "its Fletcher-32 checksum does not match the data (a bit changed on the disk or in a copy)"
    return f"HDF5 cannot read it ({text})"


def _steps_completed(handle, path: Path, attributes: dict) -> int:
    """The root attribute ``steps_completed``, checked: an integer in [0, length of steps/step]."""
    value = attributes.get("steps_completed", 0)
    stored = handle[schema.STEPS["step"].path].shape[0]
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 0 <= value <= stored:
        raise ResultsError(
            f"{path}: root attribute steps_completed = {value!r} is not an integer in [0, {stored}] (the "
            f"steps the file holds); the file is damaged"
        )
    return int(value)


def _event_values(event_data: dict, count: int, law: str) -> tuple[np.ndarray, np.ndarray]:
    """Each event's value and unit, from the dataset of each unit (schema.EVENT_VALUE_DATASETS). A file
    written before events/force_per_length held every value in events/force: there a cut_start's unit is
    its law's (``law``, the scene's cutting.law: a force per unit length for the energy law)."""
    value, unit = np.full(count, np.nan), np.full(count, "N", dtype=object)
    for name_unit, name in schema.EVENT_VALUE_DATASETS.items():
        if name in event_data:
            held = np.isfinite(event_data[name])
            value[held], unit[held] = event_data[name][held], name_unit
    if "force_per_length" not in event_data and law in CUTTING_LAWS:
        unit[np.asarray(event_data["name"], dtype=object) == "cut_start"] = CUTTING_LAWS[law].cut_start_unit
    return value, unit


def _require(handle, path: Path, dataset_path: str):
    if dataset_path not in handle:
        raise ResultsError(f"{path}: dataset {dataset_path!r} is missing; the file is damaged or incomplete")
    return handle[dataset_path]


def results_status(path) -> tuple[bool, int, str]:
    """Whether the run of a results file completed, its completed steps and why it stopped ("" when no reason
    is recorded: a run still being written, or killed), from the root attributes; the file is checked as
    :func:`read_results` opens it (a missing, truncated, non-HDF5 or non-refsim file raises, naming it)."""
    path, handle, attributes = _open(path)
    with handle:
        _require(handle, path, schema.STEPS["step"].path)
        count = _steps_completed(handle, path, attributes)
    return bool(attributes.get("complete", False)), count, str(attributes.get("stop_reason", "") or "")


def read_results(path) -> Results:
    """Read a results file.

    Parameters
    ----------
    path : The HDF5 file written by :class:`refsim.io.ResultWriter`.

    Raises
    ------
    FileNotFoundError
        When the file does not exist.
    ResultsError
        When the file is not an HDF5 file, not a refsim results file, of an unsupported schema version, or
        misses a dataset (each message names the file).
    """
    path, handle, attributes = _open(path)
    with handle:
        for spec in schema.all_datasets():
            if (spec.growing or spec.path.startswith("scene/")) and spec.path not in schema.OPTIONAL_DATASETS:
                _require(handle, path, spec.path)
        count = _steps_completed(handle, path, attributes)
        offsets = _read(handle, schema.CONSTRAINTS["offsets"].path, count + 1)
        row_count = int(offsets[-1])
        last_step = int(_read(handle, schema.STEPS["step"].path, count)[-1]) if count else 0

        quantities = {quantity.name for quantity in schema.INSTRUMENT_STEP_QUANTITIES}
        steps = {
            name: _read(handle, spec.path, count)
            for name, spec in schema.STEPS.items()
            if name not in quantities and (spec.path in handle or name != "boundary_displacement")
        }  # files before the boundary motion
        steps.update(_step_quantities(handle, "", count))
        stage_names = _names(handle[schema.STEPS["stage_seconds"].path])
        solver = {name: _read(handle, spec.path, count) for name, spec in schema.SOLVER.items()}
        rows = {
            name: _read(handle, spec.path, row_count)
            for name, spec in schema.CONSTRAINTS.items()
            if name != "offsets" and spec.path in handle  # constraints/instrument: several instruments only
        }
        tissue_steps = _read(handle, schema.TISSUE["step"].path)
        tissue_count = int(np.count_nonzero(tissue_steps <= last_step))
        scene = _scene_of(path, attributes)
        law = scene.get("cutting", {}).get("law", "energy")
        events = _read_events(handle, last_step, law)
        names, further = _read_instruments(handle, path, attributes, count, last_step, law)
        criteria = _read_criteria(handle, last_step)
        cut = None
        if "cut" in handle:
            cut_data = {
                name: _read(handle, spec.path) for name, spec in schema.CUT.items() if spec.path in handle
            }
            cut = CutHistory(**cut_data)
        return Results(
            path=path,
            attributes=attributes,
            scene=scene,
            complete=bool(attributes.get("complete", False)),
            rest_positions=_read(handle, schema.STATIC["tissue/rest_positions"].path),
            tets=_read(handle, schema.STATIC["tissue/tets"].path),
            faces=_read(handle, schema.STATIC["tissue/faces"].path),
            fixed_nodes=_read(handle, schema.STATIC["tissue/fixed_nodes"].path),
            needle_rest_nodes=_read(handle, schema.STATIC["needle/rest_nodes"].path),
            step=steps["step"],
            time=steps["time"],
            quantities=_quantities(steps),
            cut_point_count=steps["cut_point_count"],
            cut_triangle_count=steps["cut_triangle_count"],
            triangulation_seconds=steps["triangulation_seconds"],
            stage_seconds={
                name: steps["stage_seconds"][:, column] for column, name in enumerate(stage_names)
            },
            solver=solver,
            tissue_steps=tissue_steps[:tissue_count],
            tissue_times=_read(handle, schema.TISSUE["time"].path, tissue_count),
            tissue_positions=_read(handle, schema.TISSUE["positions"].path, tissue_count),
            constraint_offsets=offsets,
            constraint_kind=rows["kind"],
            constraint_source=rows["source"],
            constraint_points=rows["points"],
            constraint_directions=rows["directions"],
            constraint_forces=rows["forces"],
            kind_names=_names(handle[schema.CONSTRAINTS["kind"].path]),
            source_names=_names(handle[schema.CONSTRAINTS["source"].path]),
            phase_names=_names(handle[schema.STEPS["phase"].path]),
            stage_names=stage_names,
            events=events,
            criteria=criteria,
            trajectory_samples=_read_optional(handle, "trajectory/samples", np.zeros((0, 7))),
            boundary_nodes=_read_optional(handle, "tissue/boundary_nodes", np.zeros(0, dtype=np.int64)),
            boundary_displacement=steps["boundary_displacement"]
            if "boundary_displacement" in steps
            else np.zeros((len(steps["step"]), 0, 3)),
            cut=cut,
            problem_steps=np.array(_problem_steps(handle, last_step), dtype=np.int64),
            instrument_names=names,
            constraint_instrument=rows.get("instrument", np.zeros(row_count, dtype=np.int64)),
            further=further,
        )


def _read_instruments(handle, path: Path, attributes: dict, count: int, last_step: int, law: str):
    """The instruments' names and each further one's needle fields (root attribute ``instruments``; a
    one-needle file has none: its one instrument is "needle")."""
    text = attributes.get("instruments")
    if text is None:
        return ("needle",), {}
    try:
        listed = [(str(item["name"]), str(item["location"])) for item in json.loads(text)]
    except (json.JSONDecodeError, KeyError, TypeError) as error:
        raise ResultsError(
            f"{path}: the root attribute 'instruments' is not a list of {{name, location}} ({error})"
        ) from None
    further = {}
    for name, location in listed[1:]:
        steps = _step_quantities(handle, location, count)
        for spec in schema.INSTRUMENT_DATASETS.values():
            if spec.path not in schema.OPTIONAL_DATASETS:
                _require(handle, path, f"{location}/{spec.path}")
        further[name] = {
            "quantities": _quantities(steps),
            "events": _read_events(handle, last_step, law, location=location),
            "criteria": _read_criteria(handle, last_step, location=location),
            "needle_rest_nodes": _read(handle, f"{location}/{schema.STATIC['needle/rest_nodes'].path}"),
            "trajectory_samples": _read(handle, f"{location}/{schema.STATIC['trajectory/samples'].path}"),
        }
    return tuple(name for name, _ in listed), further


def _step_quantities(handle, location: str, count: int) -> dict:
    """An instrument's step quantities as stored (``location``: "" for the first instrument), by name; one
    added after the file's schema version (``StepQuantity.since``), absent from it, is NaN at every step."""
    prefix = f"{location}/" if location else ""
    values = {}
    for quantity in schema.INSTRUMENT_STEP_QUANTITIES:
        path = prefix + schema.STEPS[quantity.name].path
        if path in handle or quantity.since == 1:
            values[quantity.name] = _read(handle, path, count)
        else:
            values[quantity.name] = np.full((count, *quantity.entry_shape), np.nan)
    return values


def _quantities(steps: dict) -> dict:
    """The step quantities of :data:`~refsim.io.schema.INSTRUMENT_STEP_QUANTITIES` from the read ``steps``
    arrays, by name (coded ones as int64 codes)."""
    return {
        quantity.name: steps[quantity.name].astype(np.int64) if quantity.codes else steps[quantity.name]
        for quantity in schema.INSTRUMENT_STEP_QUANTITIES
    }


def _scene_of(path: Path, attributes: dict) -> dict:
    """The scene stored in the root attribute ``scene`` (JSON; {} when absent)."""
    try:
        return json.loads(attributes.get("scene", "{}"))
    except json.JSONDecodeError as error:
        raise ResultsError(f"{path}: the root attribute 'scene' is not valid JSON ({error})") from None


def _read_events(handle, last_step: int, law: str, *, location: str = "") -> tuple[RecordedEvent, ...]:
    """The events of the completed steps (up to ``last_step``), with their triggering value and unit under
    the scene's cutting ``law``; of the instrument at ``location`` ("" the first)."""
    prefix = f"{location}/" if location else ""
    event_steps = _read(handle, prefix + schema.EVENTS["step"].path)
    event_count = int(np.count_nonzero(event_steps <= last_step))
    event_data = {
        name: _read(handle, prefix + spec.path, event_count)
        for name, spec in schema.EVENTS.items()
        if prefix + spec.path in handle  # events/force_per_length is absent from files of before it
    }
    value, unit = _event_values(event_data, event_count, law)
    return tuple(
        RecordedEvent(int(s), float(t), str(n), float(f), str(u))
        for s, t, n, f, u in zip(
            event_data["step"], event_data["time"], event_data["name"], value, unit, strict=False
        )
    )


def _read_optional(handle, name: str, default: np.ndarray) -> np.ndarray:
    """A static dataset that files written before it lack (``default`` then)."""
    path = schema.STATIC[name].path
    return _read(handle, path) if path in handle else default


def _problem_steps(handle, last_step: int) -> list[int]:
    if schema.PROBLEMS_GROUP not in handle:
        return []
    steps = sorted(int(group.attrs["step"]) for group in handle[schema.PROBLEMS_GROUP].values())
    return [step for step in steps if step <= last_step]


def read_problems(path, *, steps=None) -> list[tuple[int, object]]:
    """The constraint problems recorded in a results file (scene key ``output.record_problems = true``).

    Parameters
    ----------
    path : The results file.
    steps : Only these steps (an iterable of step numbers); all recorded steps by default.

    Returns
    -------
    list of (step, refsim.solvers.ConstraintProblem), in step order; empty when none were recorded.
    """
    path, handle, attributes = _open(path)
    wanted = None if steps is None else {int(step) for step in steps}
    problems = []
    with handle:
        count = _steps_completed(handle, path, attributes)
        last_step = int(_read(handle, schema.STEPS["step"].path, count)[-1]) if count else 0
        for step in _problem_steps(handle, last_step):
            if wanted is not None and step not in wanted:
                continue
            group = handle[schema.problem_group_name(step)]
            problems.append((step, read_problem_group(group, default_name=f"{path.name} step {step}")))
    return problems


def read_problem_group(group, *, default_name: str = ""):
    """The ConstraintProblem stored in an open h5py group by :func:`refsim.io.writer.write_problem_group`.

    Fields newer than the file (absent from the group) take their defaults.
    """
    from refsim.solvers import ConstraintProblem

    try:
        fields = {
            spec.name: group[spec.name][()] for spec in schema.PROBLEM_FIELDS.values() if spec.name in group
        }
    except OSError as error:
        raise ResultsError(
            f"{group.file.filename}: group {group.name!r} is damaged: {_read_failure(error)}"
        ) from None
    name = _plain(group.attrs.get("name", "")) or default_name
    return ConstraintProblem(**fields, name=name)


def _read_criteria(handle, last_step: int, *, location: str = "") -> CriterionSeries | None:
    """The criteria of the completed steps (up to ``last_step``), None for a file without ``criteria/``;
    ``location``: a further instrument's (``instruments/<name>``)."""
    prefix = f"{location}/" if location else ""
    if prefix + schema.CRITERIA["step"].path not in handle:
        return None
    steps = _read(handle, prefix + schema.CRITERIA["step"].path)
    count = int(np.count_nonzero(steps <= last_step))
    data = {name: _read(handle, prefix + spec.path, count) for name, spec in schema.CRITERIA.items()}
    return CriterionSeries(**data)
