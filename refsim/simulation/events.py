"""Phases and events (DESIGN.md, step 7): what the forces of a step change in the state.

| phase | event | when | then |
|---|---|---|---|
| approach | puncture | tip normal force ≥ f_p | the entry point is the first insertion point; insertion |
| insertion | (new points) | the tip is farther than d_i from every point | points every d_i behind the tip |
| insertion | retraction | points lie beyond the tip | they are removed |
| insertion | withdrawal | no point is left | approach |
| insertion | cut_start | equation 3: ‖t‖ > n_i f_c | the first cut surface; cutting, the entry point kept |
| cutting | tear | a border row's force ≥ f_t | the front of the cut grows by d_t |

The cut surface itself grows in :mod:`refsim.cutting.growth`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from refsim.constraints import (
    BILATERAL,
    INSERTION,
    PENETRATION,
    UNILATERAL,
    InsertionPath,
    grow_path,
    points_beyond_tip,
)
from refsim.constraints.cut import cut_criterion
from refsim.cutting import CutGrowth, TriangulationParameters
from refsim.geometry import TetLocator
from refsim.scene import Scene
from refsim.simulation.detection import Detection
from refsim.simulation.records import Event
from refsim.simulation.state import Phase, SimulationState

__all__ = ["EventRules", "LazyLocator", "locate_under_surface"]


class LazyLocator:
    """Builds the tet locator on first use (most steps add no insertion point)."""

    def __init__(self, positions: np.ndarray, tets: np.ndarray) -> None:
        self._positions, self._tets, self._locator = positions, tets, None

    def locate(self, points: np.ndarray):
        if self._locator is None:
            self._locator = TetLocator(self._positions, self._tets)
        return self._locator.locate(points)


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
    """The events of a scene, applied to the state after each step's correction.

    Parameters
    ----------
    scene : The validated scene.
    tets : Tissue tets, shape (m, 4).
    rest_positions : Tissue rest positions [m], shape (n, 3).
    deformation_gradients : Function of tissue positions (n, 3) giving F of every tet, shape (m, 3, 3).
    needle_geometry : Function of a needle state giving its centreline.
    """

    def __init__(self, scene: Scene, tets, rest_positions, deformation_gradients, needle_geometry) -> None:
        self.insertion = scene.insertion
        self.cutting = scene.cutting
        self.tets = tets
        self.deformation_gradients = deformation_gradients
        self.needle_geometry = needle_geometry
        self.growth = None
        if scene.cutting.enabled:
            cutting = scene.cutting
            self.growth = CutGrowth(
                rest_positions=rest_positions,
                tets=tets,
                point_spacing=cutting.point_spacing,
                extent=cutting.extent,
                parameters=TriangulationParameters.from_degrees(
                    min_angle=cutting.min_angle,
                    max_angle=cutting.max_angle,
                    max_surface_angle=cutting.max_normal_angle,
                ),
            )

    def apply(
        self, state: SimulationState, detection: Detection, multipliers: np.ndarray
    ) -> tuple[SimulationState, list[Event]]:
        """The state after the step's events, and the events."""
        events: list[Event] = []
        rows = detection.rows
        if state.phase == Phase.APPROACH and rows.row_count:
            state, events = self._puncture(state, detection, multipliers)
        if state.phase == Phase.INSERTION and not events:
            # (Not in the step that punctures: the entry point is then at the tip, on either side by round-off.)
            state, more = self._insertion(state, detection, multipliers)
            events.extend(more)
        elif state.phase == Phase.CUTTING:
            state, more = self._tear(state, detection, multipliers)
            events.extend(more)
        return state, events

    def _puncture(self, state, detection, multipliers):
        rows = detection.rows
        normal_rows = np.flatnonzero((rows.source == PENETRATION) & (rows.kind == UNILATERAL))
        normal_force = float(multipliers[normal_rows].sum())
        if normal_force < self.insertion.puncture_force:
            return state, []
        contact = detection.contact
        positions = state.tissue.positions
        entry = contact.barycentric @ positions[contact.nodes]
        tets, barycentric = locate_under_surface(positions, self.tets, entry[None, :], inward=contact.normal)
        if tets[0] < 0:
            return state, []
        path = InsertionPath.empty().appended(tets, barycentric, state.step)
        return replace(state, phase=Phase.INSERTION, path=path), [Event("puncture", normal_force)]

    def _insertion(self, state, detection, multipliers):
        rows = detection.rows
        events: list[Event] = []
        positions = state.tissue.positions
        if self.growth is not None and rows.row_count:
            lateral = (rows.source == INSERTION) & (rows.kind == BILATERAL)
            force_on_needle = (rows.directions[lateral] * multipliers[lateral, None]).sum(axis=0)
            if cut_criterion(force_on_needle, state.path.point_count, self.cutting.cutting_force):
                mean_force = float(np.linalg.norm(force_on_needle)) / state.path.point_count
                direction = -force_on_needle / np.linalg.norm(force_on_needle)
                cut = self.growth.start(state.path.positions(positions, self.tets), direction, positions, state.step)
                state = replace(
                    state,
                    phase=Phase.CUTTING,
                    cut=cut,
                    cut_direction=np.asarray(direction, dtype=float),
                    path=state.path.subset(np.array([0])),
                )
                return state, [Event("cut_start", mean_force)]
        needle = self.needle_geometry(state.needle)
        path, _ = grow_path(
            state.path,
            tip=needle.tip,
            tissue_positions=positions,
            mesh_tets=self.tets,
            locator=LazyLocator(positions, self.tets),
            spacing=self.insertion.spacing,
            step=state.step,
        )
        # Ring coupling: the centre of a point is not tied to the needle (its ring is), so it drifts along the needle
        # with the tissue's strain; half a spacing of hysteresis keeps such drift from removing and re-adding it.
        margin = 0.5 * self.insertion.spacing if self.insertion.coupling == "ring" else 0.0
        beyond = points_beyond_tip(path, path.positions(positions, self.tets), needle, margin)
        if np.any(beyond):
            path = path.subset(~beyond)
            events.append(Event("retraction"))
        state = replace(state, path=path)
        if path.point_count == 0:
            state = replace(state, phase=Phase.APPROACH)
            events.append(Event("withdrawal"))
        return state, events

    def _tear(self, state, detection, multipliers):
        rows = detection.border_rows
        if rows.size == 0:
            return state, []
        forces = multipliers[rows]
        strongest = int(np.argmax(forces))
        if forces[strongest] < self.cutting.tearing_force:
            return state, []
        positions = state.tissue.positions
        needle = self.needle_geometry(state.needle)
        entry = state.path.positions(positions, self.tets)[:1]
        grown = self.growth.tear(
            state.cut,
            positions=positions,
            deformation_gradients=self.deformation_gradients(positions),
            outward=-detection.rows.directions[rows[strongest]],  # against the contact's normal −n_c
            cut_direction=state.cut_direction,
            needle=needle,
            entry_arc_length=float(needle.project(entry)[0][0]),
            step=state.step,
        )
        return replace(state, cut=grown), [Event("tear", float(forces[strongest]))]
