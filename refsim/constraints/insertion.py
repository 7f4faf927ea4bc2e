"""Insertion constraints (paper, section 3 and Figure 1b): points along the path taken by the tip.

Each point is a material point of the tissue, anchored by the barycentric coordinates of its tet (found in the
deformed state when the point is created, then fixed), and is coupled to the needle at its projection on the
centreline: two bilateral rows in the plane normal to the needle (φ_i) and one shaft friction row along it
(ψ_i), whose Coulomb bound is μ_i times the norm of the two bilateral forces (stick inside, slip at the
bound), plus, optionally, μ_i times a normal preload per point: the tissue's radial grip on the needle, which
a centreline model does not see (our extension; with a zero preload this is the paper's model).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from refsim.constraints.friction import friction_rows, stick_offsets
from refsim.constraints.needle_geometry import NeedleGeometry, needle_rows
from refsim.constraints.rows import (
    AXIAL_FRICTION,
    BILATERAL,
    FRICTION,
    INSERTION,
    LATERAL_FIRST,
    LATERAL_SECOND,
    NEEDLE,
    TISSUE,
    RowBlock,
    orthonormal_basis,
    point_rows,
    stack_jacobians,
)
from refsim.constraints.step_geometry import StepGeometry

if TYPE_CHECKING:  # coupling.py builds on this module
    from refsim.constraints.coupling import RingLayout

__all__ = [
    "InsertionOptions",
    "InsertionPath",
    "PointRings",
    "insertion_block",
    "shaft_friction_coefficients",
    "grow_path",
    "points_beyond_tip",
    "point_row_metadata",
]


@dataclass(frozen=True)
class PointRings:
    """The coupling ring each insertion point's rows were last built on (the ring coupling), one per point.

    A point keeps its ring while the needle's tangent at it stays within 1e-3 rad of ``tangents``
    (:meth:`refsim.simulation.detection.Detector.insertion_rows`); the rings travel with the points, so the
    rows of a step depend on its state only.

    Attributes
    ----------
    layout : The rings (:class:`refsim.constraints.coupling.RingLayout`), q points each: tets (p, q),
        barycentric (p, q, 4), mesh size and radius [m] (p,); a point without a ring yet has tets −1 and NaN.
    tangents : The needle's unit tangent each ring was built normal to, shape (p, 3); NaN for a point without
        a ring yet.
    """

    layout: RingLayout
    tangents: np.ndarray

    @property
    def point_count(self) -> int:
        return int(self.tangents.shape[0])

    def subset(self, keep: np.ndarray) -> PointRings:
        """The rings of the points ``keep`` selects (bool (p,) or indices)."""
        return PointRings(self.layout.subset(keep), self.tangents[keep])

    def padded(self, count: int) -> PointRings:
        """The same rings followed by ``count`` points without one."""
        layout = self.layout
        per_ring = layout.tets.shape[1]
        return PointRings(
            replace(
                layout,
                tets=np.concatenate([layout.tets, np.full((count, per_ring), -1, dtype=layout.tets.dtype)]),
                barycentric=np.concatenate([layout.barycentric, np.full((count, per_ring, 4), np.nan)]),
                mesh_size=np.concatenate([layout.mesh_size, np.full(count, np.nan)]),
                radius=np.concatenate([layout.radius, np.full(count, np.nan)]),
            ),
            np.concatenate([self.tangents, np.full((count, 3), np.nan)]),
        )


@dataclass(frozen=True)
class InsertionPath:
    """The insertion points, in creation order (the first is the puncture point).

    Attributes
    ----------
    tets : Tet of each point, shape (p,).
    barycentric : Barycentric coordinates in that tet, shape (p, 4).
    created_step : Step at which each point was created, shape (p,).
    multipliers : The point's multipliers at its last solve [N], (lateral 1, lateral 2, axial), shape (p, 3);
        the warm start of the next solve.
    stuck : Whether the point's shaft force was inside its Coulomb bound at its last solve (it sticks), bool
        shape (p,); new points start stuck. Chooses the static or the dynamic coefficient of the next step.
    anchors : Stick anchor of each point's axial friction row, the needle arc length [m] at which its sub-grid
        annulus is unstretched (:func:`refsim.constraints.friction.stick_offsets`), shape (p,); NaN where
        unset (a new point, or one that slipped at its last solve: the next step places it from ``stretch``).
    stretch : The annulus' axial stretch −C λ at the point's last solve [m], shape (p,) (0 for a new point).
    rings : The ring coupling's ring of each point (:class:`PointRings`), None before any was built (and with
        the paper's coupling).
    """

    tets: np.ndarray
    barycentric: np.ndarray
    created_step: np.ndarray
    multipliers: np.ndarray | None = None
    stuck: np.ndarray | None = None
    anchors: np.ndarray | None = None
    stretch: np.ndarray | None = None
    rings: PointRings | None = None

    def __post_init__(self) -> None:
        count = self.tets.shape[0]
        if self.multipliers is None:
            object.__setattr__(self, "multipliers", np.zeros((count, 3)))
        if self.stuck is None:
            object.__setattr__(self, "stuck", np.ones(count, dtype=bool))
        if self.anchors is None:
            object.__setattr__(self, "anchors", np.full(count, np.nan))
        if self.stretch is None:
            object.__setattr__(self, "stretch", np.zeros(count))
        if self.rings is not None and self.rings.point_count != count:
            raise ValueError(f"rings for {self.rings.point_count} points on a path of {count} points")

    @classmethod
    def empty(cls) -> InsertionPath:
        return cls(np.zeros(0, dtype=np.int64), np.zeros((0, 4)), np.zeros(0, dtype=np.int64))

    @property
    def lateral_forces(self) -> np.ndarray:
        """Each point's lateral force at its last solve, ‖(λ_lateral 1, λ_lateral 2)‖ [N], shape (p,)."""
        return np.hypot(self.multipliers[:, 0], self.multipliers[:, 1])

    def with_multipliers(self, multipliers: np.ndarray) -> InsertionPath:
        """The same points with their last multipliers [N], shape (p, k), k ≤ 3 (missing columns are zero)."""
        stored = np.zeros((self.point_count, 3))
        multipliers = np.asarray(multipliers, dtype=float).reshape(self.point_count, -1)
        stored[:, : multipliers.shape[1]] = multipliers
        return self._with(multipliers=stored)

    def with_rings(self, rings: PointRings) -> InsertionPath:
        """The same points with the rings their rows were built on (one per point)."""
        if rings is not None and rings.point_count != self.point_count:
            raise ValueError(f"rings for {rings.point_count} points on a path of {self.point_count} points")
        return self._with(rings=rings)

    def with_stuck(self, stuck: np.ndarray) -> InsertionPath:
        """The same points with their stick state (bool (p,)) after a solve."""
        return self._with(stuck=np.asarray(stuck, dtype=bool).reshape(self.point_count))

    def with_anchors(self, anchors: np.ndarray, stretch: np.ndarray) -> InsertionPath:
        """The same points with their stick anchors [m] (NaN: unset) and annulus stretches [m], (p,) each."""
        return self._with(
            anchors=np.asarray(anchors, dtype=float).reshape(self.point_count),
            stretch=np.asarray(stretch, dtype=float).reshape(self.point_count),
        )

    def _with(self, **changes) -> InsertionPath:
        """The path with per-point fields replaced by arrays of its point count (the callers shape them):
        ``dataclasses.replace`` without its pass through ``__init__`` and ``__post_init__``, whose defaults
        this path already has (a few per step)."""
        new = object.__new__(InsertionPath)
        new.__dict__.update(self.__dict__)
        new.__dict__.update(changes)
        return new

    @property
    def point_count(self) -> int:
        return int(self.tets.shape[0])

    def positions(self, tissue_positions: np.ndarray, mesh_tets: np.ndarray) -> np.ndarray:
        """Point positions [m] in a tissue configuration, shape (p, 3)."""
        from refsim.constraints.kernels import interpolated_points  # numba: imported on first use
        from refsim.kernel_cache import readonly

        # np.einsum("pk,pkj->pj", barycentric, tissue_positions[mesh_tets[tets]])'s bits, compiled
        positions = readonly(np.asarray(tissue_positions))
        return interpolated_points(np.asarray(self.barycentric, dtype=float), positions, mesh_tets[self.tets])

    def appended(self, tets: np.ndarray, barycentric: np.ndarray, step: int) -> InsertionPath:
        """A path with points added at its end."""
        return InsertionPath(
            np.concatenate([self.tets, np.asarray(tets, dtype=np.int64)]),
            np.concatenate([self.barycentric, np.asarray(barycentric, dtype=float).reshape(-1, 4)]),
            np.concatenate([self.created_step, np.full(len(tets), step, dtype=np.int64)]),
            np.concatenate([self.multipliers, np.zeros((len(tets), 3))]),
            np.concatenate([self.stuck, np.ones(len(tets), dtype=bool)]),
            np.concatenate([self.anchors, np.full(len(tets), np.nan)]),
            np.concatenate([self.stretch, np.zeros(len(tets))]),
            None if self.rings is None else self.rings.padded(len(tets)),
        )

    def subset(self, keep: np.ndarray) -> InsertionPath:
        """A path with only the points where ``keep`` (bool (p,) or indices) selects."""
        return InsertionPath(
            self.tets[keep],
            self.barycentric[keep],
            self.created_step[keep],
            self.multipliers[keep],
            self.stuck[keep],
            self.anchors[keep],
            self.stretch[keep],
            None if self.rings is None else self.rings.subset(keep),
        )


