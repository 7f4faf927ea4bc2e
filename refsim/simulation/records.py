"""What one time step did: the record the results file stores (DESIGN.md, "Results")."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["STAGES", "Event", "StepRecord"]

# The stages of one step, in order (DESIGN.md, "One time step"); their seconds are recorded every step.
STAGES = ("motion", "free_motion", "detection", "compliance", "solve", "correction", "events")


@dataclass(frozen=True)
class Event:
    """Something that happened in a step: ``name`` (puncture, cut_start, tear, retraction, ...) and the force
    [N] that triggered it (nan when no force is involved)."""

    name: str
    force: float = float("nan")


@dataclass(frozen=True, kw_only=True)
class StepRecord:
    """One step, as recorded.

    Attributes
    ----------
    step : Step index, from 1.
    time : Time at the end of the step [s].
    phase : "approach", "insertion" or "cutting" (after the step's events).
    events : Events of the step.
    base_position : Needle base [m], (3,).
    needle_positions : Needle nodes [m], (k, 3).
    needle_frames : Needle frames, (k, 3, 3).
    tissue_positions : Tissue nodes [m], (n, 3), or None when not recorded this step.
    row_kind, row_source : Kind (0 bilateral, 1 unilateral, 2 friction) and source of each row, (r,).
    row_points : Tissue-side point of each row [m], (r, 3).
    row_directions : Row directions, (r, 3).
    row_forces : Multipliers λ [N], (r,).
    needle_force : Force of the tissue on the needle, Σ λ n [N], (3,).
    insertion_point_count : Insertion points after the step.
    solver : Report of the constraint solve (iterations, residual, converged, seconds, ...), or None.
    stage_seconds : Seconds spent in each stage of STAGES.
    problem : The step's constraint problem when recorded, else None.
    cut_point_count, cut_triangle_count : Size of the cut surface after the step.
    triangulation_seconds : Seconds of the step's triangulation (0 when the cut did not grow).
    boundary_displacements : Prescribed displacement from rest of the tissue's moving boundary nodes at the
        end of the step [m], (k, 3), or None without boundary motion.
    row_role : Role of each row (``refsim.constraints.ROLE_NAMES``), (r,).
    row_point : Insertion point of each row (its index in the path, the entry is 0), −1 for others, (r,).
    """

    step: int
    time: float
    phase: str
    events: tuple[Event, ...]
    base_position: np.ndarray
    needle_positions: np.ndarray
    needle_frames: np.ndarray
    tissue_positions: np.ndarray | None
    row_kind: np.ndarray
    row_source: np.ndarray
    row_points: np.ndarray
    row_directions: np.ndarray
    row_forces: np.ndarray
    needle_force: np.ndarray
    insertion_point_count: int
    solver: object | None
    stage_seconds: dict = field(default_factory=dict)
    problem: object | None = None
    cut_point_count: int = 0
    cut_triangle_count: int = 0
    triangulation_seconds: float = 0.0
    boundary_displacements: np.ndarray | None = None
    row_role: np.ndarray | None = None
    row_point: np.ndarray | None = None
