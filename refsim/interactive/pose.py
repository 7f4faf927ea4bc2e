"""The commanded needle base pose of an interactive run: a target set by the keyboard or the pose stream, and
the pose applied at each step, which follows the target at a bounded speed.

Poses between steps: the target is sample-and-hold. Every key press or received pose replaces the target (the
latest one wins; poses received between two steps are not interpolated, only the last counts). At each step
the applied pose moves towards the target along the straight line in pose space (the base linearly, the
direction along the great circle), by at most ``max_speed · dt`` of base travel and ``max_turn · dt`` of
rotation, the same fraction of the way for both; a pose within reach is taken exactly. The bound keeps a
jump of the input (a dropped packet, a key held down) from moving the needle faster than the solver resolves.
A move shorter than :data:`SMALLEST_MOVE` is not made (the pose holds): the step's motion would be lost in
round-off, and a replay of the trajectory refuses such steps (``refsim.scene.build.check_time_resolution``).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

__all__ = [
    "KEYS",
    "SMALLEST_MOVE",
    "exact_unit",
    "KeyAction",
    "PoseError",
    "PoseTarget",
    "lateral_axes",
    "parse_pose",
]

#: Base travel plus needle length × turn [m] below which a step does not move the needle (1 nm: far above
#: the 1000 float64 epsilons of a 1 m coordinate that a step must resolve, far below any motion a hand or a
#: haptic device commands in one step).
SMALLEST_MOVE = 1e-9


class PoseError(ValueError):
    """A pose message that cannot be used; the message says which key and why."""


def _unit(vector: np.ndarray) -> np.ndarray:
    return vector / np.linalg.norm(vector)


def exact_unit(vector: np.ndarray) -> np.ndarray:
    """``vector`` normalised to a float64 vector whose norm is exactly 1.0 (for a 3-vector and for a row of an
    (m, 3) array alike), so that every later normalisation (the trajectory's, the CSV reader's) returns it
    unchanged: the direction a replay reads is the one the run applied, to the bit.

    Dividing by the norm reaches such a vector in one or two passes; otherwise the largest component is
    moved by a few ulps (a change of about 1e-16 in the direction)."""
    unit = np.array(vector, dtype=float)
    for _ in range(8):
        norm = float(np.linalg.norm(unit))
        if norm == 1.0 and float(np.linalg.norm(unit[None], axis=1)[0]) == 1.0:
            return unit
        unit = unit / norm
    largest = int(np.argmax(np.abs(unit)))
    for ulps in range(1, 9):
        for towards in (np.inf, -np.inf):
            trial = unit.copy()
            for _ in range(ulps):
                trial[largest] = np.nextafter(trial[largest], towards)
            if float(np.linalg.norm(trial)) == 1.0 and float(np.linalg.norm(trial[None], axis=1)[0]) == 1.0:
                return trial
    return unit


def lateral_axes(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit axes ``a``, ``b`` normal to the needle ``direction`` with (a, b, direction) right-handed:
    ``a`` horizontal (normal to z) unless the needle is vertical, then ``a`` = x."""
    direction = _unit(np.asarray(direction, dtype=float))
    side = np.cross(direction, [0.0, 0.0, 1.0])
    if np.linalg.norm(side) < 1e-6:
        side = np.array([1.0, 0.0, 0.0]) - direction[0] * direction
    a = _unit(side)
    return a, np.cross(direction, a)


def _vector(message: dict, key: str) -> np.ndarray:
    value = message.get(key)
    if not isinstance(value, list) or len(value) != 3:
        raise PoseError(f"{key!r}: expected a list of 3 numbers, got {value!r}")
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value):
        raise PoseError(f"{key!r}: expected 3 numbers, got {value!r}")
    array = np.array(value, dtype=float)
    if not np.all(np.isfinite(array)):
        raise PoseError(f"{key!r}: expected finite numbers, got {value!r}")
    return array


def parse_pose(message: object, *, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """The base position [m] (3,) and unit direction (3,) of a pose message ``{"t": ..., "base": [x, y, z],
    "direction": [dx, dy, dz]}`` ("t" optional, the sender's clock [s], not used for timing).

    Parameters
    ----------
    message : The decoded JSON value.
    reach : Largest accepted distance of the base from the origin [m] (a bound against unit mistakes).

    Raises
    ------
    PoseError
        Naming the key, the value and what is expected.
    """
    if not isinstance(message, dict):
        raise PoseError(f"expected a JSON object, got {type(message).__name__}")
    unknown = sorted(set(message) - {"t", "base", "direction"})
    if unknown:
        raise PoseError(
            f'unknown key {unknown[0]!r} (a pose has t, base, direction; or send {{"stop": true}})'
        )
    if "t" in message:
        t = message["t"]
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t):
            raise PoseError(f"'t': expected a finite number [s], got {t!r}")
    base = _vector(message, "base")
    if np.linalg.norm(base) > reach:
        raise PoseError(
            f"'base': {base.tolist()} m is {np.linalg.norm(base):.3g} m from the origin, beyond the "
            f"{reach:.3g} m this scene accepts (are the coordinates in metres?)"
        )
    direction = _vector(message, "direction")
    norm = float(np.linalg.norm(direction))
    if norm < 1e-12:
        raise PoseError(f"'direction': {direction.tolist()} is zero; expected a non-zero vector")
    return base, direction / norm


@dataclass(frozen=True)
class KeyAction:
    """What a key does: a translation (along the needle or sideways) or a tilt about the needle's tip.

    Attributes
    ----------
    label : For the on-screen help.
    axis : "needle", "a" or "b" (the lateral axes of :func:`lateral_axes`).
    sign : +1 or −1.
    tilt : A tilt (True) or a translation (False).
    """

    label: str
    axis: str
    sign: float
    tilt: bool = False


