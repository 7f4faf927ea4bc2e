"""Implicit Euler with one Newton step, written on the effective stiffness.

Conventions used by the whole project (DESIGN.md, "One time step"):

One step of implicit Euler, M (v₁ − v₀)/dt = f(x₁, v₁), with f linearised once about x₀
(f ≈ f_ext − f_int(x₀) − K Δx − C v₁, Δx = x₁ − x₀ = dt v₁), gives

    A Δx = f_ext − f_int(x₀) + (M/dt) v₀ + Hᵀ λ,      A = M/dt² + C/dt + K   [N/m],

with C = rayleigh_mass · M + rayleigh_stiffness · K (Rayleigh damping). A is an *effective stiffness*, so that
the compliance W = H A⁻¹ Hᵀ is in [m/N] (or [rad/N·m] on rotational DoFs), multipliers λ are forces [N], and
the constraint correction is Δx = Δx_free + A⁻¹ Hᵀ λ [m], v₁ = Δx / dt.

Fixed DoFs (Δx = 0) and prescribed DoFs (Δx given, e.g. a needle base driven by a trajectory) are eliminated
from the factorised system; the solution is zero on both in `solve`, the response to a load only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = ["ImplicitEulerSystem", "effective_stiffness"]


def effective_stiffness(
    mass: sp.spmatrix,
    stiffness: sp.spmatrix,
    dt: float,
    *,
    rayleigh_mass: float = 0.0,
    rayleigh_stiffness: float = 0.0,
) -> sp.csr_matrix:
    """Effective stiffness A = M/dt² + C/dt + K with Rayleigh damping C = α M + β K.

    Parameters
    ----------
    mass : Mass matrix M [kg] (or [kg·m²] on rotational DoFs), shape (dof_count, dof_count).
    stiffness : Tangent stiffness K [N/m], shape (dof_count, dof_count).
    dt : Time step [s], > 0.
    rayleigh_mass : α [1/s], ≥ 0.
    rayleigh_stiffness : β [s], ≥ 0.

    Returns
    -------
    A [N/m], sparse CSR, shape (dof_count, dof_count).
    """
    if not dt > 0.0:
        raise ValueError(f"dt must be > 0 s, got {dt!r}")
    if rayleigh_mass < 0.0 or rayleigh_stiffness < 0.0:
        raise ValueError(
            f"Rayleigh coefficients must be >= 0, got rayleigh_mass={rayleigh_mass!r}, "
            f"rayleigh_stiffness={rayleigh_stiffness!r}"
        )
    mass_factor = 1.0 / dt**2 + rayleigh_mass / dt
    stiffness_factor = 1.0 + rayleigh_stiffness / dt
    return (mass_factor * sp.csr_matrix(mass) + stiffness_factor * sp.csr_matrix(stiffness)).tocsr()


@dataclass(eq=False)
class ImplicitEulerSystem:
    """The factorised effective stiffness of one body at one time step.

    Build it with :meth:`build`; then :meth:`free_displacement` gives the free motion and :meth:`solve`
    applies A⁻¹ to any number of right-hand sides (one per constraint row for the compliance,
    :meth:`compliance`).

    Attributes
    ----------
    matrix : A [N/m], sparse CSR, shape (dof_count, dof_count), before elimination.
    mass : M, sparse CSR, shape (dof_count, dof_count).
    dt : Time step [s].
    constrained_dofs : Fixed or prescribed DoF indices, sorted, shape (c,).
    """

    matrix: sp.csr_matrix
    mass: sp.csr_matrix
    dt: float
    constrained_dofs: np.ndarray
    _free: np.ndarray = field(repr=False)
    _factor: object = field(repr=False)
    _coupling: sp.csr_matrix = field(repr=False)

    @classmethod
    def build(
        cls,
        mass: sp.spmatrix,
        stiffness: sp.spmatrix,
        dt: float,
        *,
        rayleigh_mass: float = 0.0,
        rayleigh_stiffness: float = 0.0,
        constrained_dofs: np.ndarray | None = None,
    ) -> ImplicitEulerSystem:
        """Assemble A = M/dt² + C/dt + K, eliminate the constrained DoFs and factorise (sparse LU).

        Parameters
        ----------
        mass : M [kg], shape (dof_count, dof_count).
        stiffness : Tangent stiffness K [N/m] at the current configuration, shape (dof_count, dof_count).
        dt : Time step [s].
        rayleigh_mass, rayleigh_stiffness : Rayleigh damping coefficients α [1/s] and β [s].
        constrained_dofs : Indices of fixed or prescribed DoFs, shape (c,); none by default.
        """
        matrix = effective_stiffness(
            mass, stiffness, dt, rayleigh_mass=rayleigh_mass, rayleigh_stiffness=rayleigh_stiffness
        )
        dof_count = matrix.shape[0]
        constrained = np.unique(
            np.asarray([] if constrained_dofs is None else constrained_dofs, dtype=np.int64)
        )
        if constrained.size and (constrained[0] < 0 or constrained[-1] >= dof_count):
            raise ValueError(
                f"constrained_dofs must lie in [0, {dof_count}), got {constrained.min()}..{constrained.max()}"
            )
        free = np.setdiff1d(np.arange(dof_count), constrained)
        if free.size == 0:
            raise ValueError("every DoF is constrained: nothing to solve")
        reduced = matrix[free][:, free].tocsc()
        # A is symmetric positive definite: no pivoting off the diagonal (SuperLU's symmetric mode), which
        # also halves the cost of each solve against the default threshold pivoting (measured on the paper's
        # cube).
        factor = spla.splu(
            reduced, permc_spec="COLAMD", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
        )
        coupling = matrix[free][:, constrained].tocsr()
        return cls(matrix, sp.csr_matrix(mass), float(dt), constrained, free, factor, coupling)

    @property
    def dof_count(self) -> int:
        """Number of DoFs, constrained ones included."""
        return self.matrix.shape[0]

    @property
    def free_dofs(self) -> np.ndarray:
        """Indices of the unconstrained DoFs, shape (dof_count − c,)."""
        return self._free

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Apply A⁻¹ on the unconstrained DoFs; zero on constrained ones.

        Parameters
        ----------
        rhs : Forces [N], shape (dof_count,) or (dof_count, k).

        Returns
        -------
        Displacements [m], same shape as ``rhs``.
        """
        rhs = np.asarray(rhs, dtype=float)
        out = np.zeros_like(rhs)
        if rhs.ndim == 2 and rhs.shape[1] == 0:
            return out
        out[self._free] = self._factor.solve(np.ascontiguousarray(rhs[self._free]))
        return out

    def free_displacement(
        self,
        forces: np.ndarray,
        velocities: np.ndarray,
        prescribed_displacements: np.ndarray | None = None,
    ) -> np.ndarray:
        """Free motion Δx_free of one Newton step of implicit Euler (no constraint force).

        Solves A Δx = forces + (M/dt) v₀ on the free DoFs with Δx given on the constrained ones.

        Parameters
        ----------
        forces : f_ext − f_int(x₀) [N], shape (dof_count,).
        velocities : v₀ [m/s], shape (dof_count,).
        prescribed_displacements : Δx on the constrained DoFs [m], shape (c,), in the order of
            ``constrained_dofs``; zero (fixed) by default.

        Returns
        -------
        Δx_free [m], shape (dof_count,).
        """
        rhs = np.asarray(forces, dtype=float) + (self.mass @ np.asarray(velocities, dtype=float)) / self.dt
        out = np.zeros(self.dof_count)
        reduced = rhs[self._free]
        if prescribed_displacements is not None and self.constrained_dofs.size:
            prescribed = np.asarray(prescribed_displacements, dtype=float)
            if prescribed.shape != self.constrained_dofs.shape:
                raise ValueError(
                    f"prescribed_displacements has shape {prescribed.shape}, expected "
                    f"{self.constrained_dofs.shape}"
                )
            reduced = reduced - self._coupling @ prescribed
            out[self.constrained_dofs] = prescribed
        out[self._free] = self._factor.solve(reduced)
        return out

    def compliance(self, jacobian: sp.spmatrix | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Compliance W = H A⁻¹ Hᵀ [m/N] and the responses A⁻¹ Hᵀ.

        Parameters
        ----------
        jacobian : Constraint rows H, shape (row_count, dof_count).

        Returns
        -------
        compliance : W, dense, shape (row_count, row_count).
        responses : A⁻¹ Hᵀ [m/N], dense, shape (dof_count, row_count); the correction is ``responses @ λ``.
        """
        jacobian = sp.csr_matrix(jacobian)
        row_count = jacobian.shape[0]
        used = np.unique(jacobian.indices)
        if used.size < row_count:
            # Rows touch few DoFs (a constraint point involves the 4 nodes of its tet): solve for the unit
            # loads on those DoFs only, Z = A⁻¹ E_D, then A⁻¹ Hᵀ = Z H_Dᵀ — min(rows, used DoFs) solves
            # instead of rows.
            unit_loads = np.zeros((self.dof_count, used.size))
            unit_loads[used, np.arange(used.size)] = 1.0
            influence = self.solve(unit_loads)
            responses = influence @ jacobian[:, used].T.toarray()
        else:
            responses = self.solve(jacobian.T.toarray())
        compliance = np.asarray(jacobian @ responses)
        return 0.5 * (compliance + compliance.T), responses
