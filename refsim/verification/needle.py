"""Verification of the needle model: cantilevers against closed forms and the elastica, and rigid motions.

Cases (each returns :class:`~refsim.verification.result.CaseResult`):

1. :func:`case_cantilever_small_load`: a tip load small enough that the response is linear; the Timoshenko
   element is exact for a point load, so δ = P L³/(3 E I) + P L/(κ G A) at any element count.
2. :func:`case_cantilever_elastica`: tip loads P L²/(E I) = 1, 3, 10 solved statically to convergence (full
   Newton with the consistent tangent, load steps), against the elastica solved independently as a boundary
   value problem with ``scipy.integrate.solve_bvp``, in Reissner's form with the needle's E A and κ G A (the
   inextensible Euler elastica is also available and checked against Bisshopp & Drucker 1945 in the tests).
   Tolerance: twice the Richardson estimate of the discretisation error from n/2 and n elements (second
   order, asserted by a fitted rate in the tests).
3. :func:`case_rigid_motions`: a translation and a 90° rotation of the rest needle give zero internal forces
   to round-off.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.integrate
import scipy.sparse.linalg as spla

from refsim.fem.needle import NeedleModel
from refsim.geometry.rotations import rotation_matrix
from refsim.verification.result import CaseResult

__all__ = [
    "CantileverResult",
    "needle_cantilever",
    "elastica_tip_displacement",
    "case_cantilever_small_load",
    "case_cantilever_elastica",
    "case_rigid_motions",
    "CASES",
]

logger = logging.getLogger(__name__)

# Any density: the cantilever is static.
_DENSITY = 7850.0
# Newton stops when ‖r‖ ≤ tolerance · ‖f_ext‖ (free DoFs, forces and moments/length scaled together).
_NEWTON_TOLERANCE = 1e-10
_NEWTON_MAX_ITERATIONS = 25
_MAX_STEP_HALVINGS = 8


@dataclass(frozen=True, kw_only=True)
class CantileverResult:
    """Static solution of a cantilever needle under a dead tip load.

    Attributes
    ----------
    tip_displacement : Tip displacement [m], shape (3,).
    positions : Node positions [m], shape (node_count, 3).
    frames : Node frames, shape (node_count, 3, 3).
    newton_iterations : Total Newton iterations over all load steps.
    load_steps : Number of load steps actually taken (after any halving).
    residual : Final ‖f_ext − f_int‖ on the free DoFs divided by ‖f_ext‖ (moments divided by the length);
        Newton stops at 1e-10 or at the round-off floor ≈ 10 ε L (E A/l₀) √(node_count) / ‖f_ext‖.
    converged : True if every load step converged.
    """

    tip_displacement: np.ndarray
    positions: np.ndarray
    frames: np.ndarray
    newton_iterations: int
    load_steps: int
    residual: float
    converged: bool


def _scaled_norm(vector: np.ndarray, length: float) -> float:
    """Norm with moments [N·m] divided by the length [m], so forces and moments compare."""
    per_node = vector.reshape(-1, 6)
    return float(np.sqrt(np.sum(per_node[:, :3] ** 2) + np.sum((per_node[:, 3:] / length) ** 2)))


def _round_off_floor(model: NeedleModel) -> float:
    """Residual [N] below which Newton cannot go: chord lengths of nodes at distance ≈ L carry a round-off of
    ε L, giving axial forces ε L E A/l₀ per node; summed in a norm over the nodes and given a factor 10."""
    s = model.section
    axial = s.youngs_modulus * s.area / model.element_length
    return 10.0 * np.finfo(float).eps * model.length * axial * np.sqrt(model.node_count)


def _newton(model, positions, frames, external, free, scale):
    """Full Newton on f_int(x) = f_ext with the consistent tangent.

    Stops when ‖r‖ ≤ 1e-10 ‖f_ext‖, or, after at least one iteration, when ‖r‖ reaches the round-off floor.
    Returns (positions, frames, iterations, ‖r‖/‖f_ext‖, converged).
    """
    length = model.length
    floor = _round_off_floor(model)
    error = np.inf
    for iteration in range(_NEWTON_MAX_ITERATIONS + 1):
        residual = external - model.internal_forces(positions, frames)
        residual[model.base_dofs] = 0.0
        norm = _scaled_norm(residual, length)
        error = norm / scale
        if not np.isfinite(error):
            return positions, frames, iteration, error, False
        if error <= _NEWTON_TOLERANCE or (iteration >= 1 and norm <= floor):
            return positions, frames, iteration, error, True
        if iteration == _NEWTON_MAX_ITERATIONS:
            break
        tangent = model.tangent_stiffness(positions, frames, kind="consistent")
        delta = np.zeros(model.dof_count)
        delta[free] = spla.spsolve(tangent[free][:, free].tocsc(), residual[free])
        positions, frames = model.apply_increment(positions, frames, delta)
    return positions, frames, _NEWTON_MAX_ITERATIONS, error, False


def needle_cantilever(
    tip_force,
    *,
    length: float,
    radius: float,
    youngs_modulus: float,
    poisson_ratio: float,
    element_count: int,
    load_steps: int | None = None,
) -> CantileverResult:
    """Static cantilever: needle along +x clamped at the origin, dead force at the tip, solved by Newton.

    Parameters
    ----------
    tip_force : Tip force [N], shape (3,).
    length : Needle length [m].
    radius : Section radius [m].
    youngs_modulus : E [Pa].
    poisson_ratio : ν [-].
    element_count : Number of beam elements.
    load_steps : Equal load increments; by default max(1, ceil(P L²/(E I) / 2)). A step that fails to
        converge is halved (up to 8 times).

    Returns
    -------
    The solution, with ``tip_displacement`` [m], shape (3,).
    """
    force = np.asarray(tip_force, dtype=float)
    if force.shape != (3,) or not np.all(np.isfinite(force)):
        raise ValueError(f"tip_force must be 3 finite numbers [N], got {tip_force!r}")
    model = NeedleModel(
        length=length,
        radius=radius,
        element_count=element_count,
        youngs_modulus=youngs_modulus,
        poisson_ratio=poisson_ratio,
        density=_DENSITY,
        direction=np.array([1.0, 0.0, 0.0]),
        up=np.array([0.0, 1.0, 0.0]),
    )
    stiffness_ratio = (
        np.linalg.norm(force) * model.length**2 / (model.youngs_modulus * model.section.second_moment)
    )
    if load_steps is None:
        load_steps = max(1, int(np.ceil(stiffness_ratio / 2.0)))
    if isinstance(load_steps, bool) or not isinstance(load_steps, (int, np.integer)) or load_steps < 1:
        raise ValueError(f"load_steps must be an integer >= 1, got {load_steps!r}")
    positions, frames = model.rest_state()
    free = np.setdiff1d(np.arange(model.dof_count), model.base_dofs)
    external = np.zeros(model.dof_count)
    scale = max(np.linalg.norm(force), np.finfo(float).tiny)
    iterations, steps_taken, converged = 0, 0, True
    residual = 0.0
    done, increment, halvings = 0.0, 1.0 / load_steps, 0
    while done < 1.0 - 1e-12:
        target = min(1.0, done + increment)
        external[model.tip_dofs[:3]] = target * force
        trial = _newton(model, positions, frames, external, free, scale)
        iterations += trial[2]
        if trial[3]:
            positions, frames, residual = trial[0], trial[1], trial[3]
            done, steps_taken = target, steps_taken + 1
        elif halvings < _MAX_STEP_HALVINGS:
            increment, halvings = 0.5 * increment, halvings + 1
            logger.debug("cantilever: load step to %.4g failed, halving to %.4g", target, increment)
        else:
            positions, frames, residual, converged = trial[0], trial[1], trial[3], False
            logger.warning("cantilever: Newton did not converge at load fraction %.4g", target)
            break
    rest_positions, _ = model.rest_state()
    return CantileverResult(
        tip_displacement=positions[-1] - rest_positions[-1],
        positions=positions,
        frames=frames,
        newton_iterations=iterations,
        load_steps=steps_taken,
        residual=float(residual),
        converged=converged,
    )


def elastica_tip_displacement(
    load_parameter: float,
    length: float = 1.0,
    *,
    axial_compliance: float = 0.0,
    shear_compliance: float = 0.0,
) -> np.ndarray:
    """Tip displacement of the elastica cantilever under a dead transverse tip load, by a BVP.

    Clamped at the origin along +x, load −P ŷ at the tip. In the arc length s ∈ [0, 1] (units of L), with θ
    the cross-section angle, m = M L/(E I) the bending moment and n = (0, −k) the dimensionless force
    transmitted through every section (k = P L²/(E I)):

        θ' = m,   m' = −(r' × n),   r' = (1 + c_a N) t + c_s V t⊥,   N = n·t, V = n·t⊥,

    t = (cos θ, sin θ), t⊥ = (−sin θ, cos θ), θ(0) = 0, m(1) = 0, r(0) = 0. With c_a = c_s = 0 this is the
    inextensible Euler elastica E I θ'' = P cos θ; c_a = E I/(E A L²) and c_s = E I/(κ G A L²) give Reissner's
    extensible, shearable rod, the continuum model that the Timoshenko elements discretise. Solved with
    ``scipy.integrate.solve_bvp`` (tolerance 1e-10) by continuation in k from the linear solution.

    Parameters
    ----------
    load_parameter : k = P L²/(E I) [-], ≥ 0.
    length : L [m].
    axial_compliance : c_a [-], ≥ 0.
    shear_compliance : c_s [-], ≥ 0.

    Returns
    -------
    (Δx, Δy) of the tip [m], shape (2,).
    """
    target = float(load_parameter)
    if not (np.isfinite(target) and target >= 0.0):
        raise ValueError(f"load_parameter must be finite and >= 0, got {load_parameter!r}")

    def make_rhs(k):
        def rhs(s, y):
            theta, moment = y[0], y[1]
            cos, sin = np.cos(theta), np.sin(theta)
            axial, shear = -k * sin, -k * cos  # N = n·t, V = n·t⊥ with n = (0, −k)
            dx = (1.0 + axial_compliance * axial) * cos - shear_compliance * shear * sin
            dy = (1.0 + axial_compliance * axial) * sin + shear_compliance * shear * cos
            return np.vstack([moment, k * dx, dx, dy])  # m' = −(x' n_y − y' n_x) = k x'

        return rhs

    def bc(ya, yb):
        return np.array([ya[0], yb[1], ya[2], ya[3]])

    mesh = np.linspace(0.0, 1.0, 201)
    k0 = min(target, 0.5)
    guess = np.vstack([-k0 * (mesh - mesh**2 / 2), -k0 * (1 - mesh), mesh, -k0 * (mesh**2 / 2 - mesh**3 / 6)])
    solution = None
    for k in np.unique(np.concatenate([np.arange(k0, target, 0.5), [target]])):
        solution = scipy.integrate.solve_bvp(make_rhs(k), bc, mesh, guess, tol=1e-10, max_nodes=100000)
        if not solution.success:
            raise RuntimeError(f"elastica BVP did not converge for P L²/(E I) = {k}: {solution.message}")
        mesh, guess = solution.x, solution.y
    tip = solution.sol(1.0)
    return length * np.array([tip[2] - 1.0, tip[3]])


# Slender needle for the elastica cases (r/L = 1/200): extension and shear change the tip deflection by about
# 1e-4 L at P L²/(E I) = 1; the reference includes them (Reissner's rod), and the inextensible Euler elastica
# is reported alongside.
_ELASTICA = dict(length=0.2, radius=1e-3, youngs_modulus=2e11, poisson_ratio=0.3)


def _section(radius, youngs_modulus, poisson_ratio):
    model = NeedleModel(
        length=1.0,
        radius=radius,
        element_count=1,
        youngs_modulus=youngs_modulus,
        poisson_ratio=poisson_ratio,
        density=_DENSITY,
    )
    return model.section


def case_cantilever_small_load(element_count: int = 4) -> CaseResult:
    """Cantilever under a small tip load against δ = P L³/(3 E I) + P L/(κ G A).

    The load makes δ/L = 1e-6, so the geometric non-linearity is O((δ/L)²) = 1e-12 relative; the tolerance
    1e-8 covers the Newton tolerance (1e-10) amplified by the condition number of the stiffness.
    """
    length, radius, e, nu = 0.12, 5e-4, 2e11, 0.3
    s = _section(radius, e, nu)
    bending = length**3 / (3 * e * s.second_moment)
    shear = length / (s.shear_coefficient * s.shear_modulus * s.area)
    force = 1e-6 * length / (bending + shear)
    expected = force * (bending + shear)
    result = needle_cantilever(
        np.array([0.0, -force, 0.0]),
        length=length,
        radius=radius,
        youngs_modulus=e,
        poisson_ratio=nu,
        element_count=element_count,
    )
    computed = float(-result.tip_displacement[1])
    return CaseResult(
        name=f"needle cantilever, small load ({element_count} elements)",
        reference="δ = P L³/(3 E I) + P L/(κ G A), κ = 6(1+ν)/(7+6ν) (Cowper 1966)",
        expected=expected,
        computed=computed,
        error=abs(computed - expected) / expected,
        tolerance=1e-8,
        unit="m",
    )


def elastica_convergence(load_parameter: float, element_counts=(8, 16, 32)) -> dict:
    """Tip displacements of the needle under P L²/(E I) = k for several element counts, and the references.

    Returns
    -------
    Dictionary: ``element_counts`` (c,); ``tip`` (c, 2) [m] (Δx, Δy); ``reference`` (2,) [m], Reissner's
    extensible shearable elastica with the needle's E A and κ G A; ``euler_reference`` (2,) [m], the
    inextensible Euler elastica; ``errors`` (c,), ‖Δtip − reference‖ / L; ``force`` [N];
    ``newton_iterations`` (c,).
    """
    p = _ELASTICA
    s = _section(p["radius"], p["youngs_modulus"], p["poisson_ratio"])
    bending = p["youngs_modulus"] * s.second_moment
    force = load_parameter * bending / p["length"] ** 2
    reference = elastica_tip_displacement(
        load_parameter,
        p["length"],
        axial_compliance=bending / (p["youngs_modulus"] * s.area * p["length"] ** 2),
        shear_compliance=bending / (s.shear_coefficient * s.shear_modulus * s.area * p["length"] ** 2),
    )
    tips, iterations = [], []
    for count in element_counts:
        result = needle_cantilever(np.array([0.0, -force, 0.0]), element_count=count, **p)
        if not result.converged:
            raise RuntimeError(
                f"cantilever Newton did not converge (P L²/EI = {load_parameter}, n = {count})"
            )
        tips.append(result.tip_displacement[:2])
        iterations.append(result.newton_iterations)
    tips = np.array(tips)
    return {
        "element_counts": np.array(element_counts),
        "tip": tips,
        "reference": reference,
        "euler_reference": elastica_tip_displacement(load_parameter, p["length"]),
        "errors": np.linalg.norm(tips - reference, axis=1) / p["length"],
        "force": force,
        "newton_iterations": np.array(iterations),
    }


def case_cantilever_elastica(load_parameters=(1.0, 3.0, 10.0), element_count: int = 32) -> list[CaseResult]:
    """Large tip loads against the elastica BVP (Reissner's rod: extension and shear included), one per load.

    Error: ‖Δtip − Δtip_ref‖ / L. Tolerance: 2 × the Richardson estimate ‖u_n − u_{n/2}‖/(2² − 1) / L of the
    discretisation error (the co-rotational two-node element converges at second order, asserted in the
    tests), plus the BVP tolerance 1e-10.
    """
    out = []
    for k in load_parameters:
        data = elastica_convergence(k, (element_count // 2, element_count))
        tips = data["tip"]
        richardson = np.linalg.norm(tips[1] - tips[0]) / 3.0 / _ELASTICA["length"]
        out.append(
            CaseResult(
                name=f"needle cantilever, elastica P L²/(E I) = {k:g} ({element_count} elements)",
                reference="Reissner elastica θ'=m, m'=−r'×n, r'=(1+N/EA)t+(V/κGA)t⊥ (scipy solve_bvp); "
                "error ‖Δtip − ref‖/L",
                expected=float(-data["reference"][1]),
                computed=float(-tips[1][1]),
                error=float(data["errors"][1]),
                tolerance=float(2.0 * richardson + 1e-10),
                unit="m",
            )
        )
    return out


def case_rigid_motions() -> list[CaseResult]:
    """A translated and a 90°-rotated rest needle have zero internal forces to round-off.

    Error: max |f| divided by the force scale (E A / l₀) L (moments by E I / l₀), the force that the round-off
    of coordinates of size L produces in a chord length; tolerance 1e3 machine epsilons.
    """
    model = NeedleModel(
        length=0.32,
        radius=8e-3,
        element_count=16,
        youngs_modulus=1e11,
        poisson_ratio=0.4,
        density=_DENSITY,
        direction=np.array([0.3, -0.5, 0.8]),
    )
    positions, frames = model.rest_state()
    s = model.section
    force_scale = s.youngs_modulus * s.area / model.element_length * model.length
    moment_scale = s.youngs_modulus * s.second_moment / model.element_length
    axis = np.array([0.6, 0.0, 0.8])
    rotation = rotation_matrix((np.pi / 2 * axis)[None])[0]
    motions = {
        "translation by (0.1, −0.2, 0.3) m": (positions + np.array([0.1, -0.2, 0.3]), frames),
        "rotation by 90° about (0.6, 0, 0.8)": (positions @ rotation.T, rotation @ frames),
    }
    out = []
    for label, (moved_positions, moved_frames) in motions.items():
        forces = model.internal_forces(moved_positions, moved_frames).reshape(-1, 6)
        error = max(np.abs(forces[:, :3]).max() / force_scale, np.abs(forces[:, 3:]).max() / moment_scale)
        out.append(
            CaseResult(
                name=f"needle rigid motion, {label}",
                reference="f_int = 0 for rigid motions (co-rotational); error in units of (EA/l₀)L, EI/l₀",
                expected=0.0,
                computed=float(error),
                error=float(error),
                tolerance=1e3 * np.finfo(float).eps,
            )
        )
    return out


CASES = (case_cantilever_small_load, case_cantilever_elastica, case_rigid_motions)
