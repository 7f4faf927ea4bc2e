"""Growth of the cut surface (paper, section 4): the strip at the cut start, and its crack tip's advance.

Pure functions of arrays and of a :class:`CutGrowth` built once per tissue (its rest positions, tets and the
scene's cutting parameters). The surface lives in rest coordinates (the paper's equation 4): a point found in
the deformed tissue keeps the tet and barycentric coordinates it has there, and its rest position is the same
coordinates applied to the rest nodes.

- Cut start (:func:`start_strip`): the insertion path, resampled every d_c, is the first layer of a strip
  (:mod:`refsim.cutting.strip`); with the paper's law it is swept along ĉ up to d_t, in layers at most d_c
  apart; with the energy law the crack tip starts on the path.
- Crack advance (:func:`advance_front`): the crack tip moves, column by column, to the material point where
  the needle pushed it (energy law) or by d_t (the paper's tear); a layer is laid once it is d_c ahead
  (:meth:`refsim.cutting.strip.CutStrip.lay`).
"""

from __future__ import annotations

import time as clock
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from refsim.cutting.surface import CutSurface
from refsim.geometry import TetLocator

__all__ = [
    "CutGrowth",
    "advance_front",
    "crack_tip_targets",
    "move_front",
    "start_strip",
    "resample_polyline",
]


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


@dataclass(frozen=True)
class CutGrowth:
    """How the cut surface of one tissue grows.

    Attributes
    ----------
    rest_positions : Rest positions of the tissue nodes [m], shape (node_count, 3).
    tets : Tissue tets, shape (tet_count, 4).
    point_spacing : d_c [m], > 0.
    """

    rest_positions: np.ndarray
    tets: np.ndarray
    point_spacing: float

    @cached_property
    def rest_locator(self) -> TetLocator:
        """Tet locator on the rest positions (built on first use, then kept)."""
        return TetLocator(self.rest_positions, self.tets)


