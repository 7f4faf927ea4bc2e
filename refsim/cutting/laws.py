"""Cutting laws: when a cut starts and how its crack front grows, one class per law, chosen once per scene.

- :class:`EnergyLaw` (``cutting.law = "energy"``, the default): Griffith's energy balance with G_c per unit
  area of new cut. The cut starts when the shaft's lateral load per unit inserted length reaches G_c,
  ‖t‖ ≥ G_c L_in; the crack front's rows carry at most G_c per unit length of needle, and the crack tip moves
  to the needle where a front row (or a sliding row at the front) reached that strength.
- :class:`PaperLaw` (``cutting.law = "paper"``): the paper's equation 3, ‖t‖ > n_i f_c over the n_i insertion
  points, a first surface reaching d_t beyond the path, and tears of d_t along ĉ when a front row's force
  reaches f_t.

A law holds its own parameters and answers every question the detection and the events ask of the cut;
nothing outside this module compares a law's name. Each parameter is a dataclass field declared with
:func:`law_key` (default, unit, valid range, meaning): it is a scene key of ``[cutting]``
(``CuttingLaw.keys``), and the scene's ``CuttingSpec`` has one field per declared key, generated from these
declarations. The scene builds the law (`refsim.scene.spec.CuttingSpec.cutting_law`), and only the chosen
law's keys may be set.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from refsim.cutting.growth import CutGrowth, advance_front, crack_tip_targets, move_front

__all__ = [
    "CUTTING_LAWS",
    "LIMIT_TOLERANCE",
    "CutStart",
    "CuttingLaw",
    "EnergyLaw",
    "FrontGrowth",
    "FrontPush",
    "PaperLaw",
    "column_mean",
    "law_key",
    "law_of_key",
    "swept_direction",
]

#: Relative tolerance of "a row at its force limit" for the crack front's rows (G_c ℓ_k) and the sliding rows
#: at the front: a row that gave way carries its limit to the solve's accuracy (≤ 1e-8), far inside 1e-6.
LIMIT_TOLERANCE = 1e-6


def law_key(
    default: float,
    *,
    unit: str,
    doc: str,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
):
    """A law parameter: a dataclass field declaring its scene key of ``[cutting]`` (default, unit, the valid
    range low..high, open or closed at each end, and a one-line meaning); the scene validates the chosen
    law's keys from these (the metadata of ``refsim.scene.fields.spec``)."""
    metadata = dict(unit=unit, doc=doc, low=low, high=high, low_open=low_open, high_open=high_open)
    return dataclasses.field(default=default, metadata=metadata)


@dataclass(frozen=True)
class CutStart:
    """A cut start: what triggered it and how far the first surface reaches.

    Attributes
    ----------
    trigger : The load that started it: a force per unit length [N/m] (energy law) or per insertion point [N]
        (paper law).
    unit : The unit of ``trigger``, "N/m" or "N".
    extent : How far the first surface reaches beyond the path along ĉ [m], ≥ 0.
    """

    trigger: float
    unit: str
    extent: float


@dataclass(frozen=True)
class FrontPush:
    """The crack front's load at the end of a step, and what moving the front needs.

    Attributes
    ----------
    growth : The tissue's cut growth (rest positions, tets, d_c).
    cut : The cut surface. strip : Its strip (columns, layers, crack front).
    direction : ĉ, unit, shape (3,).
    positions : Tissue positions at the step's end [m], shape (n, 3).
    step : The step's index (stamped on new cut points).
    needle : The needle's centreline at the step's end.
    front : The front rows (`refsim.constraints.cut.FrontRows`: ``rows``, ``segment``, ``band_rows``,
        ``band_segment``, ``gaps``), indices into the step's rows.
    multipliers : The step's multipliers [N], shape (r,).
    force_limit : The rows' force limits [N], shape (r,).
    entry_arc : Arc length where the needle enters the tissue [m] (energy law), None if not computed.
    locator : Tet locator on ``positions`` (energy law), None if not built.
    compression : ``(given_rows, given, columns) -> (c, 3)``: the compliant rows' compression C λ at the
        columns a row gave way next to [m] (`refsim.constraints.cut.crack_tip_compression`).
    compliance : The rows' added compliance C [m/N], shape (r,) (``RowBlock.compliance_diagonal``; empty:
        none).
    """

    growth: CutGrowth
    cut: Any
    strip: Any
    direction: np.ndarray
    positions: np.ndarray
    step: int
    needle: Any
    front: Any
    multipliers: np.ndarray
    force_limit: np.ndarray
    entry_arc: float | None = None
    locator: Any = None
    compression: Callable | None = None
    compliance: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True)