def point_row_metadata(point_count: int, with_friction: bool, anchors: np.ndarray | None = None) -> dict:
    """The per-row metadata of insertion points' rows, ordered point by point (lateral first, lateral second[,
    axial friction]): ``role``, ``point`` (index in the path the rows were built from) and ``anchor`` (the
    axial rows' stick anchors [m], ``anchors`` shape (p,); NaN elsewhere), each shape (rows,)."""
    per_point = 3 if with_friction else 2
    roles = np.array([LATERAL_FIRST, LATERAL_SECOND, AXIAL_FRICTION][:per_point], dtype=np.int8)
    anchor = np.full((point_count, per_point), np.nan)
    if with_friction and anchors is not None:
        anchor[:, 2] = anchors
    return dict(
        role=np.tile(roles, point_count),
        point=np.repeat(np.arange(point_count, dtype=np.int64), per_point),
        anchor=anchor.ravel(),
    )


def axial_offsets(
    path: InsertionPath,
    geometry: StepGeometry,
    arc_lengths,
    tissue_points_previous,
    *,
    needle_points: np.ndarray | None = None,
    tangents: np.ndarray | None = None,
):
    """The stick offsets D [m] and anchors s_a [m] of the points' axial rows at the start of the step, (p,)
    each (:func:`refsim.constraints.friction.stick_offsets`; ``tissue_points_previous`` (p, 3) the rows'
    tissue points at the start of the step; ``needle_points``, ``tangents``: the needle's points and unit
    tangents at ``arc_lengths`` at the start of the step when the caller has them, else computed here)."""
    needle = geometry.needle_previous
    return stick_offsets(
        arc_lengths,
        needle_points=needle.points(arc_lengths) if needle_points is None else needle_points,
        tangents=needle.tangents(arc_lengths) if tangents is None else tangents,
        tissue_points=tissue_points_previous,
        anchors=path.anchors,
        stretch=path.stretch,
    )


