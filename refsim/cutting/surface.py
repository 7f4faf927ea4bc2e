"""The cut surface: points kept in rest coordinates, their triangles, its image in the deformed tissue.

After Perrusi et al. 2021, section 4: each point of the cut is located in a tetrahedron of the tissue mesh and
stored through its barycentric coordinates there (the paper's equation 4, p_r = Σ_k α_k q̄_k^(l)), and the
same coordinates map the surface into the deformed tissue every step. The tissue mesh never changes. The
points and triangles are laid by the cut strip (:mod:`refsim.cutting.strip`).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import numpy as np

__all__ = ["CutSurface", "ClosestCutPoints", "TriangulationReport"]

# A projection is inside a triangle when its smallest barycentric coordinate is >= −_INSIDE_TOLERANCE, and a
# clamped closest point lies on an edge or vertex when its coordinate there is <= _INSIDE_TOLERANCE.
_INSIDE_TOLERANCE = 1e-9


class ClosestCutPoints(NamedTuple):
    """Closest points on the (deformed) cut surface, one per query point; unpacks as a 4-tuple."""

    triangle: np.ndarray
    """Index of the triangle holding the closest point, shape (q,)."""
    closest: np.ndarray
    """Closest points [m], shape (q, 3)."""
    barycentric: np.ndarray
    """Barycentric coordinates of the closest points in their triangle, >= 0, summing to one, shape (q, 3)."""
    inside: np.ndarray
    """Whether the query projects inside the surface, shape (q,) bool: its orthogonal projection on the
    plane of its triangle falls in the triangle (within 1e-9 in barycentric coordinates), or its closest point
    lies on an edge shared by two triangles or on a vertex that is not on the border. False when the closest
    point was clamped to the border."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class TriangulationReport:
    """What one addition of points and triangles to the surface did (refsim.cutting.strip.append_points)."""

    step: int
    """Time step of the new points."""
    new_point_count: int
    """Points added."""
    new_triangle_count: int
    """Triangles added."""
    triangulation_seconds: float
    """Wall time of laying the points and their triangles [s]."""

    @property
    def seconds(self) -> float:
        """Total wall time [s]."""
        return self.triangulation_seconds


def _readonly(array: np.ndarray) -> np.ndarray:
    array = np.array(array, copy=True)
    array.flags.writeable = False
    return array


