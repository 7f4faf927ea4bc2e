"""Growth of the cut surface (paper, section 4): the first surface at the cut start, and tears.

Pure functions of arrays and of a :class:`CutGrowth` built once per tissue (its rest positions, tets and the
scene's cutting parameters). The surface lives in rest coordinates (the paper's equation 4): a point found in
the deformed tissue keeps the tet and barycentric coordinates it has there, and its rest position is the same
coordinates applied to the rest nodes.

- Cut start: the insertion path, resampled every d_c, swept along the cut direction ĉ up to d_t every d_c.
- Tear: when a border row's force reaches f_t, the front of the cut (border points whose inward direction is
  against ĉ) along the inserted length grows by d_t against that row's direction −n_c. The growth is done in
  rest coordinates, where the triangulation lives: the deformed-state direction is pulled back through each
  front point's deformation gradient (F⁻¹ u), so new points keep the rest-state spacing d_c. Growing the whole
  front rather than one point keeps the surface triangulable under the angle limits.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from refsim.cutting.surface import CutSurface
from refsim.cutting.triangulation import TriangulationParameters
from refsim.geometry import TetLocator

__all__ = [
    "CutGrowth",
    "border_inward_directions",
    "far_from",
    "front_border_points",
    "resample_polyline",
    "sweep_points",
]

# Border points whose inward direction has less than this component against ĉ are not on the front. cos(60°).
FRONT_COSINE = 0.5


def resample_polyline(points: np.ndarray, spacing: float) -> np.ndarray:
    """Points every ``spacing`` [m] along a polyline (its first and last points included), shape (q, 3)."""
    points = np.asarray(points, dtype=float)
    if len(points) < 2:
        return points.copy()
    lengths = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    total = lengths[-1]
    if total <= 0.0:
        return points[:1].copy()
    count = max(int(round(total / spacing)), 1)
    samples = np.linspace(0.0, total, count + 1)
    return np.stack([np.interp(samples, lengths, points[:, k]) for k in range(3)], axis=1)


def sweep_points(base_points: np.ndarray, direction: np.ndarray, extent: float, spacing: float, *, first: int = 0):
    """``base_points`` swept along ``direction`` every ``spacing`` up to ``extent``: shape (q · (K + 1 − first), 3),
    K = max(round(extent / spacing), 1); ``first`` = 1 leaves out the base points themselves."""
    steps = max(int(round(extent / spacing)), 1)
    offsets = np.arange(first, steps + 1) * (extent / steps)
    direction = np.asarray(direction, dtype=float)
    if direction.ndim == 1:
        direction = np.broadcast_to(direction, np.shape(base_points))
    return (base_points[:, None, :] + offsets[None, :, None] * direction[:, None, :]).reshape(-1, 3)


def border_inward_directions(triangles: np.ndarray, points: np.ndarray, border_points: np.ndarray) -> np.ndarray:
    """Unit inward direction of the surface at each border point, in the surface, normal to the border.

    For each border edge (a, b) of triangle (a, b, c), the inward direction is the component of c − a normal to
    b − a; a border point averages those of its border edges.

    Returns
    -------
    Directions, shape (len(border_points), 3) (zero where undefined).
    """
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    opposite = np.concatenate([triangles[:, 2], triangles[:, 0], triangles[:, 1]])
    key = np.sort(edges, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    border = counts[inverse.ravel()] == 1
    a, b, c = points[edges[border, 0]], points[edges[border, 1]], points[opposite[border]]
    along = b - a
    along /= np.linalg.norm(along, axis=1, keepdims=True)
    inward = (c - a) - np.einsum("ij,ij->i", c - a, along)[:, None] * along
    inward /= np.linalg.norm(inward, axis=1, keepdims=True)
    sums = np.zeros((len(points), 3))
    np.add.at(sums, edges[border, 0], inward)
    np.add.at(sums, edges[border, 1], inward)
    out = sums[border_points]
    norms = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, norms, out=np.zeros_like(out), where=norms > 1e-12)


def front_border_points(cut, surface: np.ndarray, cut_direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Border points on the front of the cut (inward direction against ĉ by more than 60°) and their inward
    directions, shapes (b,) and (b, 3)."""
    border = cut.border_points()
    inward = border_inward_directions(cut.triangles, surface, border)
    front = inward @ cut_direction <= -FRONT_COSINE
    return border[front], inward[front]


def far_from(points: np.ndarray, existing: np.ndarray, distance: float) -> np.ndarray:
    """The points farther than ``distance`` [m] from every existing point (KD-tree), shape (k, 3)."""
    from scipy.spatial import cKDTree

    if len(points) == 0 or len(existing) == 0:
        return points
    nearest, _ = cKDTree(existing).query(points, k=1)
    return points[nearest > distance]


