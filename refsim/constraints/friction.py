"""Friction rows built from normal rows (as IPC Toolkit builds tangential collisions from normal ones).

A friction row shares the anchor of the normal rows it is built from: the same tissue material point (nodes
and weights) and the same needle point (an arc length). Along a unit tangent t it measures the relative slip
over the step,

    δ_t = tᵀ [(x_needle,free − x_needle,previous) − (x_tissue,free − x_tissue,previous)],

and its multiplier is bounded by a friction coefficient times the norm of the forces of a group of normal rows
(plus a preload): the law "friction bounded by a group" of :mod:`refsim.solvers`. The Coulomb contact of the
tip (two tangent rows bounded by its normal row) and the shaft friction of the insertion points (one axial row
bounded by the two lateral rows, plus the tissue's grip) are both built by :func:`friction_rows`; so can be
any friction on the cut surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from refsim.constraints.needle_geometry import needle_rows
from refsim.constraints.rows import point_rows
from refsim.constraints.step_geometry import StepGeometry

__all__ = ["FrictionRows", "friction_rows", "slip_gaps"]


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
    tissue_jacobian : H_tissue, shape (r, 3·tissue_node_count).
    needle_jacobian : H_needle, shape (r, needle DoFs), or None for a kinematic needle.
    free_gap : Slip over the step along each tangent [m], shape (r,).
    tangents : Unit tangent of each row, shape (r, 3).
    """

    tissue_jacobian: sp.csr_matrix
    needle_jacobian: sp.csr_matrix | None
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
    """
    tangents = np.asarray(tangents, dtype=float).reshape(-1, 3)
    arc_lengths = np.asarray(arc_lengths, dtype=float)
    previous, free = geometry.tissue_points(tissue_nodes, tissue_weights)
    if tissue_free_points is not None:
        free = np.asarray(tissue_free_points, dtype=float).reshape(-1, 3)
    if tissue_previous_points is not None:
        previous = np.asarray(tissue_previous_points, dtype=float).reshape(-1, 3)
    gaps = slip_gaps(
        tangents,
        needle_free=geometry.needle_free.points(arc_lengths),
        needle_previous=geometry.needle_previous.points(arc_lengths),
        tissue_free=free,
        tissue_previous=previous,
    )
    return FrictionRows(
        tissue_jacobian=point_rows(tissue_nodes, tissue_weights, tangents, geometry.tissue_dof_count),
        needle_jacobian=needle_rows(geometry.needle_free, arc_lengths, tangents),
        free_gap=gaps,
        tangents=tangents,
    )
