"""Co-rotational linear tetrahedra for the tissue (layer 2).

The tissue is a mesh of linear (P1) tetrahedra with a Hooke material. Each element carries its rest stiffness
Kₑ (12 × 12, from scikit-fem's vector P1 linear elasticity form) and is co-rotated: with Rₑ the rotation
of the element and X, x its rest and current node positions, the internal force and the tangent are

    fₑ = Rₑ Kₑ (Rₑᵀ xₑ − Xₑ),        Kₑ,t = Rₑ Kₑ Rₑᵀ        (Rₑ acting block-wise on the 4 nodes).

Rotations come from the **polar decomposition** of the deformation gradient F = Rₑ Sₑ (S symmetric positive),
not from SOFA's "large" method (a Gram–Schmidt frame of the first edges). The polar rotation makes the element
independent of the node order and, for an isotropic material, makes fₑ the exact gradient of the rotation
invariant energy Eₑ = ½ uₑᵀ Kₑ uₑ, uₑ = Rₑᵀ xₑ − Xₑ: dR contributes σ : (Ω S), which vanishes because the
stress σ commutes with S (σ = λ tr(S − I) I + 2μ (S − I)) and Ω is skew. The internal forces are therefore
conservative (no energy drift from the co-rotation), which the "large" frame does not guarantee.

The tangent R Kₑ Rᵀ omits the derivative of R: it equals ∂f/∂x exactly when uₑ = 0 modulo rigid motions (the
rest shape, translated and rotated), and differs from it by O(strain) otherwise. This is the standard
co-rotational tangent used by SOFA and by the paper's one-Newton-step implicit Euler.

Degrees of freedom are node-major, ``[x0, y0, z0, x1, …]``, so a (node_count, 3) array flattens (C order) to
the DoF vector. The mass is lumped (row sums of the consistent P1 mass, ρ V/4 per node and tet) unless
``lumped_mass=False``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from refsim.fem.assembly import FreePattern, assemble_free_system
from refsim.fem.compliance import BodyCompliance, Exact, StepCompliance, StepSystem
from refsim.fem.integration import effective_stiffness
from refsim.fem.threads import hot_path_threads
from refsim.geometry.rotations import polar_rotation
from refsim.materials import HookeMaterial
from refsim.mesh.validation import DEGENERATE_VOLUME_RATIO, degenerate_tets

__all__ = [
    "TissueModel",
    "TissueState",
    "StaticEquilibrium",
    "element_stiffness_matrices",
    "element_mass_matrices",
]

logger = logging.getLogger(__name__)

EPS = float(np.finfo(float).eps)
# A Newton update below this many ε of the largest coordinate is round-off: forces come from Rᵀx − X, so the
# positions carry a noise of a few ε max|x| and the residual cannot be reduced further.
_ROUNDOFF_STEP = 16.0

# Local DoF offsets of one tet, node-major: local DoF 3a + i is component i of node a.
_LOCAL_COMPONENTS = np.arange(3)


def _skfem_mesh(rest_positions: np.ndarray, tets: np.ndarray):
    """scikit-fem tetrahedral mesh of our arrays.

    This is the single place where refsim's row-major arrays meet scikit-fem's column-major layout:
    scikit-fem stores points as (3, node_count) and cells as (4, tet_count), hence the transposes.
    """
    import skfem

    return skfem.MeshTet(np.ascontiguousarray(rest_positions.T), np.ascontiguousarray(tets.T))


def _local_order(basis, tets: np.ndarray, components: int) -> np.ndarray:
    """Our local DoF index of each of scikit-fem's local basis functions, shape (tet_count, 4·components).

    scikit-fem numbers a vector element's DoFs through ``nodal_dofs`` (components, node_count) and its element
    DoFs through ``element_dofs`` (local, tet_count); it may also reorder the nodes of a cell. Neither is
    assumed here: every local scikit-fem DoF is traced back to (node, component) and then to our
    node-major local index 3·(position of the node in ``tets[e]``) + component.
    """
    nodal = basis.nodal_dofs  # (components, node_count)
    dof_count = basis.N
    node_of = np.empty(dof_count, dtype=np.int64)
    component_of = np.empty(dof_count, dtype=np.int64)
    node_of[nodal] = np.arange(nodal.shape[1])[None, :]
    component_of[nodal] = np.arange(components)[:, None]
    element_dofs = basis.element_dofs.T  # (tet_count, local)
    nodes = node_of[element_dofs]
    position = np.argmax(tets[:, None, :] == nodes[:, :, None], axis=2)  # (tet_count, local)
    order = components * position + component_of[element_dofs]
    expected = np.arange(4 * components)
    if not np.array_equal(np.sort(order, axis=1), np.broadcast_to(expected, order.shape)):
        raise RuntimeError("scikit-fem local DoFs do not map one-to-one onto the nodes of the tets")
    return order


def _to_local_order(matrices: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Permute element matrices (tet_count, k, k) from scikit-fem's local order into ours."""
    out = np.empty_like(matrices)
    elements = np.arange(matrices.shape[0])[:, None, None]
    out[elements, order[:, :, None], order[:, None, :]] = matrices
    return out