#: The keys of the window (VTK key symbols) and what each does.
KEYS = {
    "Up": KeyAction("insert along the needle", "needle", 1.0),
    "Down": KeyAction("retract along the needle", "needle", -1.0),
    "Right": KeyAction("move sideways +a", "a", 1.0),
    "Left": KeyAction("move sideways -a", "a", -1.0),
    "Prior": KeyAction("move sideways +b (Page Up)", "b", 1.0),
    "Next": KeyAction("move sideways -b (Page Down)", "b", -1.0),
    "l": KeyAction("tilt: base towards +a about the tip", "a", 1.0, tilt=True),
    "j": KeyAction("tilt: base towards -a about the tip", "a", -1.0, tilt=True),
    "i": KeyAction("tilt: base towards +b about the tip", "b", 1.0, tilt=True),
    "k": KeyAction("tilt: base towards -b about the tip", "b", -1.0, tilt=True),
}


class PoseTarget:
    """The commanded pose and the applied one; thread-safe (the pose stream's thread sets the target, the
    step loop advances).

    Parameters
    ----------
    base, direction : The starting pose (the scene's trajectory at t = 0) [m], unit (3,).
    needle_length : [m] (tilts pivot about the tip; the turn counts as length × angle of tip travel).
    max_speed : Largest base speed [m/s], > 0.
    max_turn : Largest turning rate [rad/s], > 0.
    """

    def __init__(
        self,
        base: np.ndarray,
        direction: np.ndarray,
        *,
        needle_length: float,
        max_speed: float,
        max_turn: float,
    ) -> None:
        for name, value in (("max_speed", max_speed), ("max_turn", max_turn)):
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} = {value!r}; valid range (0, inf)")
        self.needle_length = float(needle_length)
        self.max_speed = float(max_speed)
        self.max_turn = float(max_turn)
        self._lock = threading.Lock()
        self.applied_base = np.array(base, dtype=float)
        self.applied_direction = exact_unit(direction)
        self._target_base = self.applied_base.copy()
        self._target_direction = self.applied_direction.copy()
        self.received = 0  # targets set since the start
        self.superseded = 0  # targets replaced before a step used them
        self._pending = 0  # targets set since the last step

    def set(self, base: np.ndarray, direction: np.ndarray) -> None:
        """Replace the target (the latest pose wins)."""
        with self._lock:
            self._target_base = np.array(base, dtype=float)
            self._target_direction = exact_unit(direction)
            self.received += 1
            self._pending += 1

    def target(self) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            return self._target_base.copy(), self._target_direction.copy()

    def hold(self) -> None:
        """Make the applied pose the target (stop where the needle is)."""
        self.set(self.applied_base, self.applied_direction)

    def key(self, action: KeyAction, *, distance: float, angle: float) -> None:
        """Move the target by one key press: ``distance`` [m] along the needle or sideways, or a tilt by
        ``angle`` [rad] about the needle tip (the base swings, the tip stays)."""
        base, direction = self.target()
        a, b = lateral_axes(direction)
        axis = {"needle": direction, "a": a, "b": b}[action.axis]
        if not action.tilt:
            self.set(base + action.sign * distance * axis, direction)
            return
        tip = base + self.needle_length * direction
        # the base moves towards sign·axis: the direction turns towards −sign·axis
        turned = _unit(np.cos(angle) * direction - action.sign * np.sin(angle) * axis)
        self.set(tip - self.needle_length * turned, turned)

    def advance(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """The pose applied at the next step, ``dt`` [s] after the current one: towards the target by at
        most ``max_speed · dt`` and ``max_turn · dt``; returns (base [m], unit direction)."""
        with self._lock:
            target_base, target_direction = self._target_base, self._target_direction
            if self._pending > 1:
                self.superseded += self._pending - 1
            self._pending = 0
        base, direction = self.applied_base, self.applied_direction
        distance = float(np.linalg.norm(target_base - base))
        turn = float(np.arccos(np.clip(direction @ target_direction, -1.0, 1.0)))
        if distance + self.needle_length * turn < SMALLEST_MOVE:
            return base, direction
        fraction = min(
            1.0,
            self.max_speed * dt / distance if distance > 0.0 else 1.0,
            self.max_turn * dt / turn if turn > 0.0 else 1.0,
        )
        if fraction >= 1.0:
            new_base, new_direction = target_base.copy(), target_direction.copy()
        else:
            new_base = base + fraction * (target_base - base)
            new_direction = exact_unit(_slerp(direction, target_direction, turn, fraction))
        moved = float(np.linalg.norm(new_base - base)) + self.needle_length * float(
            np.arccos(np.clip(direction @ new_direction, -1.0, 1.0))
        )
        if moved < SMALLEST_MOVE:
            return base, direction
        self.applied_base, self.applied_direction = new_base, new_direction
        return new_base, new_direction


def _slerp(start: np.ndarray, end: np.ndarray, angle: float, fraction: float) -> np.ndarray:
    """The unit vector ``fraction`` of the way from ``start`` to ``end`` along their great circle (``angle``
    apart, 0 < angle); for antipodal ends any great circle (through the lateral axis ``a``)."""
    if angle < 1e-12:
        return start.copy()
    if math.pi - angle < 1e-9:
        end_normal = lateral_axes(start)[0]
    else:
        end_normal = _unit(end - (start @ end) * start)
    return _unit(np.cos(fraction * angle) * start + np.sin(fraction * angle) * end_normal)
