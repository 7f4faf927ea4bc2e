"""Writing a run to its HDF5 results file, step by step (DESIGN.md, "Results"; layout in
:mod:`refsim.io.schema`).

:meth:`ResultWriter.append` checks a step and buffers it; every ``buffer_steps`` steps
:meth:`ResultWriter.flush` grows each resizable chunked dataset once for the whole block (one resize and one
write per dataset instead of ~25 per step: 4.5 ms per step measured before), then updates the root attribute
``steps_completed`` last and flushes the file. :meth:`ResultWriter.close` flushes what is buffered, so a run
that stops (an exception, Ctrl-C, SIGTERM, a numerical error: the run driver closes the writer in every case)
leaves a readable file holding every completed step with ``complete = False`` and the reason in
``stop_reason``. Only a hard kill (SIGKILL, a power cut) can lose the last buffered steps, at most
``buffer_steps`` of them.

A failed write (a full disk) must not corrupt what was written: before each block the writer checks the free
space of the file's file system against the block's size (with a margin for HDF5's metadata) and refuses the
block with an :class:`OSError` (ENOSPC) before touching the file; an OSError raised by HDF5 itself is caught
the same way. After a failed write the writer accepts no more steps and :meth:`close` leaves the file readable
with the steps of the blocks written before.

Nothing half-written, one writer per file: the writer first takes an exclusive lock on the sidecar
``.<name>.lock`` beside the file (``fcntl.flock``, held until :meth:`close`), so a second run on the same path
fails before anything is truncated. It then checks the free space against the static part, writes the static
part (attributes, mesh, trajectory, empty growing datasets) to a temporary ``.<name>.<pid>.partial`` beside
the file and renames it into place (``os.replace``) only once that part is written and flushed: an existing
file is replaced only by a readable one, and a failure before (a full disk) removes the temporary and leaves
the old file untouched. Every numeric dataset carries HDF5's Fletcher-32 checksum filter
(``fletcher32=True``; variable-length string datasets cannot take a filter), so a damaged chunk is detected
when it is read (:func:`refsim.io.reader.read_results` names the dataset).
"""

from __future__ import annotations

import dataclasses
import datetime
import errno
import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np

from refsim.io import schema
from refsim.io.filelock import FileLock, WriterLockedError
from refsim.io.provenance import git_commit
from refsim.io.schema import DatasetSpec
from refsim.io.step_values import StepValues, check_shape

__all__ = ["FileLock", "ResultWriter", "WriterLockedError", "git_commit"]

logger = logging.getLogger(__name__)

#: The schema's groups of datasets that grow by one entry (or one ragged block) per step.
_GROWING_GROUPS = (
    schema.STEPS,
    schema.SOLVER,
    schema.TISSUE,
    schema.CONSTRAINTS,
    schema.EVENTS,
    schema.CRITERIA,
)

_CHUNK_STEPS = 64  # steps per chunk of the small per-step datasets
_CHUNK_ROWS = 1024  # rows per chunk of the ragged constraint and event datasets
#: Steps buffered before a block is written (ResultWriter(buffer_steps=...)).
DEFAULT_BUFFER_STEPS = 32
# Free space kept beyond a block's own bytes, for HDF5's metadata and the attributes written on close [bytes].
_SPACE_MARGIN = 64 * 1024
# Bytes of HDF5 metadata per dataset (object header, chunk index, attributes) counted in the static part's
# estimate: an object header with two attributes and a v1 B-tree node is 2-5 kB; 8 kB is a bound.
_METADATA_PER_DATASET = 8 * 1024


def _initial_needle_nodes(scene, models) -> np.ndarray:
    """Needle nodes [m] at the trajectory's pose at t = 0, shape (k, 3)."""
    return _instrument_rest_nodes(scene.needle, models.needle, models.trajectory)


def _instrument_rest_nodes(needle_spec, model, trajectory) -> np.ndarray:
    """An instrument's needle nodes [m] at its trajectory's pose at t = 0, shape (k, 3)."""
    from refsim.simulation.needle_body import FlexibleNeedle, RigidNeedle

    base, direction = trajectory.pose(0.0)
    if needle_spec.rigid or model is None:
        needle = RigidNeedle(needle_spec.length, needle_spec.element_count)
    else:
        needle = FlexibleNeedle(model)
    return np.asarray(needle.state_at(base, direction).positions, dtype=float)


