"""Incremental greedy projection triangulation of the cut surface's point cloud.

The paper (Perrusi et al. 2021, section 4) triangulates the rest-state point cloud with PCL's greedy
projection triangulation (GP3, Marton, Rusu and Beetz 2009) under three geometric parameters: the smallest
and largest triangle angles θ_min, θ_max and the largest angle θ_s between neighbouring surface normals.
Its history must stay consistent: adding points keeps every existing triangle and adds triangles only around
the new points.
open3d's reconstructions (ball pivoting, Poisson, alpha shapes) rebuild the whole mesh from scratch and cannot
promise that, so the incremental part is built here:

1. Neighbourhoods (scipy's cKDTree): for each new point i, its ``max_neighbours`` nearest points within
   ``neighbour_multiplier`` · d0(i), d0(i) the distance to its nearest other point (GP3's μ·d0 rule),
   capped by ``search_radius``.
2. Candidates, vectorised with numpy: every triangle (i, j, k) with j, k in the neighbourhood of i and
   |j − k| within the same radius; kept only if all three angles lie in [θ_min, θ_max], the triangle normal is
   within θ_s of the three point normals, and no other point lies in the closed triangle once projected on
   its plane (the empty-triangle rule that makes the result conforming). Candidates are oriented so that their
   normal agrees with the point normals.
3. Greedy acceptance, in order of decreasing smallest angle (ties by vertex indices, so the result is
   deterministic), in a numba kernel: a candidate is accepted when each of its edges is new or a border edge
   whose triangle lies on the other side with the opposite winding and a normal within θ_s of the candidate's,
   and when it overlaps no existing or accepted triangle in the candidate's plane (proper edge crossings and
   vertices in closed triangles are tested, with a bounding-box prefilter).

Every triangle has a new point as a vertex; existing triangles are never touched. Point normals are estimated
by a local principal-component plane fit (open3d's ``estimate_normals`` or the equivalent numpy fit here), a
first-order stand-in for the paper's Moving Least Squares, and oriented consistently by propagation over the
neighbourhood graph from the normals of existing triangles.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numba
import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "TriangulationParameters",
    "estimate_normals",
    "orient_normals",
    "triangulate_incremental",
]

logger = logging.getLogger(__name__)

_NORMAL_METHODS = ("open3d", "pca")
# A point lies in a candidate triangle when its barycentric coordinates are all >= −_INSIDE_TOLERANCE
# (a relative tolerance, far above round-off, far below any triangle the angle criteria admit).
_INSIDE_TOLERANCE = 1e-9
# Orientation tests in the greedy kernel use this tolerance times the squared longest candidate edge.
_ORIENTATION_TOLERANCE = 1e-9


@dataclasses.dataclass(frozen=True, kw_only=True)
class TriangulationParameters:
    """Parameters of the greedy projection triangulation (the paper's θ_min, θ_max, θ_s and GP3's μ)."""

    min_angle: float = math.radians(10.0)
    """Smallest angle allowed in a triangle, θ_min [rad], in (0, π/3] (PCL's usual value: 10°)."""
    max_angle: float = math.radians(120.0)
    """Largest angle allowed in a triangle, θ_max [rad], in [π/3, π) and > min_angle (PCL's usual: 120°).
    A square grid needs θ_max >= 90°."""
    max_surface_angle: float = math.radians(45.0)
    """Largest angle between the normals of two triangles sharing an edge, and between a triangle's normal and
    the normals of its vertices, θ_s [rad], in (0, π/2] (PCL's usual value: 45°)."""
    neighbour_multiplier: float = 2.5
    """GP3's μ: a new point connects to points within μ times its nearest-neighbour distance; >= 1."""
    max_neighbours: int = 16
    """Largest neighbourhood of a new point (candidates grow as its square), in [3, 64]."""
    search_radius: float | None = None
    """Optional cap on the neighbourhood radius [m], > 0; None for no cap."""
    normal_estimation: str = "open3d"
    """Point normals by open3d's ``estimate_normals`` ("open3d") or the same plane fit in numpy ("pca")."""

    def __post_init__(self) -> None:
        checks = [
            ("min_angle", self.min_angle, 0.0 < self.min_angle <= math.pi / 3.0, "(0, π/3] rad"),
            ("max_angle", self.max_angle, math.pi / 3.0 <= self.max_angle < math.pi, "[π/3, π) rad"),
            (
                "max_surface_angle",
                self.max_surface_angle,
                0.0 < self.max_surface_angle <= math.pi / 2.0,
                "(0, π/2] rad",
            ),
            ("neighbour_multiplier", self.neighbour_multiplier, self.neighbour_multiplier >= 1.0, "[1, ∞)"),
            (
                "max_neighbours",
                self.max_neighbours,
                isinstance(self.max_neighbours, int | np.integer) and 3 <= self.max_neighbours <= 64,
                "integers in [3, 64]",
            ),
            (
                "search_radius",
                self.search_radius,
                self.search_radius is None
                or (math.isfinite(self.search_radius) and self.search_radius > 0.0),
                "None or (0, ∞) m",
            ),
            (
                "normal_estimation",
                self.normal_estimation,
                self.normal_estimation in _NORMAL_METHODS,
                f"one of {_NORMAL_METHODS}",
            ),
        ]
        for name, value, valid, allowed in checks:
            if not valid or (isinstance(value, float) and not math.isfinite(value)):
                raise ValueError(
                    f"TriangulationParameters.{name} = {value!r} is out of range: allowed {allowed}"
                )
        if self.min_angle >= self.max_angle:
            raise ValueError(
                f"TriangulationParameters.min_angle = {self.min_angle!r} must be < max_angle "
                f"= {self.max_angle!r}"
            )

    @classmethod
    def from_degrees(
        cls, *, min_angle: float, max_angle: float, max_surface_angle: float, **kwargs
    ) -> TriangulationParameters:
        """Parameters with the three angles given in degrees (the other fields as keywords, unchanged)."""
        return cls(
            min_angle=math.radians(min_angle),
            max_angle=math.radians(max_angle),
            max_surface_angle=math.radians(max_surface_angle),
            **kwargs,
        )


# ----------------------------------------------------------------------------------------------------
# Normals


def _normal_neighbourhoods(points: np.ndarray, parameters: TriangulationParameters) -> tuple:
    """Nearest neighbours (self included) within μ times the median nearest-neighbour distance.

    Returns (indices (p, k), valid (p, k) bool, radius [m]).
    """
    count = points.shape[0]
    k = min(parameters.max_neighbours + 1, count)
    tree = cKDTree(points)
    distance, index = tree.query(points, k=k)
    distance, index = distance.reshape(count, k), index.reshape(count, k)
    nearest = distance[:, 1] if k > 1 else np.zeros(count)
    positive = nearest[nearest > 0.0]
    spacing = float(np.median(positive)) if positive.size else 1.0
    radius = parameters.neighbour_multiplier * spacing
    if parameters.search_radius is not None:
        radius = min(radius, parameters.search_radius)
    valid = distance <= radius * (1.0 + 1e-12)
    return index, valid, radius


def _pca_normals(points: np.ndarray, index: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Unit normals of least-squares planes through each neighbourhood (smallest covariance eigenvector)."""
    weights = valid.astype(float)
    counts = np.maximum(weights.sum(axis=1), 1.0)
    neighbours = points[index]  # (p, k, 3)
    centroid = np.einsum("pk,pki->pi", weights, neighbours) / counts[:, None]
    centred = (neighbours - centroid[:, None, :]) * weights[:, :, None]
    covariance = np.einsum("pki,pkj->pij", centred, centred)
    _, vectors = np.linalg.eigh(covariance)
    return np.ascontiguousarray(vectors[:, :, 0])


def orient_normals(
    normals: np.ndarray,
    points: np.ndarray,
    triangles: np.ndarray,
    neighbours: np.ndarray,
    valid: np.ndarray,
) -> np.ndarray:
    """Consistently oriented copy of unit normals.

    Points of triangles take the side of the sum of their triangles' normals (triangles are oriented, so the
    orientation survives re-estimation); the others take the side of the normals of already oriented
    neighbours, sweep after sweep (vectorised per sweep). A component with no oriented point is seeded at its
    lowest index with its largest normal component positive.

    Parameters
    ----------
    normals : Unit normals, any sign, shape (p, 3).
    points : Points [m], shape (p, 3).
    triangles : Oriented triangles, shape (t, 3).
    neighbours : Neighbour indices of each point, shape (p, k).
    valid : Which neighbours count, shape (p, k).

    Returns
    -------
    Oriented unit normals, shape (p, 3).
    """
    normals = np.array(normals, dtype=float)
    count = normals.shape[0]
    reference = np.zeros((count, 3))
    if triangles.shape[0]:
        corners = points[triangles]
        face = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        face /= np.linalg.norm(face, axis=1, keepdims=True)
        np.add.at(reference, triangles.reshape(-1), np.repeat(face, 3, axis=0))
    oriented = np.linalg.norm(reference, axis=1) > 0.0
    flip = oriented & (np.einsum("pi,pi->p", normals, reference) < 0.0)
    normals[flip] *= -1.0
    while not oriented.all():
        usable = valid & oriented[neighbours]
        progress = ~oriented & usable.any(axis=1)
        if not progress.any():
            seed = int(np.flatnonzero(~oriented)[0])
            if normals[seed, np.argmax(np.abs(normals[seed]))] < 0.0:
                normals[seed] *= -1.0
            oriented[seed] = True
            continue
        agreement = np.einsum("pi,pki,pk->p", normals, normals[neighbours], usable.astype(float))
        flip = progress & (agreement < 0.0)
        normals[flip] *= -1.0
        oriented |= progress
    return normals


def estimate_normals(
    points: np.ndarray, triangles: np.ndarray, parameters: TriangulationParameters
) -> np.ndarray:
    """Oriented unit normals of a point cloud by a local plane fit.

    Parameters
    ----------
    points : Point cloud [m], shape (p, 3).
    triangles : Existing oriented triangles on these points, shape (t, 3); they fix the orientation.
    parameters : Neighbourhood size and method (``normal_estimation``).

    Returns
    -------
    Unit normals, shape (p, 3), consistently oriented. Collinear or tiny neighbourhoods give an arbitrary
    direction (no triangle can use such a point until its neighbourhood spans a plane).
    """
    points = np.asarray(points, dtype=float)
    if points.shape[0] == 0:
        return np.zeros((0, 3))
    index, valid, radius = _normal_neighbourhoods(points, parameters)
    if parameters.normal_estimation == "open3d":
        from refsim.cutting.open3d_support import estimate_normals_open3d

        normals = estimate_normals_open3d(points, radius=radius, max_neighbours=parameters.max_neighbours + 1)
    else:
        normals = _pca_normals(points, index, valid)
    return orient_normals(normals, points, np.asarray(triangles, dtype=np.int64), index, valid)


# ----------------------------------------------------------------------------------------------------
# Candidates


def _angles(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Interior angles [rad] at a, b, c of triangles given by corner arrays (t, 3); shape (t, 3)."""

    def angle(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.arctan2(np.linalg.norm(np.cross(u, v), axis=1), np.einsum("ti,ti->t", u, v))

    return np.stack([angle(b - a, c - a), angle(c - b, a - b), angle(a - c, b - c)], axis=1)


def _candidates(
    points: np.ndarray,
    normals: np.ndarray,
    triangles: np.ndarray,
    first_new_point: int,
    parameters: TriangulationParameters,
) -> tuple[np.ndarray, np.ndarray]:
    """Oriented candidate triangles in greedy order and their unit normals, shapes (c, 3), (c, 3)."""
    count = points.shape[0]
    new = np.arange(first_new_point, count)
    k = min(parameters.max_neighbours + 1, count)
    distance, index = cKDTree(points).query(points[new], k=k)
    distance, index = distance.reshape(new.size, k), index.reshape(new.size, k)
    distance = np.where(index == new[:, None], np.inf, distance)
    nearest = distance.min(axis=1)
    radius = parameters.neighbour_multiplier * nearest
    if parameters.search_radius is not None:
        radius = np.minimum(radius, parameters.search_radius)
    valid = (distance <= radius[:, None]) & (nearest > 0.0)[:, None]

    first, second = np.triu_indices(k, 1)
    pair_valid = valid[:, first] & valid[:, second]
    row, pair = np.nonzero(pair_valid)
    a, b, c = new[row], index[row, first[pair]], index[row, second[pair]]
    pa, pb, pc = points[a], points[b], points[c]
    keep = np.linalg.norm(pc - pb, axis=1) <= radius[row]
    row, a, b, c, pa, pb, pc = row[keep], a[keep], b[keep], c[keep], pa[keep], pb[keep], pc[keep]

    angles = _angles(pa, pb, pc)
    keep = (angles.min(axis=1) >= parameters.min_angle) & (angles.max(axis=1) <= parameters.max_angle)
    row, a, b, c, pa, pb, pc, angles = (x[keep] for x in (row, a, b, c, pa, pb, pc, angles))

    face = np.cross(pb - pa, pc - pa)
    face /= np.linalg.norm(face, axis=1, keepdims=True)
    flip = np.einsum("ti,ti->t", face, normals[a] + normals[b] + normals[c]) < 0.0
    face[flip] *= -1.0
    b, c = np.where(flip, c, b), np.where(flip, b, c)
    pb, pc = np.where(flip[:, None], pc, pb), np.where(flip[:, None], pb, pc)
    cos_surface = math.cos(parameters.max_surface_angle)
    keep = np.ones(a.size, dtype=bool)
    for vertex in (a, b, c):
        keep &= np.einsum("ti,ti->t", face, normals[vertex]) >= cos_surface
    row, a, b, c, pa, pb, pc, angles, face = (x[keep] for x in (row, a, b, c, pa, pb, pc, angles, face))

    # One copy per triangle (several new vertices generate it), none already present.
    ordered = np.sort(np.stack([a, b, c], axis=1), axis=1)
    keys = (ordered[:, 0] * count + ordered[:, 1]) * count + ordered[:, 2]
    keys, unique = np.unique(keys, return_index=True)
    if triangles.shape[0]:
        existing = np.sort(triangles, axis=1)
        existing_keys = (existing[:, 0] * count + existing[:, 1]) * count + existing[:, 2]
        fresh = ~np.isin(keys, existing_keys)
        keys, unique = keys[fresh], unique[fresh]
    row, a, b, c, pa, pb, pc, angles, face = (x[unique] for x in (row, a, b, c, pa, pb, pc, angles, face))

    keep = ~_holds_other_point(points, index[row], a, b, c, face)
    keys, a, b, c, angles, face = keys[keep], a[keep], b[keep], c[keep], angles[keep], face[keep]
    quality = np.round(angles.min(axis=1), 10)
    order = np.lexsort((keys, -quality))
    candidates = np.stack([a[order], b[order], c[order]], axis=1).astype(np.int64)
    return candidates, np.ascontiguousarray(face[order])


def _holds_other_point(points, neighbourhood, a, b, c, face) -> np.ndarray:
    """Whether a neighbourhood point other than the corners lies in each closed triangle (in its plane).

    Points farther than half the longest edge from the triangle's plane do not count. Checking the
    neighbourhood of the generating vertex a suffices: a point in the triangle is nearer to a than the farther
    of b and c, which are both in a's nearest-neighbour list.
    """
    return _holds_other_point_kernel(
        points,
        np.ascontiguousarray(neighbourhood, dtype=np.int64),
        np.stack([a, b, c], axis=1).astype(np.int64),
        np.ascontiguousarray(face),
        _INSIDE_TOLERANCE,
    )


@numba.njit(cache=True)
def _holds_other_point_kernel(points, neighbourhood, corners, face, tolerance):
    result = np.zeros(corners.shape[0], np.bool_)
    for t in range(corners.shape[0]):
        a, b, c = corners[t, 0], corners[t, 1], corners[t, 2]
        v0 = points[b] - points[a]
        v1 = points[c] - points[a]
        d00, d01, d11 = np.sum(v0 * v0), np.sum(v0 * v1), np.sum(v1 * v1)
        denominator = d00 * d11 - d01 * d01
        longest = np.sqrt(max(d00, d11, np.sum((points[c] - points[b]) ** 2)))
        for k in range(neighbourhood.shape[1]):
            q = neighbourhood[t, k]
            if q == a or q == b or q == c:
                continue
            v2 = points[q] - points[a]
            if abs(np.sum(v2 * face[t])) > 0.5 * longest:
                continue
            d20, d21 = np.sum(v2 * v0), np.sum(v2 * v1)
            v = (d11 * d20 - d01 * d21) / denominator
            w = (d00 * d21 - d01 * d20) / denominator
            if v >= -tolerance and w >= -tolerance and 1.0 - v - w >= -tolerance:
                result[t] = True
                break
    return result


# ----------------------------------------------------------------------------------------------------
# Greedy acceptance (numba)


@numba.njit(cache=True)
def _orient2d(ax, ay, bx, by, cx, cy):
    return (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)


@numba.njit(cache=True)
def _in_closed_triangle(px, py, x, y, eps):
    """Point in the closed counter-clockwise 2-D triangle (x[0..2], y[0..2])."""
    return (
        _orient2d(x[0], y[0], x[1], y[1], px, py) >= -eps
        and _orient2d(x[1], y[1], x[2], y[2], px, py) >= -eps
        and _orient2d(x[2], y[2], x[0], y[0], px, py) >= -eps
    )


@numba.njit(cache=True)
def _overlap2d(x1, y1, id1, x2, y2, id2, eps):
    """Whether two counter-clockwise 2-D triangles with vertex ids overlap (shared ids are not tested)."""
    for i in range(3):
        shared = id2[i] == id1[0] or id2[i] == id1[1] or id2[i] == id1[2]
        if not shared and _in_closed_triangle(x2[i], y2[i], x1, y1, eps):
            return True
        shared = id1[i] == id2[0] or id1[i] == id2[1] or id1[i] == id2[2]
        if not shared and _in_closed_triangle(x1[i], y1[i], x2, y2, eps):
            return True
    for i in range(3):
        p, q = i, (i + 1) % 3
        for j in range(3):
            r, s = j, (j + 1) % 3
            if id1[p] == id2[r] or id1[p] == id2[s] or id1[q] == id2[r] or id1[q] == id2[s]:
                continue
            d1 = _orient2d(x2[r], y2[r], x2[s], y2[s], x1[p], y1[p])
            d2 = _orient2d(x2[r], y2[r], x2[s], y2[s], x1[q], y1[q])
            d3 = _orient2d(x1[p], y1[p], x1[q], y1[q], x2[r], y2[r])
            d4 = _orient2d(x1[p], y1[p], x1[q], y1[q], x2[s], y2[s])
            if ((d1 > eps and d2 < -eps) or (d1 < -eps and d2 > eps)) and (
                (d3 > eps and d4 < -eps) or (d3 < -eps and d4 > eps)
            ):
                return True
    return False


@numba.njit(cache=True)
def _unit_normal(points, tri):
    a, b, c = points[tri[0]], points[tri[1]], points[tri[2]]
    n = np.cross(b - a, c - a)
    return n / np.sqrt(np.sum(n * n))


@numba.njit(cache=True)
def _accept_greedy(points, triangles, candidates, candidate_normals, cos_surface):
    """Accept candidates in order when they keep the mesh manifold, consistently oriented and non-overlapping.

    Returns a boolean mask over the candidates.
    """
    n = points.shape[0]
    old = triangles.shape[0]
    capacity = old + candidates.shape[0]
    tri = np.empty((capacity, 3), np.int64)
    tri_normal = np.empty((capacity, 3))
    low = np.empty((capacity, 3))
    high = np.empty((capacity, 3))
    edges = numba.typed.Dict.empty(key_type=numba.types.int64, value_type=numba.types.int64)
    count = 0
    for t in range(old):
        tri[count] = triangles[t]
        tri_normal[count] = _unit_normal(points, triangles[t])
        for d in range(3):
            low[count, d] = min(points[tri[count, 0], d], points[tri[count, 1], d], points[tri[count, 2], d])
            high[count, d] = max(points[tri[count, 0], d], points[tri[count, 1], d], points[tri[count, 2], d])
        for e in range(3):
            u, v = tri[count, e], tri[count, (e + 1) % 3]
            key = min(u, v) * n + max(u, v)
            edges[key] = -1 if key in edges else count
        count += 1

    accepted = np.zeros(candidates.shape[0], np.bool_)
    x1, y1, x2, y2 = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    id2 = np.empty(3, np.int64)
    for ci in range(candidates.shape[0]):
        cand = candidates[ci]
        normal = candidate_normals[ci]
        ok = True
        for e in range(3):
            u, v = cand[e], cand[(e + 1) % 3]
            key = min(u, v) * n + max(u, v)
            if key in edges:
                t = edges[key]
                if t < 0:
                    ok = False
                    break
                # The neighbour must traverse the shared edge as v -> u (consistent winding, other side).
                reverse = False
                for f in range(3):
                    if tri[t, f] == v and tri[t, (f + 1) % 3] == u:
                        reverse = True
                if not reverse or np.sum(normal * tri_normal[t]) < cos_surface:
                    ok = False
                    break
        if not ok:
            continue

        a = points[cand[0]]
        e1 = points[cand[1]] - a
        scale2 = max(
            np.sum(e1 * e1),
            np.sum((points[cand[2]] - a) ** 2),
            np.sum((points[cand[2]] - points[cand[1]]) ** 2),
        )
        e1 = e1 / np.sqrt(np.sum(e1 * e1))
        e2 = np.cross(normal, e1)
        eps = _ORIENTATION_TOLERANCE * scale2
        pad = _ORIENTATION_TOLERANCE * np.sqrt(scale2)
        clow = np.empty(3)
        chigh = np.empty(3)
        for d in range(3):
            clow[d] = min(points[cand[0], d], points[cand[1], d], points[cand[2], d]) - pad
            chigh[d] = max(points[cand[0], d], points[cand[1], d], points[cand[2], d]) + pad
        for i in range(3):
            r = points[cand[i]] - a
            x1[i], y1[i] = np.sum(r * e1), np.sum(r * e2)
        for t in range(count):
            if (
                low[t, 0] > chigh[0]
                or high[t, 0] < clow[0]
                or low[t, 1] > chigh[1]
                or high[t, 1] < clow[1]
                or low[t, 2] > chigh[2]
                or high[t, 2] < clow[2]
            ):
                continue
            shared = 0
            for i in range(3):
                if tri[t, i] == cand[0] or tri[t, i] == cand[1] or tri[t, i] == cand[2]:
                    shared += 1
            if shared >= 2:
                continue  # shares an edge: decided by the edge test above
            for i in range(3):
                r = points[tri[t, i]] - a
                x2[i], y2[i] = np.sum(r * e1), np.sum(r * e2)
                id2[i] = tri[t, i]
            if _orient2d(x2[0], y2[0], x2[1], y2[1], x2[2], y2[2]) < 0.0:
                x2[1], x2[2] = x2[2], x2[1]
                y2[1], y2[2] = y2[2], y2[1]
                id2[1], id2[2] = id2[2], id2[1]
            if _overlap2d(x1, y1, cand, x2, y2, id2, eps):
                ok = False
                break
        if not ok:
            continue

        accepted[ci] = True
        tri[count] = cand
        tri_normal[count] = normal
        low[count] = clow
        high[count] = chigh
        for e in range(3):
            u, v = cand[e], cand[(e + 1) % 3]
            key = min(u, v) * n + max(u, v)
            edges[key] = -1 if key in edges else count
        count += 1
    return accepted


# ----------------------------------------------------------------------------------------------------
# Entry point


def triangulate_incremental(
    points: np.ndarray,
    normals: np.ndarray,
    triangles: np.ndarray,
    first_new_point: int,
    parameters: TriangulationParameters | None = None,
) -> np.ndarray:
    """New triangles around the new points of a cloud, leaving the existing triangles unchanged.

    Parameters
    ----------
    points : Point cloud [m], shape (p, 3); points ``first_new_point:`` are the new ones.
    normals : Oriented unit point normals, shape (p, 3) (see `estimate_normals`).
    triangles : Existing triangles, oriented, shape (t, 3), vertex indices < first_new_point.
    first_new_point : Index of the first new point, in [0, p].
    parameters : θ_min, θ_max, θ_s and the neighbourhood; defaults when None.

    Returns
    -------
    New triangles, shape (k, 3), each with at least one new vertex, oriented with their normal
    (b − a) × (c − a) on the side of the point normals, in acceptance order (deterministic).
    """
    parameters = parameters or TriangulationParameters()
    points = np.ascontiguousarray(points, dtype=float)
    normals = np.ascontiguousarray(normals, dtype=float)
    triangles = np.ascontiguousarray(np.asarray(triangles, dtype=np.int64).reshape(-1, 3))
    count = points.shape[0]
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"points and normals must have shape (p, 3), got {points.shape} and {normals.shape}")
    if not 0 <= first_new_point <= count:
        raise ValueError(f"first_new_point = {first_new_point} is out of range [0, {count}]")
    if triangles.size and (triangles.min() < 0 or triangles.max() >= first_new_point):
        raise ValueError(f"existing triangles must index the existing points [0, {first_new_point})")
    if first_new_point == count or count < 3:
        return np.zeros((0, 3), dtype=np.int64)
    candidates, candidate_normals = _candidates(points, normals, triangles, first_new_point, parameters)
    if candidates.shape[0] == 0:
        return np.zeros((0, 3), dtype=np.int64)
    accepted = _accept_greedy(
        points, triangles, candidates, candidate_normals, math.cos(parameters.max_surface_angle)
    )
    logger.debug(
        "triangulation: %d new points, %d candidates, %d accepted",
        count - first_new_point,
        candidates.shape[0],
        int(accepted.sum()),
    )
    return candidates[accepted]
