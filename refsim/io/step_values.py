"""What one step adds to each dataset of a results file that grows by step (layout in
:mod:`refsim.io.schema`): a :class:`refsim.simulation.StepRecord` turned into arrays by dataset path, each
checked against the file's shapes. :class:`refsim.io.writer.ResultWriter` stores them; this module only
reads records.
"""

from __future__ import annotations

import numpy as np

from refsim.io import schema

__all__ = ["StepValues", "check_shape"]


def check_shape(path, name: str, value, shape: tuple, *, dtype=np.float64) -> np.ndarray:
    """``value`` as an array of ``dtype`` with ``shape`` (None: any length there); a ValueError naming the
    file ``path``, the field and both shapes otherwise."""
    try:
        array = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: {name} is not a numeric array ({error})") from None
    if array.ndim != len(shape) or any(
        s is not None and s != a for s, a in zip(shape, array.shape, strict=False)
    ):
        expected = "(" + ", ".join("any" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{path}: {name} has shape {array.shape}, expected {expected}")
    return array


class StepValues:
    """The arrays each step adds to the growing datasets of one results file.

    Parameters
    ----------
    path : The results file (named in the errors).
    stages : The stage names of ``steps/stage_seconds``, in its column order.
    sizes : The file's entry sizes by name: ``n`` tissue nodes, ``k`` the first needle's nodes, ``b`` boundary
        nodes (at least 1), ``k:<location>`` each further instrument's needle nodes.
    boundary_nodes : The nodes of a prescribed boundary motion, shape (b,) (empty: none).
    instruments : Every instrument's name, in order, and each one after the first its location in the file
        (``instruments/<name>``), as (name, location) pairs.
    """

    def __init__(self, path, stages, sizes: dict, boundary_nodes: np.ndarray, instruments) -> None:
        self.path = path
        self._stages = tuple(stages)
        self._sizes = sizes
        self._boundary_nodes = boundary_nodes
        instruments = tuple(instruments)
        self._instrument_names = tuple(name for name, _ in instruments)
        self._further = instruments[1:]

    def of(self, record) -> dict:
        """The arrays step ``record`` adds to each growing dataset, by path, checked against the file's
        shapes."""
        rows = self._check_rows(record)
        row_count = rows["forces"].shape[0]
        values = {f"constraints/{name}": value for name, value in rows.items()}
        values["constraints/row_count"] = row_count
        if record.events:
            values.update(self._event_values(record.events, record))
        if record.criteria:
            values.update(_criteria_values(record.step, record.criteria))
        if record.tissue_positions is not None:
            positions = self._check_shape("tissue_positions", record.tissue_positions, (self._sizes["n"], 3))
            values["tissue/step"] = np.array([record.step], dtype=np.int64)
            values["tissue/time"] = np.array([record.time], dtype=np.float64)
            values["tissue/positions"] = positions[None]
        values.update(self._solver_values(record.solver))
        values.update(self._step_arrays(record))
        if self._further:
            values.update(self._instrument_values(record, count=row_count))
        return values

    def _instrument_values(self, record, *, count: int) -> dict:
        """The per-row instrument and each further instrument's step values, under its location."""
        parts = tuple(getattr(record, "instruments", ()))
        if len(parts) != len(self._further) + 1:
            raise ValueError(
                f"{self.path}: step {record.step} has {len(parts)} instruments, the file "
                f"{len(self._further) + 1} ({', '.join(self._instrument_names)})"
            )
        values = {
            schema.CONSTRAINTS["instrument"].path: self._check_shape(
                "row_instrument", record.row_instrument, (count,), dtype=np.int64
            )
        }
        for part, (name, location) in zip(parts[1:], self._further, strict=True):
            if part.name != name:
                raise ValueError(
                    f"{self.path}: step {record.step}: instrument {part.name!r}, expected {name!r}"
                )
            arrays = self._needle_arrays(part, self._sizes[f"k:{location}"], record.step)
            values.update({f"{location}/{path}": value for path, value in arrays.items()})
            if part.events:
                values.update(
                    {
                        f"{location}/{path}": value
                        for path, value in self._event_values(part.events, record).items()
                    }
                )
            if part.criteria:
                values.update(
                    {
                        f"{location}/{path}": value
                        for path, value in _criteria_values(record.step, part.criteria).items()
                    }
                )
        return values

    def _needle_arrays(self, part, k: int, step: int) -> dict:
        """One instrument's per-step arrays (``part``: its ``InstrumentRecord``), by the one-needle paths:
        each quantity of :data:`~refsim.io.schema.INSTRUMENT_STEP_QUANTITIES` from its record attribute."""
        values = {}
        for quantity in schema.INSTRUMENT_STEP_QUANTITIES:
            value = quantity.value(part)
            if quantity.codes:
                if value not in quantity.codes:
                    raise ValueError(
                        f"{self.path}: step {step} has {quantity.attribute} {value!r}; "
                        f"the results schema knows {', '.join(quantity.codes)}"
                    )
                value = quantity.codes.index(value)
            shape = tuple(k if size == "k" else size for size in quantity.entry_shape)
            array = self._check_shape(quantity.attribute, value, shape, dtype=np.dtype(quantity.dtype))
            values[schema.STEPS[quantity.name].path] = array[None]
        return values

    @staticmethod
    def _event_values(events, record) -> dict:
        """The events' entries of ``events/``, by path."""
        values = {
            "events/step": np.full(len(events), record.step, dtype=np.int64),
            "events/time": np.full(len(events), record.time, dtype=np.float64),
            "events/name": np.array([event.name for event in events], dtype=object),
        }
        for unit, name in schema.EVENT_VALUE_DATASETS.items():  # each value in the dataset of its unit
            values[f"events/{name}"] = np.array(
                [event.force if event.unit == unit else np.nan for event in events], dtype=np.float64
            )
        return values

    def _check_shape(self, name: str, value, shape: tuple, *, dtype=np.float64) -> np.ndarray:
        return check_shape(self.path, name, value, shape, dtype=dtype)

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

    def _solver_values(self, report) -> dict:
        if report is None:
            values = {
                "iterations": -1,
                "residual": np.nan,
                "converged": -1,
                "seconds": np.nan,
                "increment": np.nan,
                "name": "",
                "message": "",
            }
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
        out = {}
        for name, value in values.items():
            spec = schema.SOLVER[name]
            dtype = object if spec.dtype == "str" else spec.dtype
            out[spec.path] = np.array([value], dtype=dtype)
        return out

    def _step_arrays(self, record) -> dict:
        unknown = set(record.stage_seconds) - set(self._stages)
        if unknown:
            raise ValueError(
                f"{self.path}: step {record.step} times unknown stages {sorted(unknown)}; "
                f"stages are {', '.join(self._stages)}"
            )
        needle = self._needle_arrays(record.instruments[0], self._sizes["k"], record.step)
        values = {
            "step": np.array([record.step], dtype=np.int64),
            "time": np.array([record.time], dtype=np.float64),
            "cut_point_count": np.array([record.cut_point_count], dtype=np.int64),
            "cut_triangle_count": np.array([record.cut_triangle_count], dtype=np.int64),
            "triangulation_seconds": np.array([record.triangulation_seconds], dtype=np.float64),
            "stage_seconds": np.array(
                [[float(record.stage_seconds.get(stage, np.nan)) for stage in self._stages]], dtype=np.float64
            ),
            "boundary_displacement": self._boundary_displacement(record)[None],
        }
        return {**needle, **{schema.STEPS[name].path: value for name, value in values.items()}}

    def _boundary_displacement(self, record) -> np.ndarray:
        """The step's prescribed boundary displacement (b, 3) [m]; zeros (1, 3) without a boundary motion."""
        value = getattr(record, "boundary_displacements", None)
        if value is None or self._boundary_nodes.size == 0:
            return np.zeros((self._sizes["b"], 3))
        return self._check_shape("boundary_displacements", value, (self._boundary_nodes.size, 3))


def _criteria_values(step: int, criteria) -> dict:
    """The entries one step adds to ``criteria/`` (refsim.simulation.margins.Criterion of each)."""
    return {
        "criteria/step": np.full(len(criteria), step, dtype=np.int64),
        "criteria/name": np.array([c.name for c in criteria], dtype=object),
        "criteria/value": np.array([c.value for c in criteria], dtype=np.float64),
        "criteria/threshold": np.array([c.threshold for c in criteria], dtype=np.float64),
        "criteria/accuracy": np.array([c.accuracy for c in criteria], dtype=np.float64),
        "criteria/unit": np.array([c.unit for c in criteria], dtype=object),
    }
