"""The cut as a strip grown by the needle: a structured surface whose front is a crack tip in the tissue.

The paper grows a point cloud and triangulates it with a greedy projection. Tried on scenes it was not built
around (a diagonal stroke, a tilted needle, an entry on a mesh vertex) that cloud left holes inside the strip,
and the border of a hole, taken for the front of the cut, put a row behind the needle: the cut then tore every
step and ran to the wall of the tissue. Here the cut is a *strip* with an explicit front:

- **Columns** along the needle: the insertion path at the cut start, resampled every d_c (column j).
- **Layers** across it: layer 0 is the path (the back border); each later layer is the front at the time it
  was laid. Consecutive layers are joined by two triangles per column pair, so the surface is a manifold
  disc with no holes, whatever the mesh, the direction or the entry point.
- **Blocks** of columns added below the strip when the needle goes deeper while it cuts: each starts on the
  needle's line (the tissue below the strip was not cut) and is laid like the strip, joined to its upper
  neighbour by the layers laid after it was added (:class:`CutStrip`).
- **The crack tip**: one material point per column (a tet and barycentric coordinates, kept in rest
  coordinates like every cut point, the paper's equation 4) where the tissue is cut up to. The front rows of
  the needle press on the crack tip. It advances where the needle pushes through it, in the direction it
  pushes (pulled back to rest coordinates through the local deformation gradient, F⁻¹u), and a new layer is
  laid at the crack tip once it is d_c ahead of the last one.

So the cut extends only where the needle pushes on its front, within the region the needle sweeps, and the
surface is the region the crack tip swept, less than d_c behind it.
"""

from __future__ import annotations

import time as clock
from dataclasses import dataclass

import numpy as np

from refsim.cutting.surface import CutSurface, TriangulationReport
from refsim.geometry import TetLocator

__all__ = [
    "CutFront",
    "CutStrip",
    "locate_material_points",
    "recorded_strip",
    "recorded_surface",
    "strip_triangles",
]

# A point outside every tet by at most this much in barycentric coordinates is kept in the nearest tet (points
# on the tissue surface: the entry point, by round-off); farther ones are outside the tissue.
_OUTSIDE_TOLERANCE = 1e-6