def shaft_friction_coefficients(stuck: np.ndarray, *, static: float, dynamic: float) -> np.ndarray:
    """Per-point shaft friction coefficient: μ_s where the point stuck at the last step, μ_d where it slipped.

    Parameters
    ----------
    stuck : Whether each point was inside its Coulomb bound at the last solve, bool shape (p,) (new points:
        True, they start stuck).
    static, dynamic : μ_s ≥ μ_d ≥ 0.
    """
    if not (math.isfinite(static) and math.isfinite(dynamic) and static >= dynamic >= 0.0):
        raise ValueError(
            f"friction coefficients static = {static!r}, dynamic = {dynamic!r}; valid: static >= dynamic >= 0"
        )
    return np.where(np.asarray(stuck, dtype=bool), static, dynamic)


@dataclass(frozen=True)
class InsertionOptions:
    """The scene's ``[insertion]`` keys the insertion row builders read (:func:`insertion_block`,
    :func:`refsim.constraints.coupling.ring_insertion_block`), as one typed object built from the section by
    its field names (:meth:`from_section`): a key a builder reads is a field of the scene's section
    (``refsim.scene.spec.InsertionSpec``), a field of the same name here and the code that reads it; the
    detector passes the object as it is.

    Attributes
    ----------
    static_friction_coefficient : μ_s of a point that stuck at the last solve [-].
    shaft_friction_coefficient : μ_i (dynamic) of a point that slipped [-].
    """

    static_friction_coefficient: float = 0.0
    shaft_friction_coefficient: float = 0.0

    @classmethod
    def from_section(cls, section) -> InsertionOptions:
        """The options from a scene section (any object with attributes of the options' field names)."""
        return cls(**{field.name: getattr(section, field.name) for field in dataclasses.fields(cls)})

    def friction(self, path: InsertionPath) -> np.ndarray:
        """μ of each point of ``path``: μ_s where it stuck at the last solve, μ_i where it slipped, (p,)."""
        return shaft_friction_coefficients(
            path.stuck, static=self.static_friction_coefficient, dynamic=self.shaft_friction_coefficient
        )


