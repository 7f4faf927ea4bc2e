"""The needle as a body of the time step (:class:`refsim.simulation.bodies.Body`): rigid (kinematic) or
flexible (co-rotational beams).

A rigid needle follows its base exactly: its pose at the end of the step is the trajectory's, it has no DoFs,
adds nothing to the compliance and its correction is its free state. A flexible needle is a beam model whose
base node's six DoFs are prescribed by the trajectory; the rest moves by one Newton step of implicit Euler
through its own bound compliance strategy (:mod:`refsim.fem.compliance`; the exact one with a direct
factorisation by default: the needle is small and its A changes every step).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from refsim.constraints import NEEDLE, BeamNeedleGeometry, RigidNeedleGeometry, orthonormal_basis
from refsim.geometry import needle_rest_frame, rotation_matrix
from refsim.scene.controls import ControlValues

__all__ = [
    "NeedleState",
    "RigidNeedle",
    "FlexibleNeedle",
    "NEEDLE_LINEAR_SOLVER",
    "DIVERGED_STRAIN",
    "STRAIN_WARNING",
    "rotation_between",
]

#: The flexible needle's linear solver: SuperLU in symmetric mode with the COLAMD ordering (a direct
#: factorisation of its small banded A every step).
NEEDLE_LINEAR_SOLVER = "superlu:COLAMD"
#: An element of the flexible needle stretched or shortened by more than this (its chord against its rest
#: length) ends the run: a steel needle yields below 1 %, so such a state is a step whose one Newton step
#: diverged, not a deformation (:meth:`FlexibleNeedle.diverged`).
DIVERGED_STRAIN = 0.1
#: An element stretched or shortened by more than this (and at most :data:`DIVERGED_STRAIN`) gives a warning
#: and stays in the run: beyond the yield strain of a steel needle (0.2–0.5 %), which no elastic needle
#: reaches (the axial strain of a needle of radius 0.5 mm under 1 N is 6e-6; the built-in flexible scenes stay
#: below 4e-6), so the chord's change is the error of the step's one Newton iteration, which did not follow
#: the needle's rotation (:meth:`FlexibleNeedle.element_strain`, recorded each step as
#: ``steps/needle_strain``).
STRAIN_WARNING = 0.01


@dataclass(frozen=True)
class NeedleState:
    """Needle configuration.

    Attributes
    ----------
    positions : Node positions [m], shape (node_count, 3).
    frames : Node frames (columns: axis, then two section axes), shape (node_count, 3, 3).
    velocities : Node velocities, linear [m/s] then angular [rad/s], shape (node_count, 6).
    base_position : Base position [m], shape (3,).
    direction : Needle direction at the base, unit, shape (3,).
    """

    positions: np.ndarray
    frames: np.ndarray
    velocities: np.ndarray
    base_position: np.ndarray
    direction: np.ndarray


def rotation_between(start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Rotation vector [rad] of the smallest rotation taking unit vector ``start`` to ``end``, shape (3,)."""
    axis = np.cross(start, end)
    sine = np.linalg.norm(axis)
    cosine = float(np.clip(start @ end, -1.0, 1.0))
    if sine < 1e-15:
        if cosine > 0.0:
            return np.zeros(3)
        perpendicular, _ = orthonormal_basis(start[None, :])
        return np.pi * perpendicular[0]
    return axis / sine * np.arctan2(sine, cosine)


def _rest_frames(direction: np.ndarray, node_count: int) -> np.ndarray:
    """Every node's frame of a straight needle along ``direction``: the one rest-frame convention of
    :func:`refsim.geometry.needle_rest_frame`, shape (node_count, 3, 3)."""
    return np.broadcast_to(needle_rest_frame(direction), (node_count, 3, 3)).copy()