def start_strip(
    growth: CutGrowth,
    cut: CutSurface | None,
    path_points: np.ndarray,
    direction: np.ndarray,
    positions: np.ndarray,
    step: int,
    *,
    extent: float,
    beyond: np.ndarray | None = None,
    pieces: list[np.ndarray] | None = None,
):
    """A new strip on the insertion path: columns every d_c along it, swept along ĉ by ``extent`` (0: the
    crack tip starts on the path, as the energy law wants; d_t for the paper's initial surface).

    A needle through several parts of the tissue (layers with a gap between them) gives the path as
    ``pieces``, one per part: each is resampled on its own, its ends kept, its columns in a part of their own
    (`refsim.cutting.strip.CutStrip.parts`: never joined to another part's), their depths measured along the
    pieces and the gaps between them. Columns kept on either side of columns outside the tissue are in
    different parts too.

    Parameters
    ----------
    growth : The tissue's cut growth (rest positions, tets, d_c).
    cut : The tissue's cut surface so far (None or empty for the first cut); the strip's points are appended.
    path_points : The insertion points in the deformed tissue [m], shape (p, 3), entry first (ignored when
        ``pieces`` are given).
    direction : ĉ in the deformed state, unit, shape (3,).
    positions : Tissue positions [m], shape (n, 3).
    step : The step.
    extent : How far the first surface reaches along ĉ [m], ≥ 0.
    beyond : Where the columns go on to past the path's last point [m], shape (3,) (the needle's end in the
        tissue), or None. Columns every d_c from the path's last point, the path's own columns unchanged; a
        gap of less than d_c/2 is left (no column that close to the last one) unless the path alone gives
        fewer than two columns.
    pieces : The path as one polyline per part of the tissue [m], shapes (p_k, 3), from the entry down; None:
        ``path_points``, in one part.

    Returns
    -------
    (cut, strip) : The grown surface and the new strip, or (cut, None) when fewer than two columns lie in the
    tissue.
    """
    from refsim.cutting.strip import (
        CutFront,
        CutStrip,
        append_points,
        locate_material_points,
        strip_triangles,
    )

    started = clock.perf_counter()
    cut = CutSurface.empty() if cut is None else cut
    spacing = growth.point_spacing
    if pieces is None:
        columns = resample_polyline(path_points, spacing)
        if beyond is not None:
            gap = float(np.linalg.norm(np.asarray(beyond, dtype=float) - columns[-1]))
            if gap >= 0.5 * spacing or (len(columns) < 2 and gap > 1e-9 * spacing):
                onward = resample_polyline(np.stack([columns[-1], beyond]), spacing)[1:]
                columns = np.vstack([columns, onward])
        given_parts = np.zeros(len(columns), dtype=np.int64)
    else:
        resampled = [resample_polyline(piece, spacing) for piece in pieces]
        columns = np.concatenate(resampled)
        given_parts = np.concatenate([np.full(len(c), k, dtype=np.int64) for k, c in enumerate(resampled)])
    depths = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(columns, axis=0), axis=1))])
    layer_count = 1 if extent <= 0.0 else max(int(np.ceil(extent / spacing - 1e-9)), 1) + 1
    offsets = np.linspace(0.0, extent, layer_count) if layer_count > 1 else np.zeros(1)
    points = columns[None, :, :] + offsets[:, None, None] * np.asarray(direction, dtype=float)
    locator = TetLocator(positions, growth.tets)
    tets, barycentric, inside = locate_material_points(locator, positions, growth.tets, points.reshape(-1, 3))
    tets, barycentric = tets.reshape(layer_count, -1), barycentric.reshape(layer_count, -1, 4)
    inside = inside.reshape(layer_count, -1)
    keep = inside[0]
    if np.count_nonzero(keep) < 2:
        return cut, None
    # Columns kept on either side of dropped ones (outside the tissue: a gap between two parts of it, which
    # the path crosses) are in different parts: never joined (CutStrip.parts).
    kept = np.flatnonzero(keep)
    parts = given_parts[kept] + np.concatenate([[0], np.cumsum(np.diff(kept) > 1)]).astype(np.int64)
    tets, barycentric, inside = tets[:, keep], barycentric[:, keep], inside[:, keep]
    depths = depths[keep]
    rest = np.einsum("lqk,lqkj->lqj", barycentric, growth.rest_positions[growth.tets[np.maximum(tets, 0)]])
    # A column stops at its first point outside the tissue: later layers reuse its last point inside.
    reach = np.cumprod(inside, axis=0).astype(bool)
    layers = np.empty(tets.shape, dtype=np.int64)
    count = cut.point_count
    new_rest, new_tets, new_bary = [], [], []
    for layer in range(layer_count):  # a handful of layers (d_t / d_c), each vectorised over the columns
        fresh = reach[layer]
        layers[layer] = layers[layer - 1] if layer else -1
        layers[layer, fresh] = count + np.arange(int(fresh.sum()))
        count += int(fresh.sum())
        new_rest.append(rest[layer, fresh])
        new_tets.append(tets[layer, fresh])
        new_bary.append(barycentric[layer, fresh])
    same_part = parts[:-1] == parts[1:]
    triangles = [strip_triangles(layers[k], layers[k + 1], same_part) for k in range(layer_count - 1)]
    grown = append_points(
        cut,
        np.concatenate(new_rest),
        np.concatenate(new_tets),
        np.concatenate(new_bary),
        step,
        np.concatenate(triangles) if triangles else np.zeros((0, 3), dtype=np.int64),
        seconds=clock.perf_counter() - started,
    )
    last = layers[-1]
    front = CutFront(grown.rest_points[last], grown.tet_indices[last], grown.barycentric[last])
    return grown, CutStrip(layers, front, depths, parts=parts if parts[-1] > 0 else None)


