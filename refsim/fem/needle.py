"""The needle: serially linked co-rotational Timoshenko beams with 6-DoF nodes.

Model
-----
A straight needle of ``element_count`` equal beam elements. Each node carries a position [m] and a frame
(3×3, columns = the node's material axes in world coordinates, column 0 along the needle at rest). DoFs are
6 per node, ordered ``[ux, uy, uz, θx, θy, θz]`` node by node; rotations are world-frame (spatial)
rotation-vector increments, ``frames_new = rotation_matrix(Δθ) @ frames``
(:meth:`NeedleModel.apply_increment`).
Node 0 is the base, driven by a trajectory: its 6 DoFs are prescribed (:attr:`NeedleModel.base_dofs`).

Element operators (see :mod:`refsim.fem.beam_element`): the closed-form 12×12 Timoshenko stiffness
(Przemieniecki 1968; scikit-fem has no Timoshenko line element, the closed form is cross-checked against a
scikit-fem assembly in the tests), in co-rotational element frames after Crisfield (1990) / Battini & Pacoste
(2002): axis 0 along the chord between the two nodes, axis 2 normal to the chord and to the mean of the two
nodes' second material axes. Internal forces are the consistent gradient of the co-rotational strain energy,
f = Bᵀ K₇ d.

Two tangents are offered (:meth:`NeedleModel.tangent_stiffness`):
- ``"corotated"`` (default, as SOFA's BeamFEMForceField): R_e K_e R_eᵀ per element, symmetric, no geometric
  stiffness. It equals the consistent tangent at rest and for rigid motions of the rest state.
- ``"consistent"``: the exact derivative of :meth:`NeedleModel.internal_forces` with respect to the DoFs
  (geometric stiffness included), computed by central differences of the element kernel (all elements and all
  12 element DoFs in one batched call), accurate to about 1e-9 relative. Used by static Newton solves.

Mass: lumped (diagonal per node): ρ A l₀/2 per element end on translations and the cross-section rotary
inertia ρ l₀/2 diag(J, I, I) per element end on rotations, expressed in the node's material axes.

Section: solid circle, A = π r², I = π r⁴/4, J = π r⁴/2, G = E / (2 (1 + ν)), shear correction
κ = 6 (1 + ν) / (7 + 6 ν) (Cowper, "The shear coefficient in Timoshenko's beam theory", J. Appl. Mech.
33, 1966).

Centreline: on each element, the chord plus the cubic Hermite deflection of the co-rotated local nodal
rotations (v = l₀ (H_a θ̄z_a + H_b θ̄z_b), w = −l₀ (H_a θ̄y_a + H_b θ̄y_b) in the element frame; the rotation
is taken as the slope, neglecting shear in the shape). :meth:`NeedleModel.centreline_jacobian` is its exact
derivative. Arc lengths are rest arc lengths [m] from the base, in [0, length].
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from refsim.fem import needle_kernels
from refsim.fem.beam_element import (
    LOCAL_REDUCED_DOFS,
    beam_element_forces,
    corotational_frames,
    hermite_shapes,
    local_deformations,
    timoshenko_stiffness,
)
from refsim.geometry.rotations import needle_rest_frame, rotation_matrix, skew
from refsim.materials import HookeMaterial

__all__ = ["NeedleSection", "NeedleModel"]

logger = logging.getLogger(__name__)

# Relative step of the central differences of the consistent tangent: truncation (h/l₀)² ≈ 1e-12 and round-off
# ε·(node_count)/h ≈ 1e-10 relative for translations; the same step [rad] for rotations.
_TANGENT_STEP = 1e-5
_PROJECTION_NEWTON_ITERATIONS = 3
#: Needle configurations whose element kinematics a model keeps (`NeedleModel._element_kinematics`).
_KINEMATICS_MEMO = 4


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not (np.isfinite(value) and value > 0.0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return value


@dataclass(frozen=True, kw_only=True)
class NeedleSection:
    """Solid circular cross-section and its material.

    Attributes
    ----------
    radius : Section radius r [m], > 0.
    youngs_modulus : E [Pa], > 0.
    poisson_ratio : ν [-], in (−1, 0.5).
    density : ρ [kg/m³], > 0.
    """

    radius: float
    youngs_modulus: float
    poisson_ratio: float
    density: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "radius", _positive("radius", self.radius))
        # The material's one definition and validator (refsim.materials): E, ν, ρ and their limits.
        material = HookeMaterial(
            youngs_modulus=self.youngs_modulus, poisson_ratio=self.poisson_ratio, density=self.density
        )
        for name in ("youngs_modulus", "poisson_ratio", "density"):
            object.__setattr__(self, name, float(getattr(material, name)))

    @property
    def area(self) -> float:
        """A = π r² [m²]."""
        return np.pi * self.radius**2

    @property
    def second_moment(self) -> float:
        """I = π r⁴/4 [m⁴], about either transverse axis."""
        return np.pi * self.radius**4 / 4.0

    @property
    def polar_moment(self) -> float:
        """J = π r⁴/2 [m⁴] (torsion constant of a solid circle)."""
        return np.pi * self.radius**4 / 2.0

    @property
    def shear_modulus(self) -> float:
        """G = E / (2 (1 + ν)) [Pa]."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))

    @property
    def shear_coefficient(self) -> float:
        """κ = 6 (1 + ν) / (7 + 6 ν) [-], solid circle (Cowper 1966)."""
        return 6.0 * (1.0 + self.poisson_ratio) / (7.0 + 6.0 * self.poisson_ratio)