def locate_material_points(
    locator: TetLocator,
    positions: np.ndarray,
    tets: np.ndarray,
    points: np.ndarray,
    *,
    snap_distance: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tets and barycentric coordinates of points in a configuration of the tissue.

    A point outside every tet is moved to the closest point of one of its 8 nearest tets (by centroid; the
    barycentric coordinates clipped to [0, 1] and renormalised) when that is within ``snap_distance`` [m] (and
    always within 1e-6 of the tet's size: round-off on the surface); otherwise it is reported outside.

    Returns
    -------
    (tets (q,), barycentric (q, 4), inside (q,) bool); tets are -1 where outside.
    """
    found, barycentric = locator.locate(points)
    outside = np.flatnonzero(found < 0)
    if outside.size:
        from scipy.spatial import cKDTree

        centroids = positions[tets].mean(axis=1)
        _, nearest = cKDTree(centroids).query(points[outside], k=min(8, len(tets)))
        nearest = nearest.reshape(outside.size, -1)
        best = np.full(outside.size, np.inf)
        for column in range(nearest.shape[1]):  # 8 candidate tets per point, vectorised over the points
            candidate = nearest[:, column]
            corners = positions[tets[candidate]]
            matrix = np.concatenate([corners.transpose(0, 2, 1), np.ones((candidate.size, 1, 4))], axis=1)
            rhs = np.concatenate([points[outside], np.ones((outside.size, 1))], axis=1)
            coordinates = np.linalg.solve(matrix, rhs[..., None])[..., 0]
            clipped = np.clip(coordinates, 0.0, None)
            clipped /= clipped.sum(axis=1, keepdims=True)
            snapped = np.einsum("qk,qkj->qj", clipped, corners)
            distance = np.linalg.norm(snapped - points[outside], axis=1)
            accept = (distance < best) & (
                (distance <= snap_distance) | (coordinates.min(axis=1) >= -_OUTSIDE_TOLERANCE)
            )
            best[accept] = distance[accept]
            found[outside[accept]] = candidate[accept]
            barycentric[outside[accept]] = np.where(
                (coordinates.min(axis=1) >= -_OUTSIDE_TOLERANCE)[accept, None],
                coordinates[accept],
                clipped[accept],
            )
    return found, barycentric, found >= 0


def strip_triangles(back: np.ndarray, front: np.ndarray, joined: np.ndarray | None = None) -> np.ndarray:
    """Triangles joining two layers of point indices column by column, shape (t, 3).

    Quad j is (back_j, back_j+1, front_j+1, front_j), split into (back_j, back_j+1, front_j) and
    (back_j+1, front_j+1, front_j); triangles with a repeated vertex (a column that did not advance) are left
    out, and so are quads with a column not laid yet (index −1) or not ``joined`` (shape (q − 1,), bool: which
    column pairs are joined; all by default). Every triangle has the same winding, so the strip is oriented.
    """
    back, front = np.asarray(back), np.asarray(front)
    pairs = (back[:-1] >= 0) & (back[1:] >= 0) & (front[:-1] >= 0) & (front[1:] >= 0)
    if joined is not None:
        pairs &= np.asarray(joined, dtype=bool)
    a, b = back[:-1][pairs], back[1:][pairs]
    c, d = front[1:][pairs], front[:-1][pairs]
    first = np.stack([a, b, d], axis=1)
    second = np.stack([b, c, d], axis=1)
    triangles = np.concatenate([first, second])
    distinct = (
        (triangles[:, 0] != triangles[:, 1])
        & (triangles[:, 1] != triangles[:, 2])
        & (triangles[:, 0] != triangles[:, 2])
    )
    return triangles[distinct]


@dataclass(frozen=True)
class CutFront:
    """The crack tip: one material point per column of the strip.

    Attributes
    ----------
    rest_points : Rest positions [m], shape (q, 3).
    tet_indices : Tet of each point, shape (q,).
    barycentric : Barycentric coordinates in that tet, shape (q, 4).
    """

    rest_points: np.ndarray
    tet_indices: np.ndarray
    barycentric: np.ndarray

    def positions(self, tissue_positions: np.ndarray, tets: np.ndarray) -> np.ndarray:
        """The crack tip in a tissue configuration [m], shape (q, 3)."""
        return np.einsum("pk,pkj->pj", self.barycentric, tissue_positions[tets[self.tet_indices]])


@dataclass(frozen=True)
class CutStrip:
    """The structure of the cut: which surface points form each layer, and the crack tip.

    The strip is made of *blocks* of columns: its own, on the insertion path at the cut start, and one for
    each time the needle went deeper while cutting (:meth:`extended`), whose first layer is the needle's line
    below the strip when it was added (the tissue there had not been cut: the crack tip starts on it). Each
    block is laid like the strip (a column's points from where its crack tip started to where it is), and two
    neighbouring columns of different blocks are joined only by layers laid after the younger one was added,
    so no triangle covers tissue below the strip that the crack tip has not swept.

    Attributes
    ----------
    layers : Point indices into the `CutSurface`, shape (layer_count, column_count); row 0 is the path; −1
        where a column has no point yet (a column added below the strip, before its first layer).
    front : The crack tip.
    depths : Depth of each column along the needle below the tissue surface at the cut start [m], shape
        (column_count,) (0 for the entry column): where on the needle each column's crack tip is taken to
        (:func:`refsim.cutting.growth.crack_tip_targets`).
    origins : Where each column's crack tip started (the path, or the needle when the column was added), the
        first point laid in a column, shape (column_count,) `CutFront`. None: the strip's front when the
        strip is built (its own block only).
    births : The step each column was added at, shape (column_count,) (0 for the strip's own columns). None:
        all 0.
    parts : The part of the tissue each column is in, shape (column_count,), non-decreasing from the entry
        column (0) down: a needle through layers with a gap between them cuts each, and columns of different
        parts are never joined by a triangle, nor their crack tips by a segment. None: all in one part.
    """

    layers: np.ndarray
    front: CutFront
    depths: np.ndarray
    origins: CutFront | None = None
    births: np.ndarray | None = None
    parts: np.ndarray | None = None

    @property
    def column_count(self) -> int:
        return int(self.layers.shape[1])

    def part_ranges(self) -> tuple[tuple[int, int], ...]:
        """The columns of each part of the tissue the strip is in, as [first, end) ranges in column order."""
        if self.parts is None:
            return ((0, self.column_count),)
        starts = np.flatnonzero(np.diff(self.parts)) + 1
        bounds = [0, *starts.tolist(), self.column_count]
        return tuple(zip(bounds[:-1], bounds[1:], strict=True))

    def has_front(self) -> bool:
        """Whether some part of the tissue holds two columns or more: a crack tip with a segment the front
        rows can press on."""
        return any(end - first >= 2 for first, end in self.part_ranges())

    def own_triangles(self, cut: CutSurface) -> np.ndarray:
        """Which triangles of ``cut`` this strip laid (all their points in its layers), shape
        (triangle_count,) bool: the rest of the cut are older strips' and other needles'."""
        points = np.zeros(cut.point_count, dtype=bool)
        points[self.layers[self.layers >= 0]] = True
        return points[cut.triangles].all(axis=1)

    def _parts(self) -> np.ndarray:
        return np.zeros(self.column_count, dtype=np.int64) if self.parts is None else self.parts

    @property
    def last_layer(self) -> np.ndarray:
        """Point indices of the layer laid last, shape (q,) (−1 for a column with no point yet)."""
        return self.layers[-1]

    def rear_edge(self, cut: CutSurface, positions: np.ndarray, tets: np.ndarray) -> np.ndarray:
        """Where each column's crack tip started, in a tissue configuration [m], shape (q, 3): the path for
        the strip's own columns (layer 0), the needle's line where it was added for a column of a block added
        below the strip. The line the needle entered its cut along, column by column."""
        first = self.layers[0]
        rear = cut.deformed_points(positions, tets)[np.maximum(first, 0)]
        waiting = first < 0
        if np.any(waiting):
            rear[waiting] = self._origins().positions(positions, tets)[waiting]
        return rear

    def rest_rear_edge(self, cut: CutSurface) -> np.ndarray:
        """The rear edge (:meth:`rear_edge`) in rest coordinates [m], shape (q, 3)."""
        first = self.layers[0]
        rear = cut.rest_points[np.maximum(first, 0)]
        waiting = first < 0
        if np.any(waiting):
            rear[waiting] = self._origins().rest_points[waiting]
        return rear

    def _births(self) -> np.ndarray:
        return np.zeros(self.column_count, dtype=np.int64) if self.births is None else self.births

    def _origins(self) -> CutFront:
        return self.front if self.origins is None else self.origins

    def with_front(self, front: CutFront) -> CutStrip:
        return CutStrip(self.layers, front, self.depths, self._origins(), self._births(), self.parts)

    def extended(
        self, front: CutFront, depths: np.ndarray, step: int = 0, parts: np.ndarray | None = None
    ) -> CutStrip:
        """The strip with a block of columns added below its deepest one at ``step``: their crack tip
        ``front`` (q points, on the needle) at ``depths`` (q,), in the parts of the tissue ``parts`` (q,),
        non-decreasing from the deepest column's (None: its part). They have no point until their crack tip
        moves (:meth:`lay`); their first layer is then where it started."""
        count = int(np.asarray(depths).size)
        if count == 0:
            return self
        own = self._parts()
        added = np.full(count, own[-1], dtype=np.int64) if parts is None else np.asarray(parts, np.int64)
        joined_parts = np.concatenate([own, added])
        part_field = None if not np.any(joined_parts) else joined_parts
        layers = np.hstack([self.layers, np.full((self.layers.shape[0], count), -1, dtype=self.layers.dtype)])

        def joined(a: CutFront, b: CutFront) -> CutFront:
            return CutFront(
                np.concatenate([a.rest_points, b.rest_points]),
                np.concatenate([a.tet_indices, b.tet_indices]),
                np.concatenate([a.barycentric, b.barycentric]),
            )

        return CutStrip(
            layers,
            joined(self.front, front),
            np.concatenate([self.depths, depths]),
            joined(self._origins(), front),
            np.concatenate([self._births(), np.full(count, step, dtype=np.int64)]),
            part_field,
        )

    def lay(self, cut: CutSurface, step: int, minimum_gap: float, *, due=None) -> tuple[CutSurface, CutStrip]:
        """Lay a layer at the crack tip when any column's tip is farther than ``minimum_gap`` [m] (rest) from
        its last point (from where it started, for a column with no point yet); columns whose tip has not
        moved keep their last point. A column with no point yet gets two: where its crack tip started (in the
        last layer) and where it is; it is laid only with a neighbour it can be joined to (alone, its points
        would join no triangle). Returns the surface and strip (unchanged when no column is due). ``due``:
        :meth:`due` of the same arguments, when the caller has it."""
        due = self.due(cut, step, minimum_gap) if due is None else due
        last, origins, pending, distance, moved, starting, joined = due
        if not np.any((distance >= minimum_gap) & moved):
            return cut, self
        started = clock.perf_counter()
        back = last.copy()
        start_count = int(starting.sum())
        back[starting] = cut.point_count + np.arange(start_count)
        layer = back.copy()
        layer[moved] = cut.point_count + start_count + np.arange(int(moved.sum()))
        triangles = strip_triangles(back, layer, joined)
        grown = append_points(
            cut,
            np.concatenate([origins.rest_points[starting], self.front.rest_points[moved]]),
            np.concatenate([origins.tet_indices[starting], self.front.tet_indices[moved]]),
            np.concatenate([origins.barycentric[starting], self.front.barycentric[moved]]),
            step,
            triangles,
            seconds=clock.perf_counter() - started,
        )
        layers = self.layers.copy()
        layers[-1] = back
        births = self._births()
        layers = np.vstack([layers, layer[None, :]])
        return grown, CutStrip(layers, self.front, self.depths, origins, births, self.parts)

    def layer_distance(self, cut: CutSurface, step: int, minimum_gap: float, *, due=None) -> float:
        """How far the crack tip is from the last layer [m] (rest): the largest distance over the columns
        :meth:`lay` would lay (it lays a layer when this reaches ``minimum_gap``), 0 when none moved
        (``due``: :meth:`due` of the same arguments, when the caller has it)."""
        due = self.due(cut, step, minimum_gap) if due is None else due
        _, _, _, distance, moved, _, _ = due
        return float(distance[moved].max()) if np.any(moved) else 0.0

    def due(self, cut: CutSurface, step: int, minimum_gap: float):
        """What :meth:`lay` decides on: the last layer, the origins, the columns with no point yet, each
        column's distance from its last point [m], the columns that moved, those starting, the joined
        neighbours (read-only to callers; :meth:`layer_distance` and :meth:`lay` share it)."""
        last = self.last_layer
        origins, births = self._origins(), self._births()
        pending = last < 0
        behind = np.where(pending[:, None], origins.rest_points, cut.rest_points[np.maximum(last, 0)])
        distance = np.linalg.norm(self.front.rest_points - behind, axis=1)
        moved = distance >= 1e-3 * minimum_gap
        # Two neighbours are joined by a layer when each one's back point was laid no earlier than the other
        # column was added: the older column's points laid before a block was added border tissue below it
        # that was not cut. A column laid now (its first point) counts as laid now.
        created = np.where(pending, step, cut.created_step[np.maximum(last, 0)])
        joined = (created[:-1] >= births[1:]) & (created[1:] >= births[:-1])
        if self.parts is not None:  # columns in different parts of the tissue: never joined
            joined &= self.parts[:-1] == self.parts[1:]
        starting = pending & moved
        partner = np.zeros(last.size, dtype=bool)
        partner[:-1] |= joined & (starting[1:] | ~pending[1:])
        partner[1:] |= joined & (starting[:-1] | ~pending[:-1])
        starting &= partner
        moved &= ~pending | starting
        return last, origins, pending, distance, moved, starting, joined


#: A crack-tip column closer than this to its last laid point, relative to the cut's size, has not moved (for
#: :func:`recorded_surface`): far below any length of a scene, far above round-off.
_TIP_RESOLUTION = 1e-9


def recorded_surface(cut: CutSurface | None, strip: CutStrip | None, step: int) -> CutSurface | None:
    """The cut surface as far as the model has cut: ``cut`` with a layer laid at the crack tip where it has
    moved past the last layer (:meth:`CutStrip.lay` with no minimum gap), its points and triangles stamped
    ``step``. What the results file, the pictures and the cut-extent figures hold: the rows of the next step
    read ``cut`` and the crack tip itself (the sliding rows reach d_c past the last layer, the front rows
    press on the crack tip), so the recorded surface is the region the model treats as cut. ``cut`` itself
    when there is no strip (no cut running) or no column moved."""
    return recorded_strip(cut, strip, step)[0]


def recorded_strip(
    cut: CutSurface | None, strip: CutStrip | None, step: int
) -> tuple[CutSurface | None, CutStrip | None]:
    """:func:`recorded_surface` and the strip with that last layer: what a needle leaving its strip leaves
    in the tissue (the surface up to the crack tip, and the strip a needle found in it later cuts on from).
    ``cut`` and ``strip`` themselves when no column moved."""
    if cut is None or strip is None or cut.point_count == 0:
        return cut, strip
    size = float(np.ptp(cut.rest_points, axis=0).max()) if cut.point_count > 1 else 0.0
    size = max(size, float(np.ptp(strip.front.rest_points, axis=0).max()))
    if size <= 0.0:
        return cut, strip
    return strip.lay(cut, step, _TIP_RESOLUTION * size * 1e3)


def append_points(
    cut: CutSurface,
    rest_points: np.ndarray,
    tet_indices: np.ndarray,
    barycentric: np.ndarray,
    step: int,
    triangles: np.ndarray,
    *,
    seconds: float = 0.0,
) -> CutSurface:
    """The surface with points and explicit triangles (indices into the grown surface) appended."""
    points = np.concatenate([cut.rest_points, rest_points])
    all_triangles = np.concatenate([cut.triangles, np.asarray(triangles, dtype=np.int64).reshape(-1, 3)])
    added = int(rest_points.shape[0])
    report = TriangulationReport(
        step=step,
        new_point_count=added,
        new_triangle_count=int(all_triangles.shape[0] - cut.triangle_count),
        triangulation_seconds=seconds,
    )
    return CutSurface(
        rest_points=points,
        tet_indices=np.concatenate([cut.tet_indices, tet_indices]),
        barycentric=np.concatenate([cut.barycentric, barycentric]),
        created_step=np.concatenate([cut.created_step, np.full(added, step, dtype=np.int64)]),
        triangles=all_triangles,
        triangle_created_step=np.concatenate(
            [
                cut.triangle_created_step,
                np.full(all_triangles.shape[0] - cut.triangle_count, step, dtype=np.int64),
            ]
        ),
        last_triangulation=report,
    )