def element_stiffness_matrices(
    rest_positions: np.ndarray, tets: np.ndarray, material: HookeMaterial
) -> np.ndarray:
    """Rest stiffness of every P1 tet, from scikit-fem's linear elasticity form.

    Parameters
    ----------
    rest_positions : Node rest positions [m], shape (node_count, 3).
    tets : Node indices of the tets, shape (tet_count, 4).
    material : Hooke material (E, ν).

    Returns
    -------
    Kₑ [N/m], shape (tet_count, 12, 12), node-major local DoFs (3a + i: component i of node a of ``tets[e]``).
    """
    import skfem
    from skfem.models.elasticity import linear_elasticity

    mesh = _skfem_mesh(rest_positions, tets)
    # P1 gradients are constant on a tet: the one-point rule integrates the form exactly.
    basis = skfem.Basis(mesh, skfem.ElementVector(skfem.ElementTetP1()), intorder=0)
    form = linear_elasticity(material.lame_lambda, material.shear_modulus)
    local = form.elemental(basis).tolocal()  # (tet_count, 12, 12), symmetric
    return _to_local_order(local, _local_order(basis, tets, 3))


def element_mass_matrices(rest_positions: np.ndarray, tets: np.ndarray, density: float) -> np.ndarray:
    """Consistent mass of every P1 tet, from scikit-fem's mass form, ρ ∫ φ_a φ_b dV.

    Parameters
    ----------
    rest_positions : Node rest positions [m], shape (node_count, 3).
    tets : Node indices of the tets, shape (tet_count, 4).
    density : ρ [kg/m³].

    Returns
    -------
    Scalar element mass [kg], shape (tet_count, 4, 4), in the node order of ``tets``; the 12 × 12 vector
    mass is its Kronecker product with the 3 × 3 identity (each component has the same mass).
    """
    import skfem

    mesh = _skfem_mesh(rest_positions, tets)
    basis = skfem.Basis(mesh, skfem.ElementTetP1(), intorder=2)  # φ_a φ_b is quadratic: degree 2 is exact
    form = skfem.BilinearForm(lambda u, v, _: density * u * v)
    local = form.elemental(basis).tolocal()
    return _to_local_order(local, _local_order(basis, tets, 1))


@dataclass(frozen=True, kw_only=True)
class TissueState:
    """The changing state of the tissue.

    Attributes
    ----------
    positions : Node positions [m], shape (node_count, 3).
    velocities : Node velocities [m/s], shape (node_count, 3).
    """

    positions: np.ndarray
    velocities: np.ndarray

    def __post_init__(self) -> None:
        positions = np.asarray(self.positions, dtype=float)
        velocities = np.asarray(self.velocities, dtype=float)
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise ValueError(f"positions must have shape (node_count, 3), got {positions.shape}")
        if velocities.shape != positions.shape:
            raise ValueError(
                f"velocities must have the shape of positions {positions.shape}, got {velocities.shape}"
            )
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "velocities", velocities)


class StaticEquilibrium(NamedTuple):
    """Result of :meth:`TissueModel.solve_static`.

    Attributes
    ----------
    positions : Equilibrium node positions [m], shape (node_count, 3).
    iterations : Newton iterations done.
    residual : Final relative residual ‖(f_ext − f_int)_free‖ / max(‖f_ext‖, ‖f_int‖).
    converged : Whether ``residual`` reached the tolerance.
    """

    positions: np.ndarray
    iterations: int
    residual: float
    converged: bool