class RigidNeedle:
    """A rigid needle moved by its base: nodes on a straight line, a kinematic body (no DoFs); ``name`` is its
    instrument's (the key of its state and of its rows' Jacobian)."""

    rigid = True
    dof_count = None

    def __init__(self, length: float, element_count: int, *, name: str = NEEDLE) -> None:
        self.name = name  # the instrument's name: its state's and its Jacobian's key
        self.length = float(length)
        self.arc_lengths = np.linspace(0.0, self.length, element_count + 1)
        self._frames_key, self._frames = None, None  # the last direction's bytes and its nodes' frames

    def _frames_along(self, direction: np.ndarray) -> np.ndarray:
        """Every node's frame along ``direction`` (:func:`_rest_frames`), a fresh copy; computed again only
        when the direction's bytes change (a trajectory keeps its direction over many steps)."""
        direction = np.asarray(direction, dtype=float)
        key = direction.tobytes() if direction.shape == (3,) else None
        if key is None or key != self._frames_key:
            frames = _rest_frames(direction, self.arc_lengths.size)
            if key is None:
                return frames
            frames.setflags(write=False)
            self._frames_key, self._frames = key, frames
        return self._frames.copy()

    def state_at(
        self, base: np.ndarray, direction: np.ndarray, velocities: np.ndarray | None = None
    ) -> NeedleState:
        """The needle posed at ``base`` along ``direction``."""
        positions = base + self.arc_lengths[:, None] * direction
        frames = self._frames_along(direction)
        if velocities is None:
            velocities = np.zeros((self.arc_lengths.size, 6))
        return NeedleState(
            positions, frames, velocities, np.asarray(base, float), np.asarray(direction, float)
        )

    def geometry(self, state: NeedleState) -> RigidNeedleGeometry:
        return RigidNeedleGeometry(state.base_position, state.direction, self.length)

    @staticmethod
    def element_strain(state: NeedleState) -> tuple[float, int]:
        """(0, 0): a rigid needle keeps its shape (:meth:`FlexibleNeedle.element_strain`)."""
        return 0.0, 0

    def free_motion(self, state: NeedleState, control: ControlValues, dt: float):
        """The pose at the end of the step (kinematic); no system to solve."""
        moved = self.state_at(control.base_position, control.direction)
        velocities = np.zeros_like(state.velocities)
        velocities[:, :3] = (moved.positions - state.positions) / dt
        return NeedleState(
            moved.positions, moved.frames, velocities, moved.base_position, moved.direction
        ), None

    @staticmethod
    def compliance(system, jacobian):
        """Nothing: a kinematic body adds a zero block to W (rows its Jacobian has) and needs no responses."""
        rows = 0 if jacobian is None else jacobian.shape[0]
        return np.zeros((rows, rows)), None

    @staticmethod
    def correct(system, previous: NeedleState, free: NeedleState, responses, multipliers, dt) -> NeedleState:
        """The free state: the constraint forces do not move a kinematic body."""
        return free


