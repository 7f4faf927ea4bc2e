"""Cutting constraints (paper, section 4 and Figure 1c) on a strip cut (:mod:`refsim.cutting.strip`).

- Cut start (the paper's equation 3, selectable): with the insertion constraints' bilateral forces,
  t = Σ n_i^φ λ_i^φ is the lateral force of the tissue on the needle; the paper starts the cut when
  ‖t‖ > n_i · f_c. The default law starts it when ‖t‖ ≥ G_c L_in (a force per unit inserted length, so the
  start does not depend on d_i or the mesh). The cut runs the way the needle pushes the tissue, ĉ = −t/‖t‖.
- Sliding rows (φ_c): every needle sample (every d_c along the inserted length) whose projection falls inside
  the cut surface gets one bilateral row along the surface normal at its closest point; a needle meeting a
  cut it is not cutting only where the sample is also within d_c of the surface along its normal.
- Front rows (χ_c): every needle sample against the crack tip, along −ĉ normal to the needle, so the needle
  stays behind the crack tip; their strength G_c × (the needle length each row stands for) makes the needle
  cut through at G_c per unit length (the energy law), or, unbounded, they tear the cut by d_t when one
  reaches f_t (the paper's law).

Rows are chosen and anchored on the state at the start of the step and linearised at the free positions. The
growth of the cut is in :mod:`refsim.cutting.growth` and :mod:`refsim.cutting.strip`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from refsim.constraints.friction import FaceStretch, friction_rows
from refsim.constraints.needle_geometry import needle_rows
from refsim.constraints.rows import (
    BILATERAL,
    CUT_BORDER,
    CUT_FRICTION,
    CUT_SLIDE,
    FRICTION,
    FRONT,
    NEEDLE,
    ROLE_NAMES,
    SLIDING,
    TISSUE,
    UNILATERAL,
    RowBlock,
    concatenate,
    point_rows,
)
from refsim.constraints.step_geometry import StepGeometry
from refsim.geometry.closest import cross_rows

__all__ = [
    "FrontRows",
    "crack_tip_compression",
    "cut_criterion",
    "strip_cut_block",
]

# Border points whose inward direction has less than this component normal to the needle are ends of the
# strip (their inward direction runs along the shaft): they would only block the axial motion. cos(60°).
_MIN_NORMAL_COMPONENT = 0.5


def cut_criterion(lateral_force: np.ndarray, point_count: int, cutting_force: float) -> bool:
    """Equation (3): ‖t‖ > n_i · f_c."""
    return point_count > 0 and float(np.linalg.norm(lateral_force)) > point_count * cutting_force


def _surface_point_nodes(cut, mesh_tets, triangle, weights):
    """Tissue nodes and weights of points on cut triangles: Σ_v w_v Σ_k β_vk x_{tet_v, k}, shape (q, 12)."""
    corners = cut.triangles[triangle]  # (q, 3)
    nodes = mesh_tets[cut.tet_indices[corners]].reshape(len(triangle), 12)
    node_weights = (weights[:, :, None] * cut.barycentric[corners]).reshape(len(triangle), 12)
    return nodes, node_weights


@dataclass(frozen=True)
class FrontRows:
    """Where each front row of a strip presses on the crack tip.

    Attributes
    ----------
    rows : The front rows' indices in the block, shape (f,).
    segment : The crack-tip segment (columns j, j + 1) of each row, shape (f,).
    parameter : Position t ∈ [0, 1] on the segment, shape (f,).
    arc_lengths : The needle point of each row [m], shape (f,).
    directions : Row directions n (in the cut, normal to the needle, pointing back into the cut), shape (f,
    3).
    band_rows : The sliding rows at the front (bounded at G_c ℓ_k: the needle cuts out of the plane there when
        they give way), indices in the block, shape (b,).
    band_segment : The crack-tip segment nearest each of them, shape (b,).
    band_arc_lengths : Their needle points [m], shape (b,).
    band_directions : Their directions (the cut surface's normal), shape (b, 3).
    band_nodes, band_weights : Their tissue points on the cut surface: nodes and weights, shapes (b, 12).
    previous_gaps, band_previous_gaps : δ of each front row and of each sliding row at the front at the start
        of the step [m], shapes (f,), (b,): the same needle point (arc length) against the same material
        point of the tissue, so δ_end − δ_start is how far the needle moved through the tissue along the row
        over the step.
    slide_arc_lengths : The needle point of every sliding row [m], shape (s,), in the block's order (their
        friction rows follow it: along the needle for each, then across for each).
    slide_nodes, slide_weights : Their tissue points on the cut surface: nodes and weights, shapes (s, 12).
    """

    rows: np.ndarray
    segment: np.ndarray
    parameter: np.ndarray
    arc_lengths: np.ndarray
    directions: np.ndarray
    band_rows: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    band_segment: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    band_arc_lengths: np.ndarray = field(default_factory=lambda: np.zeros(0))
    band_directions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    band_nodes: np.ndarray = field(default_factory=lambda: np.zeros((0, 12), np.int64))
    band_weights: np.ndarray = field(default_factory=lambda: np.zeros((0, 12)))
    previous_gaps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    band_previous_gaps: np.ndarray = field(default_factory=lambda: np.zeros(0))
    slide_arc_lengths: np.ndarray = field(default_factory=lambda: np.zeros(0))
    slide_nodes: np.ndarray = field(default_factory=lambda: np.zeros((0, 12), np.int64))
    slide_weights: np.ndarray = field(default_factory=lambda: np.zeros((0, 12)))

    @classmethod
    def empty(cls) -> FrontRows:
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros((0, 3)))

    def located_in(self, block: RowBlock, rows: RowBlock) -> FrontRows:
        """These rows, given as indices into ``block`` (the strip's block, :func:`strip_cut_block`), as
        indices into ``rows``: a stack of blocks that holds ``block`` (``RowBlock.concatenate`` keeps each
        block's rows, their roles and their order). Found by role, not by where the block sits in the stack:
        the front rows are the stack's FRONT rows and the sliding rows at the front among its SLIDING rows,
        each at the same rank as in ``block``.

        Raises
        ------
        ValueError
            When the stack's FRONT or SLIDING rows are not exactly ``block``'s (another block with rows of
            those roles: which row is which could not be told).
        """
        ranked = []
        for indices, role in ((self.rows, FRONT), (self.band_rows, SLIDING)):
            own = np.flatnonzero(block.roles == role)
            stacked = np.flatnonzero(rows.roles == role)
            if own.size != stacked.size:
                raise ValueError(
                    f"front rows: the stack holds {stacked.size} rows of role {ROLE_NAMES[role]}, the "
                    f"strip's block {own.size}: the stack's rows of that role must all be the block's"
                )
            ranked.append(stacked[np.searchsorted(own, indices)])
        return replace(self, rows=ranked[0], band_rows=ranked[1])

    def band_gaps(self, tissue_positions: np.ndarray, needle) -> np.ndarray:
        """δ = nᵀ(x_needle − x_tissue) of each sliding row at the front in a configuration of both bodies
        [m], shape (b,)."""
        if self.band_rows.size == 0:
            return np.zeros(0)
        tissue = np.einsum("qk,qkj->qj", self.band_weights, tissue_positions[self.band_nodes])
        return np.einsum("ij,ij->i", self.band_directions, needle.points(self.band_arc_lengths) - tissue)

    def gaps(self, front_points: np.ndarray, needle) -> np.ndarray:
        """δ = nᵀ(x_needle − x_tip) of each row for crack-tip points (q, 3) and a needle centreline [m],
        (f,)."""
        anchor = (1.0 - self.parameter)[:, None] * front_points[self.segment] + self.parameter[:, None] * (
            front_points[self.segment + 1]
        )
        return np.einsum("ij,ij->i", self.directions, needle.points(self.arc_lengths) - anchor)


# : Fraction of the end segment's length beyond an end of the crack tip's polyline within which a needle
# sample still : projects onto the polyline (see `_closest_on_polyline`).
END_TOLERANCE = 1e-3


def _closest_on_polyline(
    points: np.ndarray, polyline: np.ndarray, reach: float | np.ndarray = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest segment, parameter t ∈ [0, 1] and whether the projection is interior (not clamped beyond an
    end of the polyline by more than ``reach`` [m] (one for all points, or one each), or than END_TOLERANCE of
    the end segment's length when that is larger), for each point; shapes (k,), (k,), (k,)."""
    from refsim.geometry.surface_kernels import polyline_closest  # numba: imported on first use

    segment, t, raw_t = polyline_closest(points, polyline)
    along = polyline[1:] - polyline[:-1]  # (s, 3)
    lengths = np.einsum("sj,sj->s", along, along)
    # A point that projects onto an end within a thousandth of the end segment's length counts as interior:
    # the crack tip's end columns are laid at the needle's tip and at the tissue surface, so the end samples
    # project onto the polyline's ends by construction, and a tolerance at round-off (1e-9) made their rows
    # come and go with the solver's last digits (cube_cut after the stroke: Gauss–Seidel and the exact mode
    # differed by 0.066 N, 34 against 35 front rows, with the same events; 9.6e-5 N with this tolerance).
    # ``reach`` widens it to a length (the front rows: half a sample spacing, see _front_rows).
    segment_lengths = np.sqrt(lengths)
    ends = (segment_lengths[0], segment_lengths[-1])
    first, last = (np.maximum(END_TOLERANCE, reach / end) if end > 0 else END_TOLERANCE for end in ends)
    interior = ~(((segment == 0) & (raw_t < -first)) | ((segment == along.shape[0] - 1) & (raw_t > 1 + last)))
    return segment, t, interior


def _closest_on_front(
    points: np.ndarray, front: np.ndarray, parts, reach: float | np.ndarray = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_closest_on_polyline` on the crack tip ``front`` (q, 3), a polyline through its columns broken
    where two neighbouring columns lie in different parts of the tissue (``parts``: the strip's
    :meth:`~refsim.cutting.strip.CutStrip.part_ranges`, [a, b) column ranges): each point takes the closest
    piece of at least two columns (the first of equal distances), its segment numbered along the whole
    front. One piece is the plain polyline."""
    if len(parts) == 1:
        return _closest_on_polyline(points, front, reach)
    count = points.shape[0]
    segment, parameter = np.zeros(count, dtype=np.int64), np.zeros(count)
    interior, best = np.zeros(count, dtype=bool), np.full(count, np.inf)
    for first, end in parts:  # a few parts of the tissue, each piece vectorised over the points
        if end - first < 2:
            continue  # a single column: no segment to press on
        piece, t, inside = _closest_on_polyline(points, front[first:end], reach)
        nearest = (1.0 - t)[:, None] * front[first + piece] + t[:, None] * front[first + piece + 1]
        distance = np.linalg.norm(points - nearest, axis=1)
        closer = distance < best
        best[closer], segment[closer], parameter[closer] = distance[closer], first + piece[closer], t[closer]
        interior[closer] = inside[closer]
    return segment, parameter, interior


def _cut_compliance(
    per_tet,
    slide_tets: np.ndarray,
    front_tets: np.ndarray,
    front_shares: np.ndarray,
    spacing: float,
    with_friction: bool,
) -> np.ndarray:
    """Diagonal compliance of the block's rows [m/N]: sliding rows, front rows, friction rows (axial, then
    across), in that order; empty when no compliance is given.

    ``per_tet`` holds the (lateral, axial) sub-grid compliance of a row standing for d_c = ``spacing`` of
    needle in each tet. A front row stands for the inserted length ℓ_k of its sample (``front_shares``) and
    presses laterally on the tissue at the crack tip: it gets the lateral compliance of the tet of its nearest
    crack-tip column, scaled to its length, C_k = C(d_c) d_c / ℓ_k (a line load's compliance is inverse to its
    length). Without it the front rows' W is singular where several rows act on the nodes of one crack-tip
    segment or one tet (docs/cutting.md, "A well-posed cut block").
    """
    if per_tet is None:
        return np.zeros(0)
    lateral, axial = (np.asarray(values, dtype=float)[slide_tets] for values in per_tet)
    front = np.asarray(per_tet[0], dtype=float)[front_tets] * (spacing / front_shares)
    parts = [lateral, front] + ([axial, lateral] if with_friction else [])
    return np.concatenate(parts)


def crack_tip_compression(
    rows: RowBlock,
    multipliers: np.ndarray,
    given_rows: np.ndarray,
    given_segments: np.ndarray,
    columns: np.ndarray,
) -> np.ndarray:
    """Where the tissue's material point in contact with the needle lies, relative to the needle's
    centreline, for crack-tip ``columns`` that the needle cuts through [m], shape (c, 3).

    A compliant row k (compliance C_k, direction d_k, force λ_k on the needle along d_k) holds the needle
    at δ_k = d_kᵀ(x_needle − x_anchor) = −C_k λ_k: the annulus around the needle, which the mesh does not
    resolve, is compressed by C_k λ_k. A crack tip moved to the needle's centreline would discard that
    compression (the row restarts from λ = 0 and the needle must move C_k λ_k further to cut again); moved to
    x_needle + C_k λ_k d_k it keeps the row's force. Each column takes the mean of C_k λ_k d_k over the rows
    that gave way on the crack-tip segments it ends (``given_rows`` in ``rows``, on segments
    ``given_segments``, columns s and s + 1). Zero without compliance (the bare rows).
    """
    columns = np.asarray(columns, dtype=np.int64)
    offsets = np.zeros((columns.size, 3))
    diagonal = np.asarray(rows.compliance_diagonal, dtype=float)
    if diagonal.size == 0 or given_rows.size == 0 or columns.size == 0:
        return offsets
    vectors = (diagonal[given_rows] * multipliers[given_rows])[:, None] * rows.directions[given_rows]
    ends = np.concatenate([given_segments, given_segments + 1])
    where = np.searchsorted(columns, ends)
    counts = np.zeros(columns.size)
    np.add.at(offsets, where, np.concatenate([vectors, vectors]))
    np.add.at(counts, where, 1.0)
    return offsets / np.maximum(counts, 1.0)[:, None]


def strip_cut_block(
    cut,
    strip,
    geometry: StepGeometry,
    *,
    stretches,
    spacing: float,
    cut_direction: np.ndarray,
    front_strength: float = np.inf,
    friction_coefficient: float = 0.0,
    subgrid_compliance: tuple[np.ndarray, np.ndarray] | None = None,
    face_stretch: FaceStretch | None = None,
) -> tuple[RowBlock | None, FrontRows]:
    """Sliding rows on the cut and front rows on its crack tip, for a strip cut (:mod:`refsim.cutting.strip`).

    The needle is sampled every d_c along its inserted length. Which rows exist, and where they are anchored,
    is decided on the state at the start of the step (a consistent state: the one the previous correction
    produced); their gaps are linearised at the free positions.

    - Sliding (bilateral): every sample on the cut surface, projecting inside it or beyond its border by
      at most d_c in its plane, plus the front rows' compression C(d_c) G_c d_c when they are compliant (the
      crack tip is at the needle, less that compression, the last layer up to d_c behind it: the tissue
      between them is cut, and without these rows the needle drifted off the plane there, 2 µm on
      cube_cut), along the surface's normal at its closest point (area-weighted vertex normals
      interpolated: a sliver's own normal is arbitrary), anchored at that point's barycentric coordinates:
      the needle stays on the cut wherever it lies in it. For a needle meeting a cut it is not cutting
      (``strip`` None, or the parts of the cut that are not ``strip``'s: its older strips, another needle's),
      only a sample within d_c of the surface along its normal: further away it is in intact tissue,
      whatever its projection (another needle beside the cut, or crossing its plane).
    - Front (unilateral): every sample against the closest point of the crack-tip polyline, along
      n = −(ĉ normal to the needle): the needle stays behind the crack tip. With ``front_strength`` finite
      (the fracture law: G_c), each row gives way at G_c ℓ_k, ℓ_k the inserted length its sample stands for
      (Σ ℓ_k = the inserted length), and the needle cuts through at G_c per unit length.

    A needle through several parts of the tissue (layers with a gap between them) is sampled along each
    stretch it has in the tissue (``stretches``), and the crack tip's polyline is broken between the strip's
    columns in different parts (`refsim.cutting.strip.CutStrip.part_ranges`): every part holds the needle and
    is cut at G_c per unit length of needle in it, and no row presses on the crack tip across a gap.

    Parameters
    ----------
    cut : The `refsim.cutting.CutSurface`.
    strip : Its `refsim.cutting.strip.CutStrip`; None for a needle inserted along an existing cut (no crack
        tip: sliding rows only, unbounded, for samples on it projecting inside it: beside an old cut's border
        the tissue is intact).
    geometry : The step's geometry.
    stretches : The needle's stretches in the tissue, (entry, end) arc lengths [m] from the base to the tip
        (:func:`refsim.constraints.inserted.inserted_stretches`: the tip, or where the needle leaves a part of
        the tissue through a far face or into a gap, ends each): the samples run along each (none, and no
        rows, when there is none: the needle is out).
    spacing : d_c [m].
    cut_direction : ĉ (deformed), unit, shape (3,).
    front_strength : Force per unit length of needle at which the front gives way [N/m], > 0 (G_c; inf:
        unbounded, the paper's criterion).
    friction_coefficient : μ_c ≥ 0 of the cut faces: with μ_c > 0 every sliding row gets two friction rows in
        the surface, along the needle and across it (along ĉ), each bounded by μ_c |λ| of its sliding row (the
        solvers' group-friction law: a square, not a disc, of admissible tangential forces), measuring the
        relative slip over the step (:func:`refsim.constraints.friction.friction_rows`).
    subgrid_compliance : (lateral, axial) compliance [m/N] of a row standing for d_c of needle in each tissue
        tet, shapes (tet_count,) each (:func:`refsim.constraints.coupling.subgrid_compliance` with the tet's
        own size): added to each sliding row (lateral) and to its friction rows (axial along the needle,
        lateral across), after the tet of the row's nearest cut point. It makes the sliding rows' multipliers
        unique (d_c ≪ h puts many rows on one triangle). None: no compliance added.
    face_stretch : The friction rows' stick anchors after the last solve
        (`refsim.constraints.friction.FaceStretch`, kept by the events from ``FrontRows.slide_arc_lengths``,
        ``slide_nodes``, ``slide_weights``): each friction row starts from its relative position measured
        from them, so a row that sticks keeps its load; None: from zero.

    Rows are ordered: sliding rows, then front rows, then the friction rows (two per sliding row).
    """
    samples = _needle_samples(geometry, stretches, spacing)
    if samples is None:
        return None, FrontRows.empty()
    front_previous = (
        np.zeros((0, 3))
        if strip is None or not strip.has_front()
        else strip.front.positions(geometry.tissue_previous, geometry.mesh_tets)
    )
    # Each sample's closest point on the crack tip at the start of the step, read by the sliding rows at the
    # front (their band) and by the front rows (interior: within half a sample spacing of the polyline's
    # ends; see _front_rows).
    on_front = None
    if front_previous.shape[0] >= 2:
        parts = strip.part_ranges()
        on_front = _closest_on_front(samples.previous, front_previous, parts, reach=0.5 * samples.step)
    sliding = _sliding_rows(
        cut,
        strip,
        geometry,
        samples,
        front_previous,
        on_front,
        spacing=spacing,
        front_strength=front_strength,
        subgrid_compliance=subgrid_compliance,
    )
    front = _front_rows(strip, geometry, samples, front_previous, on_front, cut_direction, sliding)
    if sliding.rows is None and front.rows is None:
        return None, front.info
    friction = None
    if friction_coefficient > 0.0 and sliding.anchor is not None:
        friction = _cut_friction_rows(geometry, sliding.anchor, face_stretch)
    block = _cut_block(
        sliding,
        front,
        friction,
        samples.shares,
        front_strength=front_strength,
        friction_coefficient=friction_coefficient,
        subgrid_compliance=subgrid_compliance,
        spacing=spacing,
    )
    info = front.info
    if sliding.anchor is not None:
        anchor = sliding.anchor
        info = replace(
            info, slide_arc_lengths=anchor.arc_lengths, slide_nodes=anchor.nodes, slide_weights=anchor.weights
        )
    return block, info


def _cut_rows(geometry, nodes, node_weights, directions, arcs, needle_points, anchor, *, kind, source, role):
    """Rows along ``directions`` between tissue points (``nodes``/``node_weights``, at ``anchor`` in the
    free positions) and the needle at arc lengths ``arcs`` (at ``needle_points``), all of one kind, source and
    role: δ = nᵀ(x_needle − x_tissue). A :class:`RowBlock` (its Jacobians by body, no needle one for a rigid
    needle), each row saying what it is."""
    count = directions.shape[0]
    return RowBlock(
        jacobians={
            TISSUE: point_rows(nodes, node_weights, directions, geometry.tissue_dof_count),
            NEEDLE: needle_rows(geometry.needle_free, arcs, directions),
        },
        free_gap=np.einsum("ij,ij->i", directions, needle_points - anchor),
        kind=np.full(count, kind, dtype=np.int8),
        source=np.full(count, source, dtype=np.int8),
        points=anchor,
        directions=directions,
        role=np.full(count, role, dtype=np.int8),
    )


class _NeedleSamples(NamedTuple):
    """The needle every d_c along its inserted length, each stretch of it in the tissue from its entry to its
    end (k samples in all)."""

    arc_lengths: np.ndarray  # [m], (k,)
    shares: np.ndarray  # the inserted length each sample stands for [m], (k,)
    step: np.ndarray  # the samples' spacing in their stretch [m], (k,)
    previous: np.ndarray  # their points at the start of the step [m], (k, 3)
    free: np.ndarray  # their points at the free positions [m], (k, 3)


class _SlideAnchor(NamedTuple):
    """Where the sliding rows hold the tissue (s rows): what their friction rows are built on."""

    nodes: np.ndarray  # tissue nodes, (s, 12)
    weights: np.ndarray  # their weights, (s, 12)
    arc_lengths: np.ndarray  # the rows' needle points [m], (s,)
    normals: np.ndarray  # the rows' directions, (s, 3)
    points: np.ndarray  # the anchors at the free positions [m], (s, 3)


class _Sliding(NamedTuple):
    """The sliding rows of a step (s of them) and what the front and friction rows need of them."""

    rows: RowBlock | None  # SLIDING rows
    anchor: _SlideAnchor | None
    count: int  # s
    tets: np.ndarray  # the tet of each row's nearest cut point (its sub-grid compliance), (s,)
    limits: np.ndarray  # the rows' force limits [N], (s,) (inf: unbounded), or empty: all unbounded
    band_rows: np.ndarray  # the rows at the front (bounded at G_c ℓ_k), indices among them, (b,)
    band_segment: np.ndarray  # the crack-tip segment nearest each, (b,)


class _Front(NamedTuple):
    """The front rows of a step (f of them)."""

    rows: RowBlock | None  # FRONT rows
    info: FrontRows
    keep: np.ndarray  # their samples, indices into the needle samples, (f,)
    tets: np.ndarray  # the tet of each row's nearest crack-tip column (its sub-grid compliance), (f,)


def _needle_samples(geometry: StepGeometry, stretches, spacing: float) -> _NeedleSamples | None:
    """The needle sampled every d_c = ``spacing`` along each of its ``stretches`` in the tissue ((entry, end)
    arc lengths [m], from the base to the tip), from the entry to the end of each; None when no stretch holds
    any length."""
    parts = []
    needle_length = geometry.needle_free.length
    for entry_arc_length, end in stretches:
        length = min(float(end), needle_length)
        start = max(0.0, min(entry_arc_length, length))
        if start >= length:
            continue
        count = max(int(np.ceil((length - start) / spacing)), 1)
        samples = np.linspace(start, length, count + 1)
        # The inserted length each sample stands for: [s − Δ/2, s + Δ/2] ∩ [entry, end].
        step = samples[1] - samples[0] if samples.size > 1 else spacing
        shares = np.clip(
            np.minimum(samples + 0.5 * step, length) - np.maximum(samples - 0.5 * step, entry_arc_length),
            0.0,
            None,
        )
        parts.append((samples, shares, np.full(samples.size, step)))
    if not parts:
        return None
    samples, shares, steps = (np.concatenate(values) for values in zip(*parts, strict=True))
    return _NeedleSamples(
        samples,
        shares,
        steps,
        geometry.needle_previous.points(samples),
        geometry.needle_free.points(samples),
    )


def _sliding_rows(
    cut,
    strip,
    geometry: StepGeometry,
    samples: _NeedleSamples,
    front_previous: np.ndarray,
    on_front: tuple | None,
    *,
    spacing: float,
    front_strength: float,
    subgrid_compliance: tuple[np.ndarray, np.ndarray] | None,
) -> _Sliding:
    """The sliding rows (see :func:`strip_cut_block`): the samples in the cut, or beside its border within
    reach of the crack tip, held on the surface along its normal; bounded at G_c ℓ_k at the front
    (``on_front``: each sample's closest point on the crack tip, :func:`_closest_on_front`)."""
    none = _Sliding(
        None, None, 0, np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64)
    )
    if not cut.triangle_count:
        return none
    tets = geometry.mesh_tets
    needle_previous = samples.previous
    surface_previous = cut.deformed_points(geometry.tissue_previous, tets)
    found = cut.closest_points(needle_previous, surface_previous)
    normals_previous = cut.interpolated_normals(surface_previous, found.triangle, found.barycentric)
    offset = needle_previous - found.closest
    in_plane = offset - np.einsum("ij,ij->i", offset, normals_previous)[:, None] * normals_previous
    compression = np.zeros(needle_previous.shape[0])
    if strip is not None and subgrid_compliance is not None and np.isfinite(front_strength):
        # The crack tip lies behind the needle by its front rows' compression C λ ≤ C(d_c) G_c d_c
        # (crack_tip_compression), so the last layer lies up to d_c plus that behind it.
        near = cut.triangles[found.triangle, np.argmax(found.barycentric, axis=1)]
        lateral = np.asarray(subgrid_compliance[0], dtype=float)[cut.tet_indices[near]]
        compression = lateral * float(front_strength) * spacing
    reach = spacing + compression if strip is not None else 0.0
    # A needle meeting a cut it is not cutting (another needle's, or its own old one) slides in it only ON
    # the surface: within d_c of it along its normal (the rule of new insertion points, which a needle gets
    # only outside the cut, refsim.simulation.events). A sample that merely projects inside the cut from
    # further away (beside the cut, or crossing its plane) is in intact tissue: held there, its bilateral row
    # pulled it onto the cut's plane. The needle cutting the strip made the strip's surface: all its samples
    # that project inside it (or within reach of the crack tip) are held on it; the rest of the cut (its
    # older strips, another needle's) it meets as a cut it is not cutting (its samples projecting on an old
    # cut from afar were held on that cut's plane: a second cut 1.5 or 3 mm beside and parallel to a first
    # held the needle with 5.43-5.46 N, up to 3.48 N of it normal to the cuts, against 3.41 N for the first).
    lateral_offset = np.linalg.norm(in_plane, axis=1)
    on_surface = found.inside | (lateral_offset <= reach)
    # Each sample's distance to its closest point on the crack tip at the start of the step (``on_front``):
    # within 1.5 d_c of it the needle is at its front (cutting: uncut tissue on every side but its cut's).
    # (Not widened by the front's compression: so widened, the band below took in every sliding row of the
    # liver's rigid needle, whose crack tip lies 2.8 mm behind it, and the area the crack tip swept came out
    # 230, 361, 203 mm² for d_c = 0.5, 1, 2 mm, against 199, 200, 203 mm² as it is.)
    at_front = None
    if np.isfinite(front_strength) and on_front is not None:
        segment, parameter = on_front[0], on_front[1]
        nearest_tip = (1.0 - parameter)[:, None] * front_previous[segment] + parameter[:, None] * (
            front_previous[segment + 1]
        )
        at_front = np.linalg.norm(needle_previous - nearest_tip, axis=1) <= 1.5 * spacing
    met = None if strip is None else ~strip.own_triangles(cut)[found.triangle]  # samples on older cuts
    if strip is None or met.any():
        on_cut = (found.inside | (lateral_offset <= 0.0)) & (
            np.abs(np.einsum("ij,ij->i", offset, normals_previous)) <= spacing
        )
        if at_front is not None:
            # A sample at its own front meets no other cut: what resists it there is the tissue ahead, which
            # its front rows cut at G_c per unit length wherever another cut lies (held on that cut's plane
            # too, unbounded, a needle cutting across another needle's cut was pinned to it).
            on_cut &= ~at_front
        on_surface = on_cut if strip is None else np.where(met, on_cut, on_surface)
    inside = np.flatnonzero(on_surface)
    if not inside.size:
        return none
    triangle, weights = found.triangle[inside], found.barycentric[inside]
    surface_free = cut.deformed_points(geometry.tissue_free, tets)
    normals = cut.interpolated_normals(surface_free, triangle, weights)
    anchor = np.einsum("qv,qvj->qj", weights, surface_free[cut.triangles[triangle]])
    nodes, node_weights = _surface_point_nodes(cut, tets, triangle, weights)
    arcs = samples.arc_lengths[inside]
    nearest = cut.triangles[triangle, np.argmax(weights, axis=1)]
    rows = _cut_rows(
        geometry,
        nodes,
        node_weights,
        normals,
        arcs,
        samples.free[inside],
        anchor,
        kind=BILATERAL,
        source=CUT_SLIDE,
        role=SLIDING,
    )
    # At the front (within 1.5 d_c of the crack tip) the needle has uncut tissue on every side but the
    # cut's: pushed out of the cut's plane it cuts through at G_c per unit length as it does ahead, so those
    # sliding rows carry at most G_c ℓ_k (a needle whose stroke turns then turns the cut; held by unbounded
    # rows there, an L-shaped stroke dragged the tissue sideways, 7.3 N against 3.6 N).
    limits = np.full(inside.size, np.inf)
    band_rows, band_segment = none.band_rows, none.band_segment
    if at_front is not None:
        band = np.flatnonzero(at_front[inside] & (samples.shares[inside] > 1e-9 * samples.step[inside]))
        limits[band] = float(front_strength) * samples.shares[inside][band]
        band_rows, band_segment = band, on_front[0][inside][band]
    return _Sliding(
        rows,
        _SlideAnchor(nodes, node_weights, arcs, normals, anchor),
        inside.size,
        cut.tet_indices[nearest],
        limits,
        band_rows,
        band_segment,
    )


def _front_rows(
    strip,
    geometry: StepGeometry,
    samples: _NeedleSamples,
    front_previous: np.ndarray,
    on_front: tuple | None,
    cut_direction: np.ndarray,
    sliding: _Sliding,
) -> _Front:
    """The front rows (see :func:`strip_cut_block`): the samples against the crack tip (``on_front``: each
    one's closest point on it, :func:`_closest_on_front`), along −ĉ normal to the needle; they follow the
    sliding rows in the block."""
    empty = np.zeros(0, np.int64)
    info = FrontRows.empty()
    if sliding.band_rows.size:
        band, anchor = sliding.band_rows, sliding.anchor
        tissue_previous = np.einsum(
            "qk,qkj->qj", anchor.weights[band], geometry.tissue_previous[anchor.nodes[band]]
        )
        needle_previous = geometry.needle_previous.points(anchor.arc_lengths[band])
        info = replace(
            info,
            band_rows=band,
            band_segment=sliding.band_segment,
            band_arc_lengths=anchor.arc_lengths[band],
            band_directions=anchor.normals[band],
            band_nodes=anchor.nodes[band],
            band_weights=anchor.weights[band],
            band_previous_gaps=np.einsum("ij,ij->i", anchor.normals[band], needle_previous - tissue_previous),
        )
    if on_front is None:
        return _Front(None, info, empty, empty)
    # ``on_front``'s interior reaches half a sample spacing past the polyline's ends (strip_cut_block): a
    # sample stands for the inserted length within half a spacing of it: one within half a spacing beyond
    # an end of the crack tip's polyline still faces its end column. Without that reach the needle's sample at
    # the entry point, which lies on the deformed surface, a few micrometres above the surface column the cut
    # laid earlier (once the needle has moved: pulled back through its cut), came and went from one step to
    # the next with its share G_c d_c / 2 of the force: the withdrawal's force lost it in 65, 19 and 63 % of
    # the steps at 5, 7 and 9 cells, a level-to-level offset of 0.03 to 0.06 N that was not smooth in h.
    segment, parameter, interior = on_front
    keep = np.flatnonzero(interior & (samples.shares > 1e-9 * samples.step))
    if keep.size:
        tangents = geometry.needle_free.tangents(samples.arc_lengths[keep])
        lateral = cut_direction - (tangents @ cut_direction)[:, None] * tangents
        norms = np.linalg.norm(lateral, axis=1)
        usable = norms > _MIN_NORMAL_COMPONENT
        keep, lateral, norms = keep[usable], lateral[usable], norms[usable]
    if not keep.size:
        return _Front(None, info, empty, empty)
    tets = geometry.mesh_tets
    directions = -lateral / norms[:, None]
    seg, t = segment[keep], parameter[keep]
    front_free = strip.front.positions(geometry.tissue_free, tets)
    anchor = (1.0 - t)[:, None] * front_free[seg] + t[:, None] * front_free[seg + 1]
    nodes = np.concatenate([tets[strip.front.tet_indices[seg]], tets[strip.front.tet_indices[seg + 1]]], 1)
    node_weights = np.concatenate(
        [(1.0 - t)[:, None] * strip.front.barycentric[seg], t[:, None] * strip.front.barycentric[seg + 1]], 1
    )
    arcs = samples.arc_lengths[keep]
    anchor_previous = (1.0 - t)[:, None] * front_previous[seg] + t[:, None] * front_previous[seg + 1]
    rows = _cut_rows(
        geometry,
        nodes,
        node_weights,
        directions,
        arcs,
        samples.free[keep],
        anchor,
        kind=UNILATERAL,
        source=CUT_BORDER,
        role=FRONT,
    )
    info = replace(
        info,
        rows=sliding.count + np.arange(keep.size),
        segment=seg,
        parameter=t,
        arc_lengths=arcs,
        directions=directions,
        previous_gaps=np.einsum("ij,ij->i", directions, samples.previous[keep] - anchor_previous),
    )
    return _Front(rows, info, keep, strip.front.tet_indices[np.where(t < 0.5, seg, seg + 1)])


def _cut_friction_rows(geometry: StepGeometry, anchor: _SlideAnchor, stretch: FaceStretch | None) -> RowBlock:
    """Two friction rows per sliding row, in the surface: along the needle, then across it, each from its
    relative position measured from the stick anchors of the last solve (``stretch``; none: from zero)."""
    axial = geometry.needle_free.tangents(anchor.arc_lengths)
    across = cross_rows(np.asarray(anchor.normals, dtype=float), np.asarray(axial, dtype=float))
    across /= np.linalg.norm(across, axis=1, keepdims=True)
    tangents = np.concatenate([axial, across])
    nodes, weights, arcs, points = anchor.nodes, anchor.weights, anchor.arc_lengths, anchor.points
    previous = np.einsum("qk,qkj->qj", weights, geometry.tissue_previous[nodes])
    friction = friction_rows(
        geometry,
        tissue_nodes=np.concatenate([nodes, nodes]),
        tissue_weights=np.concatenate([weights, weights]),
        arc_lengths=np.concatenate([arcs, arcs]),
        tangents=tangents,
        tissue_free_points=np.concatenate([points, points]),
        tissue_previous_points=np.concatenate([previous, previous]),
        offsets=None
        if stretch is None
        else stretch.offsets(
            np.concatenate([arcs, arcs]), tangents, geometry.needle_previous, geometry.tissue_previous
        ),
    )
    count = tangents.shape[0]
    return RowBlock(
        jacobians={TISSUE: friction.jacobians[TISSUE], NEEDLE: friction.jacobians.get(NEEDLE)},
        free_gap=friction.free_gap,
        kind=np.full(count, FRICTION, dtype=np.int8),
        source=np.full(count, CUT_SLIDE, dtype=np.int8),
        points=np.concatenate([points, points]),
        directions=tangents,
        role=np.full(count, CUT_FRICTION, dtype=np.int8),
    )


def _cut_block(
    sliding: _Sliding,
    front: _Front,
    friction: RowBlock | None,
    shares: np.ndarray,
    *,
    front_strength: float,
    friction_coefficient: float,
    subgrid_compliance: tuple[np.ndarray, np.ndarray] | None,
    spacing: float,
) -> RowBlock:
    """The block of :func:`strip_cut_block`: sliding, front and friction rows, with their force limits,
    friction groups, sub-grid compliance and roles (``shares``: the inserted length of each needle sample)."""
    rows = concatenate([sliding.rows, front.rows, friction])  # each row's kind, source and role kept
    friction_count = 0 if friction is None else friction.row_count
    limits = np.concatenate(
        [
            sliding.limits if sliding.limits.size else np.full(sliding.count, np.inf),
            float(front_strength) * shares[front.keep],
            np.full(friction_count, np.inf),
        ]
    )
    first_friction = sliding.count + front.info.rows.size
    groups = {}
    if friction_count:
        pair = np.arange(sliding.count)
        groups = dict(
            group_rows=first_friction + np.arange(friction_count),
            group_offsets=np.arange(friction_count + 1),
            group_members=np.concatenate([pair, pair]),
            group_coefficient=np.full(friction_count, float(friction_coefficient)),
        )
    block = replace(
        rows,
        force_limit=limits if np.any(np.isfinite(limits)) else np.zeros(0),
        compliance_diagonal=_cut_compliance(
            subgrid_compliance,
            sliding.tets,
            front.tets,
            shares[front.keep],
            spacing,
            friction_count > 0,
        ),
        **groups,
    )
    return block
