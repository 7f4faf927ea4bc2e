"""Implicit Euler with one Newton step, written on the effective stiffness.

Conventions used by the whole project (DESIGN.md, "One time step"):

One step of implicit Euler, M (v₁ − v₀)/dt = f(x₁, v₁), with f linearised once about x₀
(f ≈ f_ext − f_int(x₀) − K Δx − C v₁, Δx = x₁ − x₀ = dt v₁), gives

    A Δx = f_ext − f_int(x₀) + (M/dt) v₀ + Hᵀ λ,      A = M/dt² + C/dt + K   [N/m],

with C = rayleigh_mass · M + rayleigh_stiffness · K (Rayleigh damping). A is an *effective stiffness*, so that
the compliance W = H A⁻¹ Hᵀ is in [m/N] (or [rad/N·m] on rotational DoFs), multipliers λ are forces [N], and
the constraint correction is Δx = Δx_free + A⁻¹ Hᵀ λ [m], v₁ = Δx / dt.

Every deformable body (the tissue, a flexible needle) assembles A and the right-hand side at each step into a
:class:`refsim.fem.compliance.StepSystem`, with its fixed DoFs (Δx = 0) and prescribed DoFs (Δx given, e.g. a
needle base driven by a trajectory) eliminated; the body's compliance strategy (:mod:`refsim.fem.compliance`)
then gives the free motion, W and the correction, which are zero on those DoFs but for the prescribed Δx.
"""

from __future__ import annotations

import scipy.sparse as sp

__all__ = ["effective_stiffness"]


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
