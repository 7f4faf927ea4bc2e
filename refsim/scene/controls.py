"""Controls: what drives a run from outside the model, read by the step at each time (Model / State /
Control).

Two controls exist: the pose of the needle base (a trajectory: waypoints or a robot's precomputed motion) and
a tissue boundary motion (prescribed displacements of chosen nodes as a function of time: breathing, a moving
support). The built scene never changes during a run; a step asks the controls for their values at its end
time and applies them as kinematic conditions (the needle's base node, the tissue's prescribed DoFs).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar, Protocol

import numpy as np

from refsim.scene.fields import FieldError, spec

if TYPE_CHECKING:  # the scene's spec reads BOUNDARY_MOTIONS, and trajectory.py imports the spec
    from refsim.scene.trajectory import Trajectory

__all__ = [
    "BOUNDARY_MOTIONS",
    "BoundaryMotion",
    "ControlValues",
    "Controls",
    "PeriodicBoundaryMotion",
    "SampledBoundaryMotion",
    "read_displacement_csv",
]


class BoundaryMotion(Protocol):
    """Prescribed displacement from the rest position of chosen tissue nodes.

    A motion a scene can choose also has ``name`` (the value of ``boundary.motion``), ``keys`` (the keys of
    ``[boundary]`` it reads beyond the node selection, each declared as name -> (annotation, field of
    ``refsim.scene.fields.spec``): the scene's ``BoundarySpec`` has a field generated from each, and a key
    several motions read is declared once and the same field object listed by each) and
    ``from_section(section, nodes, base_directory)``, and is listed in :data:`BOUNDARY_MOTIONS`."""

    nodes: np.ndarray

    def displacement(self, time: float) -> np.ndarray:
        """Displacement of each node from its rest position at ``time`` [s] [m], shape (len(nodes), 3)."""

    def history(self, times: np.ndarray) -> np.ndarray:
        """The displacement shared by every node at each of ``times`` [s] [m], shape (len(times), 3)."""


def _checked_nodes(nodes) -> np.ndarray:
    nodes = np.asarray(nodes)
    if nodes.ndim != 1 or nodes.size == 0 or not np.issubdtype(nodes.dtype, np.integer):
        raise ValueError(
            f"boundary motion nodes must be a non-empty 1-D array of node indices, got {nodes!r}"
        )
    if np.any(nodes < 0) or np.unique(nodes).size != nodes.size:
        raise ValueError("boundary motion nodes must be distinct non-negative node indices")
    return np.sort(nodes.astype(np.int64))


@dataclass(frozen=True)
class PeriodicBoundaryMotion:
    """A periodic breathing motion after Lujan et al. (Med. Phys. 26(5), 1999): every node moves by

        d(t) = a · (1 − cos^{2n}(π t / T − φ)) − a · (1 − cos^{2n}(−φ)),

    so d(0) = 0 and the displacement swings between 0 and the amplitude vector a (end of exhale to end of
    inhale, for φ = 0) with period T; n ≥ 1 sharpens the exhale plateau (n = 1 is a sine squared).

    Attributes
    ----------
    nodes : Tissue nodes that move, shape (k,).
    amplitude : a [m], shape (3,), finite.
    period : T [s], > 0.
    exponent : n, integer ≥ 1.
    phase : φ [rad], finite.
    """

    name: ClassVar[str] = "periodic"
    #: The ``[boundary]`` keys it reads: name -> (annotation, field with its default, unit, range, meaning).
    keys: ClassVar[dict] = {
        "amplitude": (
            "tuple",
            spec(
                (0.0, 0.0, 0.0),
                unit="m",
                doc="a: the displacement at the peak of a periodic motion (also at most the tissue's size, "
                "checked with the mesh)",
                low=-1e3,
                high=1e3,
                length=3,
            ),
        ),
        "period": (
            "float",
            spec(
                4.0,
                unit="s",
                doc="T: period of a periodic motion (breathing: about 4 s)",
                low=0.0,
                low_open=True,
            ),
        ),
        "exponent": (
            "int",
            spec(
                1,
                unit="-",
                doc="n of cos^{2n}: 1 a sine squared, larger for a longer exhale plateau",
                low=1,
                high=10,
                integer=True,
            ),
        ),
        "phase": (
            "float",
            spec(0.0, unit="rad", doc="φ: phase of a periodic motion", low=-10.0, high=10.0),
        ),
    }

    nodes: np.ndarray
    amplitude: np.ndarray
    period: float
    exponent: int = 1
    phase: float = 0.0

    @classmethod
    def from_section(cls, section, nodes: np.ndarray, base_directory: str) -> PeriodicBoundaryMotion:
        """The motion of a scene's ``[boundary]`` section (``BoundarySpec``) on ``nodes``."""
        return cls(
            nodes=nodes,
            amplitude=section.amplitude,
            period=section.period,
            exponent=section.exponent,
            phase=section.phase,
        )

    def __post_init__(self) -> None:
        object.__setattr__(self, "nodes", _checked_nodes(self.nodes))
        amplitude = np.asarray(self.amplitude, dtype=float)
        if amplitude.shape != (3,) or not np.all(np.isfinite(amplitude)):
            raise ValueError(f"amplitude must be 3 finite numbers [m], got {self.amplitude!r}")
        object.__setattr__(self, "amplitude", amplitude)
        if not (np.isfinite(self.period) and self.period > 0.0):
            raise ValueError(f"period = {self.period!r} s; valid range (0, inf)")
        if isinstance(self.exponent, bool) or int(self.exponent) != self.exponent or self.exponent < 1:
            raise ValueError(f"exponent = {self.exponent!r}; an integer >= 1")
        if not np.isfinite(self.phase):
            raise ValueError(f"phase = {self.phase!r} rad; must be finite")

    def profile(self, time: float) -> float:
        """The scalar profile 1 − cos^{2n}(π t/T − φ), offset to 0 at t = 0 [-]."""
        power = 2 * int(self.exponent)
        value = 1.0 - np.cos(np.pi * time / self.period - self.phase) ** power
        return float(value - (1.0 - np.cos(-self.phase) ** power))

    def displacement(self, time: float) -> np.ndarray:
        return np.broadcast_to(self.profile(time) * self.amplitude, (self.nodes.size, 3)).copy()

    def history(self, times: np.ndarray) -> np.ndarray:
        """The displacement shared by every moving node at each of ``times`` [s] [m], (len(times), 3)."""
        power = 2 * int(self.exponent)
        times = np.asarray(times, dtype=float)
        profile = (1.0 - np.cos(np.pi * times / self.period - self.phase) ** power) - (
            1.0 - np.cos(-self.phase) ** power
        )
        return profile[:, None] * self.amplitude


