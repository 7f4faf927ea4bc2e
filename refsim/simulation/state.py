"""The state of a run: everything that changes from step to step (Model / State / Control)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from refsim.constraints import InsertionPath
from refsim.cutting import CutSurface
from refsim.cutting.strip import CutStrip
from refsim.fem.compliance import PartialSolveMarks, StaleFactor
from refsim.fem.tissue import TissueState
from refsim.simulation.needle_body import NeedleState

__all__ = ["Phase", "SimulationState"]


class Phase(StrEnum):
    """Phases of a needle's life (their values are the names stored in the results)."""

    APPROACH = "approach"  # the tip is outside: tip contact with the surface
    INSERTION = "insertion"  # after puncture: insertion points along the path
    CUTTING = "cutting"  # after the cut start: the entry point, sliding and border rows of the cut


@dataclass(frozen=True)
class SimulationState:
    """Everything that changes during a run.

    A step is a function of its state, the scene and the controls: a new :class:`refsim.simulation.Simulation`
    of the same scene continued from a state gives the bits of the run that made the state (what a simulation
    keeps across steps is either carried here, like the insertion points' coupling rings in ``path`` and the
    tissue's stale factor, or a memo of the scene's models).

    Attributes
    ----------
    step : Steps done.
    time : Simulated time [s].
    phase : The needle's phase.
    tissue : Tissue positions [m] and velocities [m/s], each (n, 3).
    needle : Needle configuration.
    path : Insertion points (material points of the tissue), with the coupling ring each point's rows were
        last built on (``InsertionPath.rings``).
    cut : The cut surface, None until the tissue is cut.
    cut_direction : ĉ, the unit direction the cut runs in the deformed state, shape (3,); None until the cut
        starts.
    cut_strip : The structure of the cut the needle is making (its layers and crack tip); None outside the
        cutting phase (a withdrawn needle leaves the cut surface behind).
    tip_tet : The tissue tet the needle's tip lies in after the step, −1 when the tip is outside the tissue
        (before puncture, after an exit through a far face or a withdrawal).
    tip_barycentric : The tip's barycentric coordinates in ``tip_tet``, shape (4,); None when outside.
    tissue_factor : What the tissue compliance carries from step to step: the refreshed strategy's stale
        factor (the matrix A it last factorised and the steps since,
        :class:`refsim.fem.compliance.StaleFactor`), or the exact strategy's partial-solve marks on PARDISO
        (the DoFs its analysis marked, :class:`refsim.fem.compliance.PartialSolveMarks`); None for the
        strategies that carry nothing, and before the first step.
    """

    step: int
    time: float
    phase: Phase
    tissue: TissueState
    needle: NeedleState
    path: InsertionPath
    cut: CutSurface | None = None
    cut_direction: np.ndarray | None = None
    cut_strip: CutStrip | None = None
    tip_tet: int = -1
    tip_barycentric: np.ndarray | None = None
    tissue_factor: StaleFactor | PartialSolveMarks | None = None