class FlexibleNeedle:
    """A flexible needle: co-rotational Timoshenko beams, base node driven by the trajectory.

    Parameters
    ----------
    model : The beam model (:class:`refsim.fem.needle.NeedleModel`).
    rayleigh_mass, rayleigh_stiffness : Rayleigh α [1/s] and β [s].
    compliance : Its bound compliance strategy; by default the exact one on :data:`NEEDLE_LINEAR_SOLVER`.
    name : The body's name (its instrument's): the key of its Jacobian in a row block.
    """

    rigid = False

    def __init__(
        self,
        model,
        *,
        rayleigh_mass: float = 0.0,
        rayleigh_stiffness: float = 0.0,
        compliance=None,
        name: str = NEEDLE,
    ) -> None:
        from refsim.fem.compliance import Exact

        self.name = name  # the instrument's name: its state's and its Jacobian's key

        self.model = model
        self.strategy = compliance if compliance is not None else Exact(NEEDLE_LINEAR_SOLVER).bind()
        self.length = float(model.length)
        self.rayleigh_mass = rayleigh_mass
        self.rayleigh_stiffness = rayleigh_stiffness
        self.dof_count = 6 * model.node_count
        self._mass = model.mass_matrix()

    def state_at(
        self, base: np.ndarray, direction: np.ndarray, velocities: np.ndarray | None = None
    ) -> NeedleState:
        positions, frames = self.model.rest_state()
        # Pose the rest needle rigidly at (base, direction).
        rest_direction = positions[-1] - positions[0]
        rest_direction /= np.linalg.norm(rest_direction)
        rotation = rotation_matrix(rotation_between(rest_direction, direction)[None, :])[0]
        positions = base + (positions - positions[0]) @ rotation.T
        frames = rotation @ frames
        if velocities is None:
            velocities = np.zeros((positions.shape[0], 6))
        return NeedleState(
            positions, frames, velocities, np.asarray(base, float), np.asarray(direction, float)
        )

    def geometry(self, state: NeedleState) -> BeamNeedleGeometry:
        return BeamNeedleGeometry(self.model, state.positions, state.frames)

    def element_strain(self, state: NeedleState) -> tuple[float, int]:
        """The largest strain of an element's chord, |‖x_{e+1} − x_e‖ / ℓ_e − 1| (ℓ_e its rest length), and
        that element. A needle's true axial strain is of the order of 1e-6 (steel, 1 N); what exceeds it is
        the error of the step's one Newton iteration of implicit Euler, which linearises the beam's rotation
        over the step (:data:`STRAIN_WARNING`, :data:`DIVERGED_STRAIN`)."""
        chords = np.linalg.norm(np.diff(state.positions, axis=0), axis=1)
        strain = np.abs(chords / self.model.element_length - 1.0)
        worst = int(np.argmax(strain))
        return float(strain[worst]), worst

    def _critical_load(self) -> float:
        """Euler's critical load of the needle, its base clamped and its tip free: π² E I / (4 L²) [N]."""
        section = self.model.section
        return float(np.pi**2 * section.youngs_modulus * section.second_moment / (4.0 * self.length**2))

    def diverged(self, state: NeedleState) -> str | None:
        """What says the step that gave ``state`` diverged, or None: an element's chord off its rest length by
        more than :data:`DIVERGED_STRAIN` (one Newton step of implicit Euler does not follow rotations that
        large in one step: a slender needle buckling under its tip's load, whose critical load is Euler's
        π² E I / (4 L²), the base clamped)."""
        strain, worst = self.element_strain(state)
        if not strain > DIVERGED_STRAIN:
            return None
        return (
            f"the needle {self.name!r} diverged: its element {worst} is {100.0 * strain:.3g} % off "
            f"its rest length (more than {100.0 * DIVERGED_STRAIN:g} %; a steel needle yields below 1 %), "
            "which one Newton step of implicit Euler gives when the needle turns too far in one step, as a "
            f"slender needle buckling under its tip's load does (Euler's critical load "
            f"{self._critical_load():.3g} N for this needle, its base clamped): use a smaller time.dt, or a "
            "stiffer needle (needle.radius) or a rigid one (needle.rigid = true)"
        )

    def strained(self, state: NeedleState) -> str | None:
        """What says the step that gave ``state`` left the beam model's range without diverging, or None: an
        element's chord off its rest length by more than :data:`STRAIN_WARNING` (at most
        :data:`DIVERGED_STRAIN`, which :meth:`diverged` reports)."""
        strain, worst = self.element_strain(state)
        if not STRAIN_WARNING < strain <= DIVERGED_STRAIN:
            return None
        return (
            f"the element {worst} of the needle {self.name!r} is {100.0 * strain:.3g} % off its rest "
            f"length (more than {100.0 * STRAIN_WARNING:g} %, beyond the yield strain of steel, which no "
            "elastic needle reaches): the step's one Newton iteration of implicit Euler did not follow the "
            "needle's rotation, and its shape and forces are off by as much (a slender needle turning fast "
            f"or buckling; Euler's critical load {self._critical_load():.3g} N for this needle, its base "
            "clamped). The run goes on; each step's largest strain is in steps/needle_strain. Use a smaller "
            "time.dt, or a stiffer needle (needle.radius)"
        )

    def free_motion(self, state: NeedleState, control: ControlValues, dt: float):
        """One Newton step of implicit Euler with the base's six DoFs prescribed by the trajectory; the step
        system is the needle's :class:`~refsim.fem.compliance.StepCompliance`."""
        model = self.model
        base, direction = control.base_position, control.direction
        increment = np.concatenate([base - state.positions[0], rotation_between(state.direction, direction)])
        system = self.strategy.step(
            model.assemble_step(
                state.positions,
                state.frames,
                state.velocities,
                dt,
                increment,
                rayleigh_mass=self.rayleigh_mass,
                rayleigh_stiffness=self.rayleigh_stiffness,
                mass=self._mass,
            )
        )
        delta = system.free_displacement
        positions, frames = model.apply_increment(state.positions, state.frames, delta)
        free = NeedleState(positions, frames, delta.reshape(-1, 6) / dt, np.asarray(base, float), direction)
        return free, system

    @staticmethod
    def compliance(system, jacobian):
        """W = H A⁻¹ Hᵀ [m/N] and the responses A⁻¹Hᵀ [m/N], dense (dof_count, rows)."""
        return system.compliance(jacobian)

    def correct(
        self, system, previous: NeedleState, free: NeedleState, responses, multipliers, dt
    ) -> NeedleState:
        """x = x_free + A⁻¹ Hᵀ λ, velocities from the whole step's increment."""
        if responses is None or multipliers.size == 0:
            return free
        delta = responses @ multipliers
        positions, frames = self.model.apply_increment(free.positions, free.frames, delta)
        velocities = free.velocities + delta.reshape(-1, 6) / dt
        return NeedleState(positions, frames, velocities, free.base_position, free.direction)