def _samples(trajectory) -> np.ndarray:
    """A trajectory as the rows t, x, y, z, dx, dy, dz, shape (w, 7)."""
    return np.column_stack([trajectory.times, trajectory.base_positions, trajectory.directions]).astype(
        np.float64
    )


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
    buffer_steps : Steps held in memory before a block is written (1 writes every step at once).

    Raises
    ------
    WriterLockedError (a FileExistsError)
        When another process is writing ``path`` (its lock is held); nothing is touched.
    FileExistsError
        When ``path`` exists and ``overwrite`` is False (the message names the path).
    OSError
        When the static part cannot be written (ENOSPC: a full disk, checked before writing); the temporary
        file is removed and an existing file at ``path`` is untouched.

    Examples
    --------
    >>> with ResultWriter("cube.h5", scene, sim.models) as writer:          # doctest: +SKIP
    ...     sim.run(on_step=lambda state, record: writer.append(record))
    """

    def __init__(
        self,
        path,
        scene,
        models,
        *,
        overwrite: bool = False,
        needle_rest_nodes=None,
        buffer_steps: int = DEFAULT_BUFFER_STEPS,
    ) -> None:
        from refsim.scene import scene_to_json
        from refsim.simulation.records import STAGES

        self.path = Path(path)
        if self.path.is_dir():
            raise IsADirectoryError(f"{self.path}: is a directory, expected a results file path")
        if isinstance(buffer_steps, bool) or not isinstance(buffer_steps, int) or buffer_steps < 1:
            raise ValueError(f"buffer_steps must be an integer >= 1, got {buffer_steps!r}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = FileLock(self.path)  # before anything else: another writer is refused, nothing touched
        try:
            if self.path.exists() and not overwrite:
                raise FileExistsError(
                    f"{self.path}: the results file exists; choose another path or pass overwrite=True "
                    "(command line: --overwrite)"
                )
            self._stages = tuple(STAGES)
            self._steps_completed = 0
            self._closed = False
            self._datasets: dict = {}
            self._buffer_steps = buffer_steps
            self._pending: list[dict] = []  # one dict {dataset path: array} per buffered step
            self._pending_problems: list = []  # (step, problem)
            self._pending_cut: dict | None = None
            self._pending_rows = 0  # constraint rows buffered (for the offsets)
            self._rows_written = 0
            self.failure: str | None = None  # why writing stopped (a failed write), or None

            static = self._static_arrays(scene, models, needle_rest_nodes)
            self._further = self._further_instruments(scene, models)
            self._values = StepValues(
                self.path,
                self._stages,
                self._sizes,
                self._boundary_nodes,
                [(self._instrument_names[0], "")] + [(name, location) for name, location, _ in self._further],
            )
            scene_json = scene_to_json(scene)
            self._check_static_space(static, len(scene_json))
            self._create_file(scene, scene_json, static)
        except BaseException:
            self._lock.release()
            raise
        logger.info("writing results to %s", self.path)

    def _static_arrays(self, scene, models, needle_rest_nodes) -> dict:
        """The static datasets {schema.STATIC name: array}; sets the dataset sizes of the growing ones."""
        mesh = models.mesh
        rest_positions = np.asarray(mesh.rest_positions, dtype=np.float64)
        rest_nodes = (
            _initial_needle_nodes(scene, models)
            if needle_rest_nodes is None
            else np.asarray(needle_rest_nodes, dtype=np.float64)
        )
        self._boundary_nodes = np.asarray(getattr(models, "boundary_nodes", np.zeros(0)), dtype=np.int64)
        self._sizes = {
            "n": rest_positions.shape[0],
            "k": rest_nodes.shape[0],
            "stages": len(self._stages),
            "b": max(self._boundary_nodes.size, 1),
        }
        return {
            "tissue/rest_positions": rest_positions,
            "tissue/tets": np.asarray(mesh.tets, dtype=np.int64),
            "tissue/faces": np.asarray(mesh.boundary_faces, dtype=np.int64),
            "tissue/fixed_nodes": np.asarray(models.tissue.fixed_nodes, dtype=np.int64),
            "tissue/boundary_nodes": self._boundary_nodes,
            "trajectory/samples": _samples(models.trajectory),
            "needle/rest_nodes": rest_nodes,
        }

    def _further_instruments(self, scene, models) -> list[tuple[str, str, dict]]:
        """Each instrument after the first: its name, its location and its static arrays (by the one-needle
        paths); sets each one's needle node count. Empty for a one-instrument run."""
        further = []
        instruments = tuple(getattr(models, "instruments", ()))
        for index, instrument in enumerate(instruments[1:] if len(instruments) > 1 else (), start=1):
            location = schema.instrument_location(index, instrument.name)
            rest = _instrument_rest_nodes(instrument.needle, instrument.model, instrument.trajectory)
            self._sizes[f"k:{location}"] = rest.shape[0]
            static = {
                schema.STATIC["trajectory/samples"].path: _samples(instrument.trajectory),
                schema.STATIC["needle/rest_nodes"].path: rest,
            }
            further.append((instrument.name, location, static))
        self._instrument_names = tuple(instrument.name for instrument in instruments) or ("needle",)
        return further

    def _create_file(self, scene, scene_json: str, static: dict) -> None:
        """Write the file's static part under a temporary name, then rename it into place: only a file with
        its static part takes the name.

        Raises
        ------
        OSError
            Naming the path when the static part cannot be written (a full disk); nothing is left.
        """
        import h5py

        temporary = self.path.with_name(f".{self.path.name}.{os.getpid()}.partial")
        try:
            self._file = h5py.File(temporary, "w")
            try:
                self._write_static_part(scene, scene_json, static)
            except BaseException:
                try:
                    self._file.close()
                except OSError:
                    pass
                raise
            os.replace(temporary, self.path)  # only a file with its static part takes the name
        except OSError as error:
            temporary.unlink(missing_ok=True)
            raise OSError(
                error.errno or errno.EIO,
                f"{self.path}: cannot write the results file's static part ({error}); nothing was "
                "written (an existing file is untouched)",
            ) from None
        except BaseException:
            temporary.unlink(missing_ok=True)
            raise

    def _write_static_part(self, scene, scene_json: str, static: dict) -> None:
        """The root attributes, the static datasets and the empty growing datasets."""
        from refsim import __version__

        attributes = self._file.attrs
        attributes["format"] = schema.FORMAT_NAME
        attributes["schema_version"] = schema.SCHEMA_VERSION
        attributes["refsim_version"] = __version__
        attributes["git_commit"] = git_commit()
        attributes["created"] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        attributes["scene"] = scene_json
        attributes["scene_name"] = scene.name
        attributes["linear_solver"] = json.dumps(_linear_solver(scene))
        attributes["threads"] = json.dumps(_threads())
        attributes["complete"] = False
        attributes["steps_completed"] = 0
        attributes["stop_reason"] = "running (or stopped without a reason: killed)"
        for name, value in static.items():
            self._write_fixed(schema.STATIC[name], value)
        several = bool(self._further)
        for group in _GROWING_GROUPS:
            for spec in group.values():
                if several or spec.path != schema.CONSTRAINTS["instrument"].path:
                    self._create_growing(spec)
        if several:
            first = schema.instrument_location(0, self._instrument_names[0])
            attributes["instruments"] = json.dumps(
                [{"name": self._instrument_names[0], "location": first}]
                + [{"name": name, "location": location} for name, location, _ in self._further]
            )
        for _, location, arrays in self._further:
            for path, value in arrays.items():
                self._write_fixed(_located(schema.INSTRUMENT_DATASETS[path], location), value)
            for spec in schema.INSTRUMENT_DATASETS.values():
                if spec.growing:
                    self._create_growing(_located(spec, location), k=self._sizes[f"k:{location}"])
        for quantity in schema.INSTRUMENT_STEP_QUANTITIES:  # coded quantities name their codes
            if quantity.codes:
                path = schema.STEPS[quantity.name].path
                for location in ("", *(location for _, location, _ in self._further)):
                    self._datasets[f"{location}/{path}" if location else path].attrs["names"] = list(
                        quantity.codes
                    )
        self._datasets["steps/stage_seconds"].attrs["names"] = list(self._stages)
        self._set_code_names()
        self._append("constraints/offsets", np.zeros(1, dtype=np.int64))
        self._file.flush()

    # ------------------------------------------------------------------ context manager

    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, exc_type, exc, traceback) -> None:
        reason = "" if exc_type is None else f"stopped by {exc_type.__name__}: {exc}"
        self.close(complete=exc_type is None and self.failure is None, reason=reason)

    @property
    def steps_completed(self) -> int:
        """Steps written to the file so far (buffered steps not included)."""
        return self._steps_completed

    def close(self, *, complete: bool = True, reason: str = "") -> None:
        """Write the buffered steps and close the file.

        Parameters
        ----------
        complete : Mark the run as finished (False for a run that stopped early); forced False after a failed
            write.
        reason : Why the run stopped (stored in the root attribute ``stop_reason``; "" for a complete run).
        """
        if self._closed:
            return
        self._closed = True
        try:
            if self.failure is None:
                try:
                    self._write_block()
                except OSError as error:
                    self._fail(error)
            if self.failure is not None:
                complete = False
                reason = (
                    reason
                    if self.failure in reason
                    else (f"{reason}; {self.failure}" if reason else self.failure)
                )
            self._file.attrs["complete"] = bool(complete)
            self._file.attrs["steps_completed"] = self._steps_completed
            self._file.attrs["stop_reason"] = "" if complete else (reason or "stopped")
        finally:
            try:
                self._file.close()
            except OSError as error:  # the file's last metadata could not be written (disk full)
                logger.error("%s: closing the results file failed: %s", self.path, error)
                if self.failure is None:
                    self.failure = f"closing the results file failed: {error}"
            finally:
                self._lock.release()
        logger.info("closed %s: %d steps, complete=%s", self.path, self._steps_completed, complete)

    # ------------------------------------------------------------------ per step

    def append(self, record) -> None:
        """Check one step (a :class:`refsim.simulation.StepRecord`) and buffer it; write a block when full.

        Raises
        ------
        ValueError
            When an array of the record has a shape that does not fit the file (naming the field).
        RuntimeError
            When the writer is closed.
        OSError
            When a block cannot be written (a full disk): the file keeps the blocks written before, and the
            writer accepts no more steps (``failure`` says why).
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: the results writer is closed; cannot append step {record.step}")
        if self.failure is not None:
            raise OSError(errno.EIO, f"{self.path}: writing stopped after a failed write ({self.failure})")
        self._pending.append(self._values.of(record))
        if record.problem is not None:
            self._pending_problems.append((record.step, record.problem))
        if len(self._pending) >= self._buffer_steps:
            self.flush()

    def flush(self) -> None:
        """Write the buffered steps now (one block) and flush the file.

        Raises
        ------
        OSError
            When the block cannot be written; the file keeps the blocks written before.
        """
        if self._closed or self.failure is not None:
            return
        try:
            self._write_block()
        except OSError as error:
            self._fail(error)
            raise OSError(
                errno.ENOSPC if "space" in str(error).lower() else errno.EIO, f"{self.path}: {self.failure}"
            ) from None

    def _fail(self, error: BaseException) -> None:
        self.failure = (
            f"writing step {self._steps_completed + 1} failed ({error}); the file keeps the "
            f"{self._steps_completed} steps written before"
        )
        self._pending.clear()
        self._pending_problems.clear()
        self._pending_cut = None
        logger.error("%s: %s", self.path, self.failure)

    @staticmethod
    def _values_bytes(values: dict) -> int:
        return sum(
            value.size * (64 if value.dtype == object else value.itemsize)
            for value in values.values()
            if isinstance(value, np.ndarray)
        )

    def _bytes_needed(self, count: int) -> int:
        """Bytes the file grows by when the first ``count`` buffered steps are written: the new chunks of
        every growing dataset (HDF5 allocates whole chunks), the recorded problems and the cut surface."""
        pending = self._pending[:count]
        total = 0
        for path, dataset in self._datasets.items():
            if path == "constraints/offsets":
                added = len(pending)
            else:
                added = sum(values[path].shape[0] for values in pending if path in values)
            if added == 0:
                continue
            length, chunk = dataset.shape[0], dataset.chunks[0]
            new_chunks = -(-(length + added) // chunk) - -(-length // chunk)
            itemsize = 64 if dataset.dtype.kind == "O" else dataset.dtype.itemsize
            total += new_chunks * int(np.prod(dataset.chunks)) * itemsize
            if dataset.dtype.kind == "O":
                total += 64 * added  # the strings themselves, in the global heap
        last = int(pending[-1][schema.STEPS["step"].path][0]) if pending else -1
        total += sum(
            sum(np.asarray(getattr(problem, spec.name)).nbytes for spec in schema.PROBLEM_FIELDS.values())
            for step, problem in self._pending_problems
            if step <= last
        )
        if self._pending_cut is not None and count == len(self._pending):
            total += sum(np.asarray(v).nbytes for v in self._pending_cut.values())
        return total

    def _check_static_space(self, static: dict, attribute_bytes: int) -> None:
        """Refuse (OSError ENOSPC, naming the path and the sizes) when the file system lacks room for the
        static part: its arrays, the attributes, the metadata of every dataset and the margin."""
        dataset_count = len(static) + sum(len(group) for group in _GROWING_GROUPS)
        needed = (
            sum(np.asarray(value).nbytes for value in static.values())
            + attribute_bytes
            + dataset_count * _METADATA_PER_DATASET
            + _SPACE_MARGIN
        )
        try:
            free = shutil.disk_usage(self.path.parent).free
        except OSError:
            return
        if free < needed:
            raise OSError(
                errno.ENOSPC,
                f"{self.path}: no space left for the results file: its static part (mesh, trajectory, "
                f"scene) needs about {needed} bytes and {free} bytes are free; nothing was written",
            )

    def _steps_that_fit(self) -> int:
        """How many of the buffered steps the file system has room for (all of them when it cannot tell)."""
        try:
            budget = shutil.disk_usage(self.path.parent).free - _SPACE_MARGIN
        except OSError:
            return len(self._pending)
        if self._bytes_needed(len(self._pending)) <= budget:
            return len(self._pending)
        low, high = 0, len(self._pending)  # the largest count that fits, by bisection
        while low < high:
            middle = (low + high + 1) // 2
            if self._bytes_needed(middle) <= budget:
                low = middle
            else:
                high = middle - 1
        return low

    def _write_block(self) -> None:
        """Write the buffered steps (those that fit on the disk); steps_completed is updated last, after every
        dataset has its data. Raises OSError (ENOSPC) after writing the steps that fit when some do not."""
        if not self._pending and self._pending_cut is None and not self._pending_problems:
            return
        fit = self._steps_that_fit()
        short = fit < len(self._pending)
        if short:
            free = shutil.disk_usage(self.path.parent).free
            logger.warning(
                "%s: %d bytes free: writing %d of %d buffered steps", self.path, free, fit, len(self._pending)
            )
        pending = self._pending[:fit]
        last_step = int(pending[-1][schema.STEPS["step"].path][0]) if pending else -1
        row_counts = np.array([values["constraints/row_count"] for values in pending], dtype=np.int64)
        paths = [path for path in self._datasets if path not in ("constraints/offsets",)]
        # Ragged and optional data first; the per-step arrays and "steps/step" last (the reader trusts
        # steps_completed, and the length of steps/step is the count of fully written steps).
        order = (
            [path for path in paths if not path.startswith("steps/")]
            + [path for path in paths if path.startswith("steps/") and path != "steps/step"]
            + ["steps/step"]
        )
        for path in order:
            blocks = [values[path] for values in pending if path in values]
            if blocks:
                self._append(path, np.concatenate(blocks))
        if pending:
            offsets = self._rows_written + np.cumsum(row_counts)
            self._append("constraints/offsets", offsets.astype(np.int64))
        for step, problem in self._pending_problems:
            if step <= last_step or not short:
                self._write_problem(step, problem)
        if self._pending_cut is not None and not short:
            self._write_cut(self._pending_cut)
        self._rows_written += int(row_counts.sum())
        self._steps_completed += len(pending)
        self._pending = self._pending[fit:]
        self._pending_problems = (
            [(step, problem) for step, problem in self._pending_problems if step > last_step] if short else []
        )
        if not short:
            self._pending_cut = None
        self._file.attrs["steps_completed"] = self._steps_completed
        self._file.flush()
        if short:
            raise OSError(
                errno.ENOSPC,
                f"no space left on the device for step {self._steps_completed + 1} "
                f"({shutil.disk_usage(self.path.parent).free} bytes free)",
                str(self.path),
            )

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
        """(Re)write the cut surface history: the whole surface so far, replacing what was written before
        (with the next block of steps).

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
            raise ValueError(
                f"cut triangles must index the {count} cut points, got indices "
                f"{values['triangles'].min()}..{values['triangles'].max()}"
            )
        if (tet_indices is None) != (barycentric is None):
            raise ValueError("write_cut_surface: give both tet_indices and barycentric, or neither")
        if tet_indices is not None:
            values["tet_indices"] = self._check_shape(
                "cut tet_indices", tet_indices, (count,), dtype=np.int64
            )
            values["barycentric"] = self._check_shape(
                "cut barycentric", barycentric, (count, 4), dtype=np.float64
            )
        self._pending_cut = values  # written with the next block (the latest surface replaces older ones)

    def _write_cut(self, values: dict) -> None:
        group_path = "cut"
        if group_path in self._file:
            del self._file[group_path]
        for name, value in values.items():
            self._write_fixed(schema.CUT[name], value)

    # ------------------------------------------------------------------ helpers

    def _set_code_names(self) -> None:
        from refsim.constraints.rows import ROW_KIND_NAMES, SOURCE_NAMES

        self._datasets["constraints/kind"].attrs["names"] = list(ROW_KIND_NAMES)
        self._datasets["constraints/source"].attrs["names"] = list(SOURCE_NAMES)

    def _entry_shape(self, spec: DatasetSpec) -> tuple[int, ...]:
        return tuple(self._sizes[size] if isinstance(size, str) else size for size in spec.entry_shape)

    def _describe(self, dataset, spec: DatasetSpec) -> None:
        dataset.attrs["units"] = spec.unit
        dataset.attrs["description"] = spec.meaning

    def _write_fixed(self, spec: DatasetSpec, value: np.ndarray) -> None:
        dataset = self._file.create_dataset(
            spec.path, data=value, dtype=schema.numpy_dtype(spec), fletcher32=_checksummed(spec, value)
        )
        self._describe(dataset, spec)

    def _create_growing(self, spec: DatasetSpec, *, k: int | None = None) -> None:
        entry = self._entry_shape(spec)
        if k is not None:  # a further instrument's needle: its own node count
            entry = tuple(
                k if size == "k" else value for size, value in zip(spec.entry_shape, entry, strict=True)
            )
        chunk = (
            (1,)
            if spec.path == "tissue/positions"
            else (
                (_CHUNK_ROWS,)
                if spec.path.split("/")[0] in ("constraints", "events", "criteria")
                else (_CHUNK_STEPS,)
            )
        )
        dataset = self._file.create_dataset(
            spec.path,
            shape=(0,) + entry,
            maxshape=(None,) + entry,
            chunks=chunk + entry,
            dtype=schema.numpy_dtype(spec),
            fletcher32=spec.dtype != "str",
        )
        self._describe(dataset, spec)
        self._datasets[spec.path] = dataset

    def _append(self, path: str, values: np.ndarray) -> None:
        dataset = self._datasets[path]
        start = dataset.shape[0]
        dataset.resize(start + values.shape[0], axis=0)
        dataset[start:] = values

    def _check_shape(self, name: str, value, shape: tuple, *, dtype=np.float64) -> np.ndarray:
        return check_shape(self.path, name, value, shape, dtype=dtype)

    def _write_problem(self, step: int, problem) -> None:
        group_path = schema.problem_group_name(step)
        if group_path in self._file:
            del self._file[group_path]
        group = self._file.create_group(group_path)
        group.attrs["step"] = int(step)
        write_problem_group(group, problem)


