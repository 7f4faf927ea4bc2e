"""The time step loop (layer 5)."""

from refsim.simulation.bodies import Body, TissueBody
from refsim.simulation.needle_body import FlexibleNeedle, NeedleState, RigidNeedle
from refsim.simulation.records import STAGES, Event, StepRecord
from refsim.simulation.simulation import Simulation, SimulationError
from refsim.simulation.state import Phase, SimulationState

__all__ = [
    "STAGES",
    "Body",
    "Event",
    "FlexibleNeedle",
    "NeedleState",
    "Phase",
    "RigidNeedle",
    "Simulation",
    "SimulationError",
    "SimulationState",
    "StepRecord",
    "TissueBody",
]
