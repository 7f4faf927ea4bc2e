"""Spatial search on tetrahedral meshes and triangle surfaces: point location and closest surface points.

An element's bounding radius is the largest distance from its centroid to its vertices; since the distance to
the centroid is convex, every point of the element lies within that radius. Candidate pairs (query, element)
come from a spatial index, are pruned by the element's own radius, and are evaluated in one vectorised call;
the best candidate of each query is picked with a lexicographic sort, so the answer does not depend on the
index (any index giving every element whose grown bounding sphere holds the point gives the same bits).
Point location uses a compiled uniform grid of the tets' bounding spheres, grown for tolerances up to 1e-6
(:class:`refsim.geometry.grid.BoxGrid`: cheap to build, which matters for the locators built on a deformed
mesh during a step); larger tolerances and the closest surface points use KD-trees (scipy's cKDTree) on
element centroids, one tree per class of bounding radius (radii within a factor two), so a graded mesh does
not make every query look at the largest elements' reach. There is no Python loop over queries or elements,
only over radius classes and over chunks of queries (to bound memory).
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from refsim.geometry.barycentric import tet_barycentric
from refsim.geometry.closest import _THIN_AREA, closest_points_on_triangles, triangle_normals

__all__ = ["ClosestSurfacePoints", "SurfaceProjector", "TetLocator", "tet_boundary_faces"]

# Queries are processed in chunks of this many points to bound the size of the candidate arrays.
_CHUNK = 4096
# Relative slack on bounding radii, far above the round-off of centroid distances (~1e-16).
_RADIUS_SLACK = 1e-9
# TetLocator's grid holds each tet's bounding sphere grown for tolerances up to this (larger ones use the
# KD-trees); the ring points of the coupling are located with 1e-6.
_GRID_TOLERANCE = 1e-6
# A locator of a sequence of configurations grows its grid's boxes by this fraction of each tet's grown
# radius, and the next configuration's locator takes that grid over while every tet's box lies in its box
# there (a larger margin keeps a grid through larger motions and adds candidates to every query).
_REUSE_MARGIN = 0.25
# SurfaceProjector scans every face for each query (compiled, no index to build) up to this many pairs
# (queries × faces) per chunk; beyond, it builds KD-trees. A step's queries (the tip and shaft samples on the
# tissue's surface, the needle's samples on the cut) are far below.
_SCAN_PAIRS = 200_000
# Faces of a tetrahedron (v0, v1, v2, v3) in the order opposite v0, v1, v2, v3, and the opposite node.
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def _check_points(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (q, 3), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ValueError("points must be finite")
    return points


def _check_elements(positions: np.ndarray, elements: np.ndarray, corners: int, name: str) -> tuple:
    positions = np.asarray(positions, dtype=float)
    elements = np.asarray(elements)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"positions must have shape (n, 3), got {positions.shape}")
    if elements.ndim != 2 or elements.shape[1] != corners or elements.shape[0] == 0:
        raise ValueError(f"{name} must have shape (count >= 1, {corners}), got {elements.shape}")
    if not np.issubdtype(elements.dtype, np.integer):
        raise ValueError(f"{name} must be integer indices, got dtype {elements.dtype}")
    if elements.min() < 0 or elements.max() >= positions.shape[0]:
        raise ValueError(
            f"{name} index out of range: values in [{elements.min()}, {elements.max()}], "
            f"valid range [0, {positions.shape[0] - 1}]"
        )
    if not np.all(np.isfinite(positions)):
        raise ValueError("positions must be finite")
    return positions, elements.astype(np.int64, copy=False)


def tet_boundary_faces(tets: np.ndarray, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Faces used by exactly one tetrahedron, oriented away from that tetrahedron's fourth node.

    Parameters
    ----------
    tets : Node indices of the tetrahedra, shape (m, 4).
    positions : Node positions [m], shape (n, 3); used only to orient the faces.

    Returns
    -------
    faces : Boundary triangles, shape (f, 3), with ``(b − a) × (c − a)`` pointing out of the owning
        tetrahedron; sorted by their sorted node triple.
    face_tets : Index of the tetrahedron owning each face, shape (f,).
    """
    tets = np.asarray(tets, dtype=np.int64)
    positions = np.asarray(positions, dtype=float)
    all_faces = tets[:, _TET_FACES].reshape(-1, 3)  # (4m, 3)
    opposite = tets.reshape(-1)  # the node opposite face k of tet t is tets[t, k]
    keys = np.sort(all_faces, axis=1)
    _, first, counts = np.unique(keys, axis=0, return_index=True, return_counts=True)
    single = first[counts == 1]
    faces = all_faces[single]
    a, b, c = (positions[faces[:, k]] for k in range(3))
    outward = np.einsum("ij,ij->i", np.cross(b - a, c - a), positions[opposite[single]] - a) <= 0.0
    faces[~outward] = faces[~outward][:, [0, 2, 1]]
    return faces, single // 4