class FrontGrowth:
    """The cut after its front grew in a step.

    Attributes
    ----------
    cut : The cut surface. strip : Its strip. direction : ĉ, unit, shape (3,).
    tear : The front's load that laid a new layer [N] (event ``tear``), None when no layer was laid.
    layer_distance : How far the crack tip was from the last layer before laying [m] (rest; a layer is laid
        when it reaches ``layer_spacing``), None when the law lays layers otherwise (paper law).
    layer_spacing : That distance's threshold [m] (d_c), None with it.
    """

    cut: Any
    strip: Any
    direction: np.ndarray
    tear: float | None
    layer_distance: float | None = None
    layer_spacing: float | None = None


class CuttingLaw:
    """What a cutting law answers; one subclass per law (a frozen dataclass of its parameters).

    Class attributes
    ----------------
    name : The law's name (the value of ``cutting.law``).
    keys : The scene keys of ``[cutting]`` that belong to this law only: its dataclass fields, each declared
        by :func:`law_key` (set when the law is listed in :data:`CUTTING_LAWS`).
    excludes_entry_point : Whether the cut-start load leaves out the entry point's rows up to f_p (at the
        free surface they also carry the surface's reaction to an oblique entry, a load no shaft cuts with:
        `refsim.simulation.events.shaft_lateral_force`).
    rows_while_cutting : Whether the path's points keep their insertion rows while cutting.
    extends_down_shaft : Whether the strip extends down a needle inserted deeper than it while cutting.
    cut_start_unit : The unit of the load a cut start reports, "N/m" or "N".
    """

    name: ClassVar[str]
    keys: ClassVar[tuple[str, ...]]
    excludes_entry_point: ClassVar[bool]
    rows_while_cutting: ClassVar[bool]
    extends_down_shaft: ClassVar[bool]
    cut_start_unit: ClassVar[str]

    @property
    def front_strength(self) -> float:
        """Force per unit length of needle at which a crack front row gives way [N/m] (inf: never)."""
        raise NotImplementedError

    def cut_start(self, lateral_force: np.ndarray, *, inserted_length: float, point_count: int):
        """The cut start under the shaft's lateral load t [N], shape (3,), or None when the criterion does not
        hold. ``inserted_length`` [m] is the needle's length below the entry point, ``point_count`` the
        insertion points n_i."""
        raise NotImplementedError

    def cut_start_load(
        self, lateral_force: np.ndarray, *, inserted_length: float, point_count: int
    ) -> tuple[float, float, float, str]:
        """What :meth:`cut_start` compares: (value, threshold, divisor, unit), value = ‖t‖ / divisor in
        ``unit`` (the margin of the event, `refsim.simulation.margins`)."""
        raise NotImplementedError

    def front_load(self, forces: np.ndarray, limits: np.ndarray) -> tuple[float, float, float, str] | None:
        """What the crack front's growth compares, for the front rows' forces and force limits [N], shape
        (f,): (value, threshold, divisor, unit) of its strongest row, the value a force over ``divisor``; None
        without front rows."""
        raise NotImplementedError

    def kept_at_cut_start(self, point_count: int) -> np.ndarray:
        """Indices of the path points kept when the cut starts (the entry point first), shape (k,)."""
        raise NotImplementedError

    def grow(self, push: FrontPush) -> FrontGrowth | None:
        """The cut after the front's load of a step, or None when the front holds."""
        raise NotImplementedError

    @classmethod
    def defaults(cls) -> dict[str, float]:
        """The law's parameters by default, by scene key."""
        return {field.name: field.default for field in dataclasses.fields(cls)}