@dataclass(frozen=True, kw_only=True, eq=False)
class NeedleModel:
    """Co-rotational Timoshenko needle (static configuration; the state is passed to every method).

    Attributes
    ----------
    length : Needle length L [m], > 0.
    radius : Section radius r [m], > 0.
    element_count : Number of beam elements, ≥ 1.
    youngs_modulus : E [Pa], > 0.
    poisson_ratio : ν [-], in (−1, 0.5).
    density : ρ [kg/m³], > 0.
    base_position : Rest position of the base node [m], shape (3,).
    direction : Rest direction from base to tip (normalised here), shape (3,).
    up : Reference vector fixing the rest cross-section frame: its part normal to ``direction`` is material
        axis 1, shape (3,); by default world z, or world y when the needle is within 25° of z.
    """

    length: float
    radius: float
    element_count: int
    youngs_modulus: float
    poisson_ratio: float
    density: float
    base_position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    direction: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    up: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "length", _positive("length", self.length))
        count = self.element_count
        if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
            raise ValueError(f"element_count must be an integer >= 1, got {count!r}")
        object.__setattr__(self, "element_count", int(count))
        # Validates radius, youngs_modulus, poisson_ratio, density.
        object.__setattr__(
            self,
            "_section",
            NeedleSection(
                radius=self.radius,
                youngs_modulus=self.youngs_modulus,
                poisson_ratio=self.poisson_ratio,
                density=self.density,
            ),
        )
        for name in ("radius", "youngs_modulus", "poisson_ratio", "density"):
            object.__setattr__(self, name, getattr(self._section, name))
        base = np.asarray(self.base_position, dtype=float)
        if base.shape != (3,) or not np.all(np.isfinite(base)):
            raise ValueError(f"base_position must be 3 finite numbers [m], got {self.base_position!r}")
        frame = needle_rest_frame(self.direction, self.up)  # validates direction and up
        direction, normal = frame[:, 0], frame[:, 1]
        object.__setattr__(self, "base_position", base)
        object.__setattr__(self, "direction", direction)
        object.__setattr__(self, "up", normal)

    # ------------------------------------------------------------------ sizes and static data
    @property
    def section(self) -> NeedleSection:
        """Cross-section and material."""
        return self._section

    @property
    def node_count(self) -> int:
        """Number of nodes, element_count + 1."""
        return self.element_count + 1

    @property
    def dof_count(self) -> int:
        """Number of DoFs, 6 node_count."""
        return 6 * self.node_count

    @property
    def element_length(self) -> float:
        """Rest element length l₀ = L / element_count [m]."""
        return self.length / self.element_count

    @property
    def base_dofs(self) -> np.ndarray:
        """DoFs of the base node, prescribed by the trajectory: [0, 1, 2, 3, 4, 5]."""
        return np.arange(6)

    @property
    def tip_dofs(self) -> np.ndarray:
        """DoFs of the tip node, shape (6,)."""
        return 6 * self.element_count + np.arange(6)

    @cached_property
    def rest_frame(self) -> np.ndarray:
        """Rest material frame of every node, columns (direction, up, direction × up), shape (3, 3)."""
        # The columns of refsim.geometry.needle_rest_frame(direction, up), from the validated direction and
        # up.
        return np.stack([self.direction, self.up, np.cross(self.direction, self.up)], axis=-1)

    @cached_property
    def rest_arc_lengths(self) -> np.ndarray:
        """Rest arc length of each node from the base [m], shape (node_count,)."""
        return np.linspace(0.0, self.length, self.node_count)

    @cached_property
    def element_stiffness(self) -> np.ndarray:
        """Local 12×12 Timoshenko stiffness of one element (all are equal), shape (12, 12)."""
        s = self.section
        return timoshenko_stiffness(
            self.element_length,
            youngs_modulus=s.youngs_modulus,
            shear_modulus=s.shear_modulus,
            area=s.area,
            second_moment=s.second_moment,
            polar_moment=s.polar_moment,
            shear_coefficient=s.shear_coefficient,
        )

    @cached_property
    def _reduced_stiffness(self) -> np.ndarray:
        k7 = self.element_stiffness[np.ix_(LOCAL_REDUCED_DOFS, LOCAL_REDUCED_DOFS)]
        return np.broadcast_to(k7, (self.element_count, 7, 7))

    @cached_property
    def _rest_lengths(self) -> np.ndarray:
        return np.full(self.element_count, self.element_length)

    @cached_property
    def _element_dofs(self) -> np.ndarray:
        return 6 * np.arange(self.element_count)[:, None] + np.arange(12)[None, :]

    @cached_property
    def _pattern(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """CSR structure of the assembled (6n, 6n) matrices and the position of each element entry in it."""
        dofs = self._element_dofs
        rows = np.repeat(dofs, 12, axis=1).ravel()
        cols = np.tile(dofs, (1, 12)).ravel()
        n = self.dof_count
        keys = rows.astype(np.int64) * n + cols
        unique = np.unique(keys)
        scatter = np.searchsorted(unique, keys)
        indices = (unique % n).astype(np.int32)
        indptr = np.searchsorted(unique // n, np.arange(n + 1)).astype(np.int32)
        return indptr, indices, scatter

    def _assemble(self, element_matrices: np.ndarray) -> sp.csr_matrix:
        indptr, indices, scatter = self._pattern
        data = np.bincount(scatter, weights=element_matrices.ravel(), minlength=indices.size)
        return sp.csr_matrix((data, indices.copy(), indptr.copy()), shape=(self.dof_count, self.dof_count))

    # ------------------------------------------------------------------ state
    def rest_state(self) -> tuple[np.ndarray, np.ndarray]:
        """Rest pose.

        Returns
        -------
        positions : Node positions [m], shape (node_count, 3).
        frames : Node frames, shape (node_count, 3, 3).
        """
        positions = self.base_position + self.rest_arc_lengths[:, None] * self.direction
        frames = np.broadcast_to(self.rest_frame, (self.node_count, 3, 3)).copy()
        return positions, frames

    def _check_state(self, positions: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        positions = np.asarray(positions, dtype=float)
        frames = np.asarray(frames, dtype=float)
        if positions.shape != (self.node_count, 3):
            raise ValueError(f"positions must have shape ({self.node_count}, 3), got {positions.shape}")
        if frames.shape != (self.node_count, 3, 3):
            raise ValueError(f"frames must have shape ({self.node_count}, 3, 3), got {frames.shape}")
        return positions, frames

    def apply_increment(
        self, positions: np.ndarray, frames: np.ndarray, delta: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """New state after a DoF increment: x + Δu, exp(Δθ) Q (world-frame rotation increments).

        Parameters
        ----------
        positions : Node positions [m], shape (node_count, 3).
        frames : Node frames, shape (node_count, 3, 3).
        delta : Increment [m, rad], shape (dof_count,), ordered [ux, uy, uz, θx, θy, θz] per node.

        Returns
        -------
        positions : New positions [m], shape (node_count, 3).
        frames : New frames, shape (node_count, 3, 3).
        """
        positions, frames = self._check_state(positions, frames)
        delta = np.asarray(delta, dtype=float)
        if delta.shape != (self.dof_count,):
            raise ValueError(f"delta must have shape ({self.dof_count},), got {delta.shape}")
        # positions + Δu, rotation_matrix(Δθ) @ frames per node: one compiled kernel with their bits
        return needle_kernels.apply_increment(positions, frames, delta)

    def _apply_increment_reference(self, positions, frames, delta):
        """:meth:`apply_increment` in NumPy: the reference its kernel is held to (tests)."""
        per_node = np.asarray(delta, dtype=float).reshape(self.node_count, 6)
        return positions + per_node[:, :3], rotation_matrix(per_node[:, 3:]) @ frames

    # ------------------------------------------------------------------ elements
    def _ends(self, positions: np.ndarray, frames: np.ndarray):
        return positions[:-1], positions[1:], frames[:-1], frames[1:]

    def element_frames(self, positions: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """Co-rotational element frames (Crisfield / Battini–Pacoste, see module docstring).

        Parameters
        ----------
        positions : Node positions [m], shape (node_count, 3).
        frames : Node frames, shape (node_count, 3, 3).

        Returns
        -------
        Element frames, columns (chord direction, e2, e3), shape (element_count, 3, 3).
        """
        positions, frames = self._check_state(positions, frames)
        return corotational_frames(*self._ends(positions, frames))[0]

    def local_deformations(self, positions: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """Local deformations [ū, θ̄_a, θ̄_b] of each element [m, rad], shape (element_count, 7)."""
        positions, frames = self._check_state(positions, frames)
        return local_deformations(*self._ends(positions, frames), self._rest_lengths)["deformations"]

    def _element_forces(self, positions: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return beam_element_forces(
            *self._ends(positions, frames), self._rest_lengths, self._reduced_stiffness
        )

    def internal_forces(self, positions: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """Internal forces f_int = ∂U/∂DoFs: forces [N] and moments [N·m] in world axes.

        Parameters
        ----------
        positions : Node positions [m], shape (node_count, 3).
        frames : Node frames, shape (node_count, 3, 3).

        Returns
        -------
        f_int, shape (dof_count,), ordered [fx, fy, fz, mx, my, mz] per node.
        """
        positions, frames = self._check_state(positions, frames)
        forces, _ = self._element_forces(positions, frames)
        # np.bincount(self._element_dofs.ravel(), weights=forces.ravel()), compiled: the same sums in order
        return needle_kernels.assemble_forces(forces, self.dof_count)

    def strain_energy(self, positions: np.ndarray, frames: np.ndarray) -> float:
        """Strain energy U [J] of the co-rotational model."""
        positions, frames = self._check_state(positions, frames)
        return float(np.sum(self._element_forces(positions, frames)[1]))

    def tangent_stiffness(
        self, positions: np.ndarray, frames: np.ndarray, *, kind: str = "corotated"
    ) -> sp.csr_matrix:
        """Tangent stiffness K [N/m, N, N·m/rad] at the given state.

        Parameters
        ----------
        positions : Node positions [m], shape (node_count, 3).
        frames : Node frames, shape (node_count, 3, 3).
        kind : ``"corotated"``: R_e K_e R_eᵀ, symmetric, no geometric stiffness (SOFA's choice, for time
            stepping); ``"consistent"``: derivative of :meth:`internal_forces` (geometric stiffness included,
            by batched central differences of the element kernel, not symmetric away from equilibrium).

        Returns
        -------
        K, sparse CSR, shape (dof_count, dof_count).
        """
        positions, frames = self._check_state(positions, frames)
        if kind == "corotated":
            rotations = self.element_frames(positions, frames)
            indptr, indices, scatter = self._pattern
            # block @ element_stiffness @ blockᵀ per element, summed into the pattern: one compiled kernel
            # with the bits of _corotated_reference
            data = needle_kernels.corotated_stiffness_data(
                rotations, self.element_stiffness, scatter, indices.size
            )
            return sp.csr_matrix(
                (data, indices.copy(), indptr.copy()), shape=(self.dof_count, self.dof_count)
            )
        elif kind == "consistent":
            matrices = self._consistent_element_tangents(positions, frames)
        else:
            raise ValueError(f"kind must be 'corotated' or 'consistent', got {kind!r}")
        return self._assemble(matrices)

    def _corotated_reference(self, positions: np.ndarray, frames: np.ndarray) -> sp.csr_matrix:
        """The co-rotated tangent in NumPy: the reference of :meth:`tangent_stiffness`' kernel (tests)."""
        rotations = self.element_frames(positions, frames)
        block = np.zeros((self.element_count, 12, 12))
        for i in range(4):  # the four 3×3 diagonal blocks of the 12×12 rotation
            block[:, 3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = rotations
        return self._assemble(block @ self.element_stiffness @ np.swapaxes(block, 1, 2))

    def _consistent_element_tangents(self, positions: np.ndarray, frames: np.ndarray) -> np.ndarray:
        m = self.element_count
        xa, xb, qa, qb = self._ends(positions, frames)
        steps = np.concatenate([np.full(3, self.element_length), np.ones(3)] * 2) * _TANGENT_STEP
        perturbations = np.concatenate([np.diag(steps), -np.diag(steps)])  # (24, 12)
        # Perturbed copies, (24, m, ...) flattened to (24 m, ...): one batched kernel call.
        pa = (xa[None] + perturbations[:, None, 0:3]).reshape(-1, 3)
        pb = (xb[None] + perturbations[:, None, 6:9]).reshape(-1, 3)
        fa = (rotation_matrix(perturbations[:, 3:6])[:, None] @ qa[None]).reshape(-1, 3, 3)
        fb = (rotation_matrix(perturbations[:, 9:12])[:, None] @ qb[None]).reshape(-1, 3, 3)
        forces, _ = beam_element_forces(
            pa,
            pb,
            fa,
            fb,
            np.tile(self._rest_lengths, 24),
            np.broadcast_to(self._reduced_stiffness[0], (24 * m, 7, 7)),
        )
        forces = forces.reshape(24, m, 12)
        columns = (forces[:12] - forces[12:]) / (2.0 * steps[:, None, None])  # (12 columns, m, 12 rows)
        return np.transpose(columns, (1, 2, 0))

    def mass_matrix(self, frames: np.ndarray | None = None) -> sp.csr_matrix:
        """Lumped mass: ρ A l₀/2 per element end on translations, ρ l₀/2 Q diag(J, I, I) Qᵀ on rotations.

        Parameters
        ----------
        frames : Node frames orienting the rotary inertia, shape (node_count, 3, 3); the rest frames if None.

        Returns
        -------
        M [kg, kg·m²], sparse CSR, shape (dof_count, dof_count).
        """
        if frames is None:
            frames = np.broadcast_to(self.rest_frame, (self.node_count, 3, 3))
        frames = np.asarray(frames, dtype=float)
        if frames.shape != (self.node_count, 3, 3):
            raise ValueError(f"frames must have shape ({self.node_count}, 3, 3), got {frames.shape}")
        s = self.section
        share = np.full(self.node_count, self.element_length)
        share[[0, -1]] *= 0.5  # length of needle lumped on each node [m]
        inertia = s.density * np.array([s.polar_moment, s.second_moment, s.second_moment])
        rotary = np.einsum("nij,j,nkj->nik", frames, inertia, frames) * share[:, None, None]
        blocks = np.zeros((self.node_count, 6, 6))
        blocks[:, :3, :3] = (s.density * s.area * share)[:, None, None] * np.eye(3)
        blocks[:, 3:, 3:] = rotary
        return sp.block_diag(list(blocks), format="csr")

    def assemble_step(
        self,
        positions: np.ndarray,
        frames: np.ndarray,
        velocities: np.ndarray,
        dt: float,
        base_increment: np.ndarray,
        *,
        rayleigh_mass: float = 0.0,
        rayleigh_stiffness: float = 0.0,
        mass: sp.spmatrix | None = None,
        forces: np.ndarray | None = None,
    ):
        """The step system of the compliance strategies (:mod:`refsim.fem.compliance`), base node prescribed.

        One Newton step of implicit Euler on A = M/dt² + C/dt + K (co-rotated tangent), the six base DoFs
        moved by ``base_increment``; a strategy's ``step`` then gives the free motion Δx, W and the
        correction, which :meth:`apply_increment` turns into positions and frames.

        Parameters
        ----------
        positions, frames : The state at the start of the step, shapes (node_count, 3) and (node_count, 3, 3).
        velocities : Node velocities, linear [m/s] then angular [rad/s], shape (node_count, 6).
        dt : Time step [s].
        base_increment : Δx of the base over the step: translation [m] then rotation vector [rad], shape (6,).
        rayleigh_mass, rayleigh_stiffness : Rayleigh α [1/s] and β [s].
        mass : M (:meth:`mass_matrix` by default).
        forces : External minus internal forces [N, N·m], shape (dof_count,); −internal_forces by default.
        """
        from refsim.fem.compliance import StepSystem
        from refsim.fem.integration import effective_stiffness

        positions, frames = self._check_state(positions, frames)
        mass = self.mass_matrix() if mass is None else mass
        if forces is None:
            forces = -self.internal_forces(positions, frames)
        matrix = effective_stiffness(
            mass,
            self.tangent_stiffness(positions, frames),
            dt,
            rayleigh_mass=rayleigh_mass,
            rayleigh_stiffness=rayleigh_stiffness,
        )
        increment = np.asarray(base_increment, dtype=float)
        if increment.shape != (6,):
            raise ValueError(f"base_increment must have shape (6,), got {increment.shape}")
        base = np.asarray(self.base_dofs)
        order = np.argsort(base)
        # M v₀ by SciPy's CSR product (a CSR mass, the flexible needle's kept one, is used as it is: the same
        # product as on its csr_matrix copy)
        mass_csr = mass if isinstance(mass, sp.csr_matrix) else sp.csr_matrix(mass)
        rhs = np.asarray(forces, dtype=float) + (mass_csr @ np.asarray(velocities, float).ravel()) / dt
        rest = np.broadcast_to(self.rest_frame, frames.shape)

        def group_rotations() -> np.ndarray:
            # One rotation per node (frame now · rest frameᵀ), for both 3-DoF groups of the node.
            return np.repeat(frames @ np.swapaxes(rest, 1, 2), 2, axis=0)

        return StepSystem.from_matrices(matrix, rhs, base, increment[order], group_rotations=group_rotations)

    # ------------------------------------------------------------------ centreline
    def _locate(self, arc_lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = np.atleast_1d(np.asarray(arc_lengths, dtype=float))
        if s.ndim != 1:
            raise ValueError(f"arc_lengths must have shape (q,), got {s.shape}")
        found = needle_kernels.locate(s, self.length, self.element_length, self.element_count)
        if found is not None:
            return found
        slack = 1e-9 * self.length
        if np.any(~np.isfinite(s)) or np.any(s < -slack) or np.any(s > self.length + slack):
            bad = s[~np.isfinite(s) | (s < -slack) | (s > self.length + slack)][0]
            raise ValueError(f"arc lengths must lie in [0, {self.length}] m, got {bad!r}")
        scaled = np.clip(s, 0.0, self.length) / self.element_length
        elements = np.minimum(np.floor(scaled).astype(np.int64), self.element_count - 1)
        return elements, scaled - elements

    @cached_property
    def _kinematics_memo(self) -> dict:
        return {}

    def _element_kinematics(self, positions: np.ndarray, frames: np.ndarray) -> dict[str, np.ndarray]:
        """`local_deformations` of every element in the configuration (positions, frames), read-only.

        A step evaluates the centreline of the same few configurations (the needle at the start of the step
        and after free motion) many times (points, tangents, projections, Jacobians); the element kinematics
        of the last :data:`_KINEMATICS_MEMO` configurations are kept (with the projection's polyline,
        :meth:`_polyline`), keyed by the configuration's bytes, so a repeated evaluation gathers them
        instead of computing them again (the same function of the same inputs: the same bits)."""
        key = (positions.tobytes(), frames.tobytes())
        memo = self._kinematics_memo
        found = memo.get(key)
        if found is None:
            found = local_deformations(*self._ends(positions, frames), self._rest_lengths)
            for value in found.values():
                value.setflags(write=False)
            while len(memo) >= _KINEMATICS_MEMO:
                memo.pop(next(iter(memo)), None)
            memo[key] = found
        return found

    def _polyline(
        self, positions: np.ndarray, frames: np.ndarray, samples_per_element: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """The projection's search polyline: its rest arc lengths (``samples_per_element`` segments per
        element) and centreline points, kept with the configuration's element kinematics (read-only)."""
        positions, frames = self._check_state(positions, frames)
        kinematics = self._element_kinematics(positions, frames)
        key = f"polyline {samples_per_element}"
        found = kinematics.get(key)
        if found is None:
            samples = np.linspace(0.0, self.length, self.element_count * samples_per_element + 1)
            found = (samples, self.centreline_points(positions, frames, samples))
            for value in found:
                value.setflags(write=False)
            kinematics[key] = found
        return found

    def _centreline(self, positions, frames, arc_lengths, *, jacobian: bool):
        """Points, dp/ds, elements and (``jacobian``) J at rest arc lengths: one compiled kernel over the
        configuration's element kinematics (:func:`refsim.fem.needle_kernels.centreline`, the bits of
        :meth:`_centreline_reference`)."""
        positions, frames = self._check_state(positions, frames)
        elements, xi = self._locate(arc_lengths)
        per_element = self._element_kinematics(positions, frames)
        points, derivatives, jac = needle_kernels.centreline(
            positions, per_element, elements, xi, self.element_length, jacobian=jacobian
        )
        out = {"points": points, "derivatives": derivatives, "elements": elements}
        if jacobian:
            out["jacobian"] = jac
        return out

    def _centreline_reference(self, positions, frames, arc_lengths, *, jacobian: bool):
        """:meth:`_centreline` in NumPy: the reference its compiled kernel is held to (tests)."""
        positions, frames = self._check_state(positions, frames)
        elements, xi = self._locate(arc_lengths)
        # Element kinematics once per element (and configuration), then gathered per query point.
        per_element = self._element_kinematics(positions, frames)
        needed = (
            ("deformations", "element_frames", "jacobian", "spin_jacobian")
            if jacobian
            else (
                "deformations",
                "element_frames",
            )
        )
        local = {key: per_element[key][elements] for key in needed}
        d, rot = local["deformations"], local["element_frames"]
        shapes, slopes = hermite_shapes(xi)
        l0 = self.element_length
        # Local deflection (0, v, w) with v' = θz and w' = −θy (d = [ū, θ̄x_a, θ̄y_a, θ̄z_a, θ̄x_b, θ̄y_b,
        # θ̄z_b]).
        v_rows, w_rows = np.array([3, 6]), np.array([2, 5])
        deflection = np.zeros((xi.size, 3))
        deflection[:, 1] = l0 * np.einsum("qk,qk->q", shapes, d[:, v_rows])
        deflection[:, 2] = -l0 * np.einsum("qk,qk->q", shapes, d[:, w_rows])
        chord = positions[elements + 1] - positions[elements]
        offset = np.einsum("qij,qj->qi", rot, deflection)
        points = positions[elements] + xi[:, None] * chord + offset
        derivative_local = np.zeros((xi.size, 3))
        derivative_local[:, 1] = l0 * np.einsum("qk,qk->q", slopes, d[:, v_rows])
        derivative_local[:, 2] = -l0 * np.einsum("qk,qk->q", slopes, d[:, w_rows])
        derivatives = (chord + np.einsum("qij,qj->qi", rot, derivative_local)) / l0  # dp/ds
        out = {"points": points, "derivatives": derivatives, "elements": elements}
        if jacobian:
            b = local["jacobian"]
            jac = np.zeros((xi.size, 3, 12))
            jac[:, :, 0:3] = (1.0 - xi)[:, None, None] * np.eye(3)
            jac[:, :, 6:9] = xi[:, None, None] * np.eye(3)
            jac -= skew(offset) @ rot @ local["spin_jacobian"]
            local_rows = np.zeros((xi.size, 3, 12))
            local_rows[:, 1] = l0 * np.einsum("qk,qkj->qj", shapes, b[:, v_rows])
            local_rows[:, 2] = -l0 * np.einsum("qk,qkj->qj", shapes, b[:, w_rows])
            jac += rot @ local_rows
            out["jacobian"] = jac
        return out

    def centreline_points(
        self, positions: np.ndarray, frames: np.ndarray, arc_lengths: np.ndarray
    ) -> np.ndarray:
        """Points of the centreline at rest arc lengths (chord + cubic Hermite deflection per element).

        Parameters
        ----------
        positions : Node positions [m], shape (node_count, 3).
        frames : Node frames, shape (node_count, 3, 3).
        arc_lengths : Rest arc lengths from the base [m], in [0, length], shape (q,).

        Returns
        -------
        Points [m], shape (q, 3).
        """
        return self._centreline(positions, frames, arc_lengths, jacobian=False)["points"]

    def centreline_tangents(
        self, positions: np.ndarray, frames: np.ndarray, arc_lengths: np.ndarray
    ) -> np.ndarray:
        """Unit tangents (direction of d point/d s) of the centreline at rest arc lengths [m], (q, 3)."""
        derivatives = self._centreline(positions, frames, arc_lengths, jacobian=False)["derivatives"]
        return derivatives / np.linalg.norm(derivatives, axis=-1, keepdims=True)

    def centreline_jacobian(
        self, positions: np.ndarray, frames: np.ndarray, arc_lengths: np.ndarray
    ) -> sp.csr_matrix:
        """Derivative of the centreline points with respect to the DoFs (arc lengths held fixed).

        Row 3 i + c is component c of point i; a constraint row along a unit normal n at arc length s_i is
        ``n @ J[3 i : 3 i + 3]``. Rotational columns are per world-frame rotation increment.

        Parameters
        ----------
        positions : Node positions [m], shape (node_count, 3).
        frames : Node frames, shape (node_count, 3, 3).
        arc_lengths : Rest arc lengths [m], shape (q,).

        Returns
        -------
        J [m/m, m/rad], sparse CSR, shape (3 q, dof_count), 12 non-zeros per row.
        """
        out = self._centreline(positions, frames, arc_lengths, jacobian=True)
        q = out["points"].shape[0]
        columns = 6 * out["elements"][:, None] + np.arange(12)[None, :]  # (q, 12)
        indices = np.repeat(columns[:, None, :], 3, axis=1).reshape(-1)
        indptr = np.arange(0, 36 * q + 1, 12)
        return sp.csr_matrix((out["jacobian"].reshape(-1), indices, indptr), shape=(3 * q, self.dof_count))

    def project_on_centreline(
        self,
        positions: np.ndarray,
        frames: np.ndarray,
        points: np.ndarray,
        *,
        samples_per_element: int = 8,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest points of the centreline to given points.

        The centreline is sampled into a polyline (``samples_per_element`` segments per element); each point's
        closest point on every segment is computed and the best segment kept, then refined by Gauss–Newton on
        the Hermite curve (accepted only where it reduces the distance). Vectorised over points and segments.

        Parameters
        ----------
        positions : Node positions [m], shape (node_count, 3).
        frames : Node frames, shape (node_count, 3, 3).
        points : Query points [m], shape (q, 3).
        samples_per_element : Polyline segments per element for the initial search, ≥ 1.

        Returns
        -------
        arc_lengths : Rest arc lengths of the closest points [m], shape (q,).
        closest : Closest centreline points [m], shape (q, 3).
        distance : Distances [m], shape (q,).
        """
        points = np.asarray(points, dtype=float)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape (q, 3), got {points.shape}")
        if samples_per_element < 1:
            raise ValueError(f"samples_per_element must be >= 1, got {samples_per_element!r}")
        samples, polyline = self._polyline(positions, frames, samples_per_element)
        positions, frames = self._check_state(positions, frames)
        found = needle_kernels.project(
            positions,
            self._element_kinematics(positions, frames),
            samples,
            polyline,
            points,
            self.length,
            self.element_length,
            self.element_count,
            _PROJECTION_NEWTON_ITERATIONS,
        )
        if found is not None:
            return found
        # an invalid arc length on the way (not finite): the NumPy code raises its error
        return self._project_reference(positions, frames, points, samples, polyline)

    def _project_reference(self, positions, frames, points, samples, polyline):
        """The closest points of :meth:`project_on_centreline` in NumPy, on its polyline: the reference its
        compiled kernel is held to (tests), and the code that raises on an invalid arc length."""
        start, segment = polyline[:-1], np.diff(polyline, axis=0)  # (S, 3)
        relative = points[:, None, :] - start[None]  # (q, S, 3)
        t = np.clip(
            np.einsum("qsi,si->qs", relative, segment) / np.einsum("si,si->s", segment, segment), 0, 1
        )
        gaps = relative - t[..., None] * segment[None]
        best = np.argmin(np.einsum("qsi,qsi->qs", gaps, gaps), axis=1)
        arc = samples[best] + t[np.arange(points.shape[0]), best] * (samples[best + 1] - samples[best])
        current = self._centreline_reference(positions, frames, arc, jacobian=False)
        closest, tangent = current["points"], current["derivatives"]
        distance = np.linalg.norm(points - closest, axis=-1)
        for _ in range(_PROJECTION_NEWTON_ITERATIONS):
            step = np.einsum("qi,qi->q", points - closest, tangent) / np.einsum("qi,qi->q", tangent, tangent)
            trial = np.clip(arc + step, 0.0, self.length)
            data = self._centreline_reference(positions, frames, trial, jacobian=False)
            trial_distance = np.linalg.norm(points - data["points"], axis=-1)
            better = trial_distance < distance
            arc = np.where(better, trial, arc)
            closest = np.where(better[:, None], data["points"], closest)
            tangent = np.where(better[:, None], data["derivatives"], tangent)
            distance = np.where(better, trial_distance, distance)
        return arc, closest, distance
