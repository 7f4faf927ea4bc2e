"""Friction rows built from normal rows (as IPC Toolkit builds tangential collisions from normal ones).

A friction row shares the anchor of the normal rows it is built from: the same tissue material point (nodes
and weights) and the same needle point (an arc length). Along a unit tangent t it measures the relative slip
over the step,

    δ_t = tᵀ [(x_needle,free − x_needle,previous) − (x_tissue,free − x_tissue,previous)] + D,

where D is the relative position at the start of the step measured from the row's *stick anchor* (zero for a
row without one: the tip's contact and cutting rows). An insertion point's axial row carries a sub-grid
compliance C (the annulus between the needle and the mesh, :mod:`refsim.constraints.coupling`) in series with
its Coulomb stick: stuck, the needle's surface does not slip on the tissue and the annulus is stretched by
−C λ, so the mesh-resolved relative position from the anchor is D = −C λ. Measured over the step alone
(D = 0), a stuck row would slip by C λ every step and forget it: a held needle's friction would decay
geometrically, by the factor W/(W + C) per step, whatever dt. With D the row's gap is the needle surface's
slip from the anchor and a stuck row keeps its load. The anchor (:func:`stick_offsets`) is a needle arc
length s_a, kept while the point sticks; after a slip it is reset so that D equals the annulus stretch −C λ of
the last solve (the slip moved the anchor, the elastic stretch stays).

and its multiplier is bounded by a friction coefficient times the norm of the forces of a group of normal rows
(plus a preload): the law "friction bounded by a group" of :mod:`refsim.solvers`. The Coulomb contact of the
tip (two tangent rows bounded by its normal row) and the shaft friction of the insertion points (one axial row
bounded by the two lateral rows, plus the tissue's grip) are both built by :func:`friction_rows`; so can be
any friction on the cut surface.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from refsim.constraints.needle_geometry import needle_rows
from refsim.constraints.rows import NEEDLE, TISSUE, point_rows
from refsim.constraints.step_geometry import StepGeometry

__all__ = ["FaceStretch", "FrictionRows", "friction_gaps", "friction_rows", "slip_gaps", "stick_offsets"]


def stick_offsets(
    arc_lengths: np.ndarray,
    *,
    needle_points: np.ndarray,
    tangents: np.ndarray,
    tissue_points: np.ndarray,
    anchors: np.ndarray,
    stretch: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Relative axial positions from the stick anchors at the start of the step, and the anchors.

    A point at arc length s on the needle (its projection) with tissue point x_t lies
    e = tᵀ(x_needle(s) − x_t) off it along the needle; measured from the anchor s_a (the needle arc length
    at which the point's annulus is unstretched) its relative position is D = e + s_a − s (a needle
    moving forward by u over a stuck point raises D by u). Where the anchor is unset (NaN: a new point, or
    one that slipped at its last solve) it is placed so that D equals ``stretch``, the annulus' stretch −C λ
    at the last solve (0 for a new point).

    Parameters
    ----------
    arc_lengths : s of each point at the start of the step [m], shape (p,).
    needle_points : x_needle(s) at the start of the step [m], shape (p, 3).
    tangents : Unit needle tangents at s at the start of the step, shape (p, 3).
    tissue_points : The rows' tissue points at the start of the step [m], shape (p, 3).
    anchors : s_a [m], NaN where unset, shape (p,).
    stretch : D to start from where the anchor is unset [m], shape (p,).

    Returns
    -------
    (offsets D [m], anchors s_a [m]) : shape (p,) each, all finite.
    """
    arc_lengths = np.asarray(arc_lengths, dtype=float)
    off_line = np.einsum("ij,ij->i", np.asarray(tangents, dtype=float), needle_points - tissue_points)
    anchors = np.asarray(anchors, dtype=float)
    unset = ~np.isfinite(anchors)
    resolved = np.where(unset, arc_lengths - off_line + np.asarray(stretch, dtype=float), anchors)
    return off_line + resolved - arc_lengths, resolved


