"""Measures of a cut surface: its topology (a manifold disc without holes or isolated points), its extent, and
how far a needle inside it is from it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SurfaceTopology", "surface_topology", "boundary_loop_count"]


@dataclass(frozen=True)
class SurfaceTopology:
    """Topology of a triangle mesh.

    Attributes
    ----------
    point_count : Points, used or not.
    isolated_points : Points in no triangle.
    triangle_count : Triangles.
    non_manifold_edges : Edges shared by more than two triangles.
    boundary_loops : Closed loops of border edges (1 for a disc; each hole adds one).
    euler_characteristic : V − E + F over the used points (1 for a disc).
    """

    point_count: int
    isolated_points: int
    triangle_count: int
    non_manifold_edges: int
    boundary_loops: int
    euler_characteristic: int

    @property
    def is_disc(self) -> bool:
        """A manifold disc: no isolated point, no non-manifold edge, one border loop, χ = 1."""
        return (
            self.triangle_count > 0
            and self.isolated_points == 0
            and self.non_manifold_edges == 0
            and self.boundary_loops == 1
            and self.euler_characteristic == 1
        )


def _edges(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    edges = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return unique, counts


def boundary_loop_count(border_edges: np.ndarray) -> int:
    """Connected components of the graph of border edges (each a closed loop in a manifold mesh)."""
    if border_edges.size == 0:
        return 0
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nodes, inverse = np.unique(border_edges, return_inverse=True)
    inverse = inverse.reshape(-1, 2)
    graph = coo_matrix(
        (np.ones(len(inverse)), (inverse[:, 0], inverse[:, 1])), shape=(nodes.size, nodes.size)
    )
    return int(connected_components(graph, directed=False)[0])


def surface_topology(triangles: np.ndarray, point_count: int) -> SurfaceTopology:
    """The topology of triangles (t, 3) over ``point_count`` points."""
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    used = np.unique(triangles)
    edges, counts = (
        _edges(triangles) if triangles.size else (np.zeros((0, 2), np.int64), np.zeros(0, np.int64))
    )
    border = edges[counts == 1]
    return SurfaceTopology(
        point_count=int(point_count),
        isolated_points=int(point_count - used.size),
        triangle_count=int(triangles.shape[0]),
        non_manifold_edges=int(np.count_nonzero(counts > 2)),
        boundary_loops=boundary_loop_count(border),
        euler_characteristic=int(used.size - edges.shape[0] + triangles.shape[0]),
    )
