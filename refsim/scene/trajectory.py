"""Motion of the needle base: piecewise-linear waypoints or a sampled file (a robot's precomputed motion)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from refsim.scene.spec import TrajectorySpec

__all__ = ["Aim", "Trajectory", "aimed", "read_numeric_csv", "read_trajectory_csv"]


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
        """From the scene's [trajectory] section (a file path is relative to the scene file); an aimed
        insertion (``spec.entry``) needs the mesh: :func:`aimed`."""
        if spec.entry is not None:
            raise ValueError("trajectory.entry: an aimed insertion is resolved on the mesh (aimed)")
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

    def poses(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Base positions [m] (m, 3) and unit directions (m, 3) at ``times`` [s] (m,): :meth:`pose` at every
        time in one call, with its bits (the same interpolation, the norms by the same dot product)."""
        times = np.asarray(times, dtype=float)
        base = np.stack([np.interp(times, self.times, self.base_positions[:, k]) for k in range(3)], axis=1)
        direction = np.stack([np.interp(times, self.times, self.directions[:, k]) for k in range(3)], axis=1)
        return base, direction / np.sqrt(np.vecdot(direction, direction))[:, None]


def read_numeric_csv(path: Path, columns: tuple[str, ...], what: str) -> np.ndarray:
    """Rows of numbers from a CSV file with the given columns, shape (rows, len(columns)).

    '#' comment lines anywhere (before the header too) and one header line are allowed; the header, when
    there is one, must name ``columns`` in their order (case and a unit in brackets, "t [s]", aside): the
    values are read by position.

    Raises
    ------
    ValueError
        Naming the file and the defect (missing, not text, a header naming other columns, a line that is not
        numbers (its line number in the file), wrong column count, non-finite values).
    """
    if not path.is_file():
        raise ValueError(f"{path}: {what} file not found")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as error:
        raise ValueError(f"{path}: not a text (UTF-8) CSV file: {error}") from None
    numbered = [
        (number, line)
        for number, line in enumerate(text.splitlines(), start=1)
        if line.strip() and not line.lstrip().startswith("#")
    ]
    names = ", ".join(columns)
    if numbered and not _is_numeric_row(numbered[0][1]):
        number, header = numbered.pop(0)
        found = tuple(item.split("[")[0].split("(")[0].strip().lower() for item in header.split(","))
        if found != columns:
            raise ValueError(
                f"{path}: line {number}: header {header.strip()!r}: expected the columns {names}, in this "
                "order (the values are read by position)"
            )
    for number, line in numbered:
        if not _is_numeric_row(line) or line.count(",") != len(columns) - 1:
            raise ValueError(
                f"{path}: line {number}: {line.strip()[:80]!r}: expected {len(columns)} numbers separated by "
                f"commas ({names})"
            )
    rows = [line for _, line in numbered]
    data = np.loadtxt(rows, delimiter=",", ndmin=2) if rows else np.zeros((0, len(columns)))
    if data.shape[0] == 0:
        raise ValueError(f"{path}: no rows of numbers; expected rows of {len(columns)} columns {names}")
    if data.shape[1] != len(columns):
        raise ValueError(f"{path}: expected rows of {len(columns)} columns {names}; got {data.shape[1]}")
    if not np.all(np.isfinite(data)):
        row = int(np.flatnonzero(~np.all(np.isfinite(data), axis=1))[0])
        raise ValueError(f"{path}: line {numbered[row][0]}: non-finite values in the {what}")
    return data


def _is_numeric_row(line: str) -> bool:
    """Whether every comma-separated item of ``line`` is a number (the rows' count is checked after)."""
    try:
        for item in line.split(","):
            float(item)
    except ValueError:
        return False
    return True


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


