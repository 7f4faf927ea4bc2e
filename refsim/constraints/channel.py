"""The needle's channel in the tissue, beyond the ring coupling's rows (refsim.constraints.coupling): the grip
of the channel's interference (Lamé) and the shaft's Coulomb bound on it, the shaft's stick state, the tip
cutting its way at the channel's end, and the shaft's contact with the surface before the channel opens
(puncture). Derivations and measurements in docs/coupling.md ("Friction on a physical normal force, tip
cutting force, puncture").

Functions of plain arrays, as the rest of ``refsim.constraints``.
"""

from __future__ import annotations

import math

import numpy as np

from refsim.constraints.friction import friction_rows
from refsim.constraints.needle_geometry import needle_rows
from refsim.constraints.rows import (
    NEEDLE,
    PENETRATION,
    SHAFT_CONTACT,
    TIP,
    TISSUE,
    UNILATERAL,
    RowBlock,
    point_rows,
    trusted_block,
)
from refsim.constraints.step_geometry import StepGeometry

__all__ = [
    "interference_pressure",
    "grip_preload",
    "channel_preload",
    "stuck_points",
    "tip_cutting_block",
    "shaft_contact_block",
]


def interference_pressure(
    *,
    shear_modulus: float,
    poisson_ratio: float,
    radius: float,
    interference: float,
    outer_radius: float = math.inf,
) -> float:
    """Contact pressure p [Pa] of an interference fit (Lamé, plane strain, outer surface clamped).

    A channel of radius r − δ_r opened to r by the needle: u_r = A ρ + B/ρ with u_r(r) = δ_r, u_r(R) = 0 gives
    p = −σ_rr(r) = B (2(λ + G)/R² + 2G/r²), B = δ_r / (1/r − r/R²); for R → ∞, p = 2 G δ_r / r.

    Parameters
    ----------
    shear_modulus : G [Pa]. poisson_ratio : ν. radius : r [m]. interference : δ_r [m], 0 ≤ δ_r < r.
    outer_radius : Clamped outer radius R [m], > r; infinite by default.
    """
    if not (math.isfinite(shear_modulus) and shear_modulus > 0.0):
        raise ValueError(f"shear_modulus = {shear_modulus!r} Pa; valid range (0, inf)")
    if not -1.0 < poisson_ratio < 0.5:
        raise ValueError(f"poisson_ratio = {poisson_ratio!r}; valid range (-1, 0.5)")
    if not (math.isfinite(radius) and radius > 0.0):
        raise ValueError(f"radius = {radius!r} m; valid range (0, inf)")
    if not (math.isfinite(interference) and 0.0 <= interference < radius):
        raise ValueError(f"interference = {interference!r} m; valid range [0, radius = {radius})")
    if not outer_radius > radius:
        raise ValueError(f"outer_radius = {outer_radius!r} m; valid range (radius = {radius}, inf]")
    lame_lambda = 2.0 * shear_modulus * poisson_ratio / (1.0 - 2.0 * poisson_ratio)
    inverse_outer = 0.0 if math.isinf(outer_radius) else 1.0 / outer_radius
    b = interference / (1.0 / radius - radius * inverse_outer**2)
    return b * (2.0 * (lame_lambda + shear_modulus) * inverse_outer**2 + 2.0 * shear_modulus / radius**2)


def grip_preload(
    *,
    shear_modulus: float,
    poisson_ratio: float,
    radius: float,
    interference: float,
    spacing: np.ndarray | float,
    outer_radius: float = math.inf,
) -> np.ndarray:
    """Normal force of the grip per insertion point [N]: 2π r p · d_i (p from :func:`interference_pressure`).

    The shaft friction bound of a point is μ (‖λ_lateral‖ + this), so in steady slip without lateral load the
    axial force grows at μ 2π r p per metre inserted.
    """
    spacing = np.asarray(spacing, dtype=float)
    if np.any(~(spacing > 0.0)) or np.any(~np.isfinite(spacing)):
        raise ValueError(f"spacing d_i = {spacing!r} m; valid range (0, inf)")
    pressure = interference_pressure(
        shear_modulus=shear_modulus,
        poisson_ratio=poisson_ratio,
        radius=radius,
        interference=interference,
        outer_radius=outer_radius,
    )
    return 2.0 * math.pi * radius * pressure * spacing


