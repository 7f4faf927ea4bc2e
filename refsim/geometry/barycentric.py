"""Barycentric coordinates of points in tetrahedra, from signed sub-volumes.

The coordinate of vertex i is the signed volume of the tetrahedron with vertex i replaced by the point,
divided by the sum of the four such volumes. Computed this way, with edge vectors from the point, a point
equal to a vertex gets exactly (0, .., 1, .., 0) (three sub-volumes have a zero edge and are exactly zero),
and a point on a face whose plane is exactly representable (axis-aligned faces, the diagonal faces of the box
generator) gets an exact zero.
"""

from __future__ import annotations

import numpy as np

__all__ = ["signed_volumes", "tet_barycentric"]

# Sub-tetrahedron i replaces vertex i by the point (index 4), reordered by an even permutation so the point
# comes first: its edges then start at the point, and a point equal to a vertex gives an exactly zero edge.
_REPLACED = np.array([[4, 1, 2, 3], [4, 0, 3, 2], [4, 0, 1, 3], [4, 0, 2, 1]])


def signed_volumes(tet_vertices: np.ndarray) -> np.ndarray:
    """Signed volumes of tetrahedra, positive when (v1 − v0, v2 − v0, v3 − v0) is right-handed.

    Parameters
    ----------
    tet_vertices : Vertex positions [m], shape (..., 4, 3).

    Returns
    -------
    Signed volumes [m³], shape (...).
    """
    tet_vertices = np.asarray(tet_vertices, dtype=float)
    edges = tet_vertices[..., 1:, :] - tet_vertices[..., :1, :]
    triple = np.einsum("...i,...i->...", edges[..., 0, :], np.cross(edges[..., 1, :], edges[..., 2, :]))
    return triple / 6.0


def tet_barycentric(points: np.ndarray, tet_vertices: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of points with respect to tetrahedra (one tetrahedron per point).

    Parameters
    ----------
    points : Query points [m], shape (q, 3).
    tet_vertices : Vertices of the tetrahedron of each point [m], shape (q, 4, 3); any orientation, not
        degenerate.

    Returns
    -------
    Barycentric coordinates, shape (q, 4): they sum to one, reproduce the point
    (``(coordinates[:, :, None] * tet_vertices).sum(1) == points`` up to round-off), are all non-negative
    exactly when the point is inside or on the tetrahedron, and are exactly 0 or 1 on vertices.
    Degenerate (zero-volume) tetrahedra give NaN.
    """
    points = np.asarray(points, dtype=float)
    tet_vertices = np.asarray(tet_vertices, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (q, 3), got {points.shape}")
    if tet_vertices.shape != (points.shape[0], 4, 3):
        raise ValueError(f"tet_vertices must have shape ({points.shape[0]}, 4, 3), got {tet_vertices.shape}")
    extended = np.concatenate([tet_vertices, points[:, None, :]], axis=1)  # (q, 5, 3)
    sub_volumes = signed_volumes(extended[:, _REPLACED, :])  # (q, 4)
    total = sub_volumes.sum(axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(total != 0.0, sub_volumes / np.where(total != 0.0, total, 1.0), np.nan)
