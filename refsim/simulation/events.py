"""Phases and events (DESIGN.md, step 7): what the forces of a step change in the state.

- phase: approach; event: puncture; when: tip normal force ≥ f_p; then: the entry point is the first insertion
  point; insertion
- phase: approach; event: reentry; when: the tip's closest surface point lies in a hole of the tissue
  (``SimulationState.channels``: within the hole's radius of its entry point, in rest coordinates), where the
  tip has no contact rows, and the tip lies in a tet after the step; then: where the needle meets the surface
  (within the hole) is the first insertion point and the hole's channel's end the channel end (no puncture:
  the surface is open there, and the tip cuts only beyond the end; a channel cut through has no tip row);
  insertion
- phase: insertion; event: (new points); when: the tip is farther than d_i from every point; then: points
  every d_i behind the tip, but none in an existing cut
- phase: insertion; event: (tip location); when: every step; then: the tip's material point (its tet and
  barycentric coordinates) is stored in the state; the tip's cutting row exists while the tip lies in a tet
- phase: insertion; event: (channel end); when: the tip's row below f_cut (it did not cut) and the tip
  behind the deepest material point it reached (moved back along its channel); then: that point is kept as
  the channel's end and the tip's cutting row acts there, from the tip's distance to it: the tip moves
  freely through its own channel and cuts again only beyond its end; after an exit the channel runs
  through the tissue and the tip has no row on that path
- phase: insertion; event: exit; when: the tip, inside the tissue at the step's start, lies in no tet at its
  end, having moved forward through the tissue (along the needle, relative to its material point: a tip
  pulled back out through its entry face is a withdrawal); then: no tip row from the next step; the shaft
  keeps its points; the part of the tissue the tip left keeps its channel, through (both holes), from where
  the tip entered it
- phase: insertion, the tip outside (out of a far face) and advancing; event: puncture, reentry; when: as in
  approach, on the surface ahead of the tip (another layer); then: the point is added to the path (the shaft
  keeps its points), the tip in that layer; until then a tip that reached the surface (its contact's free
  gap at most round-off, or a force on it) or meets a hole stays outside it
- phase: insertion; event: (back out of a layer); when: the tip, inside at the step's start, lies in no tet
  at its end, points left (an inner layer, or the mouth of its entry face); then: that layer keeps its
  channel from where the tip entered it to its end; a tip moved back into a layer it left through its far
  face is on that channel's line (through: no tip row), one pushed into the mouth of its entry face keeps the
  channel's end it cut to
- phase: insertion; event: retraction; when: points lie beyond the tip (by the coupling's release margin), or
  no part of the needle is in the tissue and its tip is farther than that margin from it; then: they are
  removed (a needle still in the tissue with every point beyond its tip gets points again along its inserted
  part: the last points go by where the needle is, not by their projections on its axis)
- phase: insertion; event: withdrawal; when: no point is left; then: approach; the tissue keeps the channel
  (``Channel``: its entry point, its end, the needle's radius), replacing the record of the hole it
  re-entered; a channel cut through to a far face is kept from both holes (the exit's record enters at the
  channel's end and runs through to its entry)
- phase: insertion; event: cut_start; when: energy law: ‖t‖ ≥ G_c L_in; paper law (equation 3): ‖t‖ > n_i f_c,
  t the lateral load of the insertion points' rows (energy law: and of the faces' rows of a cut the needle
  lies along);
  then: a strip on the path (along a cut: on the inserted needle, its first layer d_c ahead); cutting, the
  entry point kept
- phase: cutting; event: (crack advance); when: energy law: a front row at its strength G_c ℓ_k and the needle
  through the crack tip, or a sliding row at the front at G_c ℓ_k; then: the crack tip advances towards the
  needle by the needle's motion into the front relative to the tissue over the step
- phase: cutting; event: (extension); when: energy law: the needle inserted d_c deeper than the strip; then:
  columns added below the strip
- phase: cutting; event: tear; when: energy law: a new layer laid (the crack tip d_c past the last); paper
  law: a front row's force ≥ f_t; then: the surface grows (energy law: ĉ turns half-way to the layer's swept
  direction)
- phase: cutting; event: retraction; when: (paper law) the entry point, whose rows hold the needle while it
  cuts, beyond the tip; then: it is removed
- phase: cutting; event: retraction, withdrawal; when: no part of the needle in the tissue (no inserted
  stretch after the step); then: every row released; approach (the cut stays, with its strip and crack tip,
  and no hole is recorded: the cut is what the tissue keeps there, and a needle inserted along it punctures
  the surface, which the cut does not open, slides in it and cuts on from its crack tip: cut_resume)
- phase: cutting; event: exit; when: the tip, inside the tissue at the step's start, lies in no tet at its
  end, having moved forward through the tissue (along the needle, relative to its material point); then:
  the cut rows run along the part of the needle in the tissue, from its entry to where it leaves through
  the far face; the tip meets the surface ahead as in insertion (its channel's end marked through)
- phase: cutting, the tip outside (out of a far face) and advancing; event: puncture, reentry; when: as in
  approach, on the surface ahead of the tip (another layer); then: the tip in that layer, the phase and the
  cut kept (the strip extends down the shaft into it from the next step, whose events decide the cut's
  growth: none in this one, as no insertion point is added in insertion's); until then a tip that reached the
  surface or meets a hole stays outside it, and its indentation is no stretch of the needle in the tissue
- phase: cutting; event: cut_start; when: energy law: the load of its cut's faces' rows away from the crack
  tip (beyond the band of 1.5 d_c where they give way at G_c ℓ_k) meets the cut start for the inserted length
  they hold, ‖t_h‖ ≥ G_c L_h; then: the strip recorded up to its crack tip, a new strip on the inserted
  needle, ĉ = −t_h/‖t_h‖, its first layer d_c ahead
- phase: cutting; event: leave_cut; when: the needle is back behind the strip's first layer (the line it
  entered along) by more than d_c/2, along −ĉ; then: insertion points along the inserted needle every d_i
  where it lies in intact tissue (none in the cut: the part still in it slides in it); insertion (the cut
  stays, and the tissue keeps the strip with its crack tip: ``Crack``; a new cut may start)
- phase: insertion, cutting; event: cut_resume; when: the needle is inside a strip the tissue keeps (left
  by a withdrawal, a leave_cut or a cut start off its faces): at least half of its inserted length down to
  the strip's deepest column on that strip's surface, and ahead of the strip's first layer by more than d_c/2
  along its ĉ (leave_cut's mirror); then: cutting with that strip and its ĉ (a strip it was cutting left in
  the tissue), the path kept as at a cut start: the needle slides in the cut and cuts on from its crack tip

The cutting phase's rules (and the cut starts of the insertion phase) are in
:mod:`refsim.simulation.cut_events` (:class:`~refsim.simulation.cut_events.CutEventRules`, a base of
:class:`EventRules`); the cut surface itself grows in :mod:`refsim.cutting.growth` and
:mod:`refsim.cutting.strip`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from refsim.constraints import (
    PENETRATION,
    SLIDING,
    TIP,
    UNILATERAL,
    InsertionPath,
    grow_path,
    points_beyond_tip,
)
from refsim.constraints.inserted import inserted_stretches
from refsim.constraints.rows import gap_roundoff
from refsim.cutting import CutGrowth
from refsim.geometry import TetLocator
from refsim.scene import Scene
from refsim.simulation.cut_events import STICK_TOLERANCE, CutEventRules, face_stretch, in_cut
from refsim.simulation.detection import Detection
from refsim.simulation.margins import MarginWatch, shaft_lateral_rows
from refsim.simulation.records import Event
from refsim.simulation.state import Channel, ChannelEnd, Phase, SimulationState, evolved

__all__ = ["EventRules", "LazyLocator", "locate_under_surface", "shaft_lateral_force"]


def shaft_lateral_force(
    source,
    kind,
    directions,
    forces,
    *,
    without_entry: bool,
    surface_allowance: float,
    points: np.ndarray | None = None,
) -> np.ndarray:
    """The lateral force of the tissue on the needle through its insertion points, t = Σ n λ over their
    bilateral rows [N], shape (3,) (the cut-start load).

    Parameters
    ----------
    source, kind : Source and kind of each row, shape (r,).
    directions : Row directions, shape (r, 3). forces : Multipliers [N], shape (r,).
    without_entry : Leave out the entry point's rows up to ``surface_allowance`` (the law says whether:
        ``CuttingLaw.excludes_entry_point``): at the free surface they also carry the surface's reaction to
        an oblique entry, a load no shaft cuts with, which is at most what the surface held the tip with
        before it gave way, f_p. Their load e counts by its part beyond the allowance,
        e (1 − a/‖e‖) when ‖e‖ > a: the needle's lateral load is then bounded by a + the law's shaft
        strength, also when the entry point carries it all (a needle less than d_i deep).
    surface_allowance : a [N], ≥ 0: the scene's f_p (inf: the entry point's rows never count).
    points : The insertion point of each row (``RowBlock.point``: its index in the path, the entry is 0, −1
        for other rows), shape (r,). None (results files, which do not store it): the insertion rows are
        taken in path order with the entry's two lateral rows first.
    """
    directions, forces = np.asarray(directions), np.asarray(forces)
    lateral = shaft_lateral_rows(source, kind, points, False)
    if points is not None:
        entry = np.asarray(points)[lateral] == 0
    else:
        entry = np.arange(lateral.size) < 2
    loads = directions[lateral] * forces[lateral, None]
    if not without_entry:
        return loads.sum(axis=0)
    shaft = loads[~entry].sum(axis=0)
    surface = loads[entry].sum(axis=0)
    magnitude = float(np.linalg.norm(surface))
    if magnitude > surface_allowance:
        shaft = shaft + surface * (1.0 - surface_allowance / magnitude)
    return shaft


#: Relative tolerance on f_p of the puncture test (a capped row carries f_p to the solve's accuracy).
PUNCTURE_TOLERANCE = 1e-6
#: Barycentric tolerance of the tip's location among the tets around its last one (the locator's default).
TIP_TOLERANCE = 1e-12


class LazyLocator:
    """The tet locator of one tissue configuration, built on first use (most steps locate nothing beyond the
    tip's neighbourhood); the events of a step share one, on the step's corrected positions."""

    def __init__(self, positions: np.ndarray, tets: np.ndarray, previous: TetLocator | None = None) -> None:
        self._positions, self._tets, self._locator, self._previous = positions, tets, None, previous

    @property
    def locator(self) -> TetLocator:
        """The locator (built now if not yet; its grid taken over from ``previous``, the locator of an
        earlier step, while the tets have moved little: `refsim.geometry.TetLocator`)."""
        if self._locator is None:
            self._locator = TetLocator(self._positions, self._tets, previous=self._previous)
        return self._locator

    @property
    def built(self) -> TetLocator | None:
        """The locator if it was built, else None."""
        return self._locator

    def locate(self, points: np.ndarray, **options):
        """`refsim.geometry.TetLocator.locate` on the configuration."""
        return self.locator.locate(points, **options)


def _touching(rows, multipliers: np.ndarray, roundoff: float) -> bool:
    """Whether the tip touches the surface its contact rows (source PENETRATION, unilateral) hold: its free
    gap reached the surface (at most ``roundoff`` [m] above it, :func:`refsim.constraints.rows.gap_roundoff`),
    or the rows carry a force."""
    normal = (rows.source == PENETRATION) & (rows.kind == UNILATERAL)
    if not np.any(normal):
        return False
    reached = np.any(rows.free_gap[normal] <= roundoff)
    return bool(reached or float(np.asarray(multipliers)[normal].sum()) > 0.0)


def locate_under_surface(positions: np.ndarray, tets: np.ndarray, points: np.ndarray, *, inward: np.ndarray):
    """Tet and barycentric coordinates of points on or just under the surface, shapes (q,), (q, 4).

    A point exactly on the surface may be reported outside by round-off: it is then stepped inside by 1e-9 of
    the mesh size, far below any physical length of the scene.
    """
    locator = TetLocator(positions, tets)
    found, barycentric = locator.locate(points)
    if np.any(found < 0):
        size = float(np.ptp(positions, axis=0).max())
        retry = found < 0
        nudged, nudged_bary = locator.locate(points[retry] - 1e-9 * size * inward)
        found[retry], barycentric[retry] = nudged, nudged_bary
    return found, barycentric


class EventRules(CutEventRules):
    """The events of one instrument of a scene, applied to the state after each step's correction.

    Parameters
    ----------
    scene : The validated scene.
    tets : Tissue tets, shape (m, 4).
    rest_positions : Tissue rest positions [m], shape (n, 3).
    deformation_gradients : Function of tissue positions (n, 3) giving F of every tet, shape (m, 3, 3).
    needle_geometry : Function of a needle state giving its centreline.
    cuts : Whether the instrument may cut (``scene.cutting.enabled`` by default).
    needle_radius : Its needle's radius [m] (``scene.needle.radius`` by default): the radius of the holes
        it leaves (``Channel.radius``).
    """

    def __init__(
        self,
        scene: Scene,
        tets,
        rest_positions,
        deformation_gradients,
        needle_geometry,
        *,
        cuts=None,
        needle_radius: float | None = None,
    ) -> None:
        cuts = scene.cutting.enabled if cuts is None else cuts
        self.needle_radius = float(scene.needle.radius if needle_radius is None else needle_radius)
        self.insertion = scene.insertion
        self.coupling = scene.insertion.coupling_model
        self.cutting = scene.cutting
        self.law = scene.cutting.cutting_law if cuts else None
        self.tets = tets
        self.deformation_gradients = deformation_gradients
        self.needle_geometry = needle_geometry
        tets = np.asarray(tets)
        # node → tets incidence (CSR rows: the tets holding each node), for the tip's location
        incidence = sp.csr_matrix(
            (np.ones(tets.size), (tets.ravel(), np.repeat(np.arange(tets.shape[0]), tets.shape[1]))),
            shape=(int(tets.max()) + 1, tets.shape[0]),
        )
        self._node_tets = incidence
        # tet → the tets sharing a node with it (sorted), filled on first use per tet: the tip's candidates
        self._around: dict[int, np.ndarray] = {}
        # tet → the nodes of those tets, (c, 4), kept with them
        self._around_nodes: dict[int, np.ndarray] = {}
        # the last step's deformed-mesh locator, whose grid the next one takes over while the tets move little
        self._last_locator: TetLocator | None = None
        #: The criteria each step's events compare, with their margins (refsim.simulation.margins).
        self.margins = MarginWatch(scene.solver.tolerance)
        self.growth = None
        if cuts:
            cutting = scene.cutting
            self.growth = CutGrowth(
                rest_positions=rest_positions,
                tets=tets,
                point_spacing=cutting.point_spacing,
            )

    def apply(
        self, world: SimulationState, name: str, detection: Detection, multipliers: np.ndarray
    ) -> tuple[SimulationState, list[Event]]:
        """The state after the events of instrument ``name``, and the events: ``detection`` holds that
        instrument's rows and ``multipliers`` their forces (the tissue's cut, which every instrument meets,
        may change with them)."""
        events: list[Event] = []
        state = world.instrument(name)
        if state.stretches is not None:  # located on the last step's configuration
            state = evolved(state, stretches=None)
        rows = detection.rows
        # One locator of the step's configuration for every event that needs one (built when first used).
        locator = LazyLocator(world.tissue.positions, self.tets, previous=self._last_locator)
        # The tip outside the tissue (approach, or out of a far face in insertion) meets a surface: it
        # punctures it, or enters a hole in it.
        if detection.contact is not None and rows.row_count:
            state, events = self._puncture(world, state, detection, multipliers)
        if detection.contact is not None and detection.hole is not None and not events:
            state, events = self._reentry(world, state, detection, locator)
        # (Not in the step that punctures or re-enters: the entry point is then at the tip, or the tip just
        # past the surface. A capped puncture solves the step again with this instrument's state after it,
        # the tissue's cut as the step started: a cut grown here would not be the one its strip lies in.)
        if state.phase == Phase.INSERTION and not events:
            world, state, more = self._insertion(world, state, detection, multipliers, locator)
            events.extend(more)
        elif state.phase == Phase.CUTTING and not events:
            world, state, more = self._cutting(world, state, detection, multipliers, locator)
            events.extend(more)
        stretch = None
        if state.phase == Phase.CUTTING and self.cutting.friction_coefficient > 0.0:
            stretch = face_stretch(
                state.cut_face_stretch,
                detection,
                multipliers,
                self.cutting.friction_coefficient,
                self.needle_geometry(state.needle),
                world.tissue.positions,
                self.cutting.point_spacing,
            )
        if stretch is not None or state.cut_face_stretch is not None:
            state = evolved(state, cut_face_stretch=stretch)
        if locator.built is not None:
            self._last_locator = locator.built
        return world.with_instrument(state), events

    def _puncture(self, world, state, detection, multipliers):
        rows = detection.rows
        normal_rows = np.flatnonzero((rows.source == PENETRATION) & (rows.kind == UNILATERAL))
        normal_force = float(multipliers[normal_rows].sum())
        self.margins.puncture(normal_rows, self.insertion.puncture_force)
        # A capped normal row (insertion.puncture_within_step) reaches f_p to the solver's tolerance, not
        # beyond. A tip pressed into tissue that cannot move (held nodes, a rigid needle: zero compliance, its
        # gap below zero) asks for more than any force: the surface gives way there as anywhere once f_p is
        # reached, whatever multiplier the unsolvable row was left with (margins.held_rows).
        threshold = self.insertion.puncture_force * (1.0 - PUNCTURE_TOLERANCE)
        held = bool(self.margins.held(normal_rows).any())
        if normal_force < threshold and not held:
            return state, []
        if held:
            normal_force = max(normal_force, float(self.insertion.puncture_force))
        contact = detection.contact
        positions = world.tissue.positions
        entry = contact.barycentric @ positions[contact.nodes]
        tets, barycentric = locate_under_surface(positions, self.tets, entry[None, :], inward=contact.normal)
        if tets[0] < 0:
            return state, []
        return self._entered(world, state, tets, barycentric, int(tets[0]), barycentric[0], None), [
            Event("puncture", normal_force)
        ]

    @staticmethod
    def _entered(world, state, tets, barycentric, tip_tet: int, tip_barycentric, channel_end):
        """The instrument's state after its tip entered the tissue where it met the surface (``tets``,
        ``barycentric``: one point), its tip now in ``tip_tet`` at ``tip_barycentric``, ``channel_end`` the
        channel's it entered (a re-entry) or None (a puncture).

        From approach, or from a far face in insertion (another layer, the shaft in the ones before), that
        point is the first insertion point of the needle, or of the layer: the path grows from there. While
        the needle cuts, the cut holds its shaft in every part of the tissue it is through (its strip extends
        down the shaft into the new layer, refsim.simulation.cut_events), so only the tip's state changes."""
        entered_at = ChannelEnd(int(tets[0]), np.array(barycentric[0], copy=True))
        if state.phase == Phase.CUTTING:
            return evolved(
                state,
                tip_tet=tip_tet,
                tip_barycentric=tip_barycentric,
                channel_end=None,
                entered_at=entered_at,
            )
        path = state.path if state.phase == Phase.INSERTION else InsertionPath.empty()
        return evolved(
            state,
            phase=Phase.INSERTION,
            path=path.appended(tets, barycentric, world.step),
            tip_tet=tip_tet,
            tip_barycentric=tip_barycentric,
            channel_end=channel_end,
            entered_at=entered_at,
        )

    def _reentry(self, world, state, detection: Detection, locator: LazyLocator):
        """A tip that met the surface within a hole of the tissue (``detection.hole``: the step's
        detection found its closest surface point there and built no tip contact) and lies in a tet after the
        step has entered the hole's channel: the insertion phase, with where the tip met the surface (within
        the hole) as its first insertion point and the hole's end as the channel's end (the tip's cutting row
        frees the tip up to it; a channel cut through has no tip row). No puncture: the surface is already
        open there. Event ``reentry``.

        The tip is located (in the whole mesh) only once it is past the tangent plane of its surface point
        on the step's positions: a tip still above it is outside."""
        hole, contact = detection.hole, detection.contact
        positions = world.tissue.positions
        needle = self.needle_geometry(state.needle)
        surface = np.asarray(contact.barycentric) @ positions[np.asarray(contact.nodes)]
        if float((needle.tip - surface) @ contact.normal) > 0.0:
            return state, []
        tip_tet, tip_barycentric = self.locate_tip(positions, needle.tip, -1, locator)
        if tip_tet < 0:
            return state, []
        # The needle enters where it meets the surface: the hole is open over its radius, so a needle
        # entering it off the old entry point is not pulled back to that point (anchored there, the entry
        # point's rows, which the energy law's cut start leaves out, would hold it with no limit).
        tets, barycentric = locate_under_surface(
            positions, self.tets, surface[None, :], inward=contact.normal
        )
        if tets[0] < 0:
            tets, barycentric = np.array([hole.entry_tet]), np.asarray(hole.entry_barycentric).reshape(1, 4)
        return self._entered(world, state, tets, barycentric, tip_tet, tip_barycentric, hole.end), [
            Event("reentry")
        ]

    def _left_channels(self, world, state, channel_end, entry=None) -> tuple[Channel, ...]:
        """The tissue's channels after instrument ``state`` (at the step's start, in insertion) left the
        tissue in the step, its channel's end being ``channel_end`` after the step's events: its channel
        added, entering at its path's first point (the puncture's, or the re-entry's: where the needle met
        the surface in the hole; it replaces the hole's record when that is the same point) and ending at the
        deepest material point its tip reached (``channel_end``; without a tip cutting force, where no row
        reads it, the tip's last material point, or the entry's). A channel cut through to a far face (its
        end marked through) is recorded from both of its holes: also entering
        at its end (the tip's last material point inside) and running through to its entry."""
        if state.path.point_count == 0:
            return world.channels
        if entry is None:
            entry = ChannelEnd(int(state.path.tets[0]), state.path.barycentric[0])
        end = channel_end
        if end is None and state.tip_tet >= 0:
            end = ChannelEnd(state.tip_tet, state.tip_barycentric)
        elif end is None:
            end = entry
        channel = Channel(
            entry_tet=int(entry.tet),
            entry_barycentric=np.array(entry.barycentric, copy=True),
            end=end,
            radius=self.needle_radius,
            step=world.step,
        )
        made = [channel]
        if end.through:
            # Cut through to a far face: the exit is a hole too, and the channel seen from it runs through to
            # the entry (a needle entering from that side meets the same cut line, from its other end).
            made.append(
                Channel(
                    entry_tet=end.tet,
                    entry_barycentric=np.array(end.barycentric, copy=True),
                    end=ChannelEnd(channel.entry_tet, channel.entry_barycentric, through=True),
                    radius=self.needle_radius,
                    step=world.step,
                )
            )
        kept = (old for old in world.channels if not any(old.same_entry(new) for new in made))
        return (*kept, *made)

    def _insertion(self, world, state, detection, multipliers, locator: LazyLocator):
        rows = detection.rows
        events: list[Event] = []
        positions = world.tissue.positions
        needle = self.needle_geometry(state.needle)
        # the path's points on the step's configuration, read by the cut start's test and the growth below
        points = state.path.positions(positions, self.tets)
        if self.growth is not None and world.cracks:
            # Inside a strip the tissue keeps (re-inserted along its cut, or moved back into it): the cut
            # goes on from its crack tip.
            resumed = self._resumed(world, state, needle, positions, locator)
            if resumed is not None:
                return resumed
        if self.growth is not None and rows.row_count:
            force_on_needle = shaft_lateral_force(
                rows.source,
                rows.kind,
                rows.directions,
                multipliers,
                without_entry=self.law.excludes_entry_point,
                surface_allowance=self.insertion.puncture_force,
                points=rows.points_of_rows,
            )
            # A needle along an existing cut: its faces' rows hold it there, their load part of t alike (a law
            # whose front gives way: the paper's never does, nor do the faces).
            faces = rows.rows_of(SLIDING) if np.isfinite(self.law.front_strength) else None
            started = self._cut_starts(
                world,
                state,
                force_on_needle,
                needle,
                locator,
                points,
                faces=None if faces is None else (rows, multipliers, faces),
            )
            if started is not None:
                return started
        path, added = grow_path(
            state.path,
            tip=needle.tip,
            tissue_positions=positions,
            mesh_tets=self.tets,
            locator=locator,
            spacing=self.insertion.spacing,
            step=world.step,
            points=points,
        )
        if added and world.cut is not None and world.cut.triangle_count:
            path = self._outside_cut(path, world, positions)
        if path is not state.path:
            points = path.positions(positions, self.tets)
        # The tip's material state: the tet it lies in, or outside (it left the tissue through a face).
        tip_tet, tip_barycentric = self.tip_location(
            positions, needle, state, detection, multipliers, locator
        )
        released = self._released(path, points, world, needle, positions, locator, tip_tet)
        if released is not None:
            path = released
            events.append(Event("retraction"))
        channel_end = self._channel_end(state, positions, needle, tip_tet, rows, multipliers)
        entered_at = state.entered_at
        if path.point_count and self._exits(state, positions, needle, tip_tet):
            events.append(Event("exit"))
            # Cut through to the far face: the channel's line ends at the tip's last material point inside,
            # and the part of the tissue the tip left keeps it (both holes), whatever the tip meets next.
            channel_end = ChannelEnd(state.tip_tet, state.tip_barycentric, through=True)
            world = evolved(world, channels=self._left_channels(world, state, channel_end, entered_at))
            entered_at = None
        elif path.point_count and state.tip_tet >= 0 and tip_tet < 0:
            # Back out of the part of the tissue the tip was in, the shaft still in the tissue (an inner
            # layer, or the entry face with a point still kept): that part keeps its channel.
            world = evolved(world, channels=self._left_channels(world, state, channel_end, entered_at))
        elif state.tip_tet < 0 and tip_tet >= 0:
            # Back in a part of the tissue whose channel was recorded when the tip left it. Moving back, the
            # tip came in through the far face it left (only a hole cut through lets a tip in backwards): on
            # that channel's line, nothing to cut. Pushed forward into the mouth of the face it entered by,
            # its channel's end stays the one it cut to.
            entered_at = None
            if not detection.advancing:
                channel_end = ChannelEnd(tip_tet, tip_barycentric, through=True)
        if path.point_count == 0:
            # The needle left the tissue: its channel stays in it (a hole in its surface, the cut tissue
            # behind it), which any needle may enter again.
            world = evolved(world, channels=self._left_channels(world, state, channel_end, entered_at))
            return world, state.withdrawn(), [*events, Event("withdrawal")]
        state = evolved(
            state,
            path=path,
            tip_tet=tip_tet,
            tip_barycentric=tip_barycentric,
            channel_end=channel_end,
            entered_at=entered_at,
        )
        return world, state, events

    def _released(self, path, points, world, needle, positions, locator: LazyLocator, tip_tet: int):
        """The path after the retraction, or None when it releases no point.

        A point is released when it lies beyond the tip by more than the coupling's release margin (the
        ring's hysteresis: its centre drifts along the needle with the tissue's strain). The last points go
        by where the needle is, not by their projections on its axis, which a tilted needle moved sideways
        leaves away from where it crosses the surface:

        - part of the needle still in the tissue with every point beyond its tip: points are laid again along
          the inserted needle, as after leave_cut (released, a needle moved sideways as it came out was
          withdrawn with its tip 0.25 mm deep and re-entered or punctured its own hole at the next step);
        - no part of it in the tissue: every point is released once its tip is farther than the margin from
          the tissue (a needle pulled out 30° from vertical while moving 4 mm towards its tilt kept its entry
          point with its tip 1.7 mm above the surface, and 0.77 N on it in the air), the entry point kept
          until then (a bent needle released with its tip 0.015 mm above the surface sprang back into its
          hole).
        """
        if path.point_count == 0:
            return None
        margin = self.coupling.retraction_margin(self.insertion.spacing)
        beyond = points_beyond_tip(path, points, needle, margin)
        if tip_tet >= 0 and not beyond.all():
            return path.subset(~beyond) if beyond.any() else None
        stretches = inserted_stretches(
            needle, locator.locator, self.insertion.spacing, tip_outside=tip_tet < 0, confirm_out=True
        )
        if stretches:
            if beyond.all():
                return self._points_along(world, needle, positions, locator)
            return path.subset(~beyond) if beyond.any() else None
        if locator.locator.locate_nearest(needle.tip[None, :])[2][0] > margin:
            return path.subset(np.zeros(path.point_count, dtype=bool))
        beyond[0] = False  # at the surface: the entry point holds until the tip is the margin away
        return path.subset(~beyond) if beyond.any() else None

    def tip_location(self, positions, needle, state, detection, multipliers, locator: LazyLocator):
        """The tip's material state after the step (inserting or cutting): the tet it lies in and its
        barycentric coordinates there, or (−1, None) outside (it left the tissue through a face). A tip
        outside that reached the surface ahead (its contact's free gap at or below zero, or a force on it)
        stays outside until it punctures it, and one that meets a hole until it enters it (the events
        :meth:`_puncture` and :meth:`_reentry` decide both), wherever round-off puts it against that surface;
        one that met no surface ahead (it moved back into its own channel) is located."""
        tip_tet, tip_barycentric = self.locate_tip(positions, needle.tip, state.tip_tet, locator)
        if state.tip_tet < 0 and (
            detection.hole is not None
            or _touching(detection.rows, multipliers, gap_roundoff(positions, needle.tip))
        ):
            return -1, None
        return tip_tet, tip_barycentric

    def _exits(self, state, positions, needle, tip_tet: int) -> bool:
        """Whether the tip, inside the tissue at the step's start (``state``), left it through a far face in
        the step: it lies in no tet now (``tip_tet`` −1, on the corrected ``positions``) and moved forward
        through the tissue (along the needle, relative to its material point at the step's start). A tip
        pulled back out through the face it entered by (in the step before its last insertion point is
        released, the ring's release margin behind it) is a withdrawal, not an exit."""
        if not (state.tip_tet >= 0 and tip_tet < 0 and state.tip_barycentric is not None):
            return False
        where = state.tip_barycentric @ positions[self.tets[state.tip_tet]]
        return float((needle.tip - where) @ needle.tip_tangent) > 0.0

    def _channel_end(self, state, positions, needle, tip_tet: int, rows, multipliers):
        """The end of the channel the tip has cut (``InstrumentState.channel_end``) after a step whose tip
        lies in ``tip_tet`` (−1: outside), on the step's corrected ``positions`` and ``needle``, with the
        step's ``rows`` and ``multipliers``.

        The end is the deepest material point the tip reached: the tip's own (its material point at the
        step's start) while it cuts (its row at f_cut) or rests there, kept while the tip, its row below f_cut
        (it did not cut: moved back, or stuck), lies behind it along the needle; a tip that cut in the step
        (at the end, or turned out of its channel into intact tissue) has its own point as the end again,
        and so has a tip at rest whose row stays at f_cut (the tissue's transient may move it by round-off
        either way). The tissue behind the end is already cut: a needle pushed in again along its channel
        meets the channel's friction alone until its tip is at the end (Okamura, Simone and O'Leary, IEEE
        TBME 51(10), 2004, measured the friction of a needle re-inserted into its own hole with no cutting
        force). A channel the tip cut through to a far face (the event exit) ends at the tip's last material
        point inside, marked through: it stays so until the needle is withdrawn, or until its tip cuts again
        (turned out of that channel's line into intact tissue: then its own point is the end). A tip pulled
        back out through its entry face (a point still kept, the ring's release margin) keeps the end too. On
        withdrawal the end is the channel's in the tissue's record (``Channel.end``), and a needle
        re-entering the hole starts from it.
        """
        end = state.channel_end
        if self.insertion.tip_cutting_force <= 0.0:
            return end if end is not None and end.through else None
        if state.tip_tet < 0:
            return end  # pulled back out through its entry face, a point still kept: the channel stays
        tip_rows = rows.rows_of(TIP)
        strength = (1.0 - STICK_TOLERANCE) * self.insertion.tip_cutting_force
        if end is not None and end.through:
            # On the through channel's line the tip has no row; off it, a row at f_cut cut intact tissue.
            cut = tip_rows.size > 0 and float(multipliers[tip_rows].sum()) >= strength
            return None if cut else end
        if tip_rows.size == 0 or float(multipliers[tip_rows].sum()) >= strength:
            return None  # it cut (or had no row): its own point is the end
        if end is None:
            end = ChannelEnd(state.tip_tet, state.tip_barycentric)
        if tip_tet < 0:
            return end
        where = end.barycentric @ positions[self.tets[end.tet]]
        return end if float((where - needle.tip) @ needle.tip_tangent) > 0.0 else None

    def locate_tip(
        self, positions: np.ndarray, tip: np.ndarray, hint: int, locator: LazyLocator | None = None
    ) -> tuple[int, np.ndarray | None]:
        """The tet holding the tip and the tip's barycentric coordinates in it, (−1, None) outside the tissue.

        The tets around ``hint`` (the tip's last tet: those sharing a node with it) are tried first, the whole
        mesh when the tip is not among them (``locator``: the step's, on ``positions``; one is built when
        None). Among the candidates, those whose edge matrix is singular (a degenerate tet: a zero pivot of
        its LU factors, where ``np.linalg.det`` is 0) are left out: the candidates are solved in one batch,
        each matrix on its own (the same bits in any batch), and only a batch that meets a singular matrix is
        solved again without them.
        """
        tip = np.asarray(tip, dtype=float)
        if hint >= 0:
            candidates = self._tets_around(hint)
            corners = positions[self._around_nodes[hint]]  # (c, 4, 3)
            edges = np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1))  # (c, 3, 3)
            try:
                local = np.linalg.solve(edges, (tip - corners[:, 0])[:, :, None])[:, :, 0]
            except np.linalg.LinAlgError:
                valid = np.abs(np.linalg.det(edges)) > 0.0
                candidates = candidates[valid]
                local = np.linalg.solve(edges[valid], (tip - corners[valid, 0])[:, :, None])[:, :, 0]
            barycentric = np.concatenate([1.0 - local.sum(axis=1, keepdims=True), local], axis=1)
            smallest = barycentric.min(axis=1)
            inside = np.flatnonzero(smallest >= -TIP_TOLERANCE)
            if inside.size:
                best = inside[np.argmax(smallest[inside])]
                return int(candidates[best]), barycentric[best]
        locator = LazyLocator(positions, self.tets) if locator is None else locator
        found, barycentric = locator.locate(tip[None, :])
        return (int(found[0]), barycentric[0]) if found[0] >= 0 else (-1, None)

    def _tets_around(self, tet: int) -> np.ndarray:
        """The tets sharing a node with ``tet``, sorted (``tet`` among them): a function of the mesh's
        topology, which no event changes (a cut separates material points, not tets), kept per tet with
        their nodes (``_around_nodes``, (c, 4))."""
        around = self._around.get(tet)
        if around is None or tet not in self._around_nodes:
            nodes, incidence = self.tets[tet], self._node_tets
            spans = zip(incidence.indptr[nodes], incidence.indptr[nodes + 1], strict=True)
            around = np.unique(np.concatenate([incidence.indices[a:b] for a, b in spans]))
            around.flags.writeable = False
            around_nodes = np.asarray(self.tets)[around]
            around_nodes.flags.writeable = False
            self._around[tet] = around
            self._around_nodes[tet] = around_nodes
        return around

    def _outside_cut(self, path, world, positions):
        """The path without its new points that lie in the existing cut (projecting inside it, within d_c of
        it): a needle inserted along a cut slides in it (its sliding rows), it does not puncture the tissue
        there."""
        new = np.flatnonzero(path.created_step == world.step)
        if new.size == 0:
            return path
        points = path.positions(positions, self.tets)[new]
        inside, _ = in_cut(world.cut, points, positions, self.tets, self.cutting.point_spacing)
        inside &= new > 0  # the entry point stays: it marks the inserted length
        if not np.any(inside):
            return path
        keep = np.ones(path.point_count, dtype=bool)
        keep[new[inside]] = False
        return path.subset(keep)