@dataclass(frozen=True)
class FaceStretch:
    """Stick anchors of friction rows that are built anew every step (the cut faces' rows, re-anchored at the
    needle's closest point on the cut each step), kept along the needle from one solve to the next step.

    A friction row with the sub-grid compliance C in series with its Coulomb stick holds the needle's surface
    still on the tissue while the mesh-resolved relative position is −C λ (the annulus stretched). A row
    re-anchored each step at the needle's foot forgets that position: measured over the step alone (D = 0) a
    stuck row slips by C λ every step, and a held needle's friction decays by W/(W + C) per step whatever dt.
    As the shaft's rows (:func:`stick_offsets`), these rows start from their relative position D measured
    from a stick anchor: for the point at needle arc length s, a tissue material point P (on the cut) and a
    vector a, the stretch is e = x_needle(s) − x_P + a and a row along t starts from D = tᵀe (e interpolated
    along the needle between the points kept, 0 beyond them). After a solve (:meth:`after_solve`) a row that
    sticks keeps its anchor, so D is the needle's motion on the tissue measured from positions (a solve's
    error is not carried on); a row that slipped, or a point new at that arc length, gets its anchor placed
    so that D equals its annulus stretch −C λ (the slip moved the anchor, the elastic stretch stays).

    Attributes
    ----------
    arc_lengths : The points' needle arc lengths [m], increasing, shape (k,).
    nodes, weights : Their tissue material points P: nodes and weights, shapes (k, w).
    anchors : a [m], shape (k, 3).
    """

    arc_lengths: np.ndarray
    nodes: np.ndarray
    weights: np.ndarray
    anchors: np.ndarray

    def stretch(self, needle, tissue_positions: np.ndarray) -> np.ndarray:
        """e = x_needle(s) − x_P + a of each point in a configuration of both bodies [m], shape (k, 3)."""
        tissue = np.einsum("kw,kwj->kj", self.weights, tissue_positions[self.nodes])
        return needle.points(self.arc_lengths) - tissue + self.anchors

    def offsets(self, arc_lengths, tangents, needle, tissue_positions) -> np.ndarray:
        """D = tᵀe of rows at ``arc_lengths`` [m] (shape (r,)) along ``tangents`` (shape (r, 3)) at the start
        of the step (``needle``, ``tissue_positions``), e interpolated along the needle (0 beyond the points)
        [m], shape (r,)."""
        stretch = self.stretch(needle, tissue_positions)
        arcs = np.asarray(arc_lengths, dtype=float)
        along = np.stack(
            [np.interp(arcs, self.arc_lengths, stretch[:, k], left=0.0, right=0.0) for k in range(3)], axis=1
        )
        return np.einsum("ij,ij->i", np.asarray(tangents, dtype=float), along)

    @classmethod
    def after_solve(
        cls,
        previous: FaceStretch | None,
        *,
        arc_lengths: np.ndarray,
        nodes: np.ndarray,
        weights: np.ndarray,
        tangents: np.ndarray,
        compliance: np.ndarray,
        multipliers: np.ndarray,
        stuck: np.ndarray,
        needle,
        tissue_positions: np.ndarray,
        tolerance: float,
    ) -> FaceStretch | None:
        """The anchors after a solve of the step's rows, None without rows.

        Parameters
        ----------
        previous : The anchors the step's rows started from (None: none).
        arc_lengths : The step's points [m], shape (k,); ``nodes``, ``weights`` their tissue material points.
        tangents, compliance, multipliers, stuck : The rows' tangents (shape (m k, 3)), added compliances C
            [m/N], multipliers λ [N] and whether each stuck (shape (m k,)), m rows per point given point-major
            by kind (every point's first row, then every point's second, ...).
        needle, tissue_positions : The configuration at the step's end.
        tolerance : Arc lengths closer than this [m] are the same point.
        """
        arcs = np.asarray(arc_lengths, dtype=float)
        count = arcs.size
        if count == 0:
            return None
        nodes, weights = np.array(nodes, copy=True), np.array(weights, dtype=float, copy=True)
        tangents = np.asarray(tangents, dtype=float).reshape(-1, count, 3)
        target = -(np.asarray(compliance, dtype=float) * np.asarray(multipliers, dtype=float)).reshape(
            -1, count
        )
        stuck = np.asarray(stuck, dtype=bool).reshape(-1, count)
        anchors = np.zeros((count, 3))
        kept = np.zeros(count, dtype=bool)
        if previous is not None and previous.arc_lengths.size:
            where = np.clip(np.searchsorted(previous.arc_lengths, arcs), 1, previous.arc_lengths.size) - 1
            near = np.stack([where, np.minimum(where + 1, previous.arc_lengths.size - 1)], axis=1)
            closest = near[
                np.arange(count), np.argmin(np.abs(previous.arc_lengths[near] - arcs[:, None]), axis=1)
            ]
            kept = np.abs(previous.arc_lengths[closest] - arcs) <= tolerance
            nodes[kept] = previous.nodes[closest[kept]]
            weights[kept] = previous.weights[closest[kept]]
            anchors[kept] = previous.anchors[closest[kept]]
        tissue = np.einsum("kw,kwj->kj", weights, tissue_positions[nodes])
        stretch = needle.points(arcs) - tissue + anchors
        for kind in range(tangents.shape[0]):  # the rows of a point (2: along the needle, across it)
            t = tangents[kind]
            reset = ~(stuck[kind] & kept)
            change = target[kind] - np.einsum("kj,kj->k", t, stretch)
            anchors[reset] += change[reset, None] * t[reset]
            stretch[reset] += change[reset, None] * t[reset]
        order = np.argsort(arcs, kind="stable")
        return cls(arcs[order], nodes[order], weights[order], anchors[order])


