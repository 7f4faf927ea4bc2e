"""Writing a run to its HDF5 results file, step by step (DESIGN.md, "Results"; layout in :mod:`refsim.io.schema`).

Each :meth:`ResultWriter.append` grows resizable chunked datasets by one step, updates the root attribute
``steps_completed`` last and flushes the file, so a run that stops (an exception, Ctrl-C) leaves a readable file
holding every completed step with ``complete = False``.
"""

from __future__ import annotations

import datetime
import logging
import subprocess
from pathlib import Path

import numpy as np

from refsim.io import schema
from refsim.io.schema import DatasetSpec

__all__ = ["ResultWriter", "git_commit"]

logger = logging.getLogger(__name__)

_CHUNK_STEPS = 64  # steps per chunk of the small per-step datasets
_CHUNK_ROWS = 1024  # rows per chunk of the ragged constraint and event datasets


def git_commit(directory: str | Path | None = None) -> str:
    """The commit checked out where refsim lives (``git rev-parse HEAD``), or "unknown" outside a checkout.

    Parameters
    ----------
    directory : Where to ask git; the refsim package's directory by default.
    """
    directory = Path(__file__).resolve().parent if directory is None else Path(directory)
    try:
        result = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=directory, capture_output=True, text=True, timeout=10, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    commit = result.stdout.strip()
    return commit if result.returncode == 0 and commit else "unknown"


def _initial_needle_nodes(scene, models) -> np.ndarray:
    """Needle nodes [m] at the trajectory's pose at t = 0, shape (k, 3)."""
    from refsim.simulation.needle_body import FlexibleNeedle, RigidNeedle

    base, direction = models.trajectory.pose(0.0)
    if scene.needle.rigid or models.needle is None:
        needle = RigidNeedle(scene.needle.length, scene.needle.element_count)
    else:
        needle = FlexibleNeedle(models.needle)
    return np.asarray(needle.state_at(base, direction).positions, dtype=float)


