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
  keeps its points
- phase: insertion; event: retraction; when: points lie beyond the tip; then: they are removed
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
- phase: cutting; event: retraction, withdrawal; when: the entry point beyond the tip; then: every row
  released; approach (the cut stays, and no hole is recorded: the cut is what the tissue keeps there, and a
  needle inserted along it punctures the surface, which the cut does not open, and slides in it)
- phase: cutting; event: exit; when: the tip, inside the tissue at the step's start, lies in no tet at its
  end, having moved forward through the tissue (along the needle, relative to its material point); then:
  the cut rows run along the part of the needle in the tissue, from its entry to where it leaves through
  the far face
- phase: cutting; event: cut_start; when: energy law: the load of its cut's faces' rows away from the crack
  tip (beyond the band of 1.5 d_c where they give way at G_c ℓ_k) meets the cut start for the inserted length
  they hold, ‖t_h‖ ≥ G_c L_h; then: the strip recorded up to its crack tip, a new strip on the inserted
  needle, ĉ = −t_h/‖t_h‖, its first layer d_c ahead
- phase: cutting; event: leave_cut; when: the needle is back behind the strip's first layer (the line it
  entered along) by more than d_c/2, along −ĉ; then: insertion points along the inserted needle every d_i
  where it lies in intact tissue (none in the cut: the part still in it slides in it); insertion (the cut
  stays; a new cut may start)

The cut surface itself grows in :mod:`refsim.cutting.growth` and :mod:`refsim.cutting.strip`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from refsim.constraints import (
    CUT_FRICTION,
    PENETRATION,
    SLIDING,
    TIP,
    UNILATERAL,
    InsertionPath,
    grow_path,
    points_beyond_tip,
)
from refsim.constraints.cut import crack_tip_compression, inserted_arc, inserted_span
from refsim.constraints.friction import FaceStretch
from refsim.cutting import CutGrowth
from refsim.cutting.growth import start_strip
from refsim.cutting.laws import FrontPush
from refsim.cutting.strip import recorded_surface
from refsim.geometry import TetLocator
from refsim.scene import Scene
from refsim.simulation.detection import Detection
from refsim.simulation.margins import MarginWatch, shaft_lateral_rows
from refsim.simulation.records import Event
from refsim.simulation.state import Channel, ChannelEnd, Phase, SimulationState, evolved

__all__ = ["EventRules", "LazyLocator", "locate_under_surface", "shaft_lateral_force"]


def shaft_lateral_force(
    source, kind, directions, forces, *, without_entry: bool, points: np.ndarray | None = None
) -> np.ndarray:
    """The lateral force of the tissue on the needle through its insertion points, t = Σ n λ over their
    bilateral rows [N], shape (3,) (the cut-start load).

    Parameters
    ----------
    source, kind : Source and kind of each row, shape (r,).
    directions : Row directions, shape (r, 3). forces : Multipliers [N], shape (r,).
    without_entry : Leave out the entry point's rows: at the free surface they also carry the surface's
        reaction to an oblique entry, a load no shaft cuts with (the law says whether:
        ``CuttingLaw.excludes_entry_point``).
    points : The insertion point of each row (``RowBlock.point``: its index in the path, the entry is 0, −1
        for other rows), shape (r,). None (results files, which do not store it): the insertion rows are
        taken in path order with the entry's two lateral rows first.
    """
    if points is not None:
        lateral = shaft_lateral_rows(source, kind, points, without_entry)
    else:
        lateral = shaft_lateral_rows(source, kind, None, False)
        if without_entry:
            lateral = lateral[2:]
    return (np.asarray(directions)[lateral] * np.asarray(forces)[lateral, None]).sum(axis=0)


#: Relative tolerance on f_p of the puncture test (a capped row carries f_p to the solve's accuracy).
PUNCTURE_TOLERANCE = 1e-6
#: Barycentric tolerance of the tip's location among the tets around its last one (the locator's default).
TIP_TOLERANCE = 1e-12

