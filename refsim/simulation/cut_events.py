"""The cutting phase's events of an instrument (layer 4): what :class:`refsim.simulation.events.EventRules`
does once the needle cuts, and the cut starts of the insertion phase.

- the cut start, from the insertion points' lateral load (and the faces' of a cut the needle lies along):
  :meth:`CutEventRules._cut_starts`;
- the cut's growth where the needle pushes through its front, the strip's extension down a needle inserted
  deeper, the withdrawal through the cut: :meth:`CutEventRules._cutting`;
- the needle back out of its cut into intact tissue (``leave_cut``): :meth:`CutEventRules._leave_cut`;
- a new cut started by the load of its cut's faces away from the crack tip:
  :meth:`CutEventRules._face_cut_start`;
- the strip a needle leaves kept in the tissue with its crack tip (:class:`refsim.simulation.state.Crack`),
  and a needle found inside it (in insertion, or cutting into it) cutting on from its crack tip
  (``cut_resume``): :meth:`CutEventRules._left_strip`, :meth:`CutEventRules._resumed`;
- the stick anchors of the cut faces' friction rows after each solve: :func:`face_stretch`.

The table of every event, its phase, criterion and effect is the docstring of :mod:`refsim.simulation.events`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from refsim.constraints import CUT_FRICTION, SLIDING, InsertionPath, points_beyond_tip
from refsim.constraints.cut import crack_tip_compression
from refsim.constraints.friction import FaceStretch
from refsim.constraints.inserted import inserted_arc, inserted_stretches, stretch_length, stretch_span
from refsim.cutting.growth import start_strip
from refsim.cutting.laws import FrontPush
from refsim.cutting.strip import recorded_strip
from refsim.simulation.detection import Detection
from refsim.simulation.margins import shaft_lateral_rows
from refsim.simulation.records import Event
from refsim.simulation.state import ChannelEnd, Crack, Phase, evolved

if TYPE_CHECKING:
    from refsim.simulation.events import LazyLocator

__all__ = ["STICK_TOLERANCE", "CutEventRules", "face_stretch", "in_cut"]

#: A cut face's friction row sticks when its force is below its bound by more than this fraction of it (far
#: above the solve's 10⁻⁸, as for the shaft's rows: `refsim.constraints.channel.stuck_points`).
STICK_TOLERANCE = 1e-3


class CutEventRules:
    """The cutting phase's rules, a part of :class:`refsim.simulation.events.EventRules` (which holds the
    scene's parts they read: ``cutting``, ``law``, ``growth``, ``margins``, ``tets``, ``insertion``, the
    needle's geometry, the tip's location and the path's points outside a cut)."""

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
        beyond = None  # where the first surface's columns go on to past the path's last point
        pieces = None  # the path, one polyline per part of the tissue, when the needle is through several
        if along_cut:
            rows, multipliers, indices = faces
            # the criterion's accuracy over every lateral row (the entry point's load may count beyond f_p)
            lateral = shaft_lateral_rows(rows.source, rows.kind, rows.points_of_rows, False)
            force_on_needle = force_on_needle + (rows.directions[indices] * multipliers[indices, None]).sum(
                axis=0
            )
            stretches = inserted_stretches(needle, locator.locator, spacing, tip_outside=state.tip_tet < 0)
            inserted = stretch_length(stretches)
            margin_rows = np.concatenate([lateral, indices])
        else:
            end = needle.length
            arcs = needle.project(path_points[[0, -1]])[0]
            steps = np.linalg.norm(np.diff(path_points, axis=0), axis=1)
            breaks = np.flatnonzero(steps > 2.0 * self.insertion.spacing) + 1
            # Located when the tip is out of a far face, or the path crosses a gap (its points are made every
            # d_i in the tissue only; a path can also miss its points in an old cut).
            located = state.tip_tet < 0 or breaks.size
            stretches = (
                inserted_stretches(needle, locator.locator, spacing, tip_outside=state.tip_tet < 0)
                if located
                else ()
            )
            if state.tip_tet < 0:
                # The tip out of a far face: the shaft cuts along the part in the tissue only; where no
                # sample of its centreline is in the tissue (it passes beside a sliver whose insertion
                # points still hold it), along the part the insertion points hold.
                _, end = stretch_span(stretches, needle.length)
                if end >= needle.length:
                    end = float(needle.project(path_points)[0].max())
            inserted = end - float(arcs[0])
            if len(stretches) > 1 and breaks.size:
                # The needle is through several parts of the tissue, the path across the gaps: L_in is its
                # length in them, and the cut runs in each.
                inserted = stretch_length(stretches, float(arcs[0]), end)
                pieces = _path_pieces(np.split(path_points, breaks), stretches, needle, end, spacing)
            margin_rows = None
            # The cut runs on the whole inserted needle, L_in of it: the path's points reach the tip only to
            # within d_i (a needle less deep than d_i has its entry point alone). The line goes on as the
            # needle does, from the deepest point kept where it is beside the needle (the tissue's
            # compression under the lateral load sets the material point the needle's own axis is in apart
            # from the path's: 0.2 mm on the 4³ cube_cut).
            reach = needle.points(np.array([arcs[1], end]))
            beyond = path_points[-1] + reach[1] - reach[0] if end > arcs[1] else None
        self.margins.cut_start(self.law, force_on_needle, inserted, state.path.point_count, rows=margin_rows)
        start = self.law.cut_start(
            force_on_needle, inserted_length=inserted, point_count=state.path.point_count
        )
        if start is None:
            return None
        direction = -force_on_needle / float(np.linalg.norm(force_on_needle))
        extent = start.extent
        if along_cut:
            pieces = _inserted_lines(needle, stretches, spacing)
            extent = max(extent, spacing)
        cut, strip = start_strip(
            self.growth,
            world.cut,
            path_points,
            direction,
            positions,
            world.step,
            extent=extent,
            beyond=beyond,
            pieces=pieces,
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
            entered_at=None,
        )
        return world, state, [Event("cut_start", start.trigger, start.unit)]

    def _leave_cut(self, world, state, needle, positions, locator: LazyLocator):
        """The state after the needle left its cut backwards, into intact tissue: insertion points along the
        inserted needle every d_i (material points where the needle now is) but none in the cut (the rule of
        new points: a part of the needle still in its cut slides in it), the insertion phase, the cut kept
        (the needle may cut again: a new cut start). Event ``leave_cut``."""
        # The cut the strip leaves reaches its crack tip, and the tissue keeps the strip.
        world = self._left_strip(world, state)
        path = self._points_along(world, needle, positions, locator)
        events = [Event("leave_cut")]
        if path.point_count == 0:
            return world, state.withdrawn(), [*events, Event("withdrawal")]
        tip_tet, tip_barycentric = self.locate_tip(positions, needle.tip, -1, locator)
        state = evolved(
            state,
            phase=Phase.INSERTION,
            path=path,
            cut_strip=None,
            tip_tet=tip_tet,
            tip_barycentric=tip_barycentric,
            channel_end=None,
            entered_at=None,
        )
        return world, state, events

    def _points_along(self, world, needle, positions, locator: LazyLocator) -> InsertionPath:
        """Insertion points along the inserted needle every d_i from where it enters the tissue (material
        points where the needle now is), but none in the cut (the rule of new points: a part of the needle
        in a cut slides in it); what holds a needle that is in the tissue with no point of its own."""
        spacing = self.insertion.spacing
        entry_arc = inserted_arc(needle, locator, spacing)
        arcs = np.arange(entry_arc, needle.length + 1e-12 * spacing, spacing)
        tets, barycentric = locator.locate(needle.points(arcs))
        inside = tets >= 0
        path = InsertionPath.empty().appended(tets[inside], barycentric[inside], world.step)
        if world.cut is not None and world.cut.triangle_count:
            path = self._outside_cut(path, world, positions)
        return path

    @staticmethod
    def _left_strip(world, state):
        """The tissue after instrument ``state`` left its strip (withdrawn, moved back out of its cut, or
        starting a new cut off its faces): its cut laid up to the crack tip, and the strip kept with its crack
        tip and direction (a :class:`refsim.simulation.state.Crack`)."""
        cut, strip = recorded_strip(world.cut, state.cut_strip, world.step)
        if strip is None:
            return evolved(world, cut=cut)
        crack = Crack(strip, np.array(state.cut_direction, dtype=float, copy=True), world.step)
        return evolved(world, cut=cut, cracks=(*world.cracks, crack))

    def _resumed(self, world, state, needle, positions, locator: LazyLocator, *, stretches=None):
        """A needle found inside a strip the tissue keeps (a :class:`refsim.simulation.state.Crack`), in
        insertion or cutting another strip: the states and the event ``cut_resume``, or None.

        Inside: at least half of the inserted needle down to the strip's deepest column (sampled every d_c
        along its stretches in the tissue) on the strip's own triangles (:func:`in_cut`: projecting inside the
        cut, within d_c of it; a needle crossing the cut has a sample or two there), and the needle ahead of
        the strip's rear edge (the line the strip's needle entered along) by more than d_c/2 along the
        strip's ĉ (mean over its columns), the mirror of leave_cut's criterion: a needle moved back out of its
        cut does not resume it until it comes back in by d_c. There the tissue around the needle is
        cut: the needle slides in the cut (its sliding rows, no insertion point) and meets the crack tip's
        front rows where the uncut tissue begins, cutting on from there at the law's strength. Gripped by
        insertion points instead, a needle moved along an old cut dragged the tissue until a cut started
        and then cut the tissue a second time; cutting a new strip into it, it cut it a second time too. The
        strip becomes the needle's (cutting phase, its ĉ, the path kept as at a cut start) and leaves the
        tissue's list; a strip the needle was cutting is left in the tissue (:meth:`_left_strip`). A needle
        deeper than the strip cuts below it at the law's strength from the start, the strip extending down
        its shaft, under a law whose strip does (``CuttingLaw.extends_down_shaft``); under one whose strip
        does not (the paper's), it keeps its insertion points below the strip, and so its insertion phase."""
        cut = world.cut
        if cut is None or not cut.triangle_count:
            return None
        spacing = self.cutting.point_spacing
        if stretches is None:
            stretches = inserted_stretches(needle, locator.locator, spacing, tip_outside=state.tip_tet < 0)
        if not stretches:
            return None
        # The inserted needle every d_c or less, and each sample's arc length below where it enters [m].
        arcs = np.concatenate([_stretch_arcs(first, end, spacing) for first, end in stretches])
        below = arcs - stretches[0][0]
        on_cut, found = in_cut(cut, needle.points(arcs), positions, self.tets, spacing)
        for index, crack in enumerate(world.cracks):  # (a handful: one per strip left)
            # Down to the strip's deepest column (a needle inserted deeper cuts on below it: the strip extends
            # down its shaft, as while cutting)
            reach = below <= float(np.max(crack.strip.depths)) + spacing
            if not self.law.extends_down_shaft and not np.all(reach):
                continue
            inside = on_cut & crack.strip.own_triangles(cut)[found.triangle] & reach
            if 2 * int(np.count_nonzero(inside)) < int(np.count_nonzero(reach)):
                continue
            if _ahead_of_rear_edge(crack.strip, crack.direction, cut, positions, self.tets, needle) <= (
                0.5 * spacing
            ):
                continue
            world = evolved(world, cracks=(*world.cracks[:index], *world.cracks[index + 1 :]))
            if state.cut_strip is not None:
                world = self._left_strip(world, state)
            state = evolved(
                state,
                phase=Phase.CUTTING,
                cut_direction=np.array(crack.direction, dtype=float, copy=True),
                cut_strip=crack.strip,
                path=state.path.subset(self.law.kept_at_cut_start(state.path.point_count)),
                channel_end=None,
                entered_at=None,
                cut_face_stretch=None,
            )
            return world, state, [Event("cut_resume")]
        return None

    def _extended(self, strip, needle, positions, locator, stretches, step):
        """The strip with a block of columns added below its deepest one at ``step``, every d_c along the
        needle's ``stretches`` in the tissue below it (``locator`` on ``positions``), down to the first within
        d_c/2 of a stretch's end (the tip; where the needle leaves that part of the tissue, a far face or a
        gap, the column is at that end), so that the deepest sample of each stretch faces a crack-tip
        segment: a stretch below a gap is a part of the tissue of its own (a needle pushed through a gap
        into a lower layer while it cuts)."""
        from refsim.cutting.strip import CutFront, locate_material_points

        spacing = self.cutting.point_spacing
        entry_arc = stretches[0][0]
        deepest = float(strip.depths[-1])  # the strip's deepest column, its depth below the entry [m]
        depths, parts = [], []
        part = int(strip.parts[-1]) if strip.parts is not None else 0
        for first, end in stretches:
            if end - entry_arc <= deepest:
                continue
            # Below a gap: the stretch starts below the deepest column by more than d_c/2 (a gap is at least
            # d_c long, the stretches' sampling). A column laid at a lower part's entry stays in that part as
            # the entry moves along the needle by less (read as a new part, the lower layer's columns were
            # split by one that joined none).
            below_gap = first - entry_arc > deepest + 0.5 * spacing
            if below_gap:  # its own part, from its entry
                part += 1
                start = first - entry_arc
                count = int(np.floor((end - first) / spacing + 0.5))
                grid = start + spacing * np.arange(count + 1)
            else:  # the part the deepest column is in, on from it
                count = int(np.floor((end - entry_arc - deepest) / spacing + 0.5))
                grid = deepest + spacing * np.arange(1, count + 1)
            if end < needle.length and grid.size:
                # A far face or a gap ends the stretch: its last column at that end, unless that is within
                # d_c/2 of the column before it.
                before = grid[-2] if grid.size > 1 else (-np.inf if below_gap else deepest)
                grid[-1] = min(grid[-1], end - entry_arc)
                if grid[-1] - before <= 0.5 * spacing:
                    grid = grid[:-1]
            depths.append(grid)
            parts.append(np.full(grid.size, part, dtype=np.int64))
        if not depths or not sum(grid.size for grid in depths):
            return strip
        depths, parts = np.concatenate(depths), np.concatenate(parts)
        # A column less than d_c/2 below the tip is on the needle's line extended past it (as its crack tip's
        # target: refsim.cutting.growth.crack_tip_targets).
        arcs = entry_arc + depths
        points = needle.points(np.minimum(arcs, needle.length))
        below = arcs > needle.length
        if np.any(below):
            points[below] += (arcs[below] - needle.length)[:, None] * needle.tip_tangent
        tets, barycentric, inside = locate_material_points(
            locator, positions, self.tets, points, snap_distance=0.5 * spacing
        )
        if not np.any(inside):
            return strip
        # A point outside the tissue gets no column, and the columns past it are in another part.
        parts = parts + np.cumsum(~inside)
        tets, barycentric, depths, parts = tets[inside], barycentric[inside], depths[inside], parts[inside]
        rest = np.einsum("pk,pkj->pj", barycentric, self.growth.rest_positions[self.tets[tets]])
        return strip.extended(CutFront(rest, tets, barycentric), depths, step, parts=parts)

    def _cutting(self, world, state, detection, multipliers, step_locator: LazyLocator):
        """Withdrawal through the cut, and the growth of the cut where the needle pushes through its front."""
        positions = world.tissue.positions
        needle = self.needle_geometry(state.needle)
        cutting = self.cutting
        # The tip's material state, as in insertion: leaving through a far face is the event exit (the needle
        # still cuts along the part in the tissue, and its tip meets the surface ahead, another layer, as in
        # insertion: its channel's end marked through). Only forward through the tissue: a tip pulled back
        # out through the face it entered by leaves no part of the needle in the tissue, a withdrawal.
        tip_tet, tip_barycentric = self.tip_location(
            positions, needle, state, detection, multipliers, step_locator
        )
        # What of the needle lies in the tissue after the step: one stretch per part of the tissue it is
        # through (its indentation of a surface the tip has not punctured is none).
        stretches = inserted_stretches(
            needle, step_locator.locator, cutting.point_spacing, tip_outside=tip_tet < 0, confirm_out=True
        )
        if not stretches:
            # Out of the tissue: every row is released; the tissue keeps its cut, up to the crack tip, and
            # the strip. (Not read from the entry point: a needle moved along its cut is no longer where it
            # entered, and one tilted in the stroke's plane has the entry point's projection on its axis
            # above or below where it crosses the surface by the stroke times the tilt's sine: withdrawn
            # with its tip still 4 mm in the tissue, or never, on cube_cut after 8 mm at 30°.)
            world = self._left_strip(world, state)
            return world, state.withdrawn(), [Event("retraction"), Event("withdrawal")]
        # (kept in the state: the next step's rows are sampled along them, on this configuration)
        state = evolved(state, stretches=stretches)
        events: list[Event] = []
        if self.law.rows_while_cutting and state.path.point_count:
            # The points kept at the cut start hold the needle while it cuts (the paper law's entry point):
            # those the tip has gone back past are released, as in insertion. (A law whose cut alone holds
            # the needle keeps them without rows until the withdrawal.)
            beyond = points_beyond_tip(
                state.path,
                state.path.positions(positions, self.tets),
                needle,
                self.coupling.retraction_margin(self.insertion.spacing),
            )
            if beyond.any():
                state = evolved(state, path=state.path.subset(~beyond))
                events.append(Event("retraction"))
        channel_end = None if tip_tet >= 0 else state.channel_end
        if self._exits(state, positions, needle, tip_tet):
            events.append(Event("exit"))
            channel_end = ChannelEnd(state.tip_tet, state.tip_barycentric, through=True)
        elif state.tip_tet >= 0 and tip_tet < 0 and state.entered_at is not None:
            # Backed out of a part of the tissue it entered while cutting (an inner layer, into a gap), the
            # shaft still in the tissue: that part keeps its channel, as in insertion, so the tip pushed in
            # again meets it as its own channel's mouth (elsewhere on that surface, intact tissue).
            world = evolved(world, channels=self._left_channels(world, state, channel_end, state.entered_at))
        state = evolved(state, tip_tet=tip_tet, tip_barycentric=tip_barycentric, channel_end=channel_end)
        if state.cut_strip is not None and world.cut is not None:
            # Moved back through its own cut and past the line it entered along (the strip's first layer, its
            # rear edge) by more than half a cut spacing: the needle is in intact tissue again.
            ahead = _ahead_of_rear_edge(
                state.cut_strip, state.cut_direction, world.cut, positions, self.tets, needle
            )
            if ahead < -0.5 * cutting.point_spacing:
                world, state, more = self._leave_cut(world, state, needle, positions, step_locator)
                return world, state, [*events, *more]
        if state.cut_strip is not None and world.cracks:
            # Cutting along a cut the tissue keeps, into it: that cut goes on from its crack tip, and the
            # strip it ran in with is left in the tissue.
            taken = self._resumed(world, state, needle, positions, step_locator, stretches=stretches)
            if taken is not None:
                world, state, more = taken
                return world, state, [*events, *more]
        if state.cut_strip is not None:
            pressed = self._face_cut_start(
                world, state, detection.rows, multipliers, needle, step_locator, stretches=stretches
            )
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
            entry_arc, _ = stretch_span(stretches, needle.length)
            extended = self._extended(state.cut_strip, needle, positions, locator, stretches, world.step)
            state = evolved(state, cut_strip=extended)
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

    def _face_cut_start(
        self, world, state, rows, multipliers, needle, step_locator: LazyLocator, *, stretches=None
    ):
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
        if stretches is None:
            stretches = inserted_stretches(
                needle, step_locator.locator, spacing, tip_outside=state.tip_tet < 0
            )
        length = stretch_length(stretches) - float(limits[band].sum()) / strength
        self.margins.cut_start(self.law, load, length, state.path.point_count, rows=held)
        start = self.law.cut_start(load, inserted_length=length, point_count=state.path.point_count)
        if start is None:
            return None
        positions = world.tissue.positions
        world = self._left_strip(world, state)
        direction = -load / float(np.linalg.norm(load))
        cut, strip = start_strip(
            self.growth,
            world.cut,
            None,
            direction,
            positions,
            world.step,
            extent=max(start.extent, spacing),
            pieces=_inserted_lines(needle, stretches, spacing),
        )
        if strip is None:
            return None
        state = evolved(
            state,
            cut_direction=np.asarray(direction, dtype=float),
            cut_strip=strip,
            channel_end=None,
            entered_at=None,
        )
        return evolved(world, cut=cut), state, [Event("cut_start", start.trigger, start.unit)]