@dataclass(frozen=True)
class SampledBoundaryMotion:
    """A displacement sampled in time (a recorded or computed motion), linear between samples and constant
    after the last; the same displacement for every node.

    Attributes
    ----------
    nodes : Tissue nodes that move, shape (k,).
    times : Sample times [s], strictly increasing from 0, shape (w,).
    displacements : Displacement at each sample [m], shape (w, 3), zero at t = 0.
    """

    name: ClassVar[str] = "file"
    #: The ``[boundary]`` keys it reads: name -> (annotation, field with its default, unit, range, meaning).
    keys: ClassVar[dict] = {
        "file": (
            "str | None",
            spec(
                None,
                doc="CSV of displacement samples (t, dx, dy, dz [s, m]), relative to the scene file; '#' "
                "comments and a header allowed",
            ),
        ),
    }

    nodes: np.ndarray
    times: np.ndarray
    displacements: np.ndarray

    @classmethod
    def from_section(cls, section, nodes: np.ndarray, base_directory: str) -> SampledBoundaryMotion:
        """The motion of the CSV file ``section.file`` (relative to ``base_directory``) on ``nodes``; a bad
        file is a :class:`~refsim.scene.fields.FieldError` of the key ``file``."""
        path = Path(section.file)
        if not path.is_absolute():
            path = Path(base_directory) / path
        try:
            times, displacements = read_displacement_csv(path)
            return cls(nodes=nodes, times=times, displacements=displacements)
        except ValueError as error:
            raise FieldError("file", str(error)) from None

    def __post_init__(self) -> None:
        object.__setattr__(self, "nodes", _checked_nodes(self.nodes))
        times = np.asarray(self.times, dtype=float)
        values = np.asarray(self.displacements, dtype=float)
        if times.ndim != 1 or times.size == 0 or times[0] != 0.0 or np.any(np.diff(times) <= 0.0):
            raise ValueError("times must start at 0 s and increase strictly")
        if values.shape != (times.size, 3) or not np.all(np.isfinite(values)):
            raise ValueError(f"displacements must be finite with shape ({times.size}, 3), got {values.shape}")
        if np.any(values[0] != 0.0):
            raise ValueError(
                f"the displacement at t = 0 must be zero (the tissue starts at rest), got {values[0]}"
            )
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "displacements", values)

    def displacement(self, time: float) -> np.ndarray:
        value = np.array([np.interp(time, self.times, self.displacements[:, k]) for k in range(3)])
        return np.broadcast_to(value, (self.nodes.size, 3)).copy()

    def history(self, times: np.ndarray) -> np.ndarray:
        """The displacement shared by every moving node at each of ``times`` [s] [m], (len(times), 3)."""
        times = np.asarray(times, dtype=float)
        return np.stack([np.interp(times, self.times, self.displacements[:, k]) for k in range(3)], axis=1)