def _friction_of(path: InsertionPath, friction_coefficient, options: InsertionOptions | None):
    """The builders' μ_i: ``friction_coefficient`` when given, else the options' per-point value."""
    if friction_coefficient is not None:
        return friction_coefficient
    if options is None:
        raise TypeError("give friction_coefficient or options (InsertionOptions)")
    return options.friction(path)


def insertion_block(
    path: InsertionPath,
    geometry: StepGeometry,
    *,
    friction_coefficient: float | np.ndarray | None = None,
    normal_preload: float | np.ndarray = 0.0,
    options: InsertionOptions | None = None,
) -> RowBlock:
    """Rows of the insertion points: per point two bilateral rows and, when μ_i > 0, one shaft friction row.

    ``friction_coefficient``: μ_i, a scalar or one per point, shape (p,) (static or dynamic,
    :func:`shaft_friction_coefficients`); the friction rows exist when any is > 0. None: from ``options``
    (:meth:`InsertionOptions.friction`), the scene's ``[insertion]`` keys.

    ``normal_preload`` [N] (≥ 0, finite; a scalar or one per point, shape (p,)) is added to the norm of each
    point's two lateral forces in its Coulomb bound: μ_i (‖(λ_b1, λ_b2)‖ + normal_preload); the detector sets
    it from the grip (:func:`refsim.constraints.channel.channel_preload`).

    The needle point of each tissue point is its projection on the needle at the start of the step (a material
    point of the needle for this step); the friction row (built by
    :func:`refsim.constraints.friction.friction_rows` on the same points) measures the relative axial
    position from its stick anchor (``path.anchors``, :func:`refsim.constraints.friction.stick_offsets`).
    Rows are ordered point by point: (lateral 1, lateral 2[, axial]), and carry their roles and points.
    """
    friction_coefficient = _friction_of(path, friction_coefficient, options)
    point_count = path.point_count
    preload = np.broadcast_to(np.asarray(normal_preload, dtype=float), (point_count,))
    if np.any(~np.isfinite(preload)) or np.any(preload < 0.0):
        raise ValueError(f"normal_preload = {normal_preload!r} N; valid range [0, inf)")
    nodes = geometry.mesh_tets[path.tets]
    weights = path.barycentric
    tissue_point_previous, tissue_point_free = geometry.tissue_points(nodes, weights)
    arc_lengths, _ = geometry.needle_previous.project(tissue_point_previous)
    needle_point_free = geometry.needle_free.points(arc_lengths)
    tangents = geometry.needle_free.tangents(arc_lengths)
    first, second = orthonormal_basis(tangents)
    offset = needle_point_free - tissue_point_free
    lateral_directions = np.stack([first, second], axis=1).reshape(-1, 3)
    lateral_gaps = np.stack(
        [np.einsum("ij,ij->i", first, offset), np.einsum("ij,ij->i", second, offset)], axis=1
    ).ravel()
    lateral_nodes, lateral_weights = np.repeat(nodes, 2, axis=0), np.repeat(weights, 2, axis=0)
    lateral_arcs = np.repeat(arc_lengths, 2)
    jacobians = {
        TISSUE: point_rows(lateral_nodes, lateral_weights, lateral_directions, geometry.tissue_dof_count),
        NEEDLE: needle_rows(geometry.needle_free, lateral_arcs, lateral_directions),
    }
    directions, gaps = lateral_directions, lateral_gaps
    kinds = np.full(2 * point_count, BILATERAL, dtype=np.int8)
    coefficients = np.broadcast_to(np.asarray(friction_coefficient, dtype=float), (point_count,))
    with_friction = bool(np.any(np.asarray(friction_coefficient, dtype=float) > 0.0))
    per_point = 3 if with_friction else 2
    anchors = None
    if with_friction:
        offsets, anchors = axial_offsets(path, geometry, arc_lengths, tissue_point_previous)
        friction = friction_rows(
            geometry,
            tissue_nodes=nodes,
            tissue_weights=weights,
            arc_lengths=arc_lengths,
            tangents=tangents,
            offsets=offsets,
        )
        # Interleave: point p's rows are (2p, 2p + 1) of the lateral rows and p of the friction rows.
        order = np.concatenate(
            [np.arange(2 * point_count).reshape(-1, 2), 2 * point_count + np.arange(point_count)[:, None]],
            axis=1,
        ).ravel()
        stacked = stack_jacobians([jacobians, friction.jacobians])
        jacobians = {name: matrix[order] for name, matrix in stacked.items()}
        directions = np.concatenate([lateral_directions, tangents])[order]
        gaps = np.concatenate([lateral_gaps, friction.free_gap])[order]
        kinds = np.concatenate([kinds, np.full(point_count, FRICTION, dtype=np.int8)])[order]
    row_count = point_count * per_point
    base = np.arange(point_count) * per_point
    return RowBlock(
        jacobians=jacobians,
        free_gap=gaps,
        kind=kinds,
        source=np.full(row_count, INSERTION, dtype=np.int8),
        points=np.repeat(tissue_point_free, per_point, axis=0),
        directions=directions,
        shaft_rows=(base + 2) if with_friction else np.zeros(0, dtype=np.int64),
        shaft_pairs=np.stack([base, base + 1], axis=1) if with_friction else np.zeros((0, 2), dtype=np.int64),
        shaft_friction_coefficient=coefficients.copy() if with_friction else np.zeros(0),
        shaft_normal_preload=preload.copy() if with_friction else np.zeros(0),
        **point_row_metadata(point_count, with_friction, anchors),
    )


