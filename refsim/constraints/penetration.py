"""Penetration constraint (paper, section 3 and Figure 1a): the tip against the tissue surface.

While the tip is outside, the closest point of the tissue surface to the tip gives one unilateral row along
the surface normal and, with a friction coefficient μ_p > 0, two friction rows in the tangent plane (a Coulomb
contact). The tip punctures when the normal force reaches f_p (a force, not an impulse).

A flat tip of radius a (``insertion.tip_radius`` > 0) is a flat punch: its rows act on the weighted mean of
the surface points under a disc of sample points (``punch_disc``), weighted with the pressure of a rigid
flat punch on a half-space, p(ρ) ∝ 1/√(a² − ρ²) (Sneddon 1946). In the continuum that pressure gives a uniform
displacement δ under the disc, so the row's weighted mean displacement is δ and its force the punch's,
F = 2 a E δ/(1 − ν²), a quantity with a limit under mesh refinement; a point load (a = 0, the paper's tip) has
none in 3-D (its displacement is infinite in the continuum).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from refsim.constraints.friction import friction_rows
from refsim.constraints.needle_geometry import needle_rows
from refsim.constraints.rows import (
    FRICTION,
    NEEDLE,
    NORMAL,
    PENETRATION,
    TANGENT,
    TISSUE,
    UNILATERAL,
    RowBlock,
    orthonormal_basis,
    point_rows,
    stack_jacobians,
)
from refsim.constraints.step_geometry import StepGeometry
from refsim.geometry import SurfaceProjector

__all__ = ["SurfaceContact", "find_surface_contact", "penetration_block", "punch_disc"]


@dataclass(frozen=True)
class SurfaceContact:
    """The tissue surface point closest to the tip.

    Attributes
    ----------
    face : Index of the surface triangle.
    nodes : Its three tissue nodes, shape (3,).
    barycentric : Coordinates of the closest point in the triangle, shape (3,).
    point : The closest point [m], shape (3,) (the entry point if the tip punctures).
    normal : Outward unit normal used for the row, shape (3,).
    gap : Signed distance of the tip along the normal [m] (negative inside).
    area_nodes, area_weights : A flat tip's face: the nodes of the faces under every disc sample and their
        barycentric coordinates times the sample's punch weight, shape (3 k,) each (the weights sum to 1);
        None for a point tip.
    area_point : The punch-weighted mean of the samples' surface points [m], shape (3,), or None.
    """

    face: int
    nodes: np.ndarray
    barycentric: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    gap: float
    area_nodes: np.ndarray | None = None
    area_weights: np.ndarray | None = None
    area_point: np.ndarray | None = None

    def loaded(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the tip's rows act on: (nodes, weights, point), the face's closest point or the flat tip's
        punch-weighted disc."""
        if self.area_nodes is None:
            return self.nodes, self.barycentric, self.point
        return self.area_nodes, self.area_weights, self.area_point