class ResultWriter:
    """Writes one run to an HDF5 results file; a context manager.

    Parameters
    ----------
    path : The file to create.
    scene : The run's scene (stored as JSON in the root attribute ``scene``).
    models : The scene's models (``refsim.scene.build.SceneModels``): mesh, tissue (fixed nodes), needle,
        trajectory.
    overwrite : Replace an existing file; by default an existing file is an error.
    needle_rest_nodes : Needle nodes [m] to store as ``scene/needle/rest_nodes``, shape (k, 3); by default the
        needle posed at the trajectory's start.

    Raises
    ------
    FileExistsError
        When ``path`` exists and ``overwrite`` is False (the message names the path).

    Examples
    --------
    >>> with ResultWriter("cube.h5", scene, sim.models) as writer:          # doctest: +SKIP
    ...     sim.run(on_step=lambda state, record: writer.append(record))
    """

    def __init__(self, path, scene, models, *, overwrite: bool = False, needle_rest_nodes=None) -> None:
        import h5py

        from refsim import __version__
        from refsim.scene import scene_to_json
        from refsim.simulation.records import STAGES

        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise FileExistsError(
                f"{self.path}: the results file exists; choose another path or pass overwrite=True "
                "(command line: --overwrite)"
            )
        if self.path.is_dir():
            raise IsADirectoryError(f"{self.path}: is a directory, expected a results file path")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._stages = tuple(STAGES)
        self._steps_completed = 0
        self._closed = False
        self._datasets: dict = {}

        mesh = models.mesh
        rest_positions = np.asarray(mesh.rest_positions, dtype=np.float64)
        rest_nodes = (
            _initial_needle_nodes(scene, models) if needle_rest_nodes is None
            else np.asarray(needle_rest_nodes, dtype=np.float64)
        )
        self._sizes = {"n": rest_positions.shape[0], "k": rest_nodes.shape[0], "stages": len(self._stages)}

        self._file = h5py.File(self.path, "w")
        try:
            attributes = self._file.attrs
            attributes["format"] = schema.FORMAT_NAME
            attributes["schema_version"] = schema.SCHEMA_VERSION
            attributes["refsim_version"] = __version__
            attributes["git_commit"] = git_commit()
            attributes["created"] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
            attributes["scene"] = scene_to_json(scene)
            attributes["scene_name"] = scene.name
            attributes["complete"] = False
            attributes["steps_completed"] = 0
            static = {
                "tissue/rest_positions": rest_positions,
                "tissue/tets": np.asarray(mesh.tets, dtype=np.int64),
                "tissue/faces": np.asarray(mesh.boundary_faces, dtype=np.int64),
                "tissue/fixed_nodes": np.asarray(models.tissue.fixed_nodes, dtype=np.int64),
                "needle/rest_nodes": rest_nodes,
            }
            for name, value in static.items():
                self._write_fixed(schema.STATIC[name], value)
            for group in (schema.STEPS, schema.SOLVER, schema.TISSUE, schema.CONSTRAINTS, schema.EVENTS):
                for spec in group.values():
                    self._create_growing(spec)
            self._datasets["steps/phase"].attrs["names"] = list(schema.PHASE_NAMES)
            self._datasets["steps/stage_seconds"].attrs["names"] = list(self._stages)
            self._set_code_names()
            self._append("constraints/offsets", np.zeros(1, dtype=np.int64))
            self._file.flush()
        except BaseException:
            self._file.close()
            raise
        logger.info("writing results to %s", self.path)

    # ------------------------------------------------------------------ context manager

    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, exc_type, exc, traceback) -> None:
        self.close(complete=exc_type is None)

    @property
    def steps_completed(self) -> int:
        """Steps written so far."""
        return self._steps_completed

    def close(self, *, complete: bool = True) -> None:
        """Close the file; ``complete`` marks the run as finished (False for an interrupted run)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._file.attrs["complete"] = bool(complete)
            self._file.attrs["steps_completed"] = self._steps_completed
        finally:
            self._file.close()
        logger.info("closed %s: %d steps, complete=%s", self.path, self._steps_completed, complete)

    # ------------------------------------------------------------------ per step

    def append(self, record) -> None:
        """Append one step (a :class:`refsim.simulation.StepRecord`) and flush the file.

        Raises
        ------
        ValueError
            When an array of the record has a shape that does not fit the file (naming the field).
        RuntimeError
            When the writer is closed.
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: the results writer is closed; cannot append step {record.step}")
        rows = self._check_rows(record)
        row_count = rows["forces"].shape[0]

        # Ragged and optional data first; the per-step arrays and steps_completed last, so that a write cut short
        # leaves the previous steps consistent (the reader trusts steps_completed).
        for name, value in rows.items():
            self._append(f"constraints/{name}", value)
        offsets = self._datasets["constraints/offsets"]
        self._append("constraints/offsets", np.array([offsets[-1] + row_count], dtype=np.int64))
        if record.events:
            self._append("events/step", np.full(len(record.events), record.step, dtype=np.int64))
            self._append("events/time", np.full(len(record.events), record.time, dtype=np.float64))
            self._append("events/name", np.array([event.name for event in record.events], dtype=object))
            self._append("events/force", np.array([event.force for event in record.events], dtype=np.float64))
        if record.tissue_positions is not None:
            positions = self._check_shape("tissue_positions", record.tissue_positions, (self._sizes["n"], 3))
            self._append("tissue/step", np.array([record.step], dtype=np.int64))
            self._append("tissue/time", np.array([record.time], dtype=np.float64))
            self._append("tissue/positions", positions[None])
        if record.problem is not None:
            self._write_problem(record.step, record.problem)
        self._append_solver(record.solver)
        self._append_step(record)

        self._steps_completed += 1
        self._file.attrs["steps_completed"] = self._steps_completed
        self._file.flush()

    def write_cut_surface(
        self,
        points: np.ndarray,
        point_step: np.ndarray,
        triangles: np.ndarray,
        triangle_step: np.ndarray,
        *,
        tet_indices: np.ndarray | None = None,
        barycentric: np.ndarray | None = None,
    ) -> None:
        """(Re)write the cut surface history: the whole surface so far, replacing what was written before.

        Parameters
        ----------
        points : Cut surface points in rest coordinates [m], shape (p, 3).
        point_step : Step at which each point was created, shape (p,).
        triangles : Triangles (point indices), shape (t, 3).
        triangle_step : Step at which each triangle was created, shape (t,).
        tet_indices : Optional tissue tet of each point, shape (p,) (refsim.cutting.CutSurface.tet_indices).
        barycentric : Optional barycentric coordinates of each point in its tet, shape (p, 4).
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: the results writer is closed; cannot write the cut surface")
        points = self._check_shape("cut points", points, (None, 3), dtype=np.float64)
        count = points.shape[0]
        values = {
            "points": points,
            "point_step": self._check_shape("cut point_step", point_step, (count,), dtype=np.int64),
            "triangles": self._check_shape("cut triangles", triangles, (None, 3), dtype=np.int64),
        }
        values["triangle_step"] = self._check_shape(
            "cut triangle_step", triangle_step, (values["triangles"].shape[0],), dtype=np.int64
        )
        if values["triangles"].size and (values["triangles"].min() < 0 or values["triangles"].max() >= count):
            raise ValueError(f"cut triangles must index the {count} cut points, got indices "
                             f"{values['triangles'].min()}..{values['triangles'].max()}")
        if (tet_indices is None) != (barycentric is None):
            raise ValueError("write_cut_surface: give both tet_indices and barycentric, or neither")
        if tet_indices is not None:
            values["tet_indices"] = self._check_shape("cut tet_indices", tet_indices, (count,), dtype=np.int64)
            values["barycentric"] = self._check_shape("cut barycentric", barycentric, (count, 4), dtype=np.float64)
        group_path = "cut"
        if group_path in self._file:
            del self._file[group_path]
        for name, value in values.items():
            self._write_fixed(schema.CUT[name], value)
        self._file.flush()

    # ------------------------------------------------------------------ helpers

    def _set_code_names(self) -> None:
        from refsim.constraints.rows import KIND_NAMES, SOURCE_NAMES

        self._datasets["constraints/kind"].attrs["names"] = list(KIND_NAMES)
        self._datasets["constraints/source"].attrs["names"] = list(SOURCE_NAMES)

    def _entry_shape(self, spec: DatasetSpec) -> tuple[int, ...]:
        return tuple(self._sizes[size] if isinstance(size, str) else size for size in spec.entry_shape)

    def _describe(self, dataset, spec: DatasetSpec) -> None:
        dataset.attrs["units"] = spec.unit
        dataset.attrs["description"] = spec.meaning

    def _write_fixed(self, spec: DatasetSpec, value: np.ndarray) -> None:
        dataset = self._file.create_dataset(spec.path, data=value, dtype=schema.numpy_dtype(spec))
        self._describe(dataset, spec)

    def _create_growing(self, spec: DatasetSpec) -> None:
        entry = self._entry_shape(spec)
        chunk = (1,) if spec.path == "tissue/positions" else (
            (_CHUNK_ROWS,) if spec.path.split("/")[0] in ("constraints", "events") else (_CHUNK_STEPS,)
        )
        dataset = self._file.create_dataset(
            spec.path,
            shape=(0,) + entry,
            maxshape=(None,) + entry,
            chunks=chunk + entry,
            dtype=schema.numpy_dtype(spec),
        )
        self._describe(dataset, spec)
        self._datasets[spec.path] = dataset

    def _append(self, path: str, values: np.ndarray) -> None:
        dataset = self._datasets[path]
        start = dataset.shape[0]
        dataset.resize(start + values.shape[0], axis=0)
        dataset[start:] = values

    def _check_shape(self, name: str, value, shape: tuple, *, dtype=np.float64) -> np.ndarray:
        try:
            array = np.asarray(value, dtype=dtype)
        except (TypeError, ValueError) as error:
            raise ValueError(f"{self.path}: {name} is not a numeric array ({error})") from None
        if array.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, array.shape)):
            expected = "(" + ", ".join("any" if s is None else str(s) for s in shape) + ")"
            raise ValueError(f"{self.path}: {name} has shape {array.shape}, expected {expected}")
        return array

    def _check_rows(self, record) -> dict[str, np.ndarray]:
        forces = self._check_shape("row_forces", record.row_forces, (None,))
        count = forces.shape[0]
        return {
            "kind": self._check_shape("row_kind", record.row_kind, (count,), dtype=np.int8),
            "source": self._check_shape("row_source", record.row_source, (count,), dtype=np.int8),
            "points": self._check_shape("row_points", record.row_points, (count, 3)),
            "directions": self._check_shape("row_directions", record.row_directions, (count, 3)),
            "forces": forces,
        }

    def _append_solver(self, report) -> None:
        if report is None:
            values = {"iterations": -1, "residual": np.nan, "converged": -1, "seconds": np.nan,
                      "increment": np.nan, "name": "", "message": ""}
        else:
            values = {
                "iterations": int(report.iterations),
                "residual": float(report.residual),
                "converged": int(bool(report.converged)),
                "seconds": float(report.seconds),
                "increment": float(getattr(report, "increment", np.nan)),
                "name": str(getattr(report, "solver", "")),
                "message": str(getattr(report, "message", "")),
            }
        for name, value in values.items():
            spec = schema.SOLVER[name]
            dtype = object if spec.dtype == "str" else spec.dtype
            self._append(spec.path, np.array([value], dtype=dtype))

    def _append_step(self, record) -> None:
        k = self._sizes["k"]
        if record.phase not in schema.PHASE_NAMES:
            raise ValueError(f"{self.path}: step {record.step} has phase {record.phase!r}; "
                             f"the results schema knows {', '.join(schema.PHASE_NAMES)}")
        unknown = set(record.stage_seconds) - set(self._stages)
        if unknown:
            raise ValueError(f"{self.path}: step {record.step} times unknown stages {sorted(unknown)}; "
                             f"stages are {', '.join(self._stages)}")
        values = {
            "step": np.array([record.step], dtype=np.int64),
            "time": np.array([record.time], dtype=np.float64),
            "phase": np.array([schema.PHASE_NAMES.index(record.phase)], dtype=np.int8),
            "base_position": self._check_shape("base_position", record.base_position, (3,))[None],
            "needle_positions": self._check_shape("needle_positions", record.needle_positions, (k, 3))[None],
            "needle_frames": self._check_shape("needle_frames", record.needle_frames, (k, 3, 3))[None],
            "needle_force": self._check_shape("needle_force", record.needle_force, (3,))[None],
            "insertion_point_count": np.array([record.insertion_point_count], dtype=np.int64),
            "cut_point_count": np.array([record.cut_point_count], dtype=np.int64),
            "cut_triangle_count": np.array([record.cut_triangle_count], dtype=np.int64),
            "triangulation_seconds": np.array([record.triangulation_seconds], dtype=np.float64),
            "stage_seconds": np.array(
                [[float(record.stage_seconds.get(stage, np.nan)) for stage in self._stages]], dtype=np.float64
            ),
        }
        # "step" is the last dataset grown: its length is the count of fully written steps.
        for name in [name for name in values if name != "step"] + ["step"]:
            self._append(schema.STEPS[name].path, values[name])

    def _write_problem(self, step: int, problem) -> None:
        group_path = schema.problem_group_name(step)
        if group_path in self._file:
            del self._file[group_path]
        group = self._file.create_group(group_path)
        group.attrs["step"] = int(step)
        write_problem_group(group, problem)


def write_problem_group(group, problem) -> None:
    """Write every field of a ConstraintProblem (schema.PROBLEM_FIELDS, derived from the solvers' law table) and
    its name into an open h5py group; :func:`refsim.io.reader.read_problem_group` reads it back."""
    group.attrs["name"] = str(problem.name)
    for spec in schema.PROBLEM_FIELDS.values():
        dataset = group.create_dataset(spec.name, data=np.asarray(getattr(problem, spec.name)),
                                       dtype=schema.numpy_dtype(spec))
        dataset.attrs["units"] = spec.unit
        dataset.attrs["description"] = spec.meaning