def channel_preload(grip: float, lateral_previous: np.ndarray) -> np.ndarray | float:
    """The preload p of each point's shaft Coulomb bound μ (‖λ_lat‖ + p) [N] that makes its normal force the
    grip's while the channel stays closed: p = max(g − ‖λ_lat‖, 0), so the bound is μ max(g, ‖λ_lat‖).

    The grip g = 2π r p₀ d_i (:func:`grip_preload`) is the resultant of the channel's interference pressure
    p₀ over the point's length; a lateral force F on the point does not add to it but redistributes the
    pressure around the needle (p₀ + F/(π r d_i) cos θ, whose magnitude integrates to g while it stays ≥ 0):
    the normal force is g until the lateral load opens the channel behind the needle, and the lateral force
    alone beyond (the paper's law, g = 0). Adding the two counted the lateral load twice; on the ring
    coupling's lateral multipliers, which carry the mesh's lateral error of a straight insertion and grow
    under refinement, that doubled count grew the shaft friction with the mesh (docs/coupling.md).

    The solvers' law keeps its additive form: ‖λ_lat‖ is the point's lateral force at its last solve
    (``lateral_previous``, shape (p,), 0 for a new point), so the bound is μ max(g, ‖λ_lat‖) to the change of
    the lateral force over one step. g = 0 gives 0 (the paper's law) whatever the lateral forces.
    """
    if grip == 0.0:
        return grip
    return np.maximum(grip - np.asarray(lateral_previous, dtype=float), 0.0)


# ------------------------------------------------------------------ friction, tip cutting force, puncture
# (3–5)
def stuck_points(
    multipliers: np.ndarray,
    bounds: np.ndarray,
    *,
    slips: np.ndarray | None = None,
    rest_slip: float = 0.0,
    relative_tolerance: float = 1e-3,
) -> np.ndarray:
    """Which shaft rows stick, bool shape (p,): |λ_s| < (1 − tol) · bound, or the row did not slip.

    The force test's tolerance, 1e-3, is far above the solvers' (a row slipping at its bound, solved to 1e-8,
    is never read as stuck by its force). A row at its bound whose slip over the step ``slips`` [m] (the
    solved gap of its friction row: the needle surface's slip on the tissue) is at most ``rest_slip`` [m] is
    at rest, hence stuck: a point that stopped at its dynamic bound holds its load, and the static coefficient
    applies from the next step (Coulomb's law at zero relative velocity). Without ``slips`` only the force is
    read."""
    multipliers = np.abs(np.asarray(multipliers, dtype=float))
    bounds = np.asarray(bounds, dtype=float)
    stuck = multipliers < (1.0 - relative_tolerance) * bounds
    if slips is not None:
        if not (math.isfinite(rest_slip) and rest_slip >= 0.0):
            raise ValueError(f"rest_slip = {rest_slip!r} m; valid range [0, inf)")
        stuck |= np.abs(np.asarray(slips, dtype=float)) <= rest_slip
    return stuck


def tip_cutting_block(
    geometry: StepGeometry,
    *,
    tip_tet: int,
    tip_barycentric: np.ndarray,
    cutting_force: float,
    tissue_nodes: np.ndarray | None = None,
    tissue_weights: np.ndarray | None = None,
    ahead: float | None = None,
) -> tuple[RowBlock, np.ndarray, np.ndarray]:
    """The tip's cutting row after puncture: one row along the needle at the tip, its force in [0, f_cut].

    The row ties the needle tip to the tissue material point where the tip was at the start of the step
    (``tip_tet``, ``tip_barycentric``), along n = −t (t the tip tangent), and measures the relative
    displacement over the step (a friction row of :func:`refsim.constraints.friction.friction_rows`). Under
    the box law [0, f_cut]: the tip sticks (δ = 0, the tissue deforms ahead of it) while the force is below
    f_cut, cuts forward at exactly f_cut (δ ≤ 0), and is free when it retreats (λ = 0, δ ≥ 0).

    ``tissue_nodes``, ``tissue_weights`` (shape (k,) each): the row's tissue side when it is not the tip's
    material point alone, the ring around the tip with the ring coupling (:func:`ring_weights`): a point
    load on one material point among ring-averaged rows pushes the mesh asymmetrically, and the lateral
    rows then carry a lateral force a straight symmetric insertion does not have.

    ``ahead`` [m]: the material point is the end of the channel the tip has cut, this far ahead of the tip
    along the needle at the step's start (a tip moved back along its channel; the caller measures it from
    the material point itself, e = tᵀ(x_point − x_tip), not from the ring, whose points around the tip are
    displaced less by its load): the row's gap starts from it, so the tip moves forward freely through its
    channel and cuts (at f_cut) only beyond its end. None: the point is where the tip is (e = 0 up to
    round-off), and the gap is the relative displacement over the step alone.

    Returns
    -------
    (block, box_lower, box_upper) : one unilateral row (source PENETRATION: the tip's row) whose force_limit
    is f_cut (the step's problem makes it the box [0, f_cut]), and those bounds, shape (1,) each.
    """
    if not (math.isfinite(cutting_force) and cutting_force > 0.0):
        raise ValueError(f"insertion.tip_cutting_force = {cutting_force!r} N; valid range (0, inf)")
    tip_s = np.array([geometry.needle_previous.length])
    direction = -geometry.needle_free.tangents(tip_s)
    nodes = geometry.mesh_tets[[tip_tet]]
    weights = np.asarray(tip_barycentric, dtype=float).reshape(1, 4)
    if tissue_nodes is not None and tissue_weights is not None:
        nodes = np.asarray(tissue_nodes).reshape(1, -1)
        weights = np.asarray(tissue_weights, dtype=float).reshape(1, -1)
    # the tissue point at the start of the step and after free motion, interpolated once for the row's gap
    # and its point
    tissue_before, tissue_now = geometry.tissue_points(nodes, weights)
    offsets = None if ahead is None else np.array([float(ahead)])
    rows = friction_rows(
        geometry,
        tissue_nodes=nodes,
        tissue_weights=weights,
        arc_lengths=tip_s,
        tangents=direction,
        tissue_free_points=tissue_now,
        tissue_previous_points=tissue_before,
        offsets=offsets,
    )
    # one row in every field, its force limit f_cut checked above
    block = trusted_block(
        jacobians=rows.jacobians,
        free_gap=rows.free_gap,
        kind=np.array([UNILATERAL], dtype=np.int8),
        source=np.array([PENETRATION], dtype=np.int8),
        points=tissue_now,
        directions=direction,
        force_limit=np.array([float(cutting_force)]),
        role=np.array([TIP], dtype=np.int8),
    )
    return block, np.zeros(1), np.array([float(cutting_force)])