def punch_disc(radius: float, ring_count: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Sample points of a flat punch's disc and their weights, the pressure of a rigid punch.

    The pressure of a rigid flat punch of radius a on a half-space is p(ρ) ∝ 1/√(a² − ρ²). With ρ = a sin θ
    the load of the band between θ₀ and θ₁ is ∝ cos θ₀ − cos θ₁: the disc is cut into ``ring_count`` bands of
    equal Δθ = π/(2 · ring_count), each a ring of radius a sin θ_mid carrying its band's exact load, sampled
    by equally spaced points about a/ring_count apart (at least 6 a ring).

    Parameters
    ----------
    radius : a [m], > 0.
    ring_count : Number of rings, ≥ 1.

    Returns
    -------
    (offsets, weights) : offsets in the disc's plane as (ρ cos φ, ρ sin φ), shape (k, 2); weights, shape (k,),
        summing to 1.
    """
    if not (np.isfinite(radius) and radius > 0.0):
        raise ValueError(f"insertion.tip_radius = {radius!r} m; valid range (0, inf) for a flat tip")
    edges = np.linspace(0.0, 0.5 * np.pi, ring_count + 1)
    band = np.cos(edges[:-1]) - np.cos(edges[1:])
    rho = radius * np.sin(0.5 * (edges[:-1] + edges[1:]))
    counts = np.maximum(6, np.ceil(2.0 * np.pi * rho * ring_count / radius)).astype(np.int64)
    ring = np.repeat(np.arange(ring_count), counts)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    angle = 2.0 * np.pi * (np.arange(ring.size) - start[ring]) / counts[ring] + np.pi * ring / counts[ring]
    offsets = rho[ring, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    weights = band[ring] / counts[ring]
    return offsets, weights / weights.sum()


def find_surface_contact(
    projector,
    faces: np.ndarray,
    tip: np.ndarray,
    direction: np.ndarray | None = None,
    *,
    tip_radius: float = 0.0,
) -> SurfaceContact:
    """Closest surface point to the tip and the contact normal.

    The normal is the direction from the closest point to the tip when the tip is outside and away from the
    surface (right on edges and vertices, where face normals disagree), and the face's outward normal
    otherwise (tip on or under the surface).

    With the needle's ``direction`` (unit, base to tip), the contact is with the surface the tip approaches
    from outside: faces whose outward normal n has n · direction > 0 face away from the needle (the far face
    of a thin layer, which the tip could only reach from inside). When the tip is under such a face (inside
    the tissue) and it holds the closest point, the contact is the closest point on the faces turned towards
    the needle (n · direction < 0), the ones a tip can come through from outside: the tip meets the near face,
    and puncture happens there. A tip outside, beyond a face turned away (it left the tissue through that far
    face and moves away from it), meets the next surface ahead: the closest point on the faces turned towards
    the needle whose plane the tip is outside of (another layer beyond a gap; the faces it entered by lie
    behind it, the tip under their plane), or, without any, keeps the face it left. (A face parallel to the
    needle, n · direction = 0, is kept when it is the closest: a needle can slide along it.)

    Parameters
    ----------
    projector : A `refsim.geometry.SurfaceProjector` built on the current tissue positions.
    faces : Surface triangles, shape (f, 3).
    tip : Tip position [m], shape (3,).
    direction : The needle's unit direction at the tip, shape (3,), or None (any face).
    tip_radius : a [m]: 0 for a point tip; > 0 (with ``direction``) for a flat tip: the samples of
        :func:`punch_disc` in the plane normal to ``direction`` through the tip are each projected on the
        surface (their closest points), and the rows act on their punch-weighted mean (``area_*``); the
        normal and the entry point are the centre's.
    """
    found = projector.closest(np.asarray(tip, dtype=float)[None, :])
    tip = np.asarray(tip, dtype=float)
    under = float((tip - found.closest[0]) @ found.normal[0]) <= 0.0
    if direction is not None and float(found.normal[0] @ direction) > 0.0:
        # The closest face is turned away from the needle. Under it, the tip meets the near face (puncture
        # there). Outside it (the tip left the tissue through it, a far face, and moves away from it), the
        # tip meets the next surface ahead: the faces turned towards the needle with the tip outside their
        # plane (another layer beyond a gap; not the faces it entered by, behind it); without any, the face
        # it left.
        facing = projector.normals @ np.asarray(direction, dtype=float) < 0.0
        if not under:
            corners = projector.positions[np.asarray(faces)[:, 0]]
            facing &= np.einsum("ij,ij->i", projector.normals, tip - corners) > 0.0
        facing = np.flatnonzero(facing)
        if facing.size:
            near = SurfaceProjector(projector.positions, np.asarray(faces)[facing]).closest(tip[None, :])
            near.face_index[0] = facing[near.face_index[0]]
            found = near
    face = int(found.face_index[0])
    point = found.closest[0]
    face_normal = found.normal[0]
    offset = tip - point
    distance = float(np.linalg.norm(offset))
    outside = float(offset @ face_normal) > 0.0
    # Below 1e-9 m (far under any mesh size) the direction of the offset is round-off: use the face normal.
    normal = offset / distance if (outside and distance > 1e-9) else face_normal
    gap = distance if outside else -distance
    if tip_radius > 0.0 and direction is not None:
        offsets, weights = punch_disc(tip_radius)
        first, second = orthonormal_basis(np.asarray(direction, dtype=float)[None, :])
        samples = tip + offsets[:, :1] * first + offsets[:, 1:] * second
        under = projector.closest(samples)
        area_point = weights @ under.closest
        return SurfaceContact(
            face,
            faces[face],
            found.barycentric[0],
            point,
            normal,
            float(normal @ (tip - area_point)),
            area_nodes=np.asarray(faces)[under.face_index].ravel(),
            area_weights=(under.barycentric * weights[:, None]).ravel(),
            area_point=area_point,
        )
    return SurfaceContact(face, faces[face], found.barycentric[0], point, normal, gap)


def penetration_block(
    contact: SurfaceContact,
    geometry: StepGeometry,
    *,
    friction_coefficient: float,
    puncture_force: float | None = None,
) -> RowBlock:
    """Rows of the tip contact: one unilateral row, plus two friction rows when μ_p > 0.

    With ``puncture_force`` f_p [N] the normal row's force is capped at f_p (issue 9, item 5; force_limit):
    the step in which the tip would need more ends with λ = f_p and the tip through (δ < 0), so puncture
    happens at f_p whatever dt and speed. The two friction rows are then each bounded by μ_p λ_n
    (group-friction law, a square instead of the Coulomb disc: the solvers' contact cone has no capped
    normal).

    Parameters
    ----------
    contact : The surface point found on the free positions.
    geometry : The step's geometry (both bodies at the start of the step and after free motion).
    friction_coefficient : μ_p ≥ 0.
    """
    tip_s = np.array([geometry.needle_free.length])
    tip_free = geometry.needle_free.points(tip_s)[0]
    normal = contact.normal
    loaded_nodes, loaded_weights, loaded_point = contact.loaded()
    gap_normal = float(normal @ (tip_free - loaded_point))
    nodes, weights = loaded_nodes[None, :], loaded_weights[None, :]
    normal_jacobians = {
        TISSUE: point_rows(nodes, weights, normal[None, :], geometry.tissue_dof_count),
        NEEDLE: needle_rows(geometry.needle_free, tip_s, normal[None, :]),
    }
    if friction_coefficient > 0.0:
        first, second = orthonormal_basis(normal[None, :])
        tangents = np.vstack([first, second])
        friction = friction_rows(
            geometry,
            tissue_nodes=np.repeat(nodes, 2, axis=0),
            tissue_weights=np.repeat(weights, 2, axis=0),
            arc_lengths=np.repeat(tip_s, 2),
            tangents=tangents,
            tissue_free_points=np.repeat(loaded_point[None, :], 2, axis=0),
            tissue_previous_points=np.repeat(
                (loaded_weights @ geometry.tissue_previous[loaded_nodes])[None, :], 2, axis=0
            ),
        )
        directions = np.vstack([normal, tangents])
        gaps = np.concatenate([[gap_normal], friction.free_gap])
        kinds = np.array([UNILATERAL, FRICTION, FRICTION], dtype=np.int8)
        jacobians = stack_jacobians([normal_jacobians, friction.jacobians])
        contacts = np.array([[0, 1, 2]], dtype=np.int64)
        contact_friction = np.array([friction_coefficient])
        if puncture_force is not None:
            contacts, contact_friction = np.zeros((0, 3), dtype=np.int64), np.zeros(0)
            groups = dict(
                group_rows=np.array([1, 2], dtype=np.int64),
                group_offsets=np.array([0, 1, 2], dtype=np.int64),
                group_members=np.array([0, 0], dtype=np.int64),
                group_coefficient=np.full(2, float(friction_coefficient)),
            )
    else:
        directions = normal[None, :]
        gaps = np.array([gap_normal])
        kinds = np.array([UNILATERAL], dtype=np.int8)
        jacobians = normal_jacobians
        contacts = np.zeros((0, 3), dtype=np.int64)
        contact_friction = np.zeros(0)
    row_count = len(gaps)
    capped = {}
    if puncture_force is not None:
        if not (np.isfinite(puncture_force) and puncture_force > 0.0):
            raise ValueError(f"insertion.puncture_force = {puncture_force!r} N; valid range (0, inf)")
        limit = np.full(row_count, np.inf)
        limit[0] = float(puncture_force)
        capped = dict(force_limit=limit, **(groups if friction_coefficient > 0.0 else {}))
    return RowBlock(
        jacobians=jacobians,
        free_gap=gaps,
        kind=kinds,
        source=np.full(row_count, PENETRATION, dtype=np.int8),
        points=np.broadcast_to(loaded_point, (row_count, 3)).copy(),
        directions=directions,
        contacts=contacts,
        contact_friction=contact_friction,
        role=np.array([NORMAL, TANGENT, TANGENT][:row_count], dtype=np.int8),
        **capped,
    )
