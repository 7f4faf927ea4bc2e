"""Motion of the needle base: piecewise-linear waypoints or a sampled file (a robot's precomputed motion)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from refsim.scene.spec import TrajectorySpec

__all__ = ["Trajectory", "read_numeric_csv", "read_trajectory_csv"]


@dataclass(frozen=True)
class Trajectory:
    """Base pose as a function of time, linear between samples and constant after the last.

    Attributes
    ----------
    times : Sample times [s], strictly increasing from 0, shape (w,).
    base_positions : Base position [m] at each sample, shape (w, 3).
    directions : Unit needle direction (base to tip) at each sample, shape (w, 3).
    """

    times: np.ndarray
    base_positions: np.ndarray
    directions: np.ndarray

    @classmethod
    def from_spec(cls, spec: TrajectorySpec, base_directory: str = ".") -> Trajectory:
        """From the scene's [trajectory] section (a file path is relative to the scene file)."""
        if spec.file is not None:
            path = Path(spec.file)
            if not path.is_absolute():
                path = Path(base_directory) / path
            return read_trajectory_csv(path)
        directions = np.asarray(spec.directions, dtype=float)
        return cls(
            np.asarray(spec.times, dtype=float),
            np.asarray(spec.base_positions, dtype=float),
            directions / np.linalg.norm(directions, axis=1, keepdims=True),
        )

    def pose(self, time: float) -> tuple[np.ndarray, np.ndarray]:
        """Base position [m] (3,) and unit direction (3,) at ``time`` [s]."""
        base = np.array([np.interp(time, self.times, self.base_positions[:, k]) for k in range(3)])
        direction = np.array([np.interp(time, self.times, self.directions[:, k]) for k in range(3)])
        return base, direction / np.linalg.norm(direction)


def read_numeric_csv(path: Path, columns: tuple[str, ...], what: str) -> np.ndarray:
    """Rows of numbers from a CSV file with the given columns, shape (rows, len(columns)).

    '#' comment lines anywhere (before the header too) and one header line are allowed.

    Raises
    ------
    ValueError
        Naming the file and the defect (missing, not numbers, wrong column count, non-finite values).
    """
    if not path.is_file():
        raise ValueError(f"{path}: {what} file not found")
    lines = [
        line
        for line in path.read_text(encoding="utf-8").splitlines()
        if line.strip() and not line.lstrip().startswith("#")
    ]
    try:
        data = np.loadtxt(lines, delimiter=",", ndmin=2)
    except ValueError:
        try:
            data = np.loadtxt(lines[1:], delimiter=",", ndmin=2)
        except ValueError as error:
            raise ValueError(f"{path}: cannot read the {what} as numbers: {error}") from None
    names = ", ".join(columns)
    if data.shape[0] == 0 or data.shape[1] != len(columns):
        raise ValueError(f"{path}: expected rows of {len(columns)} columns {names}; got shape {data.shape}")
    if not np.all(np.isfinite(data)):
        raise ValueError(f"{path}: non-finite values in the {what}")
    return data


def read_trajectory_csv(path: Path) -> Trajectory:
    """Read a CSV trajectory: columns t, x, y, z, dx, dy, dz [s, m, -]; '#' comments and a header line
    allowed.

    Raises
    ------
    ValueError
        Naming the file and the defect (missing file, wrong column count, non-finite values, times not
        increasing from 0, zero directions).
    """
    data = read_numeric_csv(path, ("t", "x", "y", "z", "dx", "dy", "dz"), "trajectory")
    times = data[:, 0]
    if times[0] != 0.0 or np.any(np.diff(times) <= 0.0):
        raise ValueError(f"{path}: times must start at 0 s and increase strictly")
    norms = np.linalg.norm(data[:, 4:7], axis=1)
    if np.any(norms < 1e-12):
        raise ValueError(f"{path}: zero direction at row {int(np.argmax(norms < 1e-12)) + 1}")
    from refsim.scene.spec import check_directions

    try:
        check_directions(data[:, 4:7], "directions", times)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
    return Trajectory(times, data[:, 1:4], data[:, 4:7] / norms[:, None])
