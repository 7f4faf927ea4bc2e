"""Penetration constraint (paper, section 3 and Figure 1a): the tip against the tissue surface.

While the tip is outside, the closest point of the tissue surface to the tip gives one unilateral row along
the surface normal and, with a friction coefficient μ_p > 0, two friction rows in the tangent plane (a Coulomb
contact). The tip punctures when the normal force reaches f_p (a force, not an impulse).
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

__all__ = ["SurfaceContact", "find_surface_contact", "penetration_block"]


@dataclass(frozen=True)
class SurfaceContact:
    """The tissue surface point closest to the tip.

    Attributes
    ----------
    face : Index of the surface triangle.
    nodes : Its three tissue nodes, shape (3,).
    barycentric : Coordinates of the closest point in the triangle, shape (3,).
    point : The closest point [m], shape (3,).
    normal : Outward unit normal used for the row, shape (3,).
    gap : Signed distance of the tip along the normal [m] (negative inside).
    """

    face: int
    nodes: np.ndarray
    barycentric: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    gap: float


def find_surface_contact(
    projector, faces: np.ndarray, tip: np.ndarray, direction: np.ndarray | None = None
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
    and puncture happens there. (A face parallel to the needle, n · direction = 0, is kept when it is the
    closest: a needle can slide along it; a tip outside, beyond a face turned away, keeps that face: it moves
    away from it.)

    Parameters
    ----------
    projector : A `refsim.geometry.SurfaceProjector` built on the current tissue positions.
    faces : Surface triangles, shape (f, 3).
    tip : Tip position [m], shape (3,).
    direction : The needle's unit direction at the tip, shape (3,), or None (any face).
    """
    found = projector.closest(np.asarray(tip, dtype=float)[None, :])
    tip = np.asarray(tip, dtype=float)
    under = float((tip - found.closest[0]) @ found.normal[0]) <= 0.0
    if direction is not None and under and float(found.normal[0] @ direction) > 0.0:
        facing = np.flatnonzero(projector.normals @ np.asarray(direction, dtype=float) < 0.0)
        if facing.size:
            near = SurfaceProjector(projector.positions, np.asarray(faces)[facing]).closest(
                np.asarray(tip, dtype=float)[None, :]
            )
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
    gap_normal = float(normal @ (tip_free - contact.point))
    nodes, weights = contact.nodes[None, :], contact.barycentric[None, :]
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
            tissue_free_points=np.repeat(contact.point[None, :], 2, axis=0),
            tissue_previous_points=np.repeat(
                (contact.barycentric @ geometry.tissue_previous[contact.nodes])[None, :], 2, axis=0
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
        points=np.broadcast_to(contact.point, (row_count, 3)).copy(),
        directions=directions,
        contacts=contacts,
        contact_friction=contact_friction,
        role=np.array([NORMAL, TANGENT, TANGENT][:row_count], dtype=np.int8),
        **capped,
    )
