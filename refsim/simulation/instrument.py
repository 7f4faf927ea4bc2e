"""An instrument of the scene (today: a needle) owns its story: its body, its controls, its detection and
its events.

Each instrument is built once from the scene (:class:`refsim.scene.build.InstrumentModels`): its body (a
rigid, kinematic needle or a flexible one, named by the instrument: the key of its Jacobian in a row
block), the index of its trajectory in the controls, its :class:`~refsim.simulation.detection.Detector`
and its :class:`~refsim.simulation.events.EventRules`. What it changes during a run is its
:class:`~refsim.simulation.state.InstrumentState`. The instruments do not touch each other: they meet only
through the tissue (its compliance couples their rows in the one constraint problem of the step, and the cut
surface one of them makes is met by the others' rows).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from refsim.constraints import InsertionPath, RowBlock, StepGeometry
from refsim.scene import Scene
from refsim.scene.controls import ControlValues
from refsim.simulation.detection import Detection, Detector
from refsim.simulation.events import EventRules
from refsim.simulation.needle_body import FlexibleNeedle, RigidNeedle
from refsim.simulation.state import InstrumentState, Phase, SimulationState

__all__ = ["Instrument"]


class Instrument:
    """One instrument of a simulation.

    Parameters
    ----------
    index : Its place in the scene's instruments (the rows' ``instrument`` field).
    models : Its static models (:class:`refsim.scene.build.InstrumentModels`).
    scene : The validated scene.
    tissue : The tissue model (its deformation gradients, for the events).
    faces, tets, rest_positions : The tissue mesh's surface triangles, tets and rest positions.
    """

    def __init__(self, index: int, models, scene: Scene, tissue, faces, tets, rest_positions) -> None:
        self.index = index
        self.name = models.name
        self.cuts = bool(models.cuts)
        spec = models.needle
        if spec.rigid:
            self.body = RigidNeedle(spec.length, spec.element_count, name=self.name)
        else:
            self.body = FlexibleNeedle(
                models.model,
                rayleigh_mass=spec.rayleigh_mass,
                rayleigh_stiffness=spec.rayleigh_stiffness,
                name=self.name,
            )
        self.detector = Detector(
            scene, faces, self.body.dof_count, rest_positions, tets, needle=spec, cuts=self.cuts
        )
        self.event_rules = EventRules(
            scene,
            tets,
            rest_positions,
            tissue.deformation_gradients,
            self.body.geometry,
            cuts=self.cuts,
            needle_radius=spec.radius,
        )

    def control(self, control: ControlValues) -> ControlValues:
        """The step's controls with this instrument's base pose."""
        return control.instrument(self.index)

    def initial_state(self, control: ControlValues) -> InstrumentState:
        """The needle at its trajectory's pose in ``control`` (the first), the tip outside."""
        control = self.control(control)
        return InstrumentState(
            name=self.name,
            phase=Phase.APPROACH,
            needle=self.body.state_at(control.base_position, control.direction),
            path=InsertionPath.empty(),
        )

    def detect(self, world: SimulationState, geometry: StepGeometry) -> Detection:
        """Its rows of the step, every row marked with its index, its needle's Jacobian keyed by its name."""
        detection = self.detector.detect(world, world.instrument(self.name), geometry)
        rows: RowBlock = detection.rows.of_instrument(self.index, self.body.name)
        return replace(detection, rows=rows)  # every other field as the detector gave it

    def needle_force(self, rows: RowBlock, multipliers: np.ndarray) -> np.ndarray:
        """The force of the tissue on its needle, Σ λ n over its rows [N], shape (3,)."""
        mine = rows.instruments == self.index
        if not mine.any():
            return np.zeros(3)
        return (rows.directions[mine] * multipliers[mine, None]).sum(axis=0)
