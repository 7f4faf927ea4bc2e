"""The trajectory an interactive run applied, and its replay: a CSV trajectory and a scene file beside the
results file, so that ``refsim run OUT.replay.toml`` reproduces the run.

Bit-identical replay: the run's controls read the base pose from :class:`AppliedTrajectory`, which returns a
stored sample exactly as :meth:`refsim.scene.trajectory.Trajectory.pose` returns it from the CSV (the base as
stored, the direction divided by its norm; every applied direction has a norm of exactly 1.0,
:func:`refsim.interactive.pose.exact_unit`, so the CSV reader's normalisation returns it unchanged too). The
CSV holds every number with ``repr`` (the shortest decimal that reads back to the same float64), the replay's
steps fall on the same times (the same ``time + dt`` sums), and linear interpolation between two samples
returns a sample exactly at its own time; the stored samples are the step times at which the pose changed and
the two ends of every hold (interpolating between two equal samples returns them exactly).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

__all__ = ["AppliedTrajectory", "replay_paths", "toml_document", "write_replay_scene"]


class AppliedTrajectory:
    """The base poses applied so far, one per step, with holds stored as their two ends.

    Used as the trajectory of the run's :class:`~refsim.scene.controls.Controls` (it has
    :meth:`pose`): the step loop :meth:`append` s the pose of a step before the step reads it.

    Parameters
    ----------
    base : Base position at t = 0 [m], (3,).
    direction : Unit needle direction at t = 0, (3,).
    """

    def __init__(self, base: np.ndarray, direction: np.ndarray) -> None:
        self._times = [0.0]
        self._bases = [np.array(base, dtype=float)]
        self._directions = [np.array(direction, dtype=float)]
        self._holding = False  # the last two samples are equal (a hold whose end is moved forward)

    @property
    def sample_count(self) -> int:
        return len(self._times)

    @property
    def last_time(self) -> float:
        return self._times[-1]

    def append(self, time: float, base: np.ndarray, direction: np.ndarray) -> None:
        """The pose applied at ``time`` [s] (after the last sample's time)."""
        if not time > self._times[-1]:
            raise ValueError(f"time {time!r} s is not after the last sample's {self._times[-1]!r} s")
        base = np.array(base, dtype=float)
        direction = np.array(direction, dtype=float)
        same = np.array_equal(base, self._bases[-1]) and np.array_equal(direction, self._directions[-1])
        if same and self._holding:
            self._times[-1] = float(time)
            return
        self._times.append(float(time))
        self._bases.append(base)
        self._directions.append(direction)
        self._holding = same

    def pose(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        """Base position [m] (3,) and unit direction (3,) at ``time`` [s], computed as
        :meth:`refsim.scene.trajectory.Trajectory.pose` computes it from the same samples."""
        if time == self._times[-1]:
            direction = self._directions[-1]
            return self._bases[-1].copy(), direction / np.linalg.norm(direction)
        return self.trajectory().pose(time)

    def trajectory(self):
        """The samples as a :class:`refsim.scene.trajectory.Trajectory`."""
        from refsim.scene.trajectory import Trajectory

        return Trajectory(np.array(self._times), np.array(self._bases), np.array(self._directions))

    def samples(self) -> np.ndarray:
        """t [s], x, y, z [m], dx, dy, dz per sample, shape (w, 7)."""
        return np.column_stack([np.array(self._times), np.array(self._bases), np.array(self._directions)])

    def write_csv(self, path: Path) -> Path:
        """Write the samples as a trajectory CSV (``refsim.scene.trajectory.read_trajectory_csv``)."""
        lines = [
            "# the needle base trajectory applied by `refsim interactive` (t [s], base [m], direction)",
            "t,x,y,z,dx,dy,dz",
        ]
        lines.extend(",".join(repr(float(value)) for value in row) for row in self.samples())
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")
        return path


def replay_paths(output: Path) -> tuple[Path, Path]:
    """The trajectory CSV and the replay scene written beside ``output`` (OUT.h5 → OUT.trajectory.csv,
    OUT.replay.toml)."""
    output = Path(output)
    stem = output.with_suffix("") if output.suffix == ".h5" else output
    return stem.with_name(stem.name + ".trajectory.csv"), stem.with_name(stem.name + ".replay.toml")


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string: the same escapes
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    if isinstance(value, dict):
        items = (f"{key} = {_toml_value(item)}" for key, item in value.items() if item is not None)
        return "{" + ", ".join(items) + "}"
    raise TypeError(f"no TOML form for {type(value).__name__} {value!r}")


def toml_document(data: dict, header: str = "") -> str:
    """A TOML document of plain data: top-level scalars, then one table per dict; None values are left out
    (the key's default)."""
    lines = [f"# {line}" for line in header.splitlines()]
    tables = []
    for key, value in data.items():
        if isinstance(value, dict):
            tables.append((key, value))
        elif value is not None:
            lines.append(f"{key} = {_toml_value(value)}")
    for name, table in tables:
        lines.append("")
        lines.append(f"[{name}]")
        lines.extend(f"{key} = {_toml_value(value)}" for key, value in table.items() if value is not None)
    return "\n".join(lines) + "\n"


def write_replay_scene(scene, trajectory_csv: Path, steps: int, path: Path) -> Path:
    """Write the scene of an interactive run with its applied trajectory: ``refsim run`` on it repeats the
    run's ``steps`` steps.

    The trajectory section becomes ``file = "<the CSV's name>"`` (beside the scene file), ``time.duration``
    is ``steps · dt``, and the files the scene names (``mesh.file``, ``boundary.file``) become absolute.
    """
    data = scene.to_dict()
    base = Path(scene.base_directory)
    for section in ("mesh", "boundary"):
        name = data.get(section, {}).get("file")
        if name is not None and not Path(name).is_absolute():
            data[section]["file"] = str((base / name).resolve())
    data["trajectory"] = {"file": Path(trajectory_csv).name}
    data["time"]["duration"] = steps * scene.time.dt
    header = (
        f"The scene {scene.name} ({scene.source}) with the needle base trajectory\n"
        f"an interactive run applied ({steps} steps). Replay: refsim run {path.name} -o REPLAY.h5"
    )
    path.write_text(toml_document(data, header), encoding="utf-8")
    return path
