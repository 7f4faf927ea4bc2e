"""Cutting constraints and the growth of the cut (paper, section 4 and Figure 1c).

- Cut start (equation 3): with the insertion constraints' bilateral forces, t = Σ n_i^φ λ_i^φ is the lateral
  force of the tissue on the needle; cutting starts when ‖t‖ > n_i · f_c. The cut runs the way the needle pushes
  the tissue, ĉ = −t/‖t‖ (the paper's t_i up to the sign of its normals).
- Point cloud: the path (the insertion points, resampled every d_c) swept towards ĉ up to d_t, every d_c:
  p + k d_c ĉ, k = 0 … round(d_t/d_c). Each point is located in its tet in the deformed state and kept in rest
  coordinates through its barycentric coordinates (equation 4).
- Sliding rows (φ_c): every needle sample (every d_c along the inserted length) whose projection falls inside
  the cut surface gets one bilateral row along the surface normal at its closest point. The surface starts on
  the needle (its back border is the path), so "inside" admits samples within d_c/4 of the surface in its own
  plane; otherwise the needle, sitting on that border, would get no row at all.
- Border rows (χ_c): every border point of the surface gets one unilateral row against its closest point on the
  needle, along the surface's inward direction at that point (in the surface, normal to the needle), so the
  needle stays inside the border; per needle edge only the closest border point along its row direction (the
  smallest gap) is kept, so that the front of the cut, not the back border the needle leaves, holds the
  needle. The needle edges are
  those of the sampled centreline (samples every d_c), not the beam elements: with the paper's 2 cm beam
  elements and a 17 mm insertion, one row per beam element would let most of the shaft cross the border.
  Border points at the ends of the strip, whose inward direction runs along the needle, get no row, nor do
  points of the back border (inward direction along the cut direction ĉ): only the front holds the needle.
- At most one sliding row and one border row per tissue tet (the smallest gap): rows in one tet constrain the
  same four nodes, whose motion is affine; more rows only make W rank-deficient and, with a kinematic (rigid)
  needle, inconsistent, which drives the multipliers to infinity.
- Tearing: when a border row's force reaches f_t, the surface is extended by d_t against that row's direction
  (−n_c), every d_c, from every front border point along the inserted length, so the front advances as a
  whole. Growing a single point would make a spike the angle criteria cannot triangulate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from refsim.constraints.needle_geometry import needle_rows
from refsim.constraints.rows import BILATERAL, CUT_BORDER, CUT_SLIDE, UNILATERAL, RowBlock, point_rows
from refsim.constraints.step_geometry import StepGeometry
from refsim.cutting.growth import border_inward_directions, front_border_points, resample_polyline, sweep_points

__all__ = [
    "cut_criterion",
    "sweep_points",
    "resample_polyline",
    "cut_block",
    "border_inward_directions",
    "CutRowInfo",
    "front_border_points",
    "one_per_group",
]

# Border points whose inward direction has less than this component normal to the needle are ends of the
# strip (their inward direction runs along the shaft): they would only block the axial motion. cos(60°).
_MIN_NORMAL_COMPONENT = 0.5


def cut_criterion(lateral_force: np.ndarray, point_count: int, cutting_force: float) -> bool:
    """Equation (3): ‖t‖ > n_i · f_c."""
    return point_count > 0 and float(np.linalg.norm(lateral_force)) > point_count * cutting_force


def one_per_group(groups: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """Indices of the smallest score in each group (ties: the first), sorted, shape (g,)."""
    if groups.size == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.lexsort((np.arange(groups.size), scores, groups))
    first = np.concatenate([[True], groups[order][1:] != groups[order][:-1]])
    return np.sort(order[first])


@dataclass(frozen=True)
class CutRowInfo:
    """Which border point each border row belongs to (for tearing), shape (b,), and the rows' index in the block."""

    border_point: np.ndarray
    rows: np.ndarray


def _surface_point_nodes(cut, mesh_tets, triangle, weights):
    """Tissue nodes and weights of points on cut triangles: Σ_v w_v Σ_k β_vk x_{tet_v, k}, shape (q, 12)."""
    corners = cut.triangles[triangle]  # (q, 3)
    nodes = mesh_tets[cut.tet_indices[corners]].reshape(len(triangle), 12)
    node_weights = (weights[:, :, None] * cut.barycentric[corners]).reshape(len(triangle), 12)
    return nodes, node_weights


