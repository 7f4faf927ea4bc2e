"""Detection: the rows of one step from the free positions, by phase (DESIGN.md, step 3).

- approach: the tip against the closest surface point (penetration), when within the contact distance and
  not in a hole of the tissue (``SimulationState.channels``);
- insertion: the insertion points along the path;
- cutting: the entry point's rows, and the sliding and border rows of the cut surface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from refsim.constraints import (
    NEEDLE,
    TISSUE,
    RowBlock,
    StepGeometry,
    SurfaceContact,
    concatenate,
    empty_block,
    find_surface_contact,
    insertion_block,
    penetration_block,
)
from refsim.constraints.channel import channel_preload, grip_preload, shaft_contact_block, tip_cutting_block
from refsim.constraints.coupling import (
    AXIAL,
    LATERAL,
    RingLayout,
    insertion_compliance,
    local_mesh_size,
    ring_insertion_block,
    ring_weights,
    subgrid_compliance,
)
from refsim.constraints.cut import FrontRows, strip_cut_block
from refsim.constraints.inserted import inserted_stretches
from refsim.constraints.insertion import InsertionOptions, InsertionPath, PointRings
from refsim.geometry import SurfaceProjector, TetLocator
from refsim.scene import Scene
from refsim.simulation.state import Channel, InstrumentState, Phase, SimulationState

__all__ = ["Detection", "Detector"]

RING_REUSE_COSINE = math.cos(1e-3)  # a ring is rebuilt when its point's tangent turned by more than 1e-3 rad


@dataclass(frozen=True)
class Detection:
    """The rows of a step and what the events need to know about them.

    Attributes
    ----------
    rows : The step's rows, in solver order.
    contact : The tip's closest surface point while the tip is outside the tissue (approach, or after it left
        through a far face), else None.
    front : Where the front rows press on the crack tip (cutting phase); their indices are into ``rows``.
    insertion_points : The path points whose insertion rows are in ``rows``, in row order, shape (p,) (each
        row's own point is ``rows.point``, an index into the path).
    rings : The coupling rings those rows were built on, one per point of the path (the step's path carries
        them on, :meth:`refsim.constraints.InsertionPath.with_rings`); None when no ring rows were built.
    hole : The tissue's channel whose hole the tip meets (the tip outside: its closest surface point, within
        the contact distance, lies in the hole), which then has no tip contact; None elsewhere.
    advancing : Whether the needle's tip does not move back along the needle over the step (forward, or
        still: :meth:`Detector._advancing`).
    """

    rows: RowBlock
    contact: SurfaceContact | None = None
    front: FrontRows = field(default_factory=FrontRows.empty)
    insertion_points: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    rings: PointRings | None = None
    hole: Channel | None = None
    advancing: bool = True


def _no_front() -> FrontRows:
    """The front of a detection without front rows: empty, its arrays read-only (shared by every such
    detection: nothing can change it)."""
    front = FrontRows.empty()
    for value in vars(front).values():
        if isinstance(value, np.ndarray):
            value.flags.writeable = False
    return front


#: The front of every detection without front rows (:func:`_no_front`).
_NO_FRONT = _no_front()


class Detector:
    """Builds the rows of each step for a scene.

    Parameters
    ----------
    scene : The validated scene.
    faces : Tissue surface triangles, shape (f, 3).
    needle_dof_count : DoFs of the needle in the constraint problem, None for a rigid needle.
    needle : The instrument's needle section (``scene.needle`` by default).
    cuts : Whether the instrument may cut (``scene.cutting.enabled`` by default).
    """

    def __init__(
        self,
        scene: Scene,
        faces: np.ndarray,
        needle_dof_count: int | None,
        rest_positions: np.ndarray | None = None,
        tets: np.ndarray | None = None,
        *,
        needle=None,
        cuts: bool | None = None,
    ) -> None:
        needle = scene.needle if needle is None else needle
        cuts = scene.cutting.enabled if cuts is None else cuts
        self.insertion = scene.insertion
        self.options = InsertionOptions.from_section(scene.insertion)  # what the row builders read
        self.cutting = scene.cutting
        self.law = scene.cutting.cutting_law if cuts else None
        self.faces = faces
        self._face_points = np.unique(faces)  # the surface's points (its projector's scan bound, every step)
        self.needle_dof_count = needle_dof_count
        self.cut_compliance = None
        if scene.cutting.enabled and rest_positions is not None and tets is not None:
            self.cut_compliance = _cut_compliance(scene, rest_positions, tets, needle.radius)
        spec = scene.insertion
        tissue = scene.tissue
        self.shear_modulus = tissue.youngs_modulus / (2.0 * (1.0 + tissue.poisson_ratio))
        self.poisson_ratio = tissue.poisson_ratio
        self.needle_radius = needle.radius
        self.preload = spec.shaft_normal_force * spec.spacing
        if spec.interference > 0.0:
            self.preload += float(
                grip_preload(
                    shear_modulus=self.shear_modulus,
                    poisson_ratio=self.poisson_ratio,
                    radius=self.needle_radius,
                    interference=spec.interference,
                    spacing=spec.spacing,
                )
            )
        self.coupling = spec.coupling_model
        self.ring = self.coupling.rings
        if self.ring and (rest_positions is None or tets is None):
            raise ValueError(
                f"insertion.coupling = {self.coupling.name!r} needs the rest mesh (rest_positions and tets) "
                "in Detector"
            )
        self.rest_positions = None if rest_positions is None else np.asarray(rest_positions, dtype=float)
        self.rest_locator = TetLocator(self.rest_positions, np.asarray(tets)) if self.ring else None
        #: The last 2-D sub-grid compliance of insertion rows, by the bytes of its inputs (_compliance).
        self._compliance_memo: tuple[tuple[bytes, bytes], np.ndarray] | None = None
        # Shaft samples before puncture every half mean tet size (the surface cannot bend between them).
        self.shaft_spacing = 0.01
        #: The last channels of the tissue the holes were read from, with their entries' rest positions (h, 3)
        #: and radii (h,) (_hole).
        self._holes_memo: tuple[tuple[Channel, ...], np.ndarray, np.ndarray] | None = None
        # the last step's start-of-step locator of the cut rows (a needle meeting another's cut), whose grid
        # the next one takes over while the tets move little (refsim.geometry.TetLocator)
        self._cut_locator: TetLocator | None = None
        #: The local mesh size of every rest tet [m] (local_mesh_size), for the rings' radii.
        self.tet_sizes = None
        if rest_positions is not None and tets is not None:
            self.tet_sizes = local_mesh_size(rest_positions, tets, np.arange(len(tets)))
            self.shaft_spacing = 0.5 * float(self.tet_sizes.mean())

    def _rings(self, path: InsertionPath, tangents: np.ndarray, mesh_tets: np.ndarray) -> PointRings:
        """The points' rings, normal to ``tangents`` (p, 3): a point keeps the ring it carries
        (``path.rings``) while its tangent turned less than 1e-3 rad from the one that ring was built on; the
        others get new rings (all do when the new rings' point count differs from the carried ones')."""
        carried = path.rings
        reuse = np.zeros(path.point_count, dtype=bool)
        if carried is not None:
            reuse = np.einsum("ij,ij->i", carried.tangents, tangents) > RING_REUSE_COSINE  # NaN: no ring yet
        if reuse.all():
            return carried
        common = dict(
            rest_positions=self.rest_positions,
            mesh_tets=mesh_tets,
            locator=self.rest_locator,
            needle_radius=self.needle_radius,
            tet_sizes=self.tet_sizes,
        )
        if not reuse.any():
            return PointRings(RingLayout.around(path, tangents=tangents, **common), tangents.copy())
        fresh = RingLayout.around(path.subset(~reuse), tangents=tangents[~reuse], **common)
        if carried.layout.tets.shape[1] == fresh.tets.shape[1]:
            layout = RingLayout.merged(carried.layout.subset(np.flatnonzero(reuse)), fresh, reuse)
        else:
            layout = RingLayout.around(path, tangents=tangents, **common)
            reuse[:] = False
        kept_tangents = tangents.copy()
        kept_tangents[reuse] = carried.tangents[reuse]
        return PointRings(layout, kept_tangents)

    def insertion_rows(
        self, path: InsertionPath, geometry: StepGeometry, *, finite_line: bool = False
    ) -> tuple[RowBlock, PointRings | None]:
        """The insertion points' rows: the ring coupling with its sub-grid compliance, or the paper's rows;
        and the rings they were built on (one per point of ``path``; None with the paper's coupling).

        ``finite_line``: the 3-D sub-grid compliance of the inserted line (insertion); false: the 2-D values,
        which the cut rows also use (while cutting: rows of both kinds along one needle must have the same
        stiffness model; with the 3-D value on the insertion rows only, cube_cut's needle is held, 27.8 N, and
        cuts 2.3 mm of its 5 mm stroke).
        """
        # The grip's part of each point's Coulomb bound, less its last lateral force (a closed channel).
        preload = channel_preload(self.preload, path.lateral_forces)
        if not self.ring:
            block = insertion_block(path, geometry, normal_preload=preload, options=self.options)
            return block, None
        centres_previous = path.positions(geometry.tissue_previous, geometry.mesh_tets)
        arc_lengths, _ = geometry.needle_previous.project(centres_previous)
        tangents = geometry.needle_previous.tangents(arc_lengths)  # the rings' normals and the anchors' axes
        rings = self._rings(path, tangents, geometry.mesh_tets)
        block = ring_insertion_block(
            path,
            geometry,
            rings.layout,
            normal_preload=preload,
            options=self.options,
            arc_lengths=arc_lengths,
            previous_tangents=tangents,
        )
        # With finite_line, the 3-D sub-grid compliance of the inserted line, which starts at the free
        # surface.
        diagonal = self._compliance(block, rings.layout.mesh_size, arc_lengths if finite_line else None)
        return block.with_compliance_diagonal(diagonal), rings

    def _compliance(
        self, block: RowBlock, mesh_size: np.ndarray, arc_lengths: np.ndarray | None
    ) -> np.ndarray:
        """The sub-grid compliance of the insertion rows ``block`` on points of ``mesh_size``
        (:func:`insertion_compliance`). Without ``arc_lengths`` (the 2-D values) it is a function of the rows'
        kinds and of ``mesh_size`` alone, which change only when a point is added or removed or gets a new
        ring: the last result is kept with their bytes, and a copy of it given again for the same bytes."""
        key = None
        if arc_lengths is None:
            key = (block.kind.tobytes(), np.asarray(mesh_size, dtype=float).tobytes())
            if self._compliance_memo is not None and self._compliance_memo[0] == key:
                return self._compliance_memo[1].copy()
        diagonal = insertion_compliance(
            block,
            shear_modulus=self.shear_modulus,
            poisson_ratio=self.poisson_ratio,
            needle_radius=self.needle_radius,
            mesh_size=mesh_size,
            spacing=self.insertion.spacing,
            arc_lengths=arc_lengths,
        )
        if key is not None:
            self._compliance_memo = (key, diagonal.copy())
        return diagonal

    def tip_ring(
        self, state: InstrumentState, geometry: StepGeometry, point: tuple[int, np.ndarray] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The tip cutting row's tissue side with the ring coupling: the ring of material points around the
        tip's material point (or ``point``: a tet and barycentric coordinates), normal to the needle at the
        tip (nodes and weights, shape (1, k) each)."""
        tet, barycentric = (state.tip_tet, state.tip_barycentric) if point is None else point
        tip = InsertionPath(np.array([tet]), np.asarray(barycentric).reshape(1, 4), np.zeros(1, np.int64))
        tangent = geometry.needle_previous.tangents(np.array([geometry.needle_previous.length]))
        rings = RingLayout.around(
            tip,
            rest_positions=self.rest_positions,
            mesh_tets=geometry.mesh_tets,
            locator=self.rest_locator,
            tangents=tangent,
            needle_radius=self.needle_radius,
            tet_sizes=self.tet_sizes,
        )
        return ring_weights(tip, rings, geometry.mesh_tets)

    def detect(self, world: SimulationState, state: InstrumentState, geometry: StepGeometry) -> Detection:
        """The rows of one instrument (``state``) in the step that starts from ``world``, on the free
        positions of ``geometry`` (the tissue's and that instrument's needle); the needle's Jacobian is keyed
        :data:`NEEDLE`. The blocks, in row order: the phase's own rows (approach: the tip's contact and the
        shaft's; insertion and cutting: the insertion points' and the tip's cutting row), then the rows of an
        existing cut (insertion) or of the cut being made (cutting)."""
        blocks: list[RowBlock] = []
        contact = None
        advancing = self._advancing(geometry)
        front = _NO_FRONT
        insertion_points = np.zeros(0, dtype=np.int64)
        rings = None
        hole = None
        if state.phase == Phase.APPROACH:
            contact, approach, hole = self.approach_rows(geometry, world.channels)
            blocks.extend(approach)
        elif state.path.point_count:
            block, insertion_points, rings = self.path_rows(state, geometry)
            blocks.extend(b for b in (block, self.tip_row(state, geometry)) if b is not None)
        if state.phase != Phase.APPROACH and state.tip_tet < 0 and advancing:
            # The tip is out of the tissue (through a far face, or backed out of a face it entered by) while
            # the shaft stays in it (inserting or cutting: the tip's rules do not depend on what holds the
            # shaft), and does not move back: it meets the surface ahead as a tip does in approach, a contact
            # it punctures at f_p (or a hole it enters), the shaft's rows kept (_surface_ahead).
            contact, approach, hole = self._surface_ahead(world, state, geometry)
            blocks.extend(approach)
        if state.phase == Phase.INSERTION and world.cut is not None and world.cut.triangle_count:
            block, _ = self.cut_rows(world, None, geometry, tip_outside=state.tip_tet < 0)
            if block is not None:
                blocks.append(block)
        strip_block = None
        if state.phase == Phase.CUTTING and state.cut_strip is not None:
            strip_block, front = self.cut_rows(world, state, geometry)
            if strip_block is not None:
                blocks.append(strip_block)
        if not blocks:
            rows = empty_block({TISSUE: geometry.tissue_dof_count, NEEDLE: self.needle_dof_count})
        else:
            rows = concatenate(blocks)
        if strip_block is not None:  # the front rows' indices into the stack, found by their roles
            front = front.located_in(strip_block, rows)
        return Detection(rows, contact, front, insertion_points, rings, hole, advancing)

    def _surface_ahead(self, world: SimulationState, state: InstrumentState, geometry: StepGeometry):
        """The surface ahead of a tip outside the tissue, its shaft in the tissue (the insertion or the
        cutting phase, the tip outside and advancing): (contact, its rows, the hole it meets), as
        :meth:`approach_rows` without the shaft's rows; (None, [], None) when the closest surface is the face
        the tip left, turned away from it (it moves away from that face). How the tip left does not matter
        but in one case: a tip backed out of a face it entered by (``InstrumentState.channel_end`` not marked
        through: the entry face with a point still kept, or an inner layer's into a gap) that meets a hole is
        in its own channel's mouth, located there when pushed in again with its channel's end kept (no
        event); moved away from the hole (the base moved sideways in the gap), the surface ahead is intact
        tissue, a contact it punctures at f_p. A tip out of a far face (the end marked through by the event
        exit) meets a hole as a hole (the event reentry). A tip moving back meets no surface ahead (it goes
        back into its own channel through the face it left: the caller asks only for an advancing tip)."""
        contact, approach, hole = self.approach_rows(geometry, world.channels, shaft=False)
        if float(contact.normal @ self._contact_needle(geometry).tip_tangent) >= 0.0:
            return None, [], None
        through = state.channel_end is not None and state.channel_end.through
        if not through and hole is not None:
            return None, [], None
        return contact, approach, hole

    @staticmethod
    def _advancing(geometry: StepGeometry) -> bool:
        """Whether the needle's tip does not move back along the needle over the step (free tip against the
        start-of-step tip, along the tip's direction at the start): advancing, or still."""
        previous = geometry.needle_previous
        return float((geometry.needle_free.tip - previous.tip) @ previous.tip_tangent) >= 0.0

    def _contact_needle(self, geometry: StepGeometry):
        """The needle configuration the tip's contact is found on: the free one for a rigid needle (its
        kinematic pose is where the step puts it), the start-of-step one for a deformable needle (its free
        motion has no contact in it; see :meth:`approach_rows`)."""
        return geometry.needle_free if self.needle_dof_count is None else geometry.needle_previous

    def approach_rows(
        self, geometry: StepGeometry, channels: tuple[Channel, ...] = (), *, shaft: bool = True
    ) -> tuple[SurfaceContact, list[RowBlock], Channel | None]:
        """Before puncture (or after the tip left the tissue through a far face, ``shaft`` False: the shaft is
        in the tissue): the tip's closest surface point, in order its contact rows (when within the contact
        distance) and the shaft's contact rows (``insertion.shaft_contact`` and ``shaft``, when any sample is
        near the surface), and the hole of ``channels`` (the tissue's) the tip meets.

        A tip within the contact distance whose closest surface point lies in a hole (:meth:`hole`) has no
        contact rows: there is no surface to push there (the tissue is open), and the tip enters the hole's
        channel without puncture (the events' ``reentry``, on the first step after which the tip lies in a
        tet). The shaft's rows stay: its samples end two contact distances behind the tip, out of the
        tissue when the tip enters.

        The surface point is the one closest to the needle's tip where the needle is: at its free tip for a
        rigid needle (its kinematic pose is where the step puts it), at its start-of-step tip for a
        deformable one, whose free motion has no contact in it (a needle bent against the surface
        straightens in it, and its free tip can lie millimetres from the tip, beyond a thin layer's far
        face). The row's gap is the free tip's along that point's normal (the linearised step); the rows
        exist when either tip is within the contact distance."""
        spec = self.insertion
        blocks = []
        projector = SurfaceProjector(geometry.tissue_free, self.faces, vertex_indices=self._face_points)
        needle = self._contact_needle(geometry)
        tip_direction = needle.tangents(np.array([needle.length]))[0]
        contact = find_surface_contact(
            projector, self.faces, needle.tip, tip_direction, tip_radius=spec.tip_radius
        )
        free_gap = float(contact.normal @ (geometry.needle_free.tip - contact.point))
        near = min(contact.gap, free_gap) < spec.contact_distance
        hole = self.hole(contact, channels, geometry.mesh_tets) if near else None
        if near and hole is None:
            blocks.append(
                penetration_block(
                    contact,
                    geometry,
                    friction_coefficient=spec.surface_friction_coefficient,
                    puncture_force=spec.puncture_force if spec.puncture_within_step else None,
                )
            )
        if spec.shaft_contact and shaft:
            shaft_rows = shaft_contact_block(
                geometry,
                projector,
                self.faces,
                spacing=self.shaft_spacing,
                contact_distance=spec.contact_distance,
                tip_clearance=2.0 * spec.contact_distance,
            )
            if shaft_rows is not None:
                blocks.append(shaft_rows)
        return contact, blocks, hole

    def hole(
        self, contact: SurfaceContact, channels: tuple[Channel, ...], mesh_tets: np.ndarray
    ) -> Channel | None:
        """The channel of ``channels`` whose hole holds the surface point of ``contact``, None when none does.

        Compared in rest coordinates (the tissue may have moved or deformed since the hole was made): the
        contact point's rest position (its surface triangle's barycentric coordinates on the rest nodes) lies
        in a hole when it is within the hole's radius of the rest position of its channel's entry point, and
        the channel runs into the tissue under the contact's face (from its entry to its end against the
        face's outward normal; a channel of no length counts as such). Of several, the nearest entry's.
        (Another layer's surface beyond a gap is not the hole's: the exit hole of a layer seen from the next
        layer's surface, its channel running back up through the layer, was taken for a hole there when the
        gap was under the radius.)"""
        if not channels or self.rest_positions is None:
            return None
        memo = self._holes_memo
        if memo is None or memo[0] is not channels:
            tets = np.asarray(mesh_tets)
            entries = np.einsum(
                "hk,hkj->hj",
                np.array([channel.entry_barycentric for channel in channels]),
                self.rest_positions[tets[[channel.entry_tet for channel in channels]]],
            )
            ends = np.einsum(
                "hk,hkj->hj",
                np.array([channel.end.barycentric for channel in channels]),
                self.rest_positions[tets[[channel.end.tet for channel in channels]]],
            )
            radii = np.array([channel.radius for channel in channels])
            memo = self._holes_memo = (channels, entries, radii, ends - entries)
        _, entries, radii, axes = memo
        corners = self.rest_positions[np.asarray(contact.nodes)]
        point = np.asarray(contact.barycentric) @ corners
        normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        normal /= max(float(np.linalg.norm(normal)), np.finfo(float).tiny)
        distance = np.linalg.norm(entries - point, axis=1)
        into = axes @ normal < 0.0
        into |= np.linalg.norm(axes, axis=1) <= 1e-9 * np.maximum(radii, np.finfo(float).tiny)
        inside = np.flatnonzero((distance <= radii) & into)
        if inside.size == 0:
            return None
        return channels[int(inside[np.argmin(distance[inside])])]

    def path_rows(
        self, state: InstrumentState, geometry: StepGeometry
    ) -> tuple[RowBlock | None, np.ndarray, PointRings | None]:
        """The rows of the instrument's insertion points (their ``point`` field indexing its path), the
        points that have rows and the rings the rows were built on; no rows while cutting under a law whose
        cut holds the needle alone (``rows_while_cutting`` false)."""
        points = np.arange(state.path.point_count)
        if state.phase == Phase.CUTTING and not self.law.rows_while_cutting:
            # The cut holds the needle along the strip (sliding rows, crack tip; the strip extends down the
            # shaft when the needle goes deeper); the path's points kept at the cut start
            # (CuttingLaw.kept_at_cut_start) have no rows (anchored, they would drag the tissue along the
            # stroke).
            return None, points[:0], None
        # Every point of the path has rows: the builders' ``point`` field (each row's index among the points
        # they were given) is its index in the path.
        block, rings = self.insertion_rows(
            state.path,
            geometry,
            finite_line=self.insertion.subgrid_line == "finite" and state.phase != Phase.CUTTING,
        )
        return block, points, rings

    def tip_row(self, state: InstrumentState, geometry: StepGeometry) -> RowBlock | None:
        """The tip's cutting row after puncture (``insertion.tip_cutting_force`` > 0), against the tissue's
        material point at the tip (its ring with the ring coupling), or at the end of the channel the tip
        has cut while the tip lies behind it on the needle's line, within the needle's radius of it
        (``InstrumentState.channel_end``: the row then holds the tip's distance to it, and the tip cuts only
        beyond it); none outside insertion, while the tip is
        outside the tissue, or while it lies on the line of a channel cut through the tissue (the tip left
        through a far face: moved back into the tissue along that line, it meets no tissue left to cut;
        turned off it, it cuts intact tissue)."""
        spec = self.insertion
        if not (spec.tip_cutting_force > 0.0 and state.phase == Phase.INSERTION and state.tip_tet >= 0):
            return None
        tet, barycentric = (state.tip_tet, state.tip_barycentric)
        ahead = None
        channel_end = state.channel_end
        if channel_end is not None:
            tet, barycentric = channel_end.tet, channel_end.barycentric
            end = np.asarray(barycentric) @ geometry.tissue_previous[geometry.mesh_tets[tet]]
            needle = geometry.needle_previous
            offset = end - needle.tip
            ahead = float(offset @ needle.tip_tangent)
            if np.linalg.norm(offset - ahead * needle.tip_tangent) > self.needle_radius:
                # Turned out of its channel (the channel's end off the needle's line by more than its
                # radius): the tip meets intact tissue, its own material point's.
                tet, barycentric, ahead = state.tip_tet, state.tip_barycentric, None
            elif channel_end.through:  # on the line of a channel cut through to a far face: nothing to cut
                return None
        ring = self.tip_ring(state, geometry, (tet, barycentric)) if self.ring else (None, None)
        block, _, _ = tip_cutting_block(
            geometry,
            tip_tet=tet,
            tip_barycentric=barycentric,
            cutting_force=spec.tip_cutting_force,
            tissue_nodes=ring[0],
            tissue_weights=ring[1],
            ahead=ahead,
        )
        return block

    def cut_rows(
        self,
        world: SimulationState,
        state: InstrumentState | None,
        geometry: StepGeometry,
        *,
        tip_outside: bool | None = None,
    ) -> tuple[RowBlock | None, FrontRows]:
        """The cut surface's rows along the inserted part of the needle, from where it enters the tissue (not
        the entry point's projection, which a tilted needle pushed sideways leaves above the tissue) to the
        tip, on the start-of-step state. ``state`` None: a needle inserted along an existing cut slides in it
        (sliding rows, no crack tip, no friction); else the instrument's own cut strip while it cuts, with its
        crack-tip front (indices into the returned block). Where the needle enters the tissue and where its
        inserted part ends are the state's ``stretches`` when the last step's events located them on this
        configuration (one stretch per part of the tissue the needle is in: each part has its rows).
        ``tip_outside``: the tip is outside the tissue by the tip's rules (``inserted_stretches``); by default
        ``state``'s tip (inside for None)."""
        if state is not None and state.stretches is not None:
            stretches = state.stretches
        else:
            locator = TetLocator(geometry.tissue_previous, geometry.mesh_tets, previous=self._cut_locator)
            self._cut_locator = locator
            stretches = inserted_stretches(
                geometry.needle_previous,
                locator,
                self.cutting.point_spacing,
                tip_outside=(state is not None and state.tip_tet < 0) if tip_outside is None else tip_outside,
            )
        if not stretches:
            return None, FrontRows.empty()
        if state is None:
            return strip_cut_block(
                world.cut,
                None,
                geometry,
                spacing=self.cutting.point_spacing,
                cut_direction=np.zeros(3),
                subgrid_compliance=self.cut_compliance,
                stretches=stretches,
            )
        return strip_cut_block(
            world.cut,
            state.cut_strip,
            geometry,
            spacing=self.cutting.point_spacing,
            cut_direction=state.cut_direction,
            front_strength=self.law.front_strength,
            friction_coefficient=self.cutting.friction_coefficient,
            subgrid_compliance=self.cut_compliance,
            face_stretch=state.cut_face_stretch,
            stretches=stretches,
        )


def _cut_compliance(
    scene: Scene, rest_positions: np.ndarray, tets: np.ndarray, needle_radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Sub-grid compliance of a cut row in each tet [m/N], (lateral, axial), shapes (tet_count,) each: the
    coupling's (:func:`refsim.constraints.coupling.subgrid_compliance`, the annulus between the needle and the
    equivalent radius of the mesh, Peaceman's well model) with the tet's own size, for the length d_c a cut
    row stands for."""
    tets = np.asarray(tets)
    size = local_mesh_size(rest_positions, tets, np.arange(tets.shape[0]))
    tissue = scene.tissue
    common = dict(
        shear_modulus=tissue.youngs_modulus / (2.0 * (1.0 + tissue.poisson_ratio)),
        poisson_ratio=tissue.poisson_ratio,
        needle_radius=needle_radius,
        mesh_size=size,
        spacing=scene.cutting.point_spacing,
    )
    return (
        subgrid_compliance(np.full(size.size, LATERAL), **common),
        subgrid_compliance(np.full(size.size, AXIAL), **common),
    )