#: Relative tolerance on d_i of the rule of new points (:func:`grow_path`): far above the solvers' effect on a
#: point's position (the material points move with the tissue, solved to about 1e-8 of its displacement) and
#: far below any length of a scene (1e-6 d_i: half a nanometre at d_i = 0.5 mm). Without it, a tip stopped at
#: a whole number of spacings below its entry got its last point or not by round-off: the Gauss–Seidel and
#: the exact runs of cube_cut differed by one point, 0.02 N (0.6 % of the peak), once the stroke loaded them.
SPACING_TOLERANCE = 1e-6


def grow_path(
    path: InsertionPath,
    *,
    tip: np.ndarray,
    tissue_positions: np.ndarray,
    mesh_tets: np.ndarray,
    locator,
    spacing: float,
    step: int,
    points: np.ndarray | None = None,
) -> tuple[InsertionPath, int]:
    """Add points behind the tip so that no two consecutive points are farther apart than ``spacing``.

    When the tip is farther than d_i = ``spacing`` from every existing point (to within
    :data:`SPACING_TOLERANCE` of d_i), points are placed on the segment from the last point to the tip every
    d_i (several in one step when the tip moved more than d_i), located in the current deformed tissue.
    Points that fall outside the tissue are not added.

    ``points``: the path's points in this configuration (``path.positions(tissue_positions, mesh_tets)``),
    when the caller has them.

    Returns
    -------
    (path, added) : The new path and the number of points added.
    """
    if path.point_count == 0:
        return path, 0
    positions = path.positions(tissue_positions, mesh_tets) if points is None else points
    # A tip d_i from the last point to within SPACING_TOLERANCE · d_i has reached it: a depth that is a whole
    # number of spacings (a scene's design value) lays its point whatever the solver's last digits.
    reach = spacing * (1.0 - SPACING_TOLERANCE)
    if np.min(np.linalg.norm(positions - tip, axis=1)) <= reach:
        return path, 0
    last = positions[-1]
    segment = tip - last
    length = float(np.linalg.norm(segment))
    count = int(np.floor(length / spacing + SPACING_TOLERANCE))
    if count == 0:
        return path, 0
    new_points = last + np.outer(np.arange(1, count + 1) * spacing / length, segment)
    tets, barycentric = locator.locate(new_points)
    inside = tets >= 0
    return path.appended(tets[inside], barycentric[inside], step), int(np.count_nonzero(inside))


def points_beyond_tip(
    path: InsertionPath, points: np.ndarray, needle: NeedleGeometry, margin: float = 0.0
) -> np.ndarray:
    """Which points lie beyond the tip along the needle by more than ``margin`` [m] (after a withdrawal), bool
    (p,)."""
    if path.point_count == 0:
        return np.zeros(0, dtype=bool)
    return (points - needle.tip) @ needle.tip_tangent > margin