def _located(spec: DatasetSpec, location: str) -> DatasetSpec:
    """``spec`` under an instrument's location (``instruments/<name>/...``)."""
    return dataclasses.replace(spec, path=f"{location}/{spec.path}") if location else spec


def write_problem_group(group, problem) -> None:
    """Write every field of a ConstraintProblem (schema.PROBLEM_FIELDS, derived from the solvers' law table)
    and its name into an open h5py group; :func:`refsim.io.reader.read_problem_group` reads it back."""
    group.attrs["name"] = str(problem.name)
    for spec in schema.PROBLEM_FIELDS.values():
        value = np.asarray(getattr(problem, spec.name))
        dataset = group.create_dataset(
            spec.name, data=value, dtype=schema.numpy_dtype(spec), fletcher32=_checksummed(spec, value)
        )
        dataset.attrs["units"] = spec.unit
        dataset.attrs["description"] = spec.meaning


def _checksummed(spec: DatasetSpec, value) -> bool:
    """Whether a dataset takes the Fletcher-32 filter: every numeric array (a filter needs chunks, which a
    scalar cannot have, and HDF5 refuses filters on variable-length strings)."""
    return spec.dtype != "str" and np.ndim(value) > 0


def _linear_solver(scene) -> dict:
    """The sparse solver the run's compliance uses and its versions (refsim.fem.linear)."""
    from refsim.fem.linear import linear_solver_info

    try:
        return linear_solver_info(getattr(getattr(scene, "compliance", None), "linear_solver", None))
    except (ValueError, ImportError) as error:  # reported, not fatal: the run checks the solver itself
        return {"error": str(error)}


def _threads() -> list:
    """The BLAS / OpenMP thread pools when the file is created (the step pins them to one thread)."""
    from refsim.fem.threads import thread_settings

    return thread_settings()