@dataclass(frozen=True)
class EnergyLaw(CuttingLaw):
    """Griffith's energy balance: the needle cuts where it pushes with G_c per unit length (independent of
    d_i, d_c and the mesh).

    Attributes
    ----------
    fracture_energy : G_c [J/m²], > 0: energy per unit area of new cut, the lateral force per unit length of
        needle that cuts.
    """

    name: ClassVar[str] = "energy"
    excludes_entry_point: ClassVar[bool] = True
    rows_while_cutting: ClassVar[bool] = False
    extends_down_shaft: ClassVar[bool] = True
    cut_start_unit: ClassVar[str] = "N/m"

    fracture_energy: float = law_key(
        200.0,
        unit="J/m^2",
        doc="G_c: energy per unit area of new cut, the lateral force per unit length of needle that cuts "
        "(liver about 76–225 J/m², Azar and Hayward 2008)",
        low=0.0,
        low_open=True,
    )

    @property
    def front_strength(self) -> float:
        return self.fracture_energy

    def cut_start(self, lateral_force, *, inserted_length, point_count):
        """‖t‖ ≥ G_c L_in: the lateral load per unit inserted length reaches G_c. The first surface is the
        inserted needle itself (extent 0)."""
        magnitude = float(np.linalg.norm(lateral_force))
        if inserted_length <= 0.0 or magnitude < self.fracture_energy * inserted_length:
            return None
        return CutStart(magnitude / inserted_length, self.cut_start_unit, 0.0)

    def cut_start_load(self, lateral_force, *, inserted_length, point_count):
        """‖t‖ / L_in against G_c [N/m]."""
        length = max(float(inserted_length), 0.0)
        magnitude = float(np.linalg.norm(lateral_force))
        value = magnitude / length if length > 0.0 else 0.0
        return value, self.fracture_energy, length, self.cut_start_unit

    def front_load(self, forces, limits):
        """The strongest front row's force over its strength G_c ℓ_k, against 1 (it gives way at 1)."""
        if np.size(forces) == 0:
            return None
        ratios = np.asarray(forces) / np.asarray(limits)
        strongest = int(np.argmax(ratios))
        return float(ratios[strongest]), 1.0, float(np.asarray(limits)[strongest]), "1"

    def kept_at_cut_start(self, point_count):
        """The entry point and the strip's deepest point (none of a path that has no point left); neither
        has rows while cutting."""
        return (
            np.unique(np.array([0, point_count - 1], dtype=np.int64))
            if point_count
            else np.zeros(0, np.int64)
        )

    @staticmethod
    def _at_end(push: FrontPush) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The crack tip's points (q, 3), the front rows' gaps (f,) and the sliding rows' at the front (b,) at
        the step's end [m]: what :meth:`residuals`, :meth:`given_way` and :meth:`grow` read, computed once
        per push."""
        front = push.front
        tips = push.strip.front.positions(push.positions, push.growth.tets)
        return tips, front.gaps(tips, push.needle), front.band_gaps(push.positions, push.needle)

    def residuals(self, push: FrontPush, at_end=None) -> tuple[np.ndarray, np.ndarray]:
        """The front rows' and the sliding rows' at the front solved residual r = δ + C λ at the step's end
        [m], shapes (f,), (b,): δ = nᵀ(x_needle − x_tissue) on the material points the rows hold, less the
        compression C λ their compliance allows. A row that holds has r = 0 (to the solve's accuracy); a row
        at its limit has r ≠ 0 by how far the needle went through the tissue beyond that compression, along
        its direction: the needle's motion relative to the material point, so the tissue's own deformation
        (which carries the crack tip with it) counts for nothing. ``at_end``: :meth:`_at_end` of the push,
        computed here when None."""
        front, multipliers = push.front, push.multipliers
        compliance = np.asarray(push.compliance, dtype=float)

        def compressed(rows):
            return compliance[rows] * multipliers[rows] if compliance.size else np.zeros(rows.size)

        _, front_gaps, band_gaps = self._at_end(push) if at_end is None else at_end
        front_residual = front_gaps + compressed(front.rows)
        band_residual = band_gaps + compressed(front.band_rows)
        return front_residual, band_residual

    def given_way(self, push: FrontPush, at_end=None) -> tuple[np.ndarray, np.ndarray]:
        """Where the front gave way, and by how much [m].

        A front row gave way where it is at its strength G_c ℓ_k with the needle through the crack tip beyond
        its compression (r < 0, :meth:`residuals`). It cut by how far the needle moved into the front
        relative to the tissue over the step, at most −r: the same needle point (arc length) against the same
        material point of the crack tip at the start and the end of the step, δ_start − δ_end. The advance is
        thus the needle's motion through the tissue, whatever dt, and a needle and tissue moving together
        (a breathing organ carrying both) cut nothing; a row left at its strength with r < 0 by a hair (the
        load a stroke left, or a needle sliding along a kinked crack-tip polyline) moves no column. Likewise a
        sliding row at the front at its limit, with the needle gone on the way the row pushes against: its
        slip out of the cut's plane relative to the tissue over the step, at most |r|.

        Returns
        -------
        (over (f,), slip (b,)) : ≥ 0, 0 where the row holds (``at_end``: :meth:`_at_end` of the push,
        computed here when None).
        """
        front, multipliers, limit = push.front, push.multipliers, push.force_limit
        at_end = self._at_end(push) if at_end is None else at_end
        _, front_gaps, band_gaps = at_end
        front_residual, band_residual = self.residuals(push, at_end)
        at_limit = multipliers[front.rows] >= (1.0 - LIMIT_TOLERANCE) * limit[front.rows]
        relative = np.asarray(front.previous_gaps) - front_gaps
        cut = np.minimum(-front_residual, relative)
        over = np.where(at_limit & (front_residual < 0.0), np.clip(cut, 0.0, None), 0.0)
        band = front.band_rows
        sideways = np.abs(multipliers[band]) >= (1.0 - LIMIT_TOLERANCE) * limit[band]
        sideways &= band_residual * multipliers[band] < 0.0
        way = np.sign(band_residual)
        band_relative = way * (band_gaps - np.asarray(front.band_previous_gaps))
        slid = np.minimum(np.abs(band_residual), band_relative)
        slip = np.where(sideways, np.clip(slid, 0.0, None), 0.0)
        return over, slip

    def passed(self, push: FrontPush, at_end=None) -> tuple[np.ndarray, np.ndarray]:
        """The crack-tip columns the needle has gone past with no front row on them, and where they go [m],
        shapes (c,), (c, 3).

        The front rows stand at the needle's samples, each against the closest point of the crack tip's
        polyline, so a column that lags its neighbours (a notch in the crack tip) is the nearest column of no
        row: the needle goes past it freely and, moved only next to rows that gave way, it stayed behind for
        good. A column that is the nearest of no front row, at a depth the needle reaches, whose crack tip the
        needle's centreline at that depth is ahead of along ĉ (normal to the needle) by more than the front's
        compression at its strength (max C_k G_c ℓ_k over the front rows, plus d_c/1000; a column a row holds
        lies behind the needle by at most that) has been gone through: it goes to the needle, less that
        compression. Without this the crack tip was as rough in absolute terms at every d_c (on the liver,
        neighbouring columns up to 1 mm apart along ĉ at d_c = 0.25 mm), so its slopes, and the load the
        sliding rows on the notches' facets carry along ĉ, grew as d_c shrank."""
        empty = np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        front, strip = push.front, push.strip
        if push.entry_arc is None or front.rows.size == 0:
            return empty
        at_end = self._at_end(push) if at_end is None else at_end
        tips = at_end[0]
        touched = np.zeros(strip.column_count, dtype=bool)
        touched[front.segment + (front.parameter >= 0.5)] = True
        candidates = np.flatnonzero(~touched)
        if candidates.size == 0:
            return empty
        spacing = push.growth.point_spacing
        targets, reached = crack_tip_targets(strip, push.needle, push.entry_arc, candidates, spacing)
        compliance = np.asarray(push.compliance, dtype=float)
        compression = (
            float(np.max(compliance[front.rows] * push.force_limit[front.rows])) if compliance.size else 0.0
        )
        needle = push.needle
        tangents = needle.tangents(needle.project(targets)[0])
        across = push.direction - (tangents @ push.direction)[:, None] * tangents
        across /= np.linalg.norm(across, axis=1, keepdims=True)
        ahead = np.einsum("ij,ij->i", targets - tips[candidates], across)
        gone = reached & (ahead > compression + 1e-3 * spacing)
        return candidates[gone], targets[gone] - compression * across[gone]

    def grow(self, push):
        """The crack tip moves towards the needle next to every row that gave way, by how far the needle went
        through the tissue there beyond the rows' compression (so a needle moving along its own axis moves
        no column, and the advance does not depend on the step), and a column the needle went past with no
        row on it goes to the needle (:meth:`passed`); a new layer (event ``tear``) is laid once
        the crack tip is d_c past the last, and ĉ turns half-way to the layer's swept direction."""
        front, strip, positions = push.front, push.strip, push.positions
        if front.rows.size == 0 and front.band_rows.size == 0:
            return None
        at_end = self._at_end(push)
        over, slip = self.given_way(push, at_end)
        passed, passed_targets = self.passed(push, at_end)
        if not (np.any(over > 0.0) or np.any(slip > 0.0) or passed.size):
            return None
        spacing = push.growth.point_spacing
        # Each column next to a row that gave way (a front row, or a sliding row at the front) moves towards
        # the needle at its own depth below the tissue surface (moving the ends of a row's segment by the
        # row's overshoot carries a lagging column's overshoot to its neighbour).
        front_given, band_given = over > 0.0, slip > 0.0
        given = np.concatenate([front.segment[front_given], front.band_segment[band_given]])
        columns = np.unique(np.concatenate([given, given + 1]))
        tips = at_end[0][columns]
        targets, reached = crack_tip_targets(strip, push.needle, push.entry_arc, columns, spacing)
        # The material point in contact with the needle: the centreline plus the compliant rows' compression
        # C λ along their direction, so the rows keep their force as the crack tip moves.
        given_rows = np.concatenate([front.rows[front_given], front.band_rows[band_given]])
        targets = targets + push.compression(given_rows, given, columns)
        # How far the needle went through the tissue at each column (its rows' residuals along their
        # directions): the column moves towards its target by that much along it, at most to the target.
        _, band_residual = self.residuals(push, at_end)
        penetration = column_mean(
            columns, front.segment[front_given], -over[front_given, None] * front.directions[front_given]
        ) + column_mean(
            columns,
            front.band_segment[band_given],
            (np.sign(band_residual) * slip)[band_given, None] * front.band_directions[band_given],
        )
        motion = targets - tips
        along = np.einsum("ij,ij->i", motion, penetration)
        reach = np.einsum("ij,ij->i", penetration, penetration)
        scale = np.where(along > reach, reach / np.where(along > reach, along, 1.0), 1.0)
        motion = np.where((along > 0.0)[:, None], scale[:, None] * motion, 0.0)
        targets = tips + motion
        # The columns the needle has gone past with no row on them go to it (:meth:`passed`), whether or not
        # a row on a segment they end gave way.
        if passed.size:
            kept = ~np.isin(columns, passed)
            order = np.argsort(np.concatenate([columns[kept], passed]), kind="stable")
            columns = np.concatenate([columns[kept], passed])[order]
            reached = np.concatenate([reached[kept], np.ones(passed.size, dtype=bool)])[order]
            targets = np.concatenate([targets[kept], passed_targets])[order]
            tips = at_end[0][columns]
            motion = targets - tips
        needle = push.needle
        tangents = needle.tangents(needle.project(targets)[0])
        across = push.direction - (tangents @ push.direction)[:, None] * tangents
        across /= np.linalg.norm(across, axis=1, keepdims=True)
        distance = np.linalg.norm(motion, axis=1)
        # Forward, or sideways (a turning stroke): anything but back into the cut (within 60° of ĉ's opposite:
        # the needle has moved back from the crack tip, and there is nothing to cut).
        ahead = (
            reached & (distance > 1e-6 * spacing) & (np.einsum("ij,ij->i", motion, across) > -0.5 * distance)
        )
        moved = strip.with_front(
            move_front(push.growth, strip, columns[ahead], targets[ahead], positions, locator=push.locator)
        )
        due = moved.due(push.cut, push.step, spacing)  # what both read: computed once
        distance = moved.layer_distance(push.cut, push.step, spacing, due=due)
        cut, laid = moved.lay(push.cut, push.step, spacing, due=due)
        if laid.layers.shape[0] == strip.layers.shape[0]:
            return FrontGrowth(cut, laid, push.direction, None, distance, spacing)
        load = float(push.multipliers[front.rows].sum()) + float(
            np.abs(push.multipliers[front.band_rows]).sum()
        )
        points = cut.deformed_points(positions, push.growth.tets)
        direction = swept_direction(points, laid, needle, push.direction)
        return FrontGrowth(cut, laid, direction, load, distance, spacing)


@dataclass(frozen=True)
class PaperLaw(CuttingLaw):
    """The paper's law (section 4): equation 3 starts the cut, a front row at f_t tears it by d_t.

    Attributes
    ----------
    cutting_force : f_c [N], ≥ 0: mean lateral force per insertion point that starts the cut.
    tearing_force : f_t [N], ≥ 0: front row force that extends the cut by d_t.
    extent : d_t [m], > 0: extent of the first cut surface beyond the path, and of each tear (the paper gives
        no value).
    """

    name: ClassVar[str] = "paper"
    excludes_entry_point: ClassVar[bool] = False
    rows_while_cutting: ClassVar[bool] = True
    extends_down_shaft: ClassVar[bool] = False
    cut_start_unit: ClassVar[str] = "N"

    cutting_force: float = law_key(
        1.0,
        unit="N",
        doc="f_c: mean lateral force per insertion constraint that starts the cut (default: the paper's "
        "value)",
        low=0.0,
    )
    tearing_force: float = law_key(
        1.0,
        unit="N",
        doc="f_t: front row force that extends the cut by d_t (default: the paper's value)",
        low=0.0,
    )
    extent: float = law_key(
        1e-3,
        unit="m",
        doc="d_t: extent of the first cut surface beyond the path, and of each tear (the paper gives no "
        "value)",
        low=0.0,
        low_open=True,
    )

    @property
    def front_strength(self) -> float:
        return np.inf

    def cut_start(self, lateral_force, *, inserted_length, point_count):
        """Equation 3, ‖t‖ > n_i f_c. The first surface reaches d_t beyond the path."""
        magnitude = float(np.linalg.norm(lateral_force))
        if not (point_count > 0 and magnitude > point_count * self.cutting_force):
            return None
        return CutStart(magnitude / point_count, self.cut_start_unit, self.extent)

    def cut_start_load(self, lateral_force, *, inserted_length, point_count):
        """‖t‖ / n_i against f_c [N]."""
        magnitude = float(np.linalg.norm(lateral_force))
        value = magnitude / point_count if point_count > 0 else 0.0
        return value, self.cutting_force, float(max(point_count, 0)), self.cut_start_unit

    def front_load(self, forces, limits):
        """The strongest front row's force against f_t [N]."""
        if np.size(forces) == 0:
            return None
        return float(np.max(forces)), self.tearing_force, 1.0, "N"

    def kept_at_cut_start(self, point_count):
        """The entry point (none of a path that has no point left), whose rows hold the needle while it
        cuts."""
        return np.zeros(min(int(point_count), 1), dtype=np.int64)

    def grow(self, push):
        """A front row's force ≥ f_t tears the whole front by d_t along ĉ, in layers at most d_c apart."""
        forces = push.multipliers[push.front.rows]
        if forces.size == 0:
            return None
        strongest = float(forces.max())
        if strongest < self.tearing_force:
            return None
        pieces = max(int(np.ceil(self.extent / push.growth.point_spacing - 1e-9)), 1)
        cut, strip = push.cut, push.strip
        for _ in range(pieces):  # d_t / d_c layers, each vectorised over the columns
            advances = np.full(strip.column_count, self.extent / pieces)
            strip = strip.with_front(
                advance_front(push.growth, strip, advances, push.direction, push.positions)
            )
            cut, strip = strip.lay(cut, push.step, 0.5 * self.extent / pieces)
        return FrontGrowth(cut, strip, push.direction, strongest)


def _listed(*laws: type[CuttingLaw]) -> dict[str, type[CuttingLaw]]:
    """The laws by name, each with ``keys``: its declared parameters (fields with :func:`law_key`
    metadata)."""
    for law in laws:
        law.keys = tuple(field.name for field in dataclasses.fields(law) if "doc" in field.metadata)
    return {law.name: law for law in laws}


#: The laws by name (the choices of ``cutting.law``).
CUTTING_LAWS: dict[str, type[CuttingLaw]] = _listed(EnergyLaw, PaperLaw)


def law_of_key(key: str) -> str | None:
    """The name of the law a ``[cutting]`` key belongs to, None for a key common to all laws."""
    for name, law in CUTTING_LAWS.items():
        if key in law.keys:
            return name
    return None


def column_mean(columns: np.ndarray, segments: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """The mean of ``vectors`` (shape (k, 3), one per row on crack-tip segment ``segments`` (k,), which ends
    at columns s and s + 1) at each of ``columns`` (sorted, holding every such end), shape (c, 3); 0 at a
    column no row ends at."""
    out = np.zeros((columns.size, 3))
    if segments.size == 0:
        return out
    where = np.searchsorted(columns, np.concatenate([segments, segments + 1]))
    counts = np.zeros(columns.size)
    np.add.at(out, where, np.concatenate([vectors, vectors]))
    np.add.at(counts, where, 1.0)
    return out / np.maximum(counts, 1.0)[:, None]


def swept_direction(points: np.ndarray, strip, needle, direction: np.ndarray) -> np.ndarray:
    """ĉ after a layer is laid: the mean of the old ĉ and of the direction the last layer moved in (its
    columns' mean displacement from the layer before, on the cut's deformed ``points``, normal to the needle),
    unit.

    The cut's plane thus follows the needle's swept path, turned by half the angle each layer (d_c of
    sweep): a stroke that turns turns the cut, and a straight one keeps it.
    """
    last, before = strip.layers[-1], strip.layers[-2]
    moved = last != before
    if not np.any(moved):
        return direction
    swept = (points[last[moved]] - points[before[moved]]).mean(axis=0)
    tangent = needle.tangents(np.array([needle.length]))[0]
    swept -= (swept @ tangent) * tangent
    old = direction - (direction @ tangent) * tangent
    norm_swept, norm_old = np.linalg.norm(swept), np.linalg.norm(old)
    if norm_swept <= 0.0 or norm_old <= 0.0:
        return direction
    blended = old / norm_old + swept / norm_swept
    norm = np.linalg.norm(blended)
    return blended / norm if norm > 1e-6 else direction