@dataclasses.dataclass(frozen=True, kw_only=True, eq=False)
class CutSurface:
    """The cut surface in rest coordinates: an immutable value; growing it returns a new surface
    (refsim.cutting.strip.append_points).

    Start with `CutSurface.empty()`; the simulation state holds the current surface. Arrays are read-only.
    """

    rest_points: np.ndarray
    """Points of the cut in rest coordinates [m], shape (point_count, 3)."""
    tet_indices: np.ndarray
    """Tissue tetrahedron holding each point, shape (point_count,), int64."""
    barycentric: np.ndarray
    """Barycentric coordinates of each point in its tetrahedron, shape (point_count, 4)."""
    created_step: np.ndarray
    """Time step at which each point was added, shape (point_count,), int64."""
    triangles: np.ndarray
    """Point indices of the triangles, shape (triangle_count, 3), int64, all with the same winding (the strip
    is oriented)."""
    triangle_created_step: np.ndarray
    """Time step at which each triangle was added, shape (triangle_count,), int64."""
    last_triangulation: TriangulationReport | None = None
    """Report of the latest addition of points, None before the first."""

    def __post_init__(self) -> None:
        fields = {
            "rest_points": (np.float64, (-1, 3)),
            "tet_indices": (np.int64, (-1,)),
            "barycentric": (np.float64, (-1, 4)),
            "created_step": (np.int64, (-1,)),
            "triangles": (np.int64, (-1, 3)),
            "triangle_created_step": (np.int64, (-1,)),
        }
        for name, (dtype, shape) in fields.items():
            value = np.asarray(getattr(self, name), dtype=dtype)
            if value.ndim != len(shape) or value.shape[1:] != shape[1:]:
                raise ValueError(f"CutSurface.{name} must have shape {shape} (−1: any), got {value.shape}")
            object.__setattr__(self, name, _readonly(value))
        points = self.rest_points.shape[0]
        for name in ("tet_indices", "barycentric", "created_step"):
            if getattr(self, name).shape[0] != points:
                raise ValueError(
                    f"CutSurface.{name} has {getattr(self, name).shape[0]} rows, expected {points}"
                )
        if self.triangle_created_step.shape[0] != self.triangles.shape[0]:
            raise ValueError("CutSurface.triangle_created_step must have one entry per triangle")
        if self.triangles.size and (self.triangles.min() < 0 or self.triangles.max() >= points):
            raise ValueError(f"CutSurface.triangles must index the {points} points")

    # -- construction --------------------------------------------------------------------------------

    @classmethod
    def empty(cls) -> CutSurface:
        """A surface with no points."""
        return cls(
            rest_points=np.zeros((0, 3)),
            tet_indices=np.zeros(0, dtype=np.int64),
            barycentric=np.zeros((0, 4)),
            created_step=np.zeros(0, dtype=np.int64),
            triangles=np.zeros((0, 3), dtype=np.int64),
            triangle_created_step=np.zeros(0, dtype=np.int64),
        )

    # -- sizes and topology --------------------------------------------------------------------------

    @property
    def point_count(self) -> int:
        """Number of points."""
        return int(self.rest_points.shape[0])

    @property
    def triangle_count(self) -> int:
        """Number of triangles."""
        return int(self.triangles.shape[0])

    @functools.cached_property
    def _edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Directed edges of all triangles (3t, 2), their undirected keys (3t,), and each key's use count."""
        directed = self.triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        low, high = directed.min(axis=1), directed.max(axis=1)
        keys = low * max(self.point_count, 1) + high
        _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
        return directed, keys, counts[inverse]

    def border_edges(self) -> np.ndarray:
        """Edges used by exactly one triangle, as (start, end) in their triangle's winding, shape (e, 2).

        Sorted by (smaller index, larger index).
        """
        directed, keys, uses = self._edges
        single = np.flatnonzero(uses == 1)
        return directed[single[np.argsort(keys[single], kind="stable")]]

    def border_points(self) -> np.ndarray:
        """Sorted indices of the points on border edges, shape (b,) (points in no triangle excluded);
        read-only."""
        return self._border_points

    @functools.cached_property
    def _border_points(self) -> np.ndarray:
        return _readonly(np.unique(self.border_edges()))

    @functools.cached_property
    def _triangle_points(self) -> np.ndarray:
        """Sorted indices of the points the triangles use, shape (u,)."""
        return np.unique(self.triangles)

    @functools.cached_property
    def _edge_lookup(self) -> tuple[np.ndarray, np.ndarray]:
        """The undirected edge keys of ``_edges`` sorted, and their use counts in that order."""
        _, keys, uses = self._edges
        order = np.argsort(keys, kind="stable")
        return keys[order], uses[order]

    # -- deformed state ------------------------------------------------------------------------------

    def deformed_points(self, positions: np.ndarray, tets: np.ndarray) -> np.ndarray:
        """Points of the cut in the deformed tissue, by their barycentric coordinates (equation 4).

        Parameters
        ----------
        positions : Current tissue node positions [m], shape (node_count, 3).
        tets : Node indices of the tissue tetrahedra, shape (tet_count, 4).

        Returns
        -------
        Deformed cut points [m], shape (point_count, 3).
        """
        positions = np.asarray(positions, dtype=float)
        tets = np.asarray(tets)
        if positions.ndim != 2 or positions.shape[1] != 3:
            raise ValueError(f"positions must have shape (node_count, 3), got {positions.shape}")
        if tets.ndim != 2 or tets.shape[1] != 4:
            raise ValueError(f"tets must have shape (tet_count, 4), got {tets.shape}")
        if self.point_count == 0:
            return np.zeros((0, 3))
        if int(self.tet_indices.max()) >= tets.shape[0]:
            raise ValueError(
                f"cut points refer to tet {int(self.tet_indices.max())}; the mesh has {tets.shape[0]} tets"
            )
        nodes = tets[self.tet_indices]
        if nodes.min() < 0 or nodes.max() >= positions.shape[0]:
            raise ValueError(f"tets of the cut points index nodes outside [0, {positions.shape[0]})")
        return np.einsum("pk,pki->pi", self.barycentric, positions[nodes])

    def interpolated_normals(
        self, points: np.ndarray, triangle: np.ndarray, weights: np.ndarray
    ) -> np.ndarray:
        """Unit normals at points of the surface given by triangle and barycentric weights (q,), (q, 3): the
        area-weighted vertex normals on ``points`` interpolated with the weights, shape (q, 3).

        A sliver (three nearly collinear points, where the cut's border follows a straight path of the needle
        tip) has an arbitrary normal of its own; it weighs nothing in its vertices' normals.
        """
        from refsim.geometry.surface_kernels import vertex_normals  # numba: imported on first use

        vertex = vertex_normals(points, self.triangles)
        normals = np.einsum("qv,qvj->qj", weights, vertex[self.triangles[triangle]])
        return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)

    def _check_surface_points(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, dtype=float)
        if points.shape != (self.point_count, 3):
            raise ValueError(f"cut points must have shape ({self.point_count}, 3), got {points.shape}")
        return points

    def closest_points(self, points: np.ndarray, deformed_points: np.ndarray) -> ClosestCutPoints:
        """Closest points on the cut surface, and whether each query projects inside it.

        Parameters
        ----------
        points : Query points [m], shape (q, 3) (e.g. needle samples).
        deformed_points : Cut points where the surface is [m], shape (point_count, 3) (from `deformed_points`,
            or `rest_points`).

        Returns
        -------
        Triangle index, closest point, barycentric coordinates and inside flag of each query
        (see `ClosestCutPoints`). Exact: a KD-tree over triangle centroids bounds the search.

        Raises
        ------
        ValueError
            If the surface has no triangle yet, or on bad shapes.
        """
        from refsim.geometry.search import SurfaceProjector
        from refsim.geometry.surface_kernels import inside_surface  # numba: imported on first use

        deformed_points = self._check_surface_points(deformed_points)
        if self.triangle_count == 0:
            raise ValueError(
                "the cut surface has no triangle yet: check triangle_count before closest_points"
            )
        queries = np.asarray(points, dtype=float)
        face_index, barycentric = SurfaceProjector(
            deformed_points, self.triangles, vertex_indices=self._triangle_points
        ).closest_faces(queries, compiled_choice=True)
        local = self.triangles[face_index]
        corners = deformed_points[local]  # (q, 3, 3)
        closest = np.einsum("qk,qki->qi", barycentric, corners)
        # Inside: the projection on the triangle's plane is; or the point is clamped to an edge shared by two
        # triangles, or to a vertex off the border (one compiled pass, the bits of _inside_reference).
        keys, uses = self._edge_lookup
        inside = inside_surface(
            queries,
            corners,
            barycentric,
            local,
            _INSIDE_TOLERANCE,
            keys,
            uses,
            max(self.point_count, 1),
            self.border_points(),
        )
        return ClosestCutPoints(face_index, closest, barycentric, inside)

    def _inside_reference(
        self, queries: np.ndarray, corners: np.ndarray, barycentric: np.ndarray, local: np.ndarray
    ) -> np.ndarray:
        """:func:`refsim.geometry.surface_kernels.inside_surface` in NumPy: its reference (tests)."""
        projected = _plane_barycentric(queries, corners)
        inside = np.all(projected >= -_INSIDE_TOLERANCE, axis=1)
        on_feature = barycentric <= _INSIDE_TOLERANCE
        zeros = on_feature.sum(axis=1)
        on_edge = ~inside & (zeros == 1)
        if np.any(on_edge):
            opposite = np.argmax(on_feature[on_edge], axis=1)
            rows = local[on_edge]
            start = rows[np.arange(rows.shape[0]), (opposite + 1) % 3]
            end = rows[np.arange(rows.shape[0]), (opposite + 2) % 3]
            inside[on_edge] = self._edge_uses(start, end) >= 2
        on_vertex = ~inside & (zeros == 2)
        if np.any(on_vertex):
            vertex = local[on_vertex][
                np.arange(int(on_vertex.sum())), np.argmax(~on_feature[on_vertex], axis=1)
            ]
            inside[on_vertex] = ~np.isin(vertex, self.border_points())
        return inside

    def _edge_uses(self, start: np.ndarray, end: np.ndarray) -> np.ndarray:
        """Number of triangles using each undirected edge (start, end), shape (e,)."""
        keys, uses = self._edge_lookup
        query = np.minimum(start, end) * max(self.point_count, 1) + np.maximum(start, end)
        position = np.clip(np.searchsorted(keys, query), 0, keys.size - 1)
        found = keys[position] == query
        return np.where(found, uses[position], 0)


def _plane_barycentric(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Barycentric coordinates of the orthogonal projections of points on their triangles' planes, (q, 3)."""
    a = corners[:, 0]
    v0, v1, v2 = corners[:, 1] - a, corners[:, 2] - a, points - a
    d00, d01, d11 = (np.einsum("qi,qi->q", x, y) for x, y in ((v0, v0), (v0, v1), (v1, v1)))
    d20, d21 = np.einsum("qi,qi->q", v2, v0), np.einsum("qi,qi->q", v2, v1)
    denominator = d00 * d11 - d01 * d01
    with np.errstate(divide="ignore", invalid="ignore"):
        v = (d11 * d20 - d01 * d21) / denominator
        w = (d00 * d21 - d01 * d20) / denominator
    result = np.stack([1.0 - v - w, v, w], axis=1)
    return np.where(np.isfinite(result), result, -np.inf)