#: A cut face's friction row sticks when its force is below its bound by more than this fraction of it (far
#: above the solve's 10⁻⁸, as for the shaft's rows: `refsim.constraints.channel.stuck_points`).
STICK_TOLERANCE = 1e-3


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


class EventRules:
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
        if state.entry_span is not None:  # located on the last step's configuration
            state = evolved(state, entry_span=None)
        rows = detection.rows
        # One locator of the step's configuration for every event that needs one (built when first used).
        locator = LazyLocator(world.tissue.positions, self.tets, previous=self._last_locator)
        if state.phase == Phase.APPROACH and rows.row_count:
            state, events = self._puncture(world, state, detection, multipliers)
        if state.phase == Phase.APPROACH and detection.hole is not None:
            state, events = self._reentry(world, state, detection, locator)
        if state.phase == Phase.INSERTION and not events:
            # (Not in the step that punctures or re-enters: the entry point is then at the tip, or the tip
            # just past the surface.)
            world, state, more = self._insertion(world, state, detection, multipliers, locator)
            events.extend(more)
        elif state.phase == Phase.CUTTING:
            world, state, more = self._cutting(world, state, detection, multipliers, locator)
            events.extend(more)
        stretch = None
        if state.phase == Phase.CUTTING and self.cutting.friction_coefficient > 0.0:
            stretch = _face_stretch(
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
        # beyond.
        threshold = self.insertion.puncture_force * (1.0 - PUNCTURE_TOLERANCE)
        if normal_force < threshold:
            return state, []
        contact = detection.contact
        positions = world.tissue.positions
        entry = contact.barycentric @ positions[contact.nodes]
        tets, barycentric = locate_under_surface(positions, self.tets, entry[None, :], inward=contact.normal)
        if tets[0] < 0:
            return state, []
        path = InsertionPath.empty().appended(tets, barycentric, world.step)
        state = evolved(
            state, phase=Phase.INSERTION, path=path, tip_tet=int(tets[0]), tip_barycentric=barycentric[0]
        )
        return state, [Event("puncture", normal_force)]

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
        path = InsertionPath.empty().appended(tets, barycentric, world.step)
        state = evolved(
            state,
            phase=Phase.INSERTION,
            path=path,
            tip_tet=tip_tet,
            tip_barycentric=tip_barycentric,
            channel_end=hole.end,
        )
        return state, [Event("reentry")]

    def _left_channels(self, world, state, channel_end) -> tuple[Channel, ...]:
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
        end = channel_end
        if end is None and state.tip_tet >= 0:
            end = ChannelEnd(state.tip_tet, state.tip_barycentric)
        elif end is None:
            end = ChannelEnd(int(state.path.tets[0]), state.path.barycentric[0])
        channel = Channel(
            entry_tet=int(state.path.tets[0]),
            entry_barycentric=np.array(state.path.barycentric[0], copy=True),
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
        if self.growth is not None and rows.row_count:
            force_on_needle = shaft_lateral_force(
                rows.source,
                rows.kind,
                rows.directions,
                multipliers,
                without_entry=self.law.excludes_entry_point,
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
        # The coupling's release margin (the ring's hysteresis: its points' centres drift along the needle).
        margin = self.coupling.retraction_margin(self.insertion.spacing)
        beyond = points_beyond_tip(path, points, needle, margin)
        if beyond.any():
            path = path.subset(~beyond)
            events.append(Event("retraction"))
        # The tip's material state: the tet it lies in, or outside (it left the tissue through a face).
        tip_tet, tip_barycentric = self.locate_tip(positions, needle.tip, state.tip_tet, locator)
        channel_end = self._channel_end(state, positions, needle, tip_tet, rows, multipliers)
        if path.point_count and self._exits(state, positions, needle, tip_tet):
            events.append(Event("exit"))
            # Cut through to the far face: the channel's line ends at the tip's last material point inside.
            channel_end = ChannelEnd(state.tip_tet, state.tip_barycentric, through=True)
        if path.point_count == 0:
            # The needle left the tissue: its channel stays in it (a hole in its surface, the cut tissue
            # behind it), which any needle may enter again.
            world = evolved(world, channels=self._left_channels(world, state, channel_end))
            state = evolved(
                state, phase=Phase.APPROACH, path=path, tip_tet=-1, tip_barycentric=None, channel_end=None
            )
            return world, state, [*events, Event("withdrawal")]
        state = evolved(
            state, path=path, tip_tet=tip_tet, tip_barycentric=tip_barycentric, channel_end=channel_end
        )
        return world, state, events

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
        cut = world.cut
        found = cut.closest_points(
            path.positions(positions, self.tets)[new], cut.deformed_points(positions, self.tets)
        )
        distance = np.linalg.norm(path.positions(positions, self.tets)[new] - found.closest, axis=1)
        in_cut = found.inside & (distance <= self.cutting.point_spacing)
        in_cut &= new > 0  # the entry point stays: it marks the inserted length
        if not np.any(in_cut):
            return path
        keep = np.ones(path.point_count, dtype=bool)
        keep[new[in_cut]] = False
        return path.subset(keep)

    def _cut_starts(
        self, world, state, force_on_needle, needle, locator: LazyLocator, path_points=None, faces=None
    ):
        """The states (the world's, with the cut, and the instrument's) and events of a cut start, or None
        when the law's criterion does not hold (``CuttingLaw.cut_start``). The cut runs the way the needle
        pushes the tissue, ĉ = −t/‖t‖ (``needle``: the instrument's geometry, ``locator``: the step's;
        ``path_points``: the path's points on the world's tissue positions, computed here when None).

        ``faces``: (rows, multipliers, indices) of the faces' rows of an existing cut the needle lies along
        (its SLIDING rows), or None. Their load is part of t (the tissue behind a face resists the needle as
        the insertion points' tissue does, :meth:`_face_cut_start`), and with them the cut starts on the
        inserted needle (the insertion points leave out its part in the old cut), its first layer d_c ahead,
        so that the old cut's faces, which hold the needle on their plane, do not hold it against the new
        cut's direction."""
        positions = world.tissue.positions
        if path_points is None:
            path_points = state.path.positions(positions, self.tets)
        along_cut = faces is not None and faces[2].size > 0
        spacing = self.cutting.point_spacing
        if along_cut:
            rows, multipliers, indices = faces
            lateral = shaft_lateral_rows(
                rows.source, rows.kind, rows.points_of_rows, self.law.excludes_entry_point
            )
            force_on_needle = force_on_needle + (rows.directions[indices] * multipliers[indices, None]).sum(
                axis=0
            )
            entry_arc, end = inserted_span(needle, locator, spacing)
            inserted = end - entry_arc
            margin_rows = np.concatenate([lateral, indices])
        else:
            end = needle.length
            if state.tip_tet < 0:
                # The tip out of a far face: the shaft cuts along the part in the tissue only.
                _, end = inserted_span(needle, locator, spacing)
            inserted = end - float(needle.project(path_points[:1])[0][0])
            margin_rows = None
        self.margins.cut_start(self.law, force_on_needle, inserted, state.path.point_count, rows=margin_rows)
        start = self.law.cut_start(
            force_on_needle, inserted_length=inserted, point_count=state.path.point_count
        )
        if start is None:
            return None
        direction = -force_on_needle / float(np.linalg.norm(force_on_needle))
        extent = start.extent
        if along_cut:
            path_points = _inserted_line(needle, entry_arc, end, spacing)
            extent = max(extent, spacing)
        cut, strip = start_strip(
            self.growth, world.cut, path_points, direction, positions, world.step, extent=extent
        )
        if strip is None:
            return None
        world = evolved(world, cut=cut)
        state = evolved(
            state,
            phase=Phase.CUTTING,
            cut_direction=np.asarray(direction, dtype=float),
            cut_strip=strip,
            path=state.path.subset(self.law.kept_at_cut_start(state.path.point_count)),
            channel_end=None,
        )
        return world, state, [Event("cut_start", start.trigger, start.unit)]

    def _leave_cut(self, world, state, needle, positions, locator: LazyLocator):
        """The state after the needle left its cut backwards, into intact tissue: insertion points along the
        inserted needle every d_i (material points where the needle now is) but none in the cut (the rule of
        new points: a part of the needle still in its cut slides in it), the insertion phase, the cut kept
        (the needle may cut again: a new cut start). Event ``leave_cut``."""
        # The cut the strip leaves reaches its crack tip.
        world = evolved(world, cut=recorded_surface(world.cut, state.cut_strip, world.step))
        spacing = self.insertion.spacing
        entry_arc = inserted_arc(needle, locator, spacing)
        arcs = np.arange(entry_arc, needle.length + 1e-12 * spacing, spacing)
        tets, barycentric = locator.locate(needle.points(arcs))
        inside = tets >= 0
        path = InsertionPath.empty().appended(tets[inside], barycentric[inside], world.step)
        if world.cut is not None and world.cut.triangle_count:
            path = self._outside_cut(path, world, positions)
        events = [Event("leave_cut")]
        if path.point_count == 0:
            state = evolved(
                state, phase=Phase.APPROACH, path=path, cut_strip=None, tip_tet=-1, channel_end=None
            )
            return world, state, [*events, Event("withdrawal")]
        tip_tet, tip_barycentric = self.locate_tip(positions, needle.tip, -1, locator)
        state = evolved(
            state,
            phase=Phase.INSERTION,
            path=path,
            cut_strip=None,
            tip_tet=tip_tet,
            tip_barycentric=tip_barycentric,
            channel_end=None,
        )
        return world, state, events

    def _extended(self, strip, needle, positions, locator, entry_arc, step):
        """The strip with a block of columns added below its deepest one at ``step`` down to the needle's tip,
        every d_c (``locator`` on ``positions``; ``entry_arc`` where the needle enters the tissue)."""
        from refsim.cutting.strip import CutFront, locate_material_points

        spacing = self.cutting.point_spacing
        count = int(np.floor((needle.length - entry_arc - strip.depths[-1]) / spacing + 1e-9))
        if count <= 0:
            return strip
        depths = strip.depths[-1] + spacing * np.arange(1, count + 1)
        tets, barycentric, inside = locate_material_points(
            locator, positions, self.tets, needle.points(entry_arc + depths), snap_distance=0.5 * spacing
        )
        run = int(np.cumprod(inside).sum())  # down to the first point outside the tissue
        if run == 0:
            return strip
        tets, barycentric = tets[:run], barycentric[:run]
        rest = np.einsum("pk,pkj->pj", barycentric, self.growth.rest_positions[self.tets[tets]])
        return strip.extended(CutFront(rest, tets, barycentric), depths[:run], step)

    def _cutting(self, world, state, detection, multipliers, step_locator: LazyLocator):
        """Withdrawal through the cut, and the growth of the cut where the needle pushes through its front."""
        positions = world.tissue.positions
        needle = self.needle_geometry(state.needle)
        entry = state.path.positions(positions, self.tets)
        if state.path.point_count == 0 or points_beyond_tip(state.path, entry, needle)[0]:
            # The tip is back above the entry point: every row is released; the tissue keeps its cut, up to
            # the crack tip.
            world = evolved(world, cut=recorded_surface(world.cut, state.cut_strip, world.step))
            state = evolved(
                state, phase=Phase.APPROACH, path=InsertionPath.empty(), cut_strip=None, channel_end=None
            )
            return world, state, [Event("retraction"), Event("withdrawal")]
        events: list[Event] = []
        cutting = self.cutting
        # The tip's material state, as in insertion: leaving through a far face is the event exit (the needle
        # still cuts along the part in the tissue). Only forward through the tissue: a tip pulled back out
        # through the face it entered by (on the step before the entry point is beyond it) is a withdrawal.
        tip_tet, tip_barycentric = self.locate_tip(positions, needle.tip, state.tip_tet, step_locator)
        if self._exits(state, positions, needle, tip_tet):
            events.append(Event("exit"))
        state = evolved(state, tip_tet=tip_tet, tip_barycentric=tip_barycentric)
        if state.cut_strip is not None and world.cut is not None:
            # Moved back through its own cut and past the line it entered along (the strip's first layer, its
            # rear edge) by more than half a cut spacing: the needle is in intact tissue again.
            rear = state.cut_strip.rear_edge(world.cut, positions, self.tets)
            _, on_needle = needle.project(rear)
            behind = float(((on_needle - rear) @ state.cut_direction).mean())
            if behind < -0.5 * cutting.point_spacing:
                world, state, more = self._leave_cut(world, state, needle, positions, step_locator)
                return world, state, [*events, *more]
        if state.cut_strip is not None:
            pressed = self._face_cut_start(world, state, detection.rows, multipliers, needle, step_locator)
            if pressed is not None:
                world, state, more = pressed
                return world, state, [*events, *more]
        locator, entry_arc = None, None
        if self.law.extends_down_shaft and state.cut_strip is not None:
            # A needle inserted deeper than the strip while it cuts: pushed sideways with the rest of the
            # shaft, its part below the strip cuts at G_c per unit length like the rest (the energy law does
            # not depend on where along the shaft the load is), so the strip extends down along it, a column
            # every d_c to the tip, its crack tip at the needle (insertion points there, anchored in uncut
            # tissue, would drag it sideways).
            locator = step_locator.locator
            entry_arc, end = inserted_span(needle, locator, cutting.point_spacing)
            state = evolved(
                state,
                cut_strip=self._extended(state.cut_strip, needle, positions, locator, entry_arc, world.step),
                entry_span=(entry_arc, end),
            )
        rows = detection.rows
        self.margins.tear(self.law, detection.front.rows)
        grown = self.law.grow(
            FrontPush(
                growth=self.growth,
                cut=world.cut,
                strip=state.cut_strip,
                direction=state.cut_direction,
                positions=positions,
                step=world.step,
                needle=needle,
                front=detection.front,
                multipliers=multipliers,
                force_limit=rows.force_limit,
                entry_arc=entry_arc,
                locator=locator,
                compression=lambda given_rows, given, columns: crack_tip_compression(
                    rows, multipliers, given_rows, given, columns
                ),
                compliance=rows.compliance_diagonal,
            )
        )
        if grown is None:
            return world, state, events
        self.margins.layer(grown)
        if grown.tear is not None:
            events.append(Event("tear", grown.tear))
        world = evolved(world, cut=grown.cut)
        state = evolved(state, cut_strip=grown.strip, cut_direction=grown.direction)
        return world, state, events

    def _face_cut_start(self, world, state, rows, multipliers, needle, step_locator: LazyLocator):
        """A needle pressed against the faces of its cut: the states and the event of a new cut, or None.

        The faces' rows (the cut's SLIDING rows) hold the needle in its cut's plane; the load they carry
        is the tissue behind a face resisting the needle, as the insertion points' lateral rows are for a
        needle in intact tissue, so the law's cut start holds for it alike. Near the crack tip (within
        1.5 d_c of it: the band of :func:`refsim.constraints.cut.strip_cut_block`) the faces' rows already
        give way at G_c ℓ_k each, the front's strength, and the front's growth turns the cut
        (``CuttingLaw.grow``); the others are unbounded. So the criterion reads those others, the *held*
        faces: ‖t_h‖ ≥ G_c L_h (energy law), t_h = Σ n λ over the held faces' rows and L_h the inserted
        length less the band's (Σ ℓ_k over the band's rows, their limits over G_c). A needle at its crack
        tip has no held faces; one moved back into its cut, or whose shaft turned away from its crack tip,
        has. Then the strip is recorded up to its crack tip and a new one starts on the inserted needle, the
        way it pushes (ĉ = −t_h/‖t_h‖, as at a cut start), its first layer d_c ahead (the new strip's faces
        are then within its band, so they do not start another at once). Event ``cut_start``, which solves its
        step again (``STEP_SOLVED_AGAIN``). Under a law whose front never gives way (the paper's:
        ``front_strength`` infinite) the faces do not either: None."""
        faces = rows.rows_of(SLIDING)
        strength = float(self.law.front_strength)
        if faces.size == 0 or not np.isfinite(strength):
            # (the paper's law: its front's rows never give way, nor do the faces)
            return None
        limits = rows.force_limit[faces] if rows.force_limit.size else np.full(faces.size, np.inf)
        band = np.isfinite(limits)
        held = faces[~band]
        if held.size == 0:
            return None
        spacing = self.cutting.point_spacing
        load = (rows.directions[held] * multipliers[held, None]).sum(axis=0)
        entry_arc, end = inserted_span(needle, step_locator.locator, spacing)
        length = (end - entry_arc) - float(limits[band].sum()) / strength
        self.margins.cut_start(self.law, load, length, state.path.point_count, rows=held)
        start = self.law.cut_start(load, inserted_length=length, point_count=state.path.point_count)
        if start is None:
            return None
        positions = world.tissue.positions
        recorded = recorded_surface(world.cut, state.cut_strip, world.step)
        line = _inserted_line(needle, entry_arc, end, spacing)
        direction = -load / float(np.linalg.norm(load))
        cut, strip = start_strip(
            self.growth, recorded, line, direction, positions, world.step, extent=max(start.extent, spacing)
        )
        if strip is None:
            return None
        state = evolved(
            state, cut_direction=np.asarray(direction, dtype=float), cut_strip=strip, channel_end=None
        )
        return evolved(world, cut=cut), state, [Event("cut_start", start.trigger, start.unit)]


def _inserted_line(needle, entry_arc: float, end: float, spacing: float) -> np.ndarray:
    """The needle's centreline between arc lengths ``entry_arc`` and ``end`` [m], points at most ``spacing``
    apart, ends included, shape (k, 3), k ≥ 2: the line a cut started against a cut's faces runs on."""
    count = max(int(np.ceil((end - entry_arc) / spacing)), 1) + 1
    return needle.points(np.linspace(entry_arc, end, count))


def _face_stretch(
    previous, detection: Detection, multipliers: np.ndarray, coefficient: float, needle, positions, spacing
):
    """The cut faces' friction rows' stick anchors after the step's solve (the next step's rows start from
    them: `refsim.constraints.friction.FaceStretch`), None without such rows. A row sticks when its force is
    below its bound μ_c |λ| by more than 10⁻³ of it (far above the solve's 10⁻⁸; as the shaft's rows,
    `refsim.constraints.channel.stuck_points`)."""
    rows, front = detection.rows, detection.front
    friction, sliding = rows.rows_of(CUT_FRICTION), rows.rows_of(SLIDING)
    arcs = front.slide_arc_lengths
    if friction.size == 0 or friction.size != 2 * arcs.size or sliding.size != arcs.size:
        return None
    bound = coefficient * np.abs(np.concatenate([multipliers[sliding], multipliers[sliding]]))
    return FaceStretch.after_solve(
        previous,
        arc_lengths=arcs,
        nodes=front.slide_nodes,
        weights=front.slide_weights,
        tangents=rows.directions[friction],
        compliance=rows.problem_compliance_diagonal()[friction],
        multipliers=multipliers[friction],
        stuck=np.abs(multipliers[friction]) < (1.0 - STICK_TOLERANCE) * bound,
        needle=needle,
        tissue_positions=positions,
        tolerance=1e-9 * spacing,
    )
