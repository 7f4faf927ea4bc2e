"""A uniform grid over axis-aligned boxes, compiled (numba): the candidate pairs (point, box) of a point
location (layer 0).

Each box is registered in every cell it overlaps (one pass to count, one to fill: a CSR list of boxes per
cell); a query visits the one cell of each point and keeps the boxes that contain the point. Building and
querying are linear in the boxes and the points, with no Python loop over either (a KD-tree per radius class,
the former index of :class:`refsim.geometry.TetLocator`, cost more to build than the few points located on a
deformed mesh at each step).
"""

from __future__ import annotations

import numpy as np

from refsim.geometry.closest_kernel import ericson_regular, triangle_shape
from refsim.kernel_cache import numba, readonly

__all__ = [
    "BoxGrid",
    "closest_faces_scan",
    "locate_in_tets",
    "surface_candidates",
    "tet_spheres",
    "triangle_spheres",
]

# The cell edge is this many times the mean box width (along x).
_CELL_PER_BOX = 1.0
# At most this many cells per box overall (a coarser grid above).
_MAX_CELLS_PER_BOX = 8


class BoxGrid:
    """Boxes on a uniform grid; :meth:`pairs` gives every (point, box) with the point inside the box.

    Parameters
    ----------
    lower, upper : Box corners [m], shape (m, 3) each, lower ≤ upper.
    """

    def __init__(self, lower: np.ndarray, upper: np.ndarray) -> None:
        self.lower = np.ascontiguousarray(lower, dtype=float)
        self.upper = np.ascontiguousarray(upper, dtype=float)
        if self.lower.shape != self.upper.shape or self.lower.ndim != 2 or self.lower.shape[1] != 3:
            raise ValueError(f"lower and upper must have one shape (m, 3), got {lower.shape}, {upper.shape}")
        self.origin, self.edge, self.dims, self.offsets, self.items = _build(
            self.lower, self.upper, _CELL_PER_BOX, _MAX_CELLS_PER_BOX
        )

    def pairs(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every (point, box) with the point inside the closed box, as two index arrays (any order)."""
        points = np.ascontiguousarray(points, dtype=float)
        return _query(
            points, self.origin, self.edge, self.dims, self.offsets, self.items, self.lower, self.upper
        )


def locate_in_tets(
    grid: BoxGrid,
    points: np.ndarray,
    positions: np.ndarray,
    tets: np.ndarray,
    centroids: np.ndarray,
    radii: np.ndarray,
    *,
    tolerance: float,
    reach_factor: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Point location over the tets' boxes of ``grid``, in one compiled pass per point (layer 0).

    For each point: the tets whose box holds it, those within ``reach_factor`` × their bounding radius of
    their centroid, their barycentric coordinates (the sub-volume formula of
    :func:`refsim.geometry.barycentric.tet_barycentric`, same operations in the same order), and, among those
    whose smallest coordinate is ≥ −``tolerance``, the one whose smallest coordinate is largest (ties: the
    lowest tet index). The same bits as :meth:`refsim.geometry.TetLocator.locate`'s vectorised path
    (``tests/geometry/test_search.py``), without its many small arrays: a step locates a few points (the
    tip's ring, new insertion points) and NumPy's per-call cost dominated.

    Returns
    -------
    (tet_index (q,), −1 outside; barycentric (q, 4), NaN outside).
    """
    points = np.ascontiguousarray(points, dtype=float)
    return _locate(
        points,
        grid.origin,
        grid.edge,
        grid.dims,
        grid.offsets,
        grid.items,
        grid.lower,
        grid.upper,
        np.ascontiguousarray(centroids, dtype=float),
        np.ascontiguousarray(radii, dtype=float),
        readonly(np.ascontiguousarray(positions, dtype=float)),
        np.ascontiguousarray(tets, dtype=np.int64),
        float(tolerance),
        float(reach_factor),
    )


# Sub-tetrahedron i replaces vertex i by the point (index 4): refsim.geometry.barycentric._REPLACED.
_REPLACED = np.array([[4, 1, 2, 3], [4, 0, 3, 2], [4, 0, 1, 3], [4, 0, 2, 1]], dtype=np.int64)


@numba.njit(cache=True)
def _barycentric_into(point, positions, tet, replaced, out, corners, volumes):  # pragma: no cover - compiled
    """tet_barycentric of one point, written into ``out`` (4,): the sub-volumes (edge vectors from the point,
    the triple product as e₀ · (e₁ × e₂), /6) over their sum, NaN for a zero sum; the operations of the
    vectorised function in its order (tests/geometry/test_search.py holds the two to the same bits).
    ``corners`` (5, 3) and ``volumes`` (4,) are scratch arrays (allocated once per query batch: an
    allocation per candidate tet cost more than its arithmetic)."""
    for corner in range(4):
        for axis in range(3):
            corners[corner, axis] = positions[tet[corner], axis]
    for axis in range(3):
        corners[4, axis] = point[axis]
    for sub in range(4):
        o, i, j, k = replaced[sub, 0], replaced[sub, 1], replaced[sub, 2], replaced[sub, 3]
        # The edge vectors a, b, c from the point, component by component (no temporary arrays).
        a0 = corners[i, 0] - corners[o, 0]
        a1 = corners[i, 1] - corners[o, 1]
        a2 = corners[i, 2] - corners[o, 2]
        b0 = corners[j, 0] - corners[o, 0]
        b1 = corners[j, 1] - corners[o, 1]
        b2 = corners[j, 2] - corners[o, 2]
        c0 = corners[k, 0] - corners[o, 0]
        c1 = corners[k, 1] - corners[o, 1]
        c2 = corners[k, 2] - corners[o, 2]
        cross0 = b1 * c2 - b2 * c1
        cross1 = b2 * c0 - b0 * c2
        cross2 = b0 * c1 - b1 * c0
        # NumPy's einsum of three products sums (p₀ + p₂) + p₁ (its paired inner loop): the same here.
        triple = (a0 * cross0 + a2 * cross2) + a1 * cross1
        volumes[sub] = triple / 6.0
    total = volumes[0] + volumes[1] + volumes[2] + volumes[3]
    for sub in range(4):
        out[sub] = volumes[sub] / total if total != 0.0 else np.nan


@numba.njit(cache=True)
def _locate(  # pragma: no cover - compiled
    points,
    origin,
    edge,
    dims,
    offsets,
    items,
    lower,
    upper,
    centroids,
    radii,
    positions,
    tets,
    tolerance,
    reach,
):
    count = points.shape[0]
    found = np.full(count, -1, dtype=np.int64)
    barycentric = np.full((count, 4), np.nan)
    coordinates = np.empty(4)
    corners = np.empty((5, 3))
    volumes = np.empty(4)
    for q in range(count):
        point = points[q]
        cell = _cell_of(point, origin, edge, dims)
        if cell < 0:
            continue
        best = -1
        best_smallest = 0.0
        for slot in range(offsets[cell], offsets[cell + 1]):
            tet = items[slot]
            if not _in_box(point, lower[tet], upper[tet]):
                continue
            squares = 0.0
            for axis in range(3):
                offset = point[axis] - centroids[tet, axis]
                squares += offset * offset
            if not np.sqrt(squares) <= radii[tet] * reach:
                continue
            _barycentric_into(point, positions, tets[tet], _REPLACED, coordinates, corners, volumes)
            smallest = coordinates[0]
            for corner in range(1, 4):
                value = coordinates[corner]
                if value < smallest or np.isnan(value):
                    smallest = value
            if not smallest >= -tolerance:
                continue
            if best < 0 or smallest > best_smallest or (smallest == best_smallest and tet < best):
                best = tet
                best_smallest = smallest
                barycentric[q] = coordinates
        found[q] = best
    return found, barycentric


#: Faces with |ab × ac| < _THIN_MARGIN · thin · (longest edge)² are thin for the candidate scan: a margin over
#: NumPy's test (`refsim.geometry.closest`), whose |ab × ac| and longest edge this pass computes by the same
#: operations (`refsim.geometry.closest_kernel.triangle_shape`). Every face NumPy evaluates by Ericson's
#: formulas (|ab × ac| ≥ thin L²) has Ericson's
#: distance here exact to about ε L / thin² (2e-14 L), far inside the slack's 1e-9 r, so those faces can be
#: kept by their distance; the margin must only keep NumPy's thin faces on their sphere test. A factor 10
#: made every well-shaped face thin (a right isosceles face has |ab × ac| / L² = 0.5, an equilateral one
#: 0.87) and kept the whole cap of faces within D of a query (about 100 faces per shaft sample above the
#: cube) for NumPy's exact evaluation.
_THIN_MARGIN = 2.0


def surface_candidates(
    points: np.ndarray,
    triangles: np.ndarray,
    centroids: np.ndarray,
    radii: np.ndarray,
    slack: float,
    thin: float,
    vertices: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (query, face) that can hold each query's closest surface point, by one compiled pass over every
    face per query (for few queries on small surfaces: no index to build).

    The bound U of a query is its distance to the nearest vertex (a point of the surface, so U ≥ the distance
    to the surface), over ``vertices`` (v, 3), the distinct points the faces use (each corner of the faces
    when None: the same least distance, up to six times the work on a closed mesh). The faces whose bounding
    sphere comes within U (‖p − c‖ − r ≤ U (1 + slack) + slack r, c the centroid, r the bounding radius) get
    their distance d_f by Ericson's method here, and D is the least: a regular face is kept when d_f ≤
    D (1 + slack) + slack r (its distance is exact to round-off, so the closest faces and their ties are
    kept), a thin one (NumPy's careful path, ``thin`` with a factor :data:`_THIN_MARGIN` of margin) when its
    sphere comes within D. Every face that can hold the closest point is kept, so the closest point chosen
    from these pairs is the one any index giving such a superset gives
    (:class:`refsim.geometry.SurfaceProjector`), with one or two exact evaluations per query.
    """
    triangles = np.ascontiguousarray(triangles, dtype=float)
    vertices = triangles.reshape(-1, 3) if vertices is None else np.ascontiguousarray(vertices, dtype=float)
    return _surface_candidates(
        np.ascontiguousarray(points, dtype=float),
        triangles,
        vertices,
        np.ascontiguousarray(centroids, dtype=float),
        np.ascontiguousarray(radii, dtype=float),
        float(slack),
        float(thin),
    )


@numba.njit(cache=True)
def _surface_candidates(points, triangles, vertices, centroids, radii, slack, thin):  # pragma: no cover
    count, faces = points.shape[0], triangles.shape[0]
    margin = _THIN_MARGIN
    # Thin faces (NumPy's careful path, with a factor _THIN_MARGIN of margin) are kept on their sphere test
    # only.
    is_thin = np.empty(faces, dtype=np.bool_)
    for face in range(faces):
        area2, longest2 = triangle_shape(triangles, face)  # NumPy's two quantities, its bits
        is_thin[face] = not (area2 >= margin * thin * longest2)
    # the pairs kept, by query, faces ascending (at most every face of every query)
    queries = np.empty(count * faces, dtype=np.int64)
    chosen_faces = np.empty(count * faces, dtype=np.int64)
    evaluated = np.empty(faces, dtype=np.int64)  # the faces whose distance a query evaluated, ascending
    distances = np.empty(faces)
    total = 0
    for q in range(count):
        px, py, pz = points[q, 0], points[q, 1], points[q, 2]
        # the nearest vertex's distance: the root of the least square (the root is monotonic and correctly
        # rounded, so this is the least of the roots, one root per query instead of one per vertex; the least
        # of the same squares in any order)
        least = np.inf
        for vertex in range(vertices.shape[0]):
            ox = px - vertices[vertex, 0]
            oy = py - vertices[vertex, 1]
            oz = pz - vertices[vertex, 2]
            least = min(least, ox * ox + oy * oy + oz * oz)
        bound = np.sqrt(least)
        nearest = bound
        evaluated_count = 0
        for face in range(faces):
            # _surface_face_kept(points[q], centroids[face], radii[face], bound, slack), its operations on the
            # entries (no views of the rows: most faces are dropped by the first comparison)
            ox = px - centroids[face, 0]
            oy = py - centroids[face, 1]
            oz = pz - centroids[face, 2]
            squares = ox * ox + oy * oy + oz * oz
            radius = radii[face]
            limit = bound * (1.0 + slack) + slack * radius
            reach = (limit + radius) * (1.0 + 1e-9)
            if squares > reach * reach or not np.sqrt(squares) - radius <= limit:
                continue
            distance = _triangle_distance(points[q], triangles[face])
            evaluated[evaluated_count] = face
            distances[evaluated_count] = distance
            evaluated_count += 1
            nearest = min(nearest, distance)
        for slot in range(evaluated_count):
            face = evaluated[slot]
            if not np.isfinite(distances[slot]):
                continue
            if is_thin[face]:
                chosen = _surface_face_kept(points[q], centroids[face], radii[face], nearest, slack)
            else:
                chosen = distances[slot] <= nearest * (1.0 + slack) + slack * radii[face]
            if chosen:
                queries[total] = q
                chosen_faces[total] = face
                total += 1
    return queries[:total].copy(), chosen_faces[:total].copy()


def closest_faces_scan(
    points: np.ndarray,
    triangles: np.ndarray,
    centroids: np.ndarray,
    radii: np.ndarray,
    slack: float,
    thin: float,
    vertices: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The closest face of each query and its barycentric coordinates there, for few queries on a small
    surface: :func:`surface_candidates`' pairs (``vertices`` as there), Ericson's coordinates on each
    (:func:`refsim.geometry.closest_kernel.ericson_regular`), and per query the pair of least squared
    distance, ties to the lowest face (one compiled pass, :func:`_nearest_pairs`); shapes (q,), (q, 3), and
    (q,) whether each query was settled here.

    A query is settled when every one of its pairs is (a regular triangle, finite non-negative coordinates);
    the others (a thin candidate face) are left to the NumPy path, with zeros here. Where settled, the answer
    is the NumPy path's bit for bit: the closest point Σ b_k t_k summed as ``np.einsum("qk,qki->qi")`` does,
    ((b₀t₀ + b₁t₁) + b₂t₂), the squared distance as ``np.sum(d ** 2, axis=1)``, ((d₀² + d₁²) + d₂²), and the
    choice as ``np.lexsort((faces, distance2, queries))``'s first per query
    (:meth:`refsim.geometry.SurfaceProjector.closest_faces`; ``tests/geometry/test_search.py``). The three
    kernels stay separate compiled functions (one calling the others would compile them again inside it:
    seconds more of a fresh install's first run).
    """
    points = np.ascontiguousarray(points, dtype=float)
    triangles = np.ascontiguousarray(triangles, dtype=float)
    queries, faces = surface_candidates(points, triangles, centroids, radii, slack, thin, vertices)
    pair_points, pair_triangles = points[queries], triangles[faces]
    barycentric, _, settled = ericson_regular(pair_points, pair_triangles, float(thin))
    return _nearest_pairs(queries, faces, barycentric, settled, pair_points, pair_triangles, points.shape[0])


@numba.njit(cache=True)
def _nearest_pairs(
    queries, faces, barycentric, settled, pair_points, pair_triangles, count
):  # pragma: no cover - compiled
    face_index = np.zeros(count, dtype=np.int64)
    coordinates = np.zeros((count, 3))
    least = np.full(count, np.inf)
    found = np.zeros(count, dtype=np.bool_)
    done = np.ones(count, dtype=np.bool_)
    for i in range(
        queries.shape[0]
    ):  # by query, faces ascending (surface_candidates' order): a tie keeps the first
        q = queries[i]
        if not settled[i]:
            done[q] = False
            continue
        u, v, w = barycentric[i, 0], barycentric[i, 1], barycentric[i, 2]
        squares = 0.0
        for axis in range(3):
            closest = (u * pair_triangles[i, 0, axis] + v * pair_triangles[i, 1, axis]) + w * pair_triangles[
                i, 2, axis
            ]
            offset = closest - pair_points[i, axis]
            squares = squares + offset * offset if axis else offset * offset
        if not found[q] or squares < least[q]:
            found[q] = True
            least[q] = squares
            face_index[q] = faces[i]
            coordinates[q, 0], coordinates[q, 1], coordinates[q, 2] = u, v, w
    for q in range(count):
        if not done[q]:
            face_index[q] = 0
            coordinates[q, 0], coordinates[q, 1], coordinates[q, 2] = 0.0, 0.0, 0.0
    return face_index, coordinates, done


@numba.njit(cache=True)
def _triangle_distance(point, triangle):  # pragma: no cover - compiled
    """Distance from a point to a triangle (Ericson's regions; a bound only, so degenerate triangles fall
    back to their nearest vertex, a point of the triangle)."""
    ax, ay, az = triangle[0, 0], triangle[0, 1], triangle[0, 2]
    abx, aby, abz = triangle[1, 0] - ax, triangle[1, 1] - ay, triangle[1, 2] - az
    acx, acy, acz = triangle[2, 0] - ax, triangle[2, 1] - ay, triangle[2, 2] - az
    apx, apy, apz = point[0] - ax, point[1] - ay, point[2] - az
    bpx, bpy, bpz = apx - abx, apy - aby, apz - abz
    cpx, cpy, cpz = apx - acx, apy - acy, apz - acz
    d1, d2 = abx * apx + aby * apy + abz * apz, acx * apx + acy * apy + acz * apz
    d3, d4 = abx * bpx + aby * bpy + abz * bpz, acx * bpx + acy * bpy + acz * bpz
    d5, d6 = abx * cpx + aby * cpy + abz * cpz, acx * cpx + acy * cpy + acz * cpz
    vc, vb, va = d1 * d4 - d3 * d2, d5 * d2 - d1 * d6, d3 * d6 - d5 * d4
    v, w = 0.0, 0.0  # the closest point is a + v ab + w ac
    if d1 <= 0.0 and d2 <= 0.0:
        pass
    elif d3 >= 0.0 and d4 <= d3:
        v = 1.0
    elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0 and d1 - d3 > 0.0:
        v = d1 / (d1 - d3)
    elif d6 >= 0.0 and d5 <= d6:
        w = 1.0
    elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0 and d2 - d6 > 0.0:
        w = d2 / (d2 - d6)
    elif va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0 and (d4 - d3) + (d5 - d6) > 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        v = 1.0 - w
    elif va + vb + vc != 0.0 and np.isfinite(va + vb + vc):
        v, w = vb / (va + vb + vc), vc / (va + vb + vc)
    else:
        a2 = apx * apx + apy * apy + apz * apz
        b2 = bpx * bpx + bpy * bpy + bpz * bpz
        c2 = cpx * cpx + cpy * cpy + cpz * cpz
        return np.sqrt(min(a2, b2, c2))
    x = apx - v * abx - w * acx
    y = apy - v * aby - w * acy
    z = apz - v * abz - w * acz
    return np.sqrt(x * x + y * y + z * z)


@numba.njit(cache=True)
def _surface_face_kept(point, centroid, radius, bound, slack):  # pragma: no cover - compiled
    squares = 0.0
    for axis in range(3):
        offset = point[axis] - centroid[axis]
        squares += offset * offset
    limit = bound * (1.0 + slack) + slack * radius
    # A face whose centroid lies farther than (limit + radius) (1 + 1e-9) fails the test below by far more
    # than its round-off: it is dropped without the root (most faces of a scan).
    reach = (limit + radius) * (1.0 + 1e-9)
    if squares > reach * reach:
        return False
    return np.sqrt(squares) - radius <= limit


def tet_spheres(positions: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid [m] and bounding radius [m] (the largest centroid–vertex distance) of each tet, shapes (m, 3)
    and (m,): the bits of ``positions[tets].mean(axis=1)`` and of the NumPy norm of the vertices' offsets, in
    one compiled pass."""
    positions = readonly(np.ascontiguousarray(positions, dtype=float))
    return _tet_spheres(positions, np.ascontiguousarray(tets, dtype=np.int64))


def triangle_spheres(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid [m] and bounding radius [m] (the largest centroid–vertex distance) of each triangle (f, 3, 3),
    shapes (f, 3) and (f,): the bits of ``triangles.mean(axis=1)`` and of the NumPy norm of the vertices'
    offsets, in one compiled pass (:class:`refsim.geometry.SurfaceProjector` is built on a deformed surface
    at each query of a step)."""
    return _triangle_spheres(np.ascontiguousarray(triangles, dtype=float))


@numba.njit(cache=True)
def _triangle_spheres(triangles):  # pragma: no cover - compiled
    count = triangles.shape[0]
    centroids = np.empty((count, 3))
    radii = np.empty(count)
    for t in range(count):
        for axis in range(3):
            centroids[t, axis] = (triangles[t, 0, axis] + triangles[t, 1, axis] + triangles[t, 2, axis]) / 3.0
        largest = -np.inf
        for corner in range(3):
            squares = 0.0
            for axis in range(3):
                offset = triangles[t, corner, axis] - centroids[t, axis]
                squares += offset * offset
            distance = np.sqrt(squares)
            if distance > largest or np.isnan(distance):
                largest = distance
        radii[t] = largest
    return centroids, radii


@numba.njit(cache=True)
def _tet_spheres(positions, tets):  # pragma: no cover - compiled
    count = tets.shape[0]
    centroids = np.empty((count, 3))
    radii = np.empty(count)
    for t in range(count):
        for axis in range(3):
            total = positions[tets[t, 0], axis]
            for corner in range(1, 4):
                total += positions[tets[t, corner], axis]
            centroids[t, axis] = total / 4.0
        largest = -np.inf
        for corner in range(4):
            squares = 0.0
            for axis in range(3):
                offset = positions[tets[t, corner], axis] - centroids[t, axis]
                squares += offset * offset
            distance = np.sqrt(squares)
            if distance > largest or np.isnan(distance):
                largest = distance
        radii[t] = largest
    return centroids, radii


@numba.njit(cache=True)
def _build(lower, upper, cell_per_box, max_cells_per_box):  # pragma: no cover - compiled
    count = lower.shape[0]
    origin = np.zeros(3)
    extent = np.ones(3)
    edge = 1.0
    if count:
        width = 0.0
        for axis in range(3):
            low, high = lower[0, axis], upper[0, axis]
            for box in range(1, count):
                low = min(low, lower[box, axis])
                high = max(high, upper[box, axis])
            origin[axis], extent[axis] = low, high - low
        for box in range(count):
            width += upper[box, 0] - lower[box, 0]
        edge = width / count * cell_per_box
    edge = max(edge, extent.max() * 1e-9, 1e-300)
    dims = np.ones(3, dtype=np.int64)
    while True:
        cells = 1
        for axis in range(3):
            dims[axis] = np.int64(np.floor(extent[axis] / edge)) + 1
            cells *= dims[axis]
        if cells <= max_cells_per_box * max(count, 1):
            break
        edge *= 1.5
    first = np.empty((count, 3), dtype=np.int64)
    last = np.empty((count, 3), dtype=np.int64)
    for box in range(count):
        for axis in range(3):
            first[box, axis] = min(
                max(np.int64(np.floor((lower[box, axis] - origin[axis]) / edge)), 0), dims[axis] - 1
            )
            last[box, axis] = min(
                max(np.int64(np.floor((upper[box, axis] - origin[axis]) / edge)), 0), dims[axis] - 1
            )
    offsets, items = _register(first, last, dims)
    return origin, edge, dims, offsets, items


@numba.njit(cache=True)
def _register(first, last, dims):  # pragma: no cover - compiled
    cells = dims[0] * dims[1] * dims[2]
    counts = np.zeros(cells + 1, dtype=np.int64)
    for box in range(first.shape[0]):
        for i in range(first[box, 0], last[box, 0] + 1):
            for j in range(first[box, 1], last[box, 1] + 1):
                for k in range(first[box, 2], last[box, 2] + 1):
                    counts[(i * dims[1] + j) * dims[2] + k + 1] += 1
    offsets = np.cumsum(counts)
    items = np.empty(offsets[-1], dtype=np.int64)
    filled = offsets[:-1].copy()
    for box in range(first.shape[0]):
        for i in range(first[box, 0], last[box, 0] + 1):
            for j in range(first[box, 1], last[box, 1] + 1):
                for k in range(first[box, 2], last[box, 2] + 1):
                    cell = (i * dims[1] + j) * dims[2] + k
                    items[filled[cell]] = box
                    filled[cell] += 1
    return offsets, items


@numba.njit(cache=True)
def _cell_of(point, origin, edge, dims):  # pragma: no cover - compiled
    cell = 0
    for axis in range(3):
        index = np.floor((point[axis] - origin[axis]) / edge)
        if not (index >= 0.0 and index < dims[axis]):
            return -1
        cell = cell * dims[axis] + np.int64(index)
    return cell


@numba.njit(cache=True)
def _in_box(point, lower, upper):  # pragma: no cover - compiled
    for axis in range(3):
        if not (lower[axis] <= point[axis] <= upper[axis]):
            return False
    return True


@numba.njit(cache=True)
def _query(points, origin, edge, dims, offsets, items, lower, upper):  # pragma: no cover - compiled
    found = np.zeros(points.shape[0] + 1, dtype=np.int64)
    for q in range(points.shape[0]):
        cell = _cell_of(points[q], origin, edge, dims)
        if cell < 0:
            continue
        for slot in range(offsets[cell], offsets[cell + 1]):
            box = items[slot]
            if _in_box(points[q], lower[box], upper[box]):
                found[q + 1] += 1
    starts = np.cumsum(found)
    queries = np.empty(starts[-1], dtype=np.int64)
    boxes = np.empty(starts[-1], dtype=np.int64)
    for q in range(points.shape[0]):
        cell = _cell_of(points[q], origin, edge, dims)
        if cell < 0:
            continue
        at = starts[q]
        for slot in range(offsets[cell], offsets[cell + 1]):
            box = items[slot]
            if _in_box(points[q], lower[box], upper[box]):
                queries[at] = q
                boxes[at] = box
                at += 1
    return queries, boxes
