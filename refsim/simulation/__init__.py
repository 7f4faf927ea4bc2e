"""The time step loop (layer 5)."""

from refsim.simulation.bodies import Body, TissueBody
from refsim.simulation.instrument import Instrument
from refsim.simulation.needle_body import FlexibleNeedle, NeedleState, RigidNeedle
from refsim.simulation.records import STAGES, Event, InstrumentRecord, StepRecord
from refsim.simulation.simulation import Simulation, SimulationError
from refsim.simulation.state import InstrumentState, Phase, SimulationState

__all__ = [
    "STAGES",
    "Body",
    "Event",
    "FlexibleNeedle",
    "Instrument",
    "InstrumentRecord",
    "InstrumentState",
    "NeedleState",
    "Phase",
    "RigidNeedle",
    "Simulation",
    "SimulationError",
    "SimulationState",
    "StepRecord",
    "TissueBody",
]