def _path_pieces(pieces, stretches, needle, end: float, spacing: float) -> list[np.ndarray]:
    """The insertion path's ``pieces`` (one per part of the tissue, points (p_k, 3) [m], from the entry
    down) carried to the ends of the needle's stretch in that part (``stretches``: (entry, end) arc lengths
    [m], :func:`refsim.constraints.inserted.inserted_stretches`; the deepest piece to ``end``): a piece's
    points lie up to d_i inside its part (its points are made every d_i as the tip goes), so the line goes on
    from its first and last points as the needle does, by more than half a d_c, kept beside the needle (the
    tissue's compression, as the single part's line past its deepest point). The entry point is on the
    tissue's surface: the first piece starts there."""
    # The stretch of each piece: the one holding its middle, else the nearest; pieces of one stretch (a path
    # that misses its points in an old cut) are one.
    owners = []
    for piece in pieces:
        middle = float(needle.project(piece[[0, -1]])[0].mean())
        owners.append(int(np.argmin([max(a - middle, middle - b, 0.0) for a, b in stretches])))
    joined = []
    for owner, piece in zip(owners, pieces, strict=True):
        if joined and joined[-1][0] == owner:
            joined[-1] = (owner, np.concatenate([joined[-1][1], piece]))
        else:
            joined.append((owner, piece))
    carried = []
    for index, (owner, piece) in enumerate(joined):
        arcs = needle.project(piece[[0, -1]])[0]
        first, last = stretches[owner]
        if index == len(joined) - 1:
            last = end
        points = [piece]
        if index > 0 and arcs[0] - first > 0.5 * spacing:
            moved = needle.points(np.array([first, arcs[0]]))
            points.insert(0, (piece[0] + moved[0] - moved[1])[None])
        if last - arcs[1] > 0.5 * spacing:
            moved = needle.points(np.array([arcs[1], last]))
            points.append((piece[-1] + moved[1] - moved[0])[None])
        carried.append(np.concatenate(points))
    return carried