@dataclass(frozen=True)
class Aim:
    """An aimed straight insertion resolved on the mesh (:func:`aimed`).

    Attributes
    ----------
    requested : The scene's trajectory.entry [m], (3,).
    entry : The closest point of the tissue's boundary surface [m], (3,).
    normal : Inward unit surface normal at the entry (area-weighted over the faces holding it), (3,).
    direction : Unit insertion direction (base to tip), (3,).
    angle : Angle between the direction and the inward normal [deg].
    standoff, depth : Tip distance before the entry at t = 0 and past it at the end [m].
    trajectory : The two-waypoint trajectory: tip ``standoff`` before the entry at t = 0, ``depth`` past it at
        t = (standoff + depth) / speed, then still.
    """

    requested: np.ndarray
    entry: np.ndarray
    normal: np.ndarray
    direction: np.ndarray
    angle: float
    standoff: float
    depth: float
    trajectory: Trajectory

    def describe(self) -> str:
        """One line for the load report."""
        moved = float(np.linalg.norm(self.entry - self.requested))
        end = float(self.trajectory.times[-1])
        reach = end * self.standoff / (self.standoff + self.depth)
        return (
            f"aimed insertion: entry {np.round(self.entry, 6).tolist()} m on the tissue surface "
            f"({moved:.3g} m from trajectory.entry), direction {np.round(self.direction, 4).tolist()} at "
            f"{self.angle:.1f} deg to the inward normal {np.round(self.normal, 4).tolist()}; the tip reaches "
            f"the entry at t = {reach:.3g} s and {self.depth:.3g} m past it at t = {end:.3g} s"
        )


def aimed(spec: TrajectorySpec, rest_positions: np.ndarray, faces: np.ndarray, needle_length: float) -> Aim:
    """Resolve an aimed insertion (spec.entry and its keys) on a tissue mesh.

    Parameters
    ----------
    spec : The [trajectory] section with ``entry`` set.
    rest_positions : Tissue nodes at rest [m], (n, 3).
    faces : Boundary triangles oriented outward (node indices), (f, 3).
    needle_length : Needle length [m] (the base is this far behind the tip).

    Raises
    ------
    ValueError
        Naming the key: an entry_direction pointing out of the tissue at the entry, a tilt_towards along
        the normal.
    """
    from refsim.geometry.closest import closest_points_on_triangles

    triangles = rest_positions[faces]  # (f, 3, 3)
    requested = np.asarray(spec.entry, dtype=float)
    closest, _ = closest_points_on_triangles(np.broadcast_to(requested, (faces.shape[0], 3)), triangles)
    distances = np.linalg.norm(closest - requested, axis=1)
    entry = closest[int(np.argmin(distances))]
    size = float(np.linalg.norm(rest_positions.max(axis=0) - rest_positions.min(axis=0)))
    holding = np.linalg.norm(closest - entry, axis=1) <= 1e-9 * size  # the faces through the entry point
    area_normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    outward = area_normals[holding].sum(axis=0)
    normal = -outward / np.linalg.norm(outward)
    if spec.entry_direction is not None:
        direction = np.asarray(spec.entry_direction, dtype=float)
        direction = direction / np.linalg.norm(direction)
        if direction @ normal <= 0.0:
            raise ValueError(
                f"trajectory.entry_direction = {list(spec.entry_direction)!r} points out of the tissue at "
                f"the entry {np.round(entry, 6).tolist()} m (inward surface normal "
                f"{np.round(normal, 4).tolist()})"
            )
    else:
        direction = normal
        if spec.entry_angle > 0.0:
            towards = np.asarray(spec.tilt_towards, dtype=float)
            along = towards - (towards @ normal) * normal
            if np.linalg.norm(along) < 1e-6 * np.linalg.norm(towards):
                raise ValueError(
                    f"trajectory.tilt_towards = {list(spec.tilt_towards)!r} is along the surface normal "
                    f"{np.round(normal, 4).tolist()} at the entry: it gives no tilt direction"
                )
            angle = np.radians(spec.entry_angle)
            direction = np.cos(angle) * normal + np.sin(angle) * along / np.linalg.norm(along)
    angle = float(np.degrees(np.arccos(np.clip(direction @ normal, -1.0, 1.0))))
    tips = np.stack([entry - spec.standoff * direction, entry + spec.depth * direction])
    trajectory = Trajectory(
        np.array([0.0, (spec.standoff + spec.depth) / spec.speed]),
        tips - needle_length * direction,
        np.stack([direction, direction]),
    )
    return Aim(
        requested, entry, normal, direction, angle, float(spec.standoff), float(spec.depth), trajectory
    )