def slip_gaps(
    tangents: np.ndarray,
    *,
    needle_free: np.ndarray,
    needle_previous: np.ndarray,
    tissue_free: np.ndarray,
    tissue_previous: np.ndarray,
) -> np.ndarray:
    """Relative slip over the step along each tangent [m], shape (r,).

    Parameters
    ----------
    tangents : Unit tangents of the friction rows, shape (r, 3).
    needle_free, needle_previous : Needle point of each row after free motion and at the start of the step
        [m], shape (r, 3).
    tissue_free, tissue_previous : Tissue point of each row after free motion and at the start of the step
        [m], shape (r, 3).
    """
    slip = (needle_free - needle_previous) - (tissue_free - tissue_previous)
    return np.einsum("ij,ij->i", np.asarray(tangents, dtype=float), slip)


@dataclass(frozen=True)
class FrictionRows:
    """Friction rows of one builder, before they join a :class:`~refsim.constraints.rows.RowBlock`.

    Attributes
    ----------
    jacobians : H_b by body name (:class:`~refsim.constraints.rows.RowBlock`'s ``jacobians``): H_tissue of
        shape (r, 3·tissue_node_count) and H_needle of shape (r, needle DoFs), none for a kinematic needle.
    free_gap : Slip over the step along each tangent [m], shape (r,).
    tangents : Unit tangent of each row, shape (r, 3).
    """

    jacobians: Mapping[str, sp.csr_matrix]
    free_gap: np.ndarray
    tangents: np.ndarray