def advance_front(
    growth: CutGrowth, strip, advances: np.ndarray, direction: np.ndarray, positions: np.ndarray
):
    """The crack tip moved by ``advances`` [m] (deformed length, per column) along ``direction`` (deformed,
    unit): each moving tip point goes to the material point found at its deformed position plus a·u in the
    current configuration (kept in rest coordinates, equation 4). Columns whose target lies outside the tissue
    stay. Returns the new `CutFront`."""
    moving = np.flatnonzero(np.asarray(advances) > 0.0)
    if moving.size == 0:
        return strip.front
    current = strip.front.positions(positions, growth.tets)[moving]
    target = current + np.asarray(advances, dtype=float)[moving, None] * np.asarray(direction, dtype=float)
    return move_front(growth, strip, moving, target, positions)


def crack_tip_targets(strip, needle, entry_arc: float, columns: np.ndarray, spacing: float):
    """Where the needle has cut each of ``columns`` up to: the point of the needle's centreline at the
    column's depth below the tissue surface (``strip.depths``; ``entry_arc`` is where the needle enters the
    tissue, :func:`refsim.constraints.inserted.inserted_arc`), and whether the needle reaches that depth,
    shapes (c, 3) [m] and (c,): a column deeper than the inserted needle (a needle pushed sideways and partly
    out, or retracting) stays where the tip left it (sent to the tip, such columns bunched up along the needle
    into slivers).

    The crack tip is the needle's inserted segment, column j at depth d_j along it. Taking instead the foot of
    the perpendicular from the column's tip to the needle sends the top columns of a tilted needle pushed
    sideways out of the tissue (the push has a component normal to the surface): snapped back onto the tissue
    surface they lagged (2.1 mm against 4.4 mm for a 30° needle) and bunched up into slivers lying in the
    tissue surface, whose normals (nearly vertical) then pinned the needle to the surface (10.8 N against 3.6
    N).
    """
    arcs = entry_arc + np.asarray(strip.depths)[columns]
    # Half a column spacing of slack: the tissue surface moves along the needle while it cuts (the entry arc
    # moves with it) and the deepest column, at the tip at the cut start, must not stop for a hair. A column
    # in that slack below the tip is taken to the needle's line extended past the tip at its own depth, not
    # to the tip point: sent to the tip, it moved up along the needle by the slack whenever it was moved.
    length = needle.length
    targets = needle.points(np.minimum(arcs, length))
    below = arcs > length
    if np.any(below):
        tangent = needle.tangents(np.array([length]))[0]
        targets[below] += (arcs[below] - length)[:, None] * tangent
    return targets, arcs <= length + 0.5 * spacing


def move_front(
    growth: CutGrowth,
    strip,
    columns: np.ndarray,
    targets: np.ndarray,
    positions: np.ndarray,
    *,
    locator: TetLocator | None = None,
):
    """The crack tip with ``columns`` moved to ``targets`` (deformed, shape (c, 3)): each goes to the material
    point found there in the current configuration (kept in rest coordinates, equation 4); a target outside
    the tissue by more than d_c/2 leaves its column where it is (``locator``: one on ``positions``, built when
    None). Returns the new `CutFront`."""
    from refsim.cutting.strip import CutFront, locate_material_points

    front = strip.front
    columns = np.asarray(columns, dtype=np.int64)
    if columns.size == 0:
        return front
    locator = TetLocator(positions, growth.tets) if locator is None else locator
    # The crack tip on the tissue surface (the entry column) may step a hair outside it: keep it on the
    # surface.
    tets, barycentric, inside = locate_material_points(
        locator,
        positions,
        growth.tets,
        np.asarray(targets, dtype=float),
        snap_distance=0.5 * growth.point_spacing,
    )
    rest_points, tet_indices, bary = (
        front.rest_points.copy(),
        front.tet_indices.copy(),
        front.barycentric.copy(),
    )
    chosen = columns[inside]
    tet_indices[chosen] = tets[inside]
    bary[chosen] = barycentric[inside]
    rest_points[chosen] = np.einsum(
        "pk,pkj->pj", barycentric[inside], growth.rest_positions[growth.tets[tets[inside]]]
    )
    return CutFront(rest_points, tet_indices, bary)
