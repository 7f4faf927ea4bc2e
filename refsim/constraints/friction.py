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

__all__ = ["FrictionRows", "friction_gaps", "friction_rows", "slip_gaps", "stick_offsets"]


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
    """
    tangents = np.asarray(tangents, dtype=float).reshape(-1, 3)
    arc_lengths = np.asarray(arc_lengths, dtype=float)
    gaps = slip_gaps(
        tangents,
        needle_free=geometry.needle_free.points(arc_lengths),
        needle_previous=geometry.needle_previous.points(arc_lengths),
        tissue_free=tissue_free,
        tissue_previous=tissue_previous,
    )
    if offsets is not None:
        gaps = gaps + np.asarray(offsets, dtype=float).reshape(gaps.shape)
    return gaps


def _without_none(jacobians: dict) -> dict:
    """The Jacobians of the bodies that have DoFs (a kinematic needle's rows give None)."""
    return {name: matrix for name, matrix in jacobians.items() if matrix is not None}
