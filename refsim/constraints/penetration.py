"""Penetration constraint (paper, section 3 and Figure 1a): the tip against the tissue surface.

While the tip is outside, the closest point of the tissue surface to the tip gives one unilateral row along the
surface normal and, with a friction coefficient μ_p > 0, two friction rows in the tangent plane (a Coulomb
contact). The tip punctures when the normal force reaches f_p (a force, not an impulse).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from refsim.constraints.needle_geometry import NeedleGeometry, needle_rows
from refsim.constraints.rows import FRICTION, PENETRATION, UNILATERAL, RowBlock, orthonormal_basis, point_rows

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


def find_surface_contact(projector, faces: np.ndarray, tip: np.ndarray) -> SurfaceContact:
    """Closest surface point to the tip and the contact normal.

    The normal is the direction from the closest point to the tip when the tip is outside and away from the
    surface (right on edges and vertices, where face normals disagree), and the face's outward normal otherwise
    (tip on or under the surface).

    Parameters
    ----------
    projector : A `refsim.geometry.SurfaceProjector` built on the current tissue positions.
    faces : Surface triangles, shape (f, 3).
    tip : Tip position [m], shape (3,).
    """
    found = projector.closest(np.asarray(tip, dtype=float)[None, :])
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
    *,
    contact: SurfaceContact,
    tissue_free: np.ndarray,
    tissue_previous: np.ndarray,
    needle_free: NeedleGeometry,
    needle_previous: NeedleGeometry,
    friction_coefficient: float,
    tissue_dof_count: int,
) -> RowBlock:
    """Rows of the tip contact: one unilateral row, plus two friction rows when μ_p > 0.

    Parameters
    ----------
    contact : The surface point found on the free positions.
    tissue_free, tissue_previous : Tissue positions after free motion and at the start of the step [m], (n, 3).
    needle_free, needle_previous : The needle after free motion and at the start of the step.
    friction_coefficient : μ_p ≥ 0.
    tissue_dof_count : 3 · tissue node count.
    """
    tip_s = np.array([needle_free.length])
    tip_free = needle_free.points(tip_s)[0]
    tip_previous = needle_previous.points(tip_s)[0]
    normal = contact.normal
    gap_normal = float(normal @ (tip_free - contact.point))
    if friction_coefficient > 0.0:
        first, second = orthonormal_basis(normal[None, :])
        directions = np.vstack([normal, first, second])
        surface_previous = contact.barycentric @ tissue_previous[contact.nodes]
        slip = (tip_free - tip_previous) - (contact.point - surface_previous)
        gaps = np.array([gap_normal, first[0] @ slip, second[0] @ slip])
        kinds = np.array([UNILATERAL, FRICTION, FRICTION], dtype=np.int8)
        contacts = np.array([[0, 1, 2]], dtype=np.int64)
        contact_friction = np.array([friction_coefficient])
    else:
        directions = normal[None, :]
        gaps = np.array([gap_normal])
        kinds = np.array([UNILATERAL], dtype=np.int8)
        contacts = np.zeros((0, 3), dtype=np.int64)
        contact_friction = np.zeros(0)
    row_count = len(gaps)
    nodes = np.broadcast_to(contact.nodes, (row_count, 3))
    weights = np.broadcast_to(contact.barycentric, (row_count, 3))
    needle_jacobian = needle_rows(needle_free, np.repeat(tip_s, row_count), directions)
    return RowBlock(
        tissue_jacobian=point_rows(nodes, weights, directions, tissue_dof_count),
        needle_jacobian=needle_jacobian,
        free_gap=gaps,
        kind=kinds,
        source=np.full(row_count, PENETRATION, dtype=np.int8),
        points=np.broadcast_to(contact.point, (row_count, 3)).copy(),
        directions=directions,
        contacts=contacts,
        contact_friction=contact_friction,
    )