#: The boundary motions a scene can choose, by name (``boundary.motion``; "none" is no motion).
BOUNDARY_MOTIONS: dict[str, type] = {
    motion.name: motion for motion in (PeriodicBoundaryMotion, SampledBoundaryMotion)
}


def read_displacement_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A displacement history: columns t, dx, dy, dz [s, m]; '#' comment lines and one header line allowed.

    Returns
    -------
    (times (w,), displacements (w, 3)).

    Raises
    ------
    ValueError
        Naming the file and the defect.
    """
    from refsim.scene.trajectory import read_numeric_csv

    data = read_numeric_csv(path, ("t", "dx", "dy", "dz"), "boundary motion")
    return data[:, 0], data[:, 1:]


@dataclass(frozen=True)
class ControlValues:
    """The controls' values at one time.

    Attributes
    ----------
    time : Time [s].
    base_position : Needle base position [m], shape (3,).
    direction : Unit needle direction (base to tip), shape (3,).
    boundary_nodes : Tissue nodes with a prescribed displacement, shape (k,) (empty without boundary motion).
    boundary_displacements : Their displacement from rest [m], shape (k, 3).
    poses : With several instruments, each one's (base position, direction) in the scene's order; empty with
        one (its pose is ``base_position`` and ``direction``).
    """

    time: float
    base_position: np.ndarray
    direction: np.ndarray
    boundary_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    boundary_displacements: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    poses: tuple = ()

    def instrument(self, index: int) -> ControlValues:
        """The values with instrument ``index``'s pose as the needle base pose (what its body reads)."""
        if not self.poses:
            if index != 0:
                raise IndexError(f"the controls hold one instrument's pose, not instrument {index}'s")
            return self
        base, direction = self.poses[index]
        return replace(self, base_position=base, direction=direction)


@dataclass(frozen=True)
class Controls:
    """The controls of a run.

    Attributes
    ----------
    trajectory : Pose of the needle base against time.
    boundary : Tissue boundary motion, or None (the fixed nodes stay in place).
    trajectories : With several instruments, every instrument's trajectory in the scene's order (the first is
        ``trajectory``); empty with one.
    """

    trajectory: Trajectory
    boundary: BoundaryMotion | None = None
    trajectories: tuple = ()

    def at(self, time: float) -> ControlValues:
        """Values of every control at ``time`` [s]."""
        base, direction = self.trajectory.pose(time)
        poses = tuple(trajectory.pose(time) for trajectory in self.trajectories)
        if self.boundary is None:
            return ControlValues(time, base, direction, poses=poses)
        return ControlValues(
            time, base, direction, self.boundary.nodes, self.boundary.displacement(time), poses=poses
        )