def _inserted_lines(needle, stretches, spacing: float) -> list[np.ndarray]:
    """The needle's centreline along each of its ``stretches`` in the tissue (:func:`_inserted_line`), one
    polyline per part of the tissue: the line a cut started against a cut's faces runs on (the tip alone,
    twice, when there is no stretch: no column lies in the tissue, no strip)."""
    spans = stretches or (stretch_span(stretches, needle.length),)
    return [_inserted_line(needle, first, end, spacing) for first, end in spans]


def _inserted_line(needle, entry_arc: float, end: float, spacing: float) -> np.ndarray:
    """The needle's centreline between arc lengths ``entry_arc`` and ``end`` [m], points at most ``spacing``
    apart, ends included, shape (k, 3), k ≥ 2: the line a cut started against a cut's faces runs on."""
    return needle.points(_stretch_arcs(entry_arc, end, spacing))


def _stretch_arcs(first: float, end: float, spacing: float) -> np.ndarray:
    """Arc lengths [m] from ``first`` to ``end``, evenly at most ``spacing`` [m] apart, both ends included,
    shape (k,), k ≥ 2."""
    return np.linspace(first, end, max(int(np.ceil((end - first) / spacing)), 1) + 1)


def _ahead_of_rear_edge(strip, direction, cut, positions, tets, needle) -> float:
    """How far the needle is ahead of ``strip``'s rear edge (the line its needle entered along) along the
    strip's ``direction`` ĉ [m]: the mean over its columns of each column's projection on the needle less
    the column, along ĉ (negative: behind it). leave_cut reads it on the needle's own strip, cut_resume on a
    strip the tissue keeps."""
    rear = strip.rear_edge(cut, positions, tets)
    _, on_needle = needle.project(rear)
    return float(((on_needle - rear) @ direction).mean())


def in_cut(cut, points: np.ndarray, positions: np.ndarray, tets: np.ndarray, spacing: float):
    """Which ``points`` [m], shape (q, 3), lie in the tissue's ``cut`` as deformed by ``positions``:
    projecting inside it and within ``spacing`` (d_c) [m] of it; shape (q,) bool, and the closest points
    (`refsim.cutting.surface.ClosestCutPoints`). A needle there slides in the cut: no insertion point is laid
    there, and a strip the tissue keeps is taken up there."""
    found = cut.closest_points(points, cut.deformed_points(positions, tets))
    distance = np.linalg.norm(points - found.closest, axis=1)
    return found.inside & (distance <= spacing), found


def face_stretch(
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