class TissueModel:
    """Co-rotational linear tetrahedra with lumped (or consistent) mass and Rayleigh damping.

    The model is static (built once, never mutated); the state (positions, velocities) is passed
    to its methods.

    Parameters
    ----------
    rest_positions : Node rest positions [m], shape (node_count, 3).
    tets : Node indices of the tets, shape (tet_count, 4); either orientation.
    material : Hooke material (E [Pa], ν, ρ [kg/m³]).
    rayleigh_mass : Rayleigh α [1/s], ≥ 0; C = α M + β K.
    rayleigh_stiffness : Rayleigh β [s], ≥ 0.
    fixed_nodes : Indices of the nodes held in place (all three DoFs), shape (k,); none by default.
    gravity : Gravitational acceleration [m/s²], shape (3,); zero by default.
    lumped_mass : Lumped (row-sum, diagonal) mass if True (default, what the simulation uses),
    else consistent.
    """

    def __init__(
        self,
        rest_positions: np.ndarray,
        tets: np.ndarray,
        material: HookeMaterial,
        *,
        rayleigh_mass: float = 0.0,
        rayleigh_stiffness: float = 0.0,
        fixed_nodes: np.ndarray | None = None,
        gravity: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
        lumped_mass: bool = True,
    ) -> None:
        rest_positions, tets = _validated_mesh(rest_positions, tets)
        if not isinstance(material, HookeMaterial):
            raise ValueError(f"material must be a HookeMaterial, got {type(material).__name__}")
        for name, value in (("rayleigh_mass", rayleigh_mass), ("rayleigh_stiffness", rayleigh_stiffness)):
            if not (np.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        gravity = np.asarray(gravity, dtype=float)
        if gravity.shape != (3,) or not np.all(np.isfinite(gravity)):
            raise ValueError(f"gravity must be 3 finite numbers [m/s^2], got {gravity!r}")
        node_count = rest_positions.shape[0]
        fixed = np.unique(np.asarray([] if fixed_nodes is None else fixed_nodes, dtype=np.int64).ravel())
        if fixed.size and (fixed[0] < 0 or fixed[-1] >= node_count):
            raise ValueError(f"fixed_nodes must lie in [0, {node_count}), got {fixed.min()}..{fixed.max()}")

        self.rest_positions = _read_only(rest_positions)
        self.tets = _read_only(tets)
        self.material = material
        self.rayleigh_mass = float(rayleigh_mass)
        self.rayleigh_stiffness = float(rayleigh_stiffness)
        self.fixed_nodes = _read_only(fixed)
        self.gravity = _read_only(gravity)
        self.lumped_mass = bool(lumped_mass)

        edges = rest_positions[tets[:, 1:]] - rest_positions[tets[:, :1]]  # (tet_count, 3 edges, 3)
        self._rest_edges_inverse = np.linalg.inv(np.swapaxes(edges, 1, 2))  # Dm⁻¹, Dm = [X1−X0, X2−X0, X3−X0]
        element_rest = rest_positions[tets]
        self._centred_rest = element_rest - element_rest.mean(axis=1, keepdims=True)  # (tet_count, 4, 3)
        self.element_volumes = _read_only(np.abs(np.linalg.det(np.swapaxes(edges, 1, 2))) / 6.0)

        stiffness = element_stiffness_matrices(rest_positions, tets, material)
        tet_count = tets.shape[0]
        # Block layout (tet_count, 4, 4, 3, 3): block [a, b] couples node a to node b; rotating is then two
        # batched 3 × 3 products per block.
        self._element_stiffness_blocks = np.ascontiguousarray(
            stiffness.reshape(tet_count, 4, 3, 4, 3).transpose(0, 1, 3, 2, 4)
        )
        self._element_stiffness = stiffness
        # The compiled assembly reads one tet's 144 entries together; scikit-fem's array has the tet index
        # fastest (each entry of one tet on another cache line).
        self._element_stiffness_rows = np.ascontiguousarray(stiffness)
        self._element_dofs = (3 * tets[:, :, None] + _LOCAL_COMPONENTS).reshape(tet_count, 12)
        self._build_pattern()

        element_mass = element_mass_matrices(rest_positions, tets, material.density)
        self.nodal_masses = _read_only(
            np.bincount(tets.ravel(), weights=element_mass.sum(axis=2).ravel(), minlength=node_count)
        )
        if self.lumped_mass:
            self.mass_matrix = sp.diags(np.repeat(self.nodal_masses, 3)).tocsr()
        else:
            eye = np.eye(3)
            blocks = element_mass[:, :, :, None, None] * eye  # (tet_count, 4, 4, 3, 3)
            self.mass_matrix = self._assemble(blocks.ravel())
        self.rest_stiffness = self.tangent_stiffness(np.broadcast_to(np.eye(3), (tet_count, 3, 3)))
        self._gravity_forces = _read_only(self.external_forces().ravel())  # f_ext of every step, (dof_count,)
        logger.debug(
            "tissue model: %d nodes, %d tets, %d fixed nodes, stiffness nnz %d",
            node_count,
            tet_count,
            fixed.size,
            self._pattern.nnz,
        )

    # ---------------------------------------------------------------- sizes

    @property
    def node_count(self) -> int:
        """Number of nodes."""
        return self.rest_positions.shape[0]

    @property
    def tet_count(self) -> int:
        """Number of tets."""
        return self.tets.shape[0]

    @property
    def dof_count(self) -> int:
        """Number of DoFs, 3 · node_count."""
        return 3 * self.node_count

    @property
    def fixed_dofs(self) -> np.ndarray:
        """DoF indices of the fixed nodes, sorted, shape (3k,)."""
        return (3 * self.fixed_nodes[:, None] + _LOCAL_COMPONENTS).ravel()

    @property
    def element_stiffness(self) -> np.ndarray:
        """Rest element stiffness Kₑ [N/m], shape (tet_count, 12, 12), node-major local DoFs (read-only)."""
        return _read_only(self._element_stiffness)

    def rest_state(self) -> TissueState:
        """The state at rest: rest positions, zero velocities."""
        return TissueState(
            positions=self.rest_positions.copy(), velocities=np.zeros_like(self.rest_positions)
        )

    # ---------------------------------------------------------------- co-rotation

    def deformation_gradients(self, positions: np.ndarray) -> np.ndarray:
        """Deformation gradients F = [x1−x0, x2−x0, x3−x0] [X1−X0, X2−X0, X3−X0]⁻¹ of the tets.

        Parameters
        ----------
        positions : Node positions [m], shape (node_count, 3).

        Returns
        -------
        F, shape (tet_count, 3, 3).
        """
        positions = self._checked_positions(positions)
        edges = positions[self.tets[:, 1:]] - positions[self.tets[:, :1]]  # (tet_count, 3 edges, 3)
        return np.swapaxes(edges, 1, 2) @ self._rest_edges_inverse

    def element_rotations(self, positions: np.ndarray) -> np.ndarray:
        """Co-rotational frames: the rotation of the polar decomposition F = R S of every tet.

        Parameters
        ----------
        positions : Node positions [m], shape (node_count, 3).

        Returns
        -------
        Rotations R, shape (tet_count, 3, 3), det R = +1.
        """
        return polar_rotation(self.deformation_gradients(positions))

    def _local_displacements(self, positions: np.ndarray, rotations: np.ndarray) -> np.ndarray:
        """uₑ = Rₑᵀ xₑ − Xₑ for every tet, up to a translation, shape (tet_count, 4, 3) [m].

        Positions are taken relative to the element centroid: Kₑ annihilates translations, so forces and
        energy are unchanged, and the round-off becomes ε times the element size instead of ε times the
        distance to the origin (a body far from the origin would otherwise carry spurious forces).
        """
        element_positions = positions[self.tets]  # (tet_count, 4, 3)
        element_positions = element_positions - element_positions.mean(axis=1, keepdims=True)
        # Row-vector form of Rᵀ x for each node: x Rᵀᵀ = x R.
        return element_positions @ rotations - self._centred_rest

    def internal_forces(self, positions: np.ndarray, rotations: np.ndarray) -> np.ndarray:
        """Elastic internal forces f = Σₑ Rₑ Kₑ (Rₑᵀ xₑ − Xₑ).

        Parameters
        ----------
        positions : Node positions [m], shape (node_count, 3).
        rotations : Element rotations, shape (tet_count, 3, 3) (from :meth:`element_rotations`).

        Returns
        -------
        Internal forces [N] (the force the tissue exerts is their opposite), shape (node_count, 3).
        """
        positions = self._checked_positions(positions)
        rotations = self._checked_rotations(rotations)
        local = self._local_displacements(positions, rotations).reshape(self.tet_count, 12)
        local_forces = np.einsum("eij,ej->ei", self._element_stiffness, local).reshape(self.tet_count, 4, 3)
        element_forces = local_forces @ np.swapaxes(rotations, 1, 2)  # row-vector form of R f
        dof_forces = np.bincount(
            self._element_dofs.ravel(), weights=element_forces.ravel(), minlength=self.dof_count
        )
        return dof_forces.reshape(self.node_count, 3)

    def strain_energy(self, positions: np.ndarray, rotations: np.ndarray | None = None) -> float:
        """Co-rotational strain energy Σₑ ½ uₑᵀ Kₑ uₑ, uₑ = Rₑᵀ xₑ − Xₑ [J].

        Parameters
        ----------
        positions : Node positions [m], shape (node_count, 3).
        rotations : Element rotations, shape (tet_count, 3, 3); the polar rotations of
        ``positions`` by default.
        """
        positions = self._checked_positions(positions)
        if rotations is None:
            rotations = self.element_rotations(positions)
        local = self._local_displacements(positions, self._checked_rotations(rotations)).reshape(
            self.tet_count, 12
        )
        return float(0.5 * np.einsum("ei,eij,ej->", local, self._element_stiffness, local))

    def tangent_stiffness(self, rotations: np.ndarray) -> sp.csr_matrix:
        """Co-rotational tangent K = Σₑ Rₑ Kₑ Rₑᵀ, assembled into the fixed sparsity pattern.

        Parameters
        ----------
        rotations : Element rotations, shape (tet_count, 3, 3).

        Returns
        -------
        K [N/m], sparse CSR, shape (dof_count, dof_count), symmetric positive semi-definite.
        """
        rotations = self._checked_rotations(rotations)
        r = rotations[:, None, None]  # broadcast over the 4 × 4 node blocks
        blocks = r @ self._element_stiffness_blocks @ np.swapaxes(r, -1, -2)
        return self._assemble(blocks.ravel())

    def external_forces(self) -> np.ndarray:
        """Gravity on the nodes, mᵢ g (the same for lumped and consistent mass).

        Returns
        -------
        External forces [N], shape (node_count, 3).
        """
        return self.nodal_masses[:, None] * self.gravity[None, :]

    def kinetic_energy(self, velocities: np.ndarray) -> float:
        """Kinetic energy ½ vᵀ M v [J] of velocities [m/s], shape (node_count, 3)."""
        v = np.asarray(velocities, dtype=float).ravel()
        return float(0.5 * v @ (self.mass_matrix @ v))

    def gravity_energy(self, positions: np.ndarray) -> float:
        """Potential energy of gravity −Σᵢ mᵢ g·(xᵢ − Xᵢ) [J], zero at rest."""
        displacements = self._checked_positions(positions) - self.rest_positions
        return float(-np.sum(self.external_forces() * displacements))

    # ---------------------------------------------------------------- time stepping

    def step_system(self, rotations: np.ndarray, dt: float) -> StepCompliance:
        """The exact strategy's compliance of one implicit Euler step with the tangent of ``rotations``:
        A = M/dt² + C/dt + K factorised, fixed DoFs eliminated (its ``compliance(H)`` gives W and A⁻¹Hᵀ, its
        ``free_displacement`` the response to zero load).

        Parameters
        ----------
        rotations : Element rotations at the start of the step, shape (tet_count, 3, 3).
        dt : Time step [s].
        """
        matrix = effective_stiffness(
            self.mass_matrix,
            self.tangent_stiffness(rotations),
            dt,
            rayleigh_mass=self.rayleigh_mass,
            rayleigh_stiffness=self.rayleigh_stiffness,
        )
        system = StepSystem.from_matrices(matrix, np.zeros(self.dof_count), self.fixed_dofs)
        return Exact().bind().step(system)

    def assemble_step(
        self,
        state: TissueState,
        dt: float,
        *,
        fixed_displacements: np.ndarray | None = None,
        compiled: bool = True,
        upper_triangle: bool = False,
        matrix_free: bool = False,
    ) -> StepSystem:
        """The step system of the compliance strategies: A on the free DoFs and the free motion's right-hand
        side.

        A = M/dt² + C/dt + K with the co-rotational tangent at x₀ (see :mod:`refsim.fem.integration`), the
        fixed DoFs eliminated; rhs = f_ext − f_int(x₀) + (M/dt) v₀ − A_fc Δx_c.

        Parameters
        ----------
        state : Positions x₀ [m] and velocities v₀ [m/s] at the start of the step, each (node_count, 3).
        dt : Time step [s], > 0.
        fixed_displacements : Displacement of the fixed nodes over the step [m], shape (k, 3) in the order of
            ``fixed_nodes`` (a boundary motion: a Dirichlet condition on those nodes); zero (held) by default.
        compiled : Co-rotation and assembly in one compiled pass into the fixed free-DoF pattern
            (:mod:`refsim.fem.assembly`, default); False: the NumPy path (batched products, then elimination),
            equal to round-off and bit-identical to refsim before the compiled path.
        upper_triangle : A's upper triangle only (``StepSystem.upper_triangle``; compiled path only), for a
            linear solver that reads nothing else (PARDISO); the full matrix by default.
        matrix_free : No A: the system's ``operator`` applies it (:mod:`refsim.fem.corotated_matvec`, the
            fast compliance strategy's free motion by CG).
        """
        if not dt > 0.0:
            raise ValueError(f"dt must be > 0 s, got {dt!r}")
        positions = self._checked_positions(state.positions)
        velocities = np.asarray(state.velocities, dtype=float)
        prescribed = self._prescribed(fixed_displacements)
        if matrix_free:
            from refsim.fem.corotated_matvec import Elements, matrix_free_step

            free_dofs, constrained_dofs = self.free_and_constrained_dofs
            material = self.material
            elements = getattr(self, "_elements", (None, None))
            if elements[0] is not material:  # what the kernels read, made once per material
                elements = (
                    material,
                    Elements(
                        self.tets,
                        self._rest_edges_inverse,
                        self.element_volumes,
                        material.lame_lambda,
                        material.shear_modulus,
                    ),
                )
                self._elements = elements
            return matrix_free_step(
                dof_count=self.dof_count,
                free_dofs=free_dofs,
                constrained_dofs=constrained_dofs,
                positions=positions,
                velocities=velocities,
                elements=elements[1],
                mass_matrix=self.mass_matrix,
                external_forces=self._gravity_forces,
                mass_factor=1.0 / dt**2 + self.rayleigh_mass / dt,
                stiffness_factor=1.0 + self.rayleigh_stiffness / dt,
                dt=dt,
                prescribed=prescribed,
                rest_matrix=lambda: self._rest_effective_stiffness(dt),
            )
        if not compiled:
            if upper_triangle:
                raise ValueError("upper_triangle needs the compiled assembly (compiled=True)")
            rotations = self.element_rotations(positions)
            forces = self.external_forces() - self.internal_forces(positions, rotations)
            matrix = effective_stiffness(
                self.mass_matrix,
                self.tangent_stiffness(rotations),
                dt,
                rayleigh_mass=self.rayleigh_mass,
                rayleigh_stiffness=self.rayleigh_stiffness,
            )
            rhs = forces.ravel() + (self.mass_matrix @ velocities.ravel()) / dt
            return StepSystem.from_matrices(
                matrix,
                rhs,
                self.fixed_dofs,
                prescribed,
                group_rotations=lambda: self.node_rotations(rotations),
                rest_matrix=lambda: self._rest_effective_stiffness(dt),
            )
        pattern = self.free_pattern
        data, coupling_data, internal, rotations = assemble_free_system(
            pattern,
            positions,
            self.tets,
            self._rest_edges_inverse,
            self._centred_rest,
            self._element_stiffness_rows,
            1.0 / dt**2 + self.rayleigh_mass / dt,
            1.0 + self.rayleigh_stiffness / dt,
            upper=upper_triangle,
        )
        rhs = self._gravity_forces - internal + (self.mass_matrix @ velocities.ravel()) / dt
        reduced = rhs[pattern.free_dofs]
        if prescribed is not None and prescribed.size:
            reduced = reduced - pattern.coupling(coupling_data) @ prescribed
        else:
            prescribed = np.zeros(pattern.constrained_dofs.size)
        return StepSystem(
            self.dof_count,
            pattern.free_dofs,
            pattern.constrained_dofs,
            pattern.upper_matrix(data) if upper_triangle else pattern.matrix(data),
            reduced,
            prescribed,
            group_rotations=lambda: self.node_rotations(rotations),
            rest_matrix=lambda: self._rest_effective_stiffness(dt),
            upper_triangle=upper_triangle,
        )

    @property
    def free_and_constrained_dofs(self) -> tuple[np.ndarray, np.ndarray]:
        """The free DoFs and the constrained (fixed) DoFs, sorted, int64 (the arrays of :attr:`free_pattern`
        when it is built; else computed once, without the pattern, which a matrix-free step never reads)."""
        if hasattr(self, "_free_pattern"):
            return self._free_pattern.free_dofs, self._free_pattern.constrained_dofs
        if not hasattr(self, "_free_and_constrained"):
            constrained = np.asarray(self.fixed_dofs, dtype=np.int64)
            self._free_and_constrained = (np.setdiff1d(np.arange(self.dof_count), constrained), constrained)
        return self._free_and_constrained

    @property
    def free_pattern(self) -> FreePattern:
        """The fixed CSR patterns of A_ff and A_fc (built on first use)."""
        if not hasattr(self, "_free_pattern"):
            self._free_pattern = FreePattern(self._pattern, self._scatter, self.fixed_dofs, self.mass_matrix)
        return self._free_pattern

    def _prescribed(self, fixed_displacements: np.ndarray | None) -> np.ndarray | None:
        if fixed_displacements is None:
            return None
        fixed_displacements = np.asarray(fixed_displacements, dtype=float)
        if fixed_displacements.shape != (self.fixed_nodes.size, 3) or not np.all(
            np.isfinite(fixed_displacements)
        ):
            raise ValueError(
                f"fixed_displacements must be finite, of shape ({self.fixed_nodes.size}, 3) [m] (one row per "
                f"fixed "
                f"node, in the order of fixed_nodes), got shape {fixed_displacements.shape}"
            )
        return fixed_displacements.ravel()  # fixed_dofs are node-major over the sorted fixed nodes

    def rest_system(self, dt: float) -> StepSystem:
        """The step system at rest for a time step ``dt`` [s]: no load, no motion, identity rotations, A at
        the rest shape behind ``rest_matrix``, no matrix assembled. What a compliance strategy that keeps the
        rest matrix's factor for the run prepares from before the first step (``BodyCompliance.prepare``)."""
        free_dofs, constrained_dofs = self.free_and_constrained_dofs
        return StepSystem(
            self.dof_count,
            free_dofs,
            constrained_dofs,
            None,
            np.zeros(free_dofs.size),
            np.zeros(constrained_dofs.size),
            group_rotations=lambda: np.broadcast_to(np.eye(3), (self.node_count, 3, 3)),
            rest_matrix=lambda: self._rest_effective_stiffness(dt),
        )

    def _rest_effective_stiffness(self, dt: float) -> sp.csr_matrix:
        """A at the rest shape on the free DoFs (the precomputed strategy's C₀ = A₀⁻¹)."""
        matrix = effective_stiffness(
            self.mass_matrix,
            self.rest_stiffness,
            dt,
            rayleigh_mass=self.rayleigh_mass,
            rayleigh_stiffness=self.rayleigh_stiffness,
        )
        free = np.setdiff1d(np.arange(self.dof_count), self.fixed_dofs)
        reduced = matrix[free][:, free].tocsr()
        reduced.sort_indices()
        return reduced

    def node_rotations(self, rotations: np.ndarray) -> np.ndarray:
        """One rotation per node: the polar rotation of the sum of the rotations of its tets, shape
        (node_count, 3, 3).

        Parameters
        ----------
        rotations : Element rotations, shape (tet_count, 3, 3).
        """
        rotations = self._checked_rotations(rotations)
        if not hasattr(self, "_incidence"):
            tet_count = self.tet_count
            self._incidence = sp.csr_matrix(
                (np.ones(4 * tet_count), (self.tets.ravel(), np.repeat(np.arange(tet_count), 4))),
                shape=(self.node_count, tet_count),
            )
        summed = (self._incidence @ rotations.reshape(self.tet_count, 9)).reshape(self.node_count, 3, 3)
        return polar_rotation(summed)

    def free_motion(
        self,
        state: TissueState,
        dt: float,
        *,
        fixed_displacements: np.ndarray | None = None,
        compliance: BodyCompliance | None = None,
    ) -> tuple[np.ndarray, np.ndarray, StepCompliance]:
        """Free motion: one Newton step of implicit Euler without constraint forces.

        Solves A Δx = f_ext − f_int(x₀) + (M/dt) v₀ (see :mod:`refsim.fem.integration`) with the co-rotational
        tangent at x₀, through a compliance strategy; x_free = x₀ + Δx, v_free = Δx / dt. The constraint
        correction is then ``x = x_free + step.correction(H, λ)`` and ``v = (x − x₀)/dt``.

        Parameters
        ----------
        state : Positions x₀ [m] and velocities v₀ [m/s] at the start of the step, each (node_count, 3).
        dt : Time step [s].
        fixed_displacements : Displacement of the fixed nodes over the step [m], shape (k, 3) in the order of
            ``fixed_nodes``; zero (held in place) by default. The fixed nodes end the step exactly there.
        compliance : A strategy bound to this tissue for the run (``Exact().bind()``,
            ``Refreshed(...).bind()``, …, :mod:`refsim.fem.compliance`); a fresh exact one (factorised now) by
            default.

        Returns
        -------
        free_positions : x_free [m], shape (node_count, 3).
        free_velocities : v_free [m/s], shape (node_count, 3).
        step : The step's compliance: ``delassus(H)``, ``correction(H, λ)``, and ``compliance(H)`` → (W,
        A⁻¹Hᵀ).
        """
        positions = self._checked_positions(state.positions)
        if compliance is None:
            compliance = Exact().bind()
        # A's upper triangle is all a strategy reads whose only use of it is PARDISO's factorisation
        upper = getattr(compliance, "matrix_storage", "full") == "upper"
        with hot_path_threads():
            system = self.assemble_step(
                state,
                dt,
                fixed_displacements=fixed_displacements,
                upper_triangle=upper,
                matrix_free=getattr(compliance, "matrix_free", False),
            )
            step = compliance.step(system)
        displacement = step.free_displacement.reshape(self.node_count, 3)
        return positions + displacement, displacement / dt, step

    # ---------------------------------------------------------------- statics

    def solve_static(
        self,
        forces: np.ndarray | None = None,
        *,
        positions: np.ndarray | None = None,
        constrained_dofs: np.ndarray | None = None,
        tolerance: float = 1e-10,
        max_iterations: int = 50,
    ) -> StaticEquilibrium:
        """Static equilibrium f_int(x) = f_ext by Newton iterations with the co-rotational tangent.

        Parameters
        ----------
        forces : External forces [N], shape (node_count, 3); gravity (:meth:`external_forces`) by default.
        positions : Initial guess [m], shape (node_count, 3), rest positions by default. Its values on the
            constrained DoFs are kept: that is how displacements are prescribed.
        constrained_dofs : DoFs held at their value in ``positions``, shape (c,); ``fixed_dofs`` by default.
        tolerance : Relative residual ‖(f_ext − f_int)_free‖ / max(‖f_ext‖, ‖f_int‖) to reach.
        max_iterations : Newton iterations allowed, ≥ 1.

        Returns
        -------
        The equilibrium positions with the iteration count, the final residual and whether it converged
        (residual below ``tolerance``, or a Newton update at the round-off of the positions, 16 ε max|x|,
        which is as far as a position-based model can go). The tangent omits ∂R/∂x, so convergence is
        linear (fast for small strains), quadratic only near rest.
        """
        external = self.external_forces() if forces is None else np.asarray(forces, dtype=float)
        if external.shape != (self.node_count, 3):
            raise ValueError(f"forces must have shape ({self.node_count}, 3), got {external.shape}")
        x = (self.rest_positions if positions is None else self._checked_positions(positions)).copy().ravel()
        constrained = self.fixed_dofs if constrained_dofs is None else np.unique(np.asarray(constrained_dofs))
        if constrained.size and (constrained[0] < 0 or constrained[-1] >= self.dof_count):
            raise ValueError(f"constrained_dofs must lie in [0, {self.dof_count})")
        if max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {max_iterations!r}")
        free = np.setdiff1d(np.arange(self.dof_count), constrained)

        def imbalance_at(x_flat: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
            current = x_flat.reshape(self.node_count, 3)
            rotations = self.element_rotations(current)
            internal = self.internal_forces(current, rotations).ravel()
            imbalance = external.ravel() - internal
            scale = max(np.linalg.norm(external), np.linalg.norm(internal), np.finfo(float).tiny)
            return rotations, imbalance, float(np.linalg.norm(imbalance[free]) / scale)

        rotations, imbalance, residual = imbalance_at(x)
        iteration, at_roundoff = 0, False
        while residual > tolerance and iteration < max_iterations and not at_roundoff:
            tangent = self.tangent_stiffness(rotations)[free][:, free].tocsc()
            update = spla.spsolve(tangent, imbalance[free])
            x[free] += update
            iteration += 1
            # An update at the round-off of the positions: the residual cannot decrease further.
            at_roundoff = bool(np.abs(update).max() <= _ROUNDOFF_STEP * EPS * np.abs(x).max())
            rotations, imbalance, residual = imbalance_at(x)
        converged = residual <= tolerance or at_roundoff
        if not converged:
            logger.warning("static solve: residual %.3e after %d iterations", residual, iteration)
        return StaticEquilibrium(x.reshape(self.node_count, 3), iteration, residual, converged)

    # ---------------------------------------------------------------- assembly

    def _build_pattern(self) -> None:
        """Sparsity pattern of the stiffness and the scatter of element block entries into its ``data``.

        Entries are taken in the order of ``blocks.ravel()`` for blocks of shape (tet_count, 4, 4, 3, 3):
        entry (e, a, b, i, j) sits at row 3·tets[e, a] + i, column 3·tets[e, b] + j.
        """
        dofs = (3 * self.tets[:, :, None] + _LOCAL_COMPONENTS).astype(np.int64)  # (tet_count, 4, 3)
        rows = np.broadcast_to(dofs[:, :, None, :, None], (self.tet_count, 4, 4, 3, 3)).ravel()
        cols = np.broadcast_to(dofs[:, None, :, None, :], (self.tet_count, 4, 4, 3, 3)).ravel()
        keys = rows * self.dof_count + cols
        unique_keys, scatter = np.unique(keys, return_inverse=True)
        pattern_rows = unique_keys // self.dof_count
        indptr = np.zeros(self.dof_count + 1, dtype=np.int64)
        np.cumsum(np.bincount(pattern_rows, minlength=self.dof_count), out=indptr[1:])
        self._pattern = sp.csr_matrix(
            (np.zeros(unique_keys.size), unique_keys % self.dof_count, indptr),
            shape=(self.dof_count, self.dof_count),
        )
        self._scatter = scatter.ravel()

    def _assemble(self, entries: np.ndarray) -> sp.csr_matrix:
        """Sum element block entries (``_build_pattern`` order) into a new CSR matrix on the fixed pattern."""
        data = np.bincount(self._scatter, weights=entries, minlength=self._pattern.nnz)
        return sp.csr_matrix(
            (data, self._pattern.indices, self._pattern.indptr), shape=self._pattern.shape, copy=False
        )

    # ---------------------------------------------------------------- input checks

    def _checked_positions(self, positions: np.ndarray) -> np.ndarray:
        positions = np.asarray(positions, dtype=float)
        if positions.shape != (self.node_count, 3):
            raise ValueError(f"positions must have shape ({self.node_count}, 3), got {positions.shape}")
        return positions

    def _checked_rotations(self, rotations: np.ndarray) -> np.ndarray:
        rotations = np.asarray(rotations, dtype=float)
        if rotations.shape != (self.tet_count, 3, 3):
            raise ValueError(f"rotations must have shape ({self.tet_count}, 3, 3), got {rotations.shape}")
        return rotations


def _validated_mesh(rest_positions: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Check shapes, finiteness, index range and non-degenerate tets; return float and int64 copies."""
    rest_positions = np.array(rest_positions, dtype=float)
    if rest_positions.ndim != 2 or rest_positions.shape[1] != 3 or rest_positions.shape[0] < 4:
        raise ValueError(f"rest_positions must have shape (node_count >= 4, 3), got {rest_positions.shape}")
    bad = ~np.all(np.isfinite(rest_positions), axis=1)
    if np.any(bad):
        raise ValueError(
            f"rest_positions has non-finite coordinates at nodes {np.flatnonzero(bad)[:10].tolist()}"
        )
    tets_in = np.asarray(tets)
    if tets_in.ndim != 2 or tets_in.shape[1] != 4 or tets_in.shape[0] == 0:
        raise ValueError(f"tets must have shape (tet_count >= 1, 4), got {tets_in.shape}")
    if not np.issubdtype(tets_in.dtype, np.integer):
        raise ValueError(f"tets must hold integer node indices, got dtype {tets_in.dtype}")
    tets = tets_in.astype(np.int64)
    node_count = rest_positions.shape[0]
    out_of_range = np.any((tets < 0) | (tets >= node_count), axis=1)
    if np.any(out_of_range):
        raise ValueError(
            f"tets {np.flatnonzero(out_of_range)[:10].tolist()} have node indices outside [0, {node_count})"
        )
    degenerate = degenerate_tets(rest_positions, tets)  # the one threshold, refsim.mesh.validation
    if degenerate.size:
        raise ValueError(
            f"tets {degenerate[:10].tolist()} have zero volume "
            f"(|V| <= {DEGENERATE_VOLUME_RATIO:g} * longest edge^3)"
        )
    return rest_positions, tets


def _read_only(array: np.ndarray) -> np.ndarray:
    """A read-only view, so the static model cannot be changed through its attributes."""
    view = np.asarray(array).view()
    view.flags.writeable = False
    return view
