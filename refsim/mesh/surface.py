"""Boundary surfaces of tetrahedral meshes and checks on triangle surfaces."""

from __future__ import annotations

import numpy as np

from refsim.geometry.search import tet_boundary_faces

__all__ = ["boundary_faces", "is_closed_surface", "surface_edges"]


def boundary_faces(tets: np.ndarray, rest_positions: np.ndarray) -> np.ndarray:
    """Boundary surface of a tetrahedral mesh: faces used by exactly one tetrahedron, oriented outward.

    Parameters
    ----------
    tets : Node indices of the tetrahedra, shape (tet_count, 4).
    rest_positions : Node positions [m], shape (node_count, 3); orient each face away from the fourth node of
        its tetrahedron.

    Returns
    -------
    Boundary triangles, shape (face_count, 3), with ``(b − a) × (c − a)`` pointing out of the mesh; sorted by
    their sorted node triple.
    """
    faces, _ = tet_boundary_faces(tets, rest_positions)
    return faces


def surface_edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edges of a triangle surface and the number of faces using each.

    Parameters
    ----------
    faces : Node indices of the triangles, shape (face_count, 3).

    Returns
    -------
    edges : Node index pairs (smaller first), sorted, shape (edge_count, 2).
    face_counts : Number of faces using each edge, shape (edge_count,).
    """
    faces = np.asarray(faces, dtype=np.int64)
    edges = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    return np.unique(edges, axis=0, return_counts=True)


def is_closed_surface(faces: np.ndarray) -> bool:
    """Whether a triangle surface is closed and consistently oriented.

    Every edge must be used by exactly two faces, once in each direction.

    Parameters
    ----------
    faces : Node indices of the triangles, shape (face_count, 3).
    """
    faces = np.asarray(faces, dtype=np.int64)
    if faces.shape[0] == 0:
        return False
    _, counts = surface_edges(faces)
    directed = faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    _, directed_counts = np.unique(directed, axis=0, return_counts=True)
    return bool(np.all(counts == 2) and np.all(directed_counts == 1))
