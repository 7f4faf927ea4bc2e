"""What one time step did: the record the results file stores (DESIGN.md, "Results")."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

__all__ = [
    "EVENT_UNITS",
    "STAGES",
    "STEP_SOLVED_AGAIN",
    "Event",
    "InstrumentRecord",
    "StepRecord",
    "WithinStep",
]

# The stages of one step, in order (DESIGN.md, "One time step"); their seconds are recorded every step.
STAGES = ("motion", "free_motion", "detection", "compliance", "solve", "correction", "events")


#: Units an event's value can have, each stored in its own dataset of the results file
#: (:data:`refsim.io.schema.EVENT_VALUE_DATASETS`): a force, or a force per unit length (the energy law's cut
#: start compares the lateral force per inserted length with G_c).
EVENT_UNITS = ("N", "N/m")


#: Events after which their step is solved again from its start, every instrument's events of the first solve
#: standing, with the rows after them (`refsim.simulation.Simulation`): each is crossed inside the step and
#: changes what holds the needle, so the rows chosen at the step's start would carry the step to its end with
#: a force the event has ended, or without one it has begun. A change of phase: the cut start (the insertion
#: rows give way to the cut's, which hold the needle at the cut's force), the cut resumed (the insertion rows
#: give way to the rows of the cut the needle is in), leaving the cut (the cut's rows give
#: way to insertion points in intact tissue), the re-entry into a hole (the channel's rows hold a needle that
#: was free in the hole) and the withdrawal (the tip is out of the tissue: nothing holds the needle); and rows
#: removed: the exit (the tip is out through a far face, its cutting row is gone) and the retraction (points
#: left beyond the tip). Rows added as the needle advances (insertion points every d_i, the cut's layers every
#: d_c) take effect at the next step: they are laid where the tissue is at the step's end. The puncture
#: through a capped tip contact is solved again too, located inside the step (:class:`WithinStep`).
STEP_SOLVED_AGAIN = frozenset(
    {"cut_resume", "cut_start", "exit", "leave_cut", "reentry", "retraction", "withdrawal"}
)


@dataclass(frozen=True)
class Event:
    """Something that happened in a step: ``name`` (puncture, cut_start, tear, retraction, ...), the value
    that triggered it, ``force`` (nan when none), and that value's ``unit``, one of :data:`EVENT_UNITS`: "N"
    for a force, "N/m" for a force per unit length (the energy law's cut start)."""

    name: str
    force: float = float("nan")
    unit: str = "N"

    def __post_init__(self) -> None:
        if self.unit not in EVENT_UNITS:
            raise ValueError(f"event {self.name!r}: unit {self.unit!r} is not one of {EVENT_UNITS}")

    @property
    def solves_step_again(self) -> bool:
        """Whether its step is solved again with the rows after it (:data:`STEP_SOLVED_AGAIN`)."""
        return self.name in STEP_SOLVED_AGAIN


@dataclass(frozen=True, kw_only=True)
class WithinStep:
    """An instrument at an event located inside its step, from the solve that located it.

    The one such event is the puncture through a capped tip contact (``insertion.puncture_within_step``): the
    solve that locates it ends with the contact at f_p, giving way, and the rest of the step's motion without
    it; the step is then solved again from its start with the insertion phase's rows (the entry point's, the
    tip's cutting row: :class:`refsim.simulation.Simulation`), and the step's record is the end of that second
    solve. This is the give-way: the peak of the force profile. (The events of :data:`STEP_SOLVED_AGAIN` also
    solve their step again but locate no state inside it: their step records the second solve's end only.)

    Attributes
    ----------
    event : The event's name ("puncture").
    needle_force : Force of the tissue on the needle in the solve that located the event, Σ λ n over the
        instrument's rows [N], (3,): the tip contact at f_p with the other rows' forces of that solve (for a
        needle bent against the surface, those carry the bending the give-way releases).
    tip_force : Force of the tip's contact rows on the needle at the give-way (normal f_p and friction) [N],
        (3,).
    normal_force : The tip contact's normal force at the give-way, Σ λ over its normal rows [N] (f_p to the
        solve's accuracy; in the results file, the puncture event's ``events/force``).
    point : Where the event happened: the tissue-side point of the tip contact, on the surface, where the tip
        is when the contact gives way [m], (3,).
    """

    event: str
    needle_force: np.ndarray
    tip_force: np.ndarray
    point: np.ndarray
    normal_force: float = float("nan")


@dataclass(frozen=True, kw_only=True)
class InstrumentRecord:
    """What one step did to one instrument.

    Attributes
    ----------
    name : The instrument's name.
    phase : Its phase after the step's events.
    events : Its events of the step.
    base_position : Its needle's base [m], (3,).
    needle_positions : Its needle's nodes [m], (k, 3).
    needle_frames : Its needle's frames, (k, 3, 3).
    needle_force : Force of the tissue on its needle, Σ λ n over its rows [N], (3,).
    insertion_point_count : Its insertion points after the step.
    needle_strain : The largest strain of its needle's element chords after the step, |chord / rest length −
        1| (0 for a rigid needle): a needle's true axial strain is of the order of 1e-6, so this is the error
        of the step's one Newton iteration (``refsim.simulation.needle_body.STRAIN_WARNING``).
    criteria : The criteria its events compared, with threshold and accuracy
        (``refsim.simulation.margins.Criterion``); in a step solved twice, those of the solve its events were
        decided on.
    within_step : Its state at an event located inside the step (:class:`WithinStep`), or None. The fields
        above are the end of the step (what the next step starts from).
    """

    name: str
    phase: str
    events: tuple[Event, ...]
    base_position: np.ndarray
    needle_positions: np.ndarray
    needle_frames: np.ndarray
    needle_force: np.ndarray
    insertion_point_count: int
    needle_strain: float = 0.0
    criteria: tuple = ()
    within_step: WithinStep | None = None


#: The first instrument's fields a StepRecord reads through (every InstrumentRecord field but its name).
_FIRST_INSTRUMENT_FIELDS = frozenset(name for name in InstrumentRecord.__dataclass_fields__ if name != "name")


@dataclass(frozen=True, kw_only=True)
class StepRecord:
    """One step, as recorded.

    Every field of :class:`InstrumentRecord` but its name (``phase``, ``events``, ``base_position``,
    ``needle_positions``, ``needle_frames``, ``needle_force``, ``insertion_point_count``, ``criteria``,
    ``within_step``, and any field added there) reads as the first instrument's (the only one's in a
    one-instrument scene): ``record.needle_force`` is ``record.instruments[0].needle_force``.
    ``instruments`` holds every instrument's, in the scene's order; :meth:`with_first` replaces
    first-instrument fields.

    Attributes
    ----------
    step : Step index, from 1.
    time : Time at the end of the step [s].
    tissue_positions : Tissue nodes [m], (n, 3), or None when not recorded this step.
    row_kind, row_source : Kind (0 bilateral, 1 unilateral, 2 friction) and source of each row, (r,).
    row_points : Tissue-side point of each row [m], (r, 3).
    row_directions : Row directions, (r, 3).
    row_forces : Multipliers λ [N], (r,).
    solver : Report of the constraint solve (iterations, residual, converged, seconds, ...), or None.
    stage_seconds : Seconds spent in each stage of STAGES.
    problem : The step's constraint problem when recorded, else None.
    cut_point_count, cut_triangle_count : Size of the cut surface after the step.
    triangulation_seconds : Seconds of the step's triangulation (0 when the cut did not grow).
    boundary_displacements : Prescribed displacement from rest of the tissue's moving boundary nodes at the
        end of the step [m], (k, 3), or None without boundary motion.
    row_role : Role of each row (``refsim.constraints.ROLE_NAMES``), (r,).
    row_point : Insertion point of each row (its index in its instrument's path, the entry is 0), −1 for
        others, (r,).
    instruments : Every instrument's part of the step, in the scene's order (at least one).
    row_instrument : The instrument of each row (its index in ``instruments``), (r,).
    """

    step: int
    time: float
    tissue_positions: np.ndarray | None
    row_kind: np.ndarray
    row_source: np.ndarray
    row_points: np.ndarray
    row_directions: np.ndarray
    row_forces: np.ndarray
    solver: object | None
    instruments: tuple[InstrumentRecord, ...]
    stage_seconds: dict = field(default_factory=dict)
    problem: object | None = None
    cut_point_count: int = 0
    cut_triangle_count: int = 0
    triangulation_seconds: float = 0.0
    boundary_displacements: np.ndarray | None = None
    row_role: np.ndarray | None = None
    row_point: np.ndarray | None = None
    row_instrument: np.ndarray | None = None

    def __getattr__(self, name: str):
        # called only for names that are not fields: the first instrument's fields read through
        if name in _FIRST_INSTRUMENT_FIELDS:
            instruments = self.__dict__.get("instruments")
            if instruments:
                return getattr(instruments[0], name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def with_first(self, **changes) -> StepRecord:
        """The record with fields of its first instrument replaced (``needle_force=...``)."""
        first = replace(self.instruments[0], **changes)
        return replace(self, instruments=(first, *self.instruments[1:]))