def friction_rows(
    geometry: StepGeometry,
    *,
    tissue_nodes: np.ndarray,
    tissue_weights: np.ndarray,
    arc_lengths: np.ndarray,
    tangents: np.ndarray,
    tissue_free_points: np.ndarray | None = None,
    tissue_previous_points: np.ndarray | None = None,
    offsets: np.ndarray | None = None,
) -> FrictionRows:
    """Friction rows anchored where normal rows are: tissue points (nodes, weights) against needle points.

    Parameters
    ----------
    geometry : The step's geometry.
    tissue_nodes, tissue_weights : The tissue material point of each row, shape (r, p) each.
    arc_lengths : The needle point of each row (arc length from the base [m]), shape (r,).
    tangents : Unit tangent of each row, shape (r, 3).
    tissue_free_points, tissue_previous_points : The tissue points after free motion and at the start of the
        step [m], shape (r, 3) each, when the caller has them (a closest point found on the free surface); by
        default interpolated from ``tissue_nodes``.
    offsets : Relative position from each row's stick anchor at the start of the step, D [m], shape (r,)
        (:func:`stick_offsets`), added to the slip; None: rows without an anchor (D = 0).
    """
    tangents = np.asarray(tangents, dtype=float).reshape(-1, 3)
    arc_lengths = np.asarray(arc_lengths, dtype=float)
    if tissue_free_points is None or tissue_previous_points is None:
        # (interpolated only when the caller lacks one of them: a given pair replaces both)
        previous, free = geometry.tissue_points(tissue_nodes, tissue_weights)
    if tissue_free_points is not None:
        free = np.asarray(tissue_free_points, dtype=float).reshape(-1, 3)
    if tissue_previous_points is not None:
        previous = np.asarray(tissue_previous_points, dtype=float).reshape(-1, 3)
    gaps = friction_gaps(
        geometry,
        arc_lengths=arc_lengths,
        tangents=tangents,
        tissue_free=free,
        tissue_previous=previous,
        offsets=offsets,
    )
    return FrictionRows(
        jacobians=_without_none(
            {
                TISSUE: point_rows(tissue_nodes, tissue_weights, tangents, geometry.tissue_dof_count),
                NEEDLE: needle_rows(geometry.needle_free, arc_lengths, tangents),
            }
        ),
        free_gap=gaps,
        tangents=tangents,
    )


def friction_gaps(
    geometry: StepGeometry,
    *,
    arc_lengths: np.ndarray,
    tangents: np.ndarray,
    tissue_free: np.ndarray,
    tissue_previous: np.ndarray,
    offsets: np.ndarray | None = None,
    needle_free_points: np.ndarray | None = None,
    needle_previous_points: np.ndarray | None = None,
) -> np.ndarray:
    """The free gaps of :func:`friction_rows` alone [m], shape (r,), for a builder that makes the rows'
    Jacobians itself: the slip over the step along each tangent, plus the offset from the stick anchor.

    Parameters
    ----------
    geometry : The step's geometry.
    arc_lengths : The needle point of each row (arc length from the base [m]), shape (r,).
    tangents : Unit tangent of each row, shape (r, 3).
    tissue_free, tissue_previous : The tissue point of each row after free motion and at the start of the
        step [m], shape (r, 3) each.
    offsets : As in :func:`friction_rows`.
    needle_free_points, needle_previous_points : The needle's points at ``arc_lengths`` after free motion and
        at the start of the step [m], shape (r, 3), when the caller has them; else computed here.
    """
    tangents = np.asarray(tangents, dtype=float).reshape(-1, 3)
    arc_lengths = np.asarray(arc_lengths, dtype=float)
    if needle_free_points is None:
        needle_free_points = geometry.needle_free.points(arc_lengths)
    if needle_previous_points is None:
        needle_previous_points = geometry.needle_previous.points(arc_lengths)
    gaps = slip_gaps(
        tangents,
        needle_free=needle_free_points,
        needle_previous=needle_previous_points,
        tissue_free=tissue_free,
        tissue_previous=tissue_previous,
    )
    if offsets is not None:
        gaps = gaps + np.asarray(offsets, dtype=float).reshape(gaps.shape)
    return gaps


def _without_none(jacobians: dict) -> dict:
    """The Jacobians of the bodies that have DoFs (a kinematic needle's rows give None)."""
    return {name: matrix for name, matrix in jacobians.items() if matrix is not None}