# ------------------------------------------------------------------------ shaft contact before puncture (6)
def shaft_contact_block(
    geometry: StepGeometry,
    projector,
    faces: np.ndarray,
    *,
    spacing: float,
    contact_distance: float,
    tip_clearance: float,
) -> RowBlock | None:
    """Unilateral rows keeping the needle's centreline out of the tissue before puncture (issue 9, item 6).

    The shaft is sampled every ``spacing`` from the base to ``tip_clearance`` before the tip (the tip has its
    own contact); each sample closer to the surface than ``contact_distance`` (or under it) gets one
    frictionless unilateral row against its closest surface point, along the direction from that point to the
    sample (the face's outward normal for a sample on or under the surface): δ = nᵀ(x_needle(s) − x_surface) ≥
    0.

    Parameters
    ----------
    geometry : The step's geometry.
    projector : A :class:`refsim.geometry.SurfaceProjector` on the free tissue positions.
    faces : Surface triangles, shape (f, 3).
    spacing, contact_distance, tip_clearance : [m], > 0.

    Returns
    -------
    The rows (source SHAFT_CONTACT), or None when no sample is near the surface.
    """
    for name, value in (
        ("spacing", spacing),
        ("contact_distance", contact_distance),
        ("tip_clearance", tip_clearance),
    ):
        if not (math.isfinite(value) and value > 0.0):
            raise ValueError(f"{name} = {value!r} m; valid range (0, inf)")
    needle = geometry.needle_free
    end = needle.length - tip_clearance
    if end <= 0.0:
        return None
    arc_lengths = np.arange(0.5 * spacing, end, spacing)
    samples = needle.points(arc_lengths)
    # A sample farther than the contact distance from the box of the surface's vertices is outside the surface
    # and farther than that from it: it gets no row, and its closest point is not searched (most of a needle
    # held above the tissue).
    lower, upper = projector.bounds
    beyond = np.maximum(np.maximum(lower - samples, samples - upper), 0.0)
    reach = contact_distance * (1.0 + 1e-9)  # a margin over the round-off of both distances
    candidate = np.einsum("ij,ij->i", beyond, beyond) < reach * reach
    if not np.any(candidate):
        return None
    arc_lengths, samples = arc_lengths[candidate], samples[candidate]
    found = projector.closest(samples)
    offsets = samples - found.closest
    distance = np.linalg.norm(offsets, axis=1)
    outside = np.einsum("ij,ij->i", offsets, found.normal) > 0.0
    near = ~outside | (distance < contact_distance)
    if not np.any(near):
        return None
    arc_lengths, offsets, distance, outside = arc_lengths[near], offsets[near], distance[near], outside[near]
    face_index, barycentric = found.face_index[near], found.barycentric[near]
    points = found.closest[near]
    use_offset = outside & (distance > 1e-9)
    normals = np.where(
        use_offset[:, None], offsets / np.maximum(distance, 1e-300)[:, None], found.normal[near]
    )
    nodes = np.asarray(faces)[face_index]
    gaps = np.einsum("ij,ij->i", normals, offsets)
    count = arc_lengths.size
    return RowBlock(
        jacobians={
            TISSUE: point_rows(nodes, barycentric, normals, geometry.tissue_dof_count),
            NEEDLE: needle_rows(needle, arc_lengths, normals),
        },
        free_gap=gaps,
        kind=np.full(count, UNILATERAL, dtype=np.int8),
        source=np.full(count, SHAFT_CONTACT, dtype=np.int8),
        points=points,
        directions=normals,
    )