@dataclass(frozen=True)
class CutGrowth:
    """How the cut surface of one tissue grows.

    Attributes
    ----------
    rest_positions : Rest positions of the tissue nodes [m], shape (node_count, 3).
    tets : Tissue tets, shape (tet_count, 4).
    point_spacing : d_c [m], > 0.
    extent : d_t [m], > 0: how far the first surface reaches from the path and how far a tear extends.
    parameters : Triangulation limits.
    """

    rest_positions: np.ndarray
    tets: np.ndarray
    point_spacing: float
    extent: float
    parameters: TriangulationParameters

    @cached_property
    def rest_locator(self) -> TetLocator:
        """Tet locator on the rest positions (built on first use, then kept)."""
        return TetLocator(self.rest_positions, self.tets)

    def start(self, path_points: np.ndarray, direction: np.ndarray, positions: np.ndarray, step: int) -> CutSurface:
        """The first cut surface: the path swept along the cut direction.

        Parameters
        ----------
        path_points : The insertion points in the deformed tissue [m], shape (p, 3), entry first.
        direction : ĉ, unit, shape (3,).
        positions : Tissue positions [m], shape (node_count, 3).
        step : The step creating the points.
        """
        resampled = resample_polyline(path_points, self.point_spacing)
        cloud = sweep_points(resampled, direction, self.extent, self.point_spacing)
        return self.grow_deformed(CutSurface.empty(self.parameters), cloud, positions, step)

    def grow_deformed(self, cut: CutSurface, points: np.ndarray, positions: np.ndarray, step: int) -> CutSurface:
        """Add deformed-state points, kept in rest coordinates (equation 4); drop those outside the tissue and
        those within d_c/2 of an existing point."""
        if cut.point_count:
            points = far_from(points, cut.deformed_points(positions, self.tets), 0.5 * self.point_spacing)
        if len(points) == 0:
            return cut
        tets, barycentric = TetLocator(positions, self.tets).locate(points)
        inside = tets >= 0
        if not np.any(inside):
            return cut
        rest = np.einsum("pk,pkj->pj", barycentric[inside], self.rest_positions[self.tets[tets[inside]]])
        return cut.with_points(rest, tets[inside], barycentric[inside], step)

    def grow_rest(self, cut: CutSurface, rest_points: np.ndarray, step: int) -> CutSurface:
        """Add rest-state points (those inside the tissue and farther than d_c/2 from every point)."""
        if cut.point_count and len(rest_points):
            rest_points = far_from(rest_points, cut.rest_points, 0.5 * self.point_spacing)
        if len(rest_points) == 0:
            return cut
        tets, barycentric = self.rest_locator.locate(rest_points)
        inside = tets >= 0
        if not np.any(inside):
            return cut
        return cut.with_points(rest_points[inside], tets[inside], barycentric[inside], step)

    def tear(
        self,
        cut: CutSurface,
        *,
        positions: np.ndarray,
        deformation_gradients: np.ndarray,
        outward: np.ndarray,
        cut_direction: np.ndarray,
        needle,
        entry_arc_length: float,
        step: int,
    ) -> CutSurface:
        """Extend the front of the cut along the inserted length by d_t, along ``outward`` (deformed state).

        Parameters
        ----------
        cut : The cut surface.
        positions : Tissue positions [m], shape (node_count, 3).
        deformation_gradients : F of every tet at ``positions``, shape (tet_count, 3, 3).
        outward : Unit direction of the growth in the deformed state (−n_c of the tearing row), shape (3,).
        cut_direction : ĉ, unit, shape (3,).
        needle : The needle's centreline (anything with ``project(points) -> (arc_lengths, closest)``).
        entry_arc_length : Arc length of the needle at the entry point [m].
        step : The step creating the points.
        """
        surface = cut.deformed_points(positions, self.tets)
        front, _ = front_border_points(cut, surface, cut_direction)
        arc, _ = needle.project(surface[front])
        front = front[arc >= entry_arc_length - self.point_spacing]  # along the inserted length
        gradients = deformation_gradients[cut.tet_indices[front]]
        rest_outward = np.linalg.solve(gradients, np.broadcast_to(outward, (front.size, 3))[..., None])[..., 0]
        rest_outward /= np.linalg.norm(rest_outward, axis=1, keepdims=True)
        new_points = sweep_points(cut.rest_points[front], rest_outward, self.extent, self.point_spacing, first=1)
        return self.grow_rest(cut, new_points, step)