def cut_block(
    cut,
    geometry: StepGeometry,
    *,
    entry_arc_length: float,
    spacing: float,
    cut_direction: np.ndarray,
) -> tuple[RowBlock | None, CutRowInfo]:
    """Sliding (bilateral) and border (unilateral) rows of the cut surface, on the free positions.

    Parameters
    ----------
    cut : The `refsim.cutting.CutSurface`.
    geometry : The step's geometry.
    entry_arc_length : Arc length [m] of the needle at the entry point; the inserted part is [entry, length].
    spacing : d_c [m], the needle sampling.
    cut_direction : ĉ, the unit direction the cut runs (deformed state), shape (3,).
    """
    mesh_tets, tissue_free, needle_free = geometry.mesh_tets, geometry.tissue_free, geometry.needle_free
    tissue_dof_count = geometry.tissue_dof_count
    empty = CutRowInfo(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    if cut.triangle_count == 0:
        return None, empty
    surface = cut.deformed_points(tissue_free, mesh_tets)
    length = needle_free.length
    start = max(0.0, min(entry_arc_length, length) - spacing)
    count = max(int(np.ceil((length - start) / spacing)), 1)
    samples = np.linspace(start, length, count + 1)
    needle_points = needle_free.points(samples)

    # Sliding rows: needle samples whose projection falls inside the surface.
    found = cut.closest_points(needle_points, surface)
    all_normals = cut.triangle_normals(surface)[found.triangle]
    offset = needle_points - found.closest
    in_plane = offset - np.einsum("ij,ij->i", offset, all_normals)[:, None] * all_normals
    inside = np.flatnonzero(found.inside | (np.linalg.norm(in_plane, axis=1) <= 0.25 * spacing))
    nearest_vertex = cut.triangles[found.triangle[inside], np.argmax(found.barycentric[inside], axis=1)]
    slide_gap_all = np.abs(np.einsum("ij,ij->i", all_normals[inside], offset[inside]))
    inside = inside[one_per_group(cut.tet_indices[nearest_vertex], slide_gap_all)]
    normals = all_normals[inside]
    slide_gaps = np.einsum("ij,ij->i", normals, needle_points[inside] - found.closest[inside])
    slide_nodes, slide_weights = _surface_point_nodes(cut, mesh_tets, found.triangle[inside], found.barycentric[inside])

    # Border rows: each border point against its closest needle point, the closest per needle edge kept.
    border, inward = front_border_points(cut, surface, cut_direction)
    arc, closest = needle_free.project(surface[border])
    tangents = needle_free.tangents(arc)
    direction = inward - np.einsum("ij,ij->i", inward, tangents)[:, None] * tangents
    norms = np.linalg.norm(direction, axis=1)
    usable = (norms >= _MIN_NORMAL_COMPONENT) & (arc >= start) & (arc <= length)
    direction[usable] /= norms[usable, None]
    gaps = np.einsum("ij,ij->i", direction, closest - surface[border])
    edge = np.minimum(np.searchsorted(samples, arc, side="right") - 1, count - 1)
    candidates = np.flatnonzero(usable)
    keep = candidates[one_per_group(edge[candidates], gaps[candidates])]
    keep = keep[one_per_group(cut.tet_indices[border[keep]], gaps[keep])]
    border_gaps = gaps[keep]
    border_nodes = mesh_tets[cut.tet_indices[border[keep]]]
    border_weights = cut.barycentric[border[keep]]

    slide_count, border_count = inside.size, keep.size
    if slide_count + border_count == 0:
        return None, empty
    jacobian_slide = point_rows(slide_nodes, slide_weights, normals, tissue_dof_count)
    jacobian_border = point_rows(border_nodes, border_weights, direction[keep], tissue_dof_count)
    directions = np.concatenate([normals, direction[keep]])
    arc_lengths = np.concatenate([samples[inside], arc[keep]])
    block = RowBlock(
        tissue_jacobian=sp.vstack([jacobian_slide, jacobian_border], format="csr"),
        needle_jacobian=needle_rows(needle_free, arc_lengths, directions),
        free_gap=np.concatenate([slide_gaps, border_gaps]),
        kind=np.concatenate([np.full(slide_count, BILATERAL), np.full(border_count, UNILATERAL)]).astype(np.int8),
        source=np.concatenate([np.full(slide_count, CUT_SLIDE), np.full(border_count, CUT_BORDER)]).astype(np.int8),
        points=np.concatenate([found.closest[inside], surface[border[keep]]]),
        directions=directions,
    )
    return block, CutRowInfo(border[keep], slide_count + np.arange(border_count))