class _RadiusClasses:
    """KD-trees on element centroids, one per class of bounding radius (radii within a factor two)."""

    def __init__(self, centroids: np.ndarray, radii: np.ndarray):
        self.radii = radii
        largest = max(float(radii.max()), np.finfo(float).tiny)
        level = np.floor(np.log2(np.maximum(radii, largest * 2.0**-30) / largest)).astype(int)
        self.classes = []
        for value in np.unique(level):
            members = np.flatnonzero(level == value)
            self.classes.append((cKDTree(centroids[members]), members, float(radii[members].max())))

    def pairs(self, points: np.ndarray, reach: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (query, element) with centroid distance <= class radius + reach, as two index arrays."""
        queries, elements = [], []
        for tree, members, radius in self.classes:
            lists = tree.query_ball_point(
                points, (radius + reach) * (1.0 + _RADIUS_SLACK), return_sorted=False
            )
            counts = np.fromiter(map(len, lists), dtype=np.intp, count=len(lists))
            flat = np.fromiter(itertools.chain.from_iterable(lists), dtype=np.intp, count=int(counts.sum()))
            queries.append(np.repeat(np.arange(points.shape[0]), counts))
            elements.append(members[flat])
        return np.concatenate(queries), np.concatenate(elements)


def _boxes_within(centroids: np.ndarray, radii: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> bool:
    """Whether every box centroid ± radius lies in the box (lower, upper) of the same index."""
    return bool(np.all(centroids - radii[:, None] >= lower) and np.all(centroids + radii[:, None] <= upper))


def _first_per_query(queries: np.ndarray, order: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Given pair indices sorted by query then preference, the first pair of each query and its query."""
    sorted_queries = queries[order]
    first = np.ones(sorted_queries.shape[0], dtype=bool)
    first[1:] = sorted_queries[1:] != sorted_queries[:-1]
    return sorted_queries[first], order[first]


class TetLocator:
    """Locate points in a tetrahedral mesh: containing tetrahedron and barycentric coordinates.

    Parameters
    ----------
    positions : Node positions [m], shape (node_count, 3); rest or deformed.
    tets : Node indices of the tetrahedra, shape (tet_count, 4); non-degenerate, any orientation.
    previous : The locator of the same tets on an earlier configuration (the last step's), or None: its grid
        of the tets' boxes is taken over while every tet's box still lies in its box there (the answers are
        those of a grid built now, bit for bit); a locator given one builds its own grid with room to spare
        (_REUSE_MARGIN) for the next.

    Notes
    -----
    A point is in tetrahedron t when all its barycentric coordinates in t are >= −tolerance. A point on a
    face, edge or vertex shared by several tetrahedra is given, deterministically, to the one whose smallest
    coordinate is largest, ties going to the lowest tetrahedron index.
    """

    def __init__(self, positions: np.ndarray, tets: np.ndarray, *, previous: TetLocator | None = None):
        self.positions, self.tets = _check_elements(positions, tets, 4, "tets")
        from refsim.geometry.grid import tet_spheres

        self.centroids, self._radii = tet_spheres(self.positions, self.tets)
        self._grid = None  # BoxGrid of the grown bounding spheres (tolerance <= _GRID_TOLERANCE), when used
        # With ``previous`` (a locator of the same tets on an earlier configuration: a sequence of
        # configurations, one per step) the grid is built with room to spare (_REUSE_MARGIN) and taken over
        # from ``previous`` while every tet's box still lies in its box there (:meth:`_box_grid`).
        self._reusable = previous is not None
        self._previous_grid = None
        if previous is not None and previous._reusable:
            grid = previous._grid if previous._grid is not None else previous._previous_grid
            if grid is not None and previous.tets.shape == self.tets.shape:
                if previous.tets is self.tets or np.array_equal(previous.tets, self.tets):
                    self._previous_grid = grid
        self._classes = None  # KD-trees per radius class (larger tolerances), on first use
        self._surface: tuple[SurfaceProjector, np.ndarray] | None = None

    def locate(self, points: np.ndarray, *, tolerance: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
        """Containing tetrahedron and barycentric coordinates of each point.

        Parameters
        ----------
        points : Query points [m], shape (q, 3).
        tolerance : Smallest barycentric coordinate accepted is −tolerance (dimensionless, >= 0).

        Returns
        -------
        tet_index : Index of the containing tetrahedron, −1 for points outside the mesh, shape (q,).
        barycentric : Barycentric coordinates in that tetrahedron, NaN for points outside, shape (q, 4).
        """
        if not (np.isfinite(tolerance) and tolerance >= 0.0):
            raise ValueError(f"tolerance must be finite and >= 0, got {tolerance}")
        points = _check_points(points)
        if tolerance <= _GRID_TOLERANCE:
            from refsim.geometry.grid import locate_in_tets  # numba: imported on first use

            return locate_in_tets(
                self._box_grid(),
                points,
                self.positions,
                self.tets,
                self.centroids,
                self._radii,
                tolerance=tolerance,
                reach_factor=1.0 + 6.0 * tolerance + _RADIUS_SLACK,
            )
        return self._locate_vectorised(points, tolerance)

    def _locate_vectorised(self, points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        """``locate`` by candidate pairs evaluated in vectorised chunks (any tolerance; ``locate`` uses it
        above 1e-6, the compiled pass below, which gives the same bits)."""
        tet_index = np.full(points.shape[0], -1, dtype=np.int64)
        barycentric = np.full((points.shape[0], 4), np.nan)
        for start in range(0, points.shape[0], _CHUNK):
            chunk = slice(start, start + _CHUNK)
            found, indices, coordinates = self._locate_chunk(points[chunk], tolerance)
            tet_index[chunk][found] = indices
            barycentric[chunk][found] = coordinates
        return tet_index, barycentric

    @property
    def tet_vertices(self) -> np.ndarray:
        """The vertices of every tet [m], shape (m, 4, 3)."""
        return self.positions[self.tets]

    def _candidates(self, points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (query, tet) holding every pair with a centroid distance <= (1 + 6 tol + slack) × the tet's
        bounding radius (more are pruned by the caller)."""
        if tolerance <= _GRID_TOLERANCE:
            return self._box_grid().pairs(points)
        if self._classes is None:
            self._classes = _RadiusClasses(self.centroids, self._radii)
        return self._classes.pairs(points, 6.0 * tolerance * self._radii.max())

    def _box_grid(self):
        """The compiled grid of boxes around the tets' bounding spheres grown for tolerances up to 1e-6, built
        on first use, or taken over from the previous configuration's locator.

        A grid only proposes candidates: a point is then tested against each candidate tet's current sphere
        and barycentric coordinates, and the choice among the tets that hold it does not depend on their
        order. A grid whose every box contains the tet's current box therefore gives the answer of a grid
        built now, bit for bit. A locator given a ``previous`` one grows its boxes by _REUSE_MARGIN of the
        grown radius and takes over ``previous``'s grid while every tet's box lies in it (a tissue whose tets
        each moved less than that margin since the grid was built)."""
        if self._grid is None:
            grown = self._radii * (1.0 + 6.0 * _GRID_TOLERANCE + 2.0 * _RADIUS_SLACK)
            previous = self._previous_grid
            self._previous_grid = None
            if previous is not None and _boxes_within(self.centroids, grown, previous.lower, previous.upper):
                self._grid = previous
                return self._grid
            from refsim.geometry.grid import BoxGrid  # numba: imported on first use

            if self._reusable:
                grown = grown * (1.0 + _REUSE_MARGIN)
            self._grid = BoxGrid(self.centroids - grown[:, None], self.centroids + grown[:, None])
        return self._grid

    def _locate_chunk(self, points: np.ndarray, tolerance: float) -> tuple:
        # Barycentric coordinates >= −tol imply a centroid distance <= (1 + 6 tol) × bounding radius.
        reach_factor = 1.0 + 6.0 * tolerance + _RADIUS_SLACK
        queries, tets = self._candidates(points, tolerance)
        distance = np.linalg.norm(points[queries] - self.centroids[tets], axis=1)
        keep = distance <= self._radii[tets] * reach_factor
        queries, tets = queries[keep], tets[keep]
        coordinates = tet_barycentric(points[queries], self.positions[self.tets[tets]])
        smallest = coordinates.min(axis=1)
        inside = smallest >= -tolerance
        queries, tets, coordinates, smallest = (
            queries[inside],
            tets[inside],
            coordinates[inside],
            smallest[inside],
        )
        order = np.lexsort((tets, -smallest, queries))
        found, best = _first_per_query(queries, order)
        return found, tets[best], coordinates[best]

    def locate_nearest(
        self, points: np.ndarray, *, tolerance: float = 1e-12
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Like `locate`, but points outside the mesh are clamped to the closest point of the mesh.

        Parameters
        ----------
        points : Query points [m], shape (q, 3).
        tolerance : As in `locate`.

        Returns
        -------
        tet_index : Containing tetrahedron, or for points outside the tetrahedron owning the closest boundary
            face, shape (q,); never −1.
        barycentric : Barycentric coordinates, shape (q, 4); for points outside those of the closest point of
            the boundary (all >= 0, one exactly 0).
        distance : Distance from each point to the mesh [m], 0 for points located inside, shape (q,).
        """
        tet_index, barycentric = self.locate(points, tolerance=tolerance)
        distance = np.zeros(tet_index.shape[0])
        outside = tet_index < 0
        if np.any(outside):
            if self._surface is None:
                faces, face_tets = tet_boundary_faces(self.tets, self.positions)
                self._surface = (SurfaceProjector(self.positions, faces), face_tets)
            projector, face_tets = self._surface
            nearest = projector.closest(np.asarray(points, dtype=float)[outside])
            owners = face_tets[nearest.face_index]
            face_nodes = projector.faces[nearest.face_index]  # (k, 3) node indices
            slots = np.argmax(self.tets[owners][:, None, :] == face_nodes[:, :, None], axis=2)  # (k, 3)
            clamped = np.zeros((owners.shape[0], 4))
            np.put_along_axis(clamped, slots, nearest.barycentric, axis=1)
            tet_index[outside], barycentric[outside], distance[outside] = owners, clamped, nearest.distance
        return tet_index, barycentric, distance


class ClosestSurfacePoints(NamedTuple):
    """Closest points on a triangle surface, one per query point."""

    face_index: np.ndarray
    """Index of the face holding the closest point, shape (q,)."""
    closest: np.ndarray
    """Closest points [m], shape (q, 3)."""
    barycentric: np.ndarray
    """Barycentric coordinates of the closest points in their face, shape (q, 3), >= 0, summing to one."""
    distance: np.ndarray
    """Distance from each query point to the surface [m], shape (q,)."""
    normal: np.ndarray
    """Unit normal of the face, (b − a) × (c − a) normalised (outward for outward-oriented faces),
    shape (q, 3); zero for degenerate faces."""


class SurfaceProjector:
    """Exact closest points on a triangle surface, with a spatial index on the faces.

    Parameters
    ----------
    positions : Node positions [m], shape (node_count, 3).
    faces : Node indices of the triangles, shape (face_count, 3); outward-oriented for outward normals.
    vertex_indices : ``np.unique(faces)``, when the caller keeps it for its faces (a surface queried at every
        step in new positions): the scan's bound is then taken over each point once. It must be exactly the
        points the faces use (a point off the surface could make the bound smaller than the distance to it).

    Notes
    -----
    For each query an upper bound U on the distance to the surface (a compiled scan of every vertex for few
    queries × faces, :func:`refsim.geometry.grid.surface_candidates`; else the exact distances to the faces of
    the nearest centroids, from KD-trees built on first use); only faces whose centroid is within U plus their
    bounding radius can hold the closest point, and those are evaluated exactly (Ericson's method). Ties in
    distance go to the lowest face index. Both searches keep every face that can hold the closest point, so
    they give the same bits.
    """

    def __init__(self, positions: np.ndarray, faces: np.ndarray, *, vertex_indices: np.ndarray | None = None):
        self.positions, self.faces = _check_elements(positions, faces, 3, "faces")
        self.triangles = self.positions[self.faces]  # (f, 3, 3)
        # The scan's bound over the faces' distinct points; None: over every face's corners (the same bound,
        # up to six times the work on a closed surface)
        self._vertices = None if vertex_indices is None else self.positions[vertex_indices]
        from refsim.geometry.grid import triangle_spheres  # numba: imported on first use

        # triangles.mean(axis=1) and the largest norm of the vertices' offsets, compiled (the same bits)
        self.centroids, self.radii = triangle_spheres(self.triangles)
        self._normals: np.ndarray | None = None
        self._bounds: tuple[np.ndarray, np.ndarray] | None = None
        self._tree: cKDTree | None = None  # the KD-trees, built on the first query too large for the scan
        self._index: _RadiusClasses | None = None

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The axis-aligned box of the faces' vertices [m]: lower and upper corners, shapes (3,), (3,)."""
        if self._bounds is None:
            vertices = self.triangles.reshape(-1, 3)
            self._bounds = (vertices.min(axis=0), vertices.max(axis=0))
        return self._bounds

    @property
    def normals(self) -> np.ndarray:
        """Unit outward normal of every face, shape (f, 3) (computed on first use)."""
        if self._normals is None:
            self._normals = triangle_normals(self.triangles)
        return self._normals

    def closest(self, points: np.ndarray) -> ClosestSurfacePoints:
        """Closest point on the surface to each query point.

        Parameters
        ----------
        points : Query points [m], shape (q, 3).

        Returns
        -------
        The face, closest point, barycentric coordinates, distance and face normal of each query point.
        """
        points = _check_points(points)
        face_index, barycentric = self.closest_faces(points)
        closest = np.einsum("qk,qki->qi", barycentric, self.triangles[face_index])
        distance = np.linalg.norm(points - closest, axis=1)
        # The chosen faces' normals only (row by row: the bits of all the faces' normals, indexed).
        return ClosestSurfacePoints(
            face_index, closest, barycentric, distance, triangle_normals(self.triangles[face_index])
        )

    def closest_faces(
        self, points: np.ndarray, *, compiled_choice: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """The face holding each query point's closest point and its barycentric coordinates there, shapes
        (q,), (q, 3): what :meth:`closest` finds, without the points, distances and normals it derives.

        ``compiled_choice``: for few queries (the scan), Ericson's coordinates and the choice of the nearest
        pair in compiled passes (:func:`refsim.geometry.grid.closest_faces_scan`), the same bits as the
        NumPy path; for a caller at every step of a run (the needle on its cut), whose cost was that path's
        NumPy calls. Off, a run that never asks compiles nothing more (a fresh install's first run)."""
        points = _check_points(points)
        count = points.shape[0]
        face_index = np.zeros(count, dtype=np.int64)
        barycentric = np.zeros((count, 3))
        for start in range(0, count, _CHUNK):
            chunk = slice(start, start + _CHUNK)
            face_index[chunk], barycentric[chunk] = self._closest_chunk(points[chunk], compiled_choice)
        return face_index, barycentric

    def _closest_chunk(
        self, points: np.ndarray, compiled_choice: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        scan = points.shape[0] * self.faces.shape[0] <= _SCAN_PAIRS
        if scan and compiled_choice:
            from refsim.geometry.grid import closest_faces_scan  # numba: imported on first use

            # the queries whose candidates are all regular faces (the bits of the NumPy path below); a query
            # with a thin candidate takes that path
            face_index, barycentric, settled = closest_faces_scan(
                points, self.triangles, self.centroids, self.radii, _RADIUS_SLACK, _THIN_AREA, self._vertices
            )
            if not settled.all():
                careful = np.flatnonzero(~settled)
                face_index[careful], barycentric[careful] = self._closest_pairs(points[careful])
            return face_index, barycentric
        return self._closest_pairs(points, indexed=not scan)

    def _closest_pairs(self, points: np.ndarray, *, indexed: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The closest face of each query from its candidate pairs in NumPy (the careful path for thin
        triangles included): the pairs from the scan (:func:`refsim.geometry.grid.surface_candidates`), or
        from the KD-trees when ``indexed``."""
        count = points.shape[0]
        if not indexed:
            from refsim.geometry.grid import surface_candidates  # numba: imported on first use

            queries, faces = surface_candidates(
                points, self.triangles, self.centroids, self.radii, _RADIUS_SLACK, _THIN_AREA, self._vertices
            )
        else:
            queries, faces = self._indexed_candidates(points)
        closest, coordinates = closest_points_on_triangles(points[queries], self.triangles[faces])
        distance2 = np.sum((closest - points[queries]) ** 2, axis=1)
        order = np.lexsort((faces, distance2, queries))
        found, best = _first_per_query(queries, order)
        face_index = np.zeros(count, dtype=np.int64)
        barycentric = np.zeros((count, 3))
        face_index[found], barycentric[found] = faces[best], coordinates[best]
        return face_index, barycentric

    def _indexed_candidates(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pairs (query, face) that can hold each query's closest point, from the KD-trees: the bound is the
        nearest of the exact distances to the faces of the 4 nearest centroids."""
        if self._tree is None:
            self._tree = cKDTree(self.centroids)
            self._index = _RadiusClasses(self.centroids, self.radii)
        count = points.shape[0]
        neighbours = min(4, self.faces.shape[0])
        _, nearest = self._tree.query(points, k=neighbours)
        nearest = nearest.reshape(count, neighbours)
        candidates, _ = closest_points_on_triangles(
            np.repeat(points, neighbours, axis=0), self.triangles[nearest.reshape(-1)]
        )
        bound = np.linalg.norm(candidates - np.repeat(points, neighbours, axis=0), axis=1)
        bound = bound.reshape(count, neighbours).min(axis=1)  # upper bound on the distance to the surface
        queries, faces = self._index.pairs(points, bound)
        lower = np.linalg.norm(points[queries] - self.centroids[faces], axis=1) - self.radii[faces]
        keep = lower <= bound[queries] * (1.0 + _RADIUS_SLACK) + _RADIUS_SLACK * self.radii[faces]
        return queries[keep], faces[keep]
