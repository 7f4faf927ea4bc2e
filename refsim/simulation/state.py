"""The state of a run: everything that changes from step to step (Model / State / Control)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from refsim.constraints import TISSUE, InsertionPath
from refsim.constraints.friction import FaceStretch
from refsim.cutting import CutSurface
from refsim.cutting.strip import CutStrip
from refsim.fem.compliance import FreeMotionStart, PartialSolveMarks, StaleFactor
from refsim.fem.tissue import TissueState
from refsim.simulation.needle_body import NeedleState

__all__ = [
    "KEPT_AT_WITHDRAWAL",
    "Channel",
    "ChannelEnd",
    "Crack",
    "InstrumentState",
    "Phase",
    "SimulationState",
    "evolved",
]


def evolved(instance, **changes):
    """``dataclasses.replace`` for the run's frozen dataclasses without ``__post_init__``
    (``InstrumentState``, ``SimulationState``): a copy of the instance's fields with ``changes`` in place
    (field names only), without ``replace``'s per-field pass through ``__init__`` (8 µs for an instrument's
    state, several per step)."""
    cls = type(instance)
    if not changes.keys() <= cls.__dataclass_fields__.keys():
        unknown = sorted(changes.keys() - cls.__dataclass_fields__.keys())
        raise TypeError(f"{cls.__name__} has no field(s) {', '.join(unknown)}")
    new = object.__new__(cls)
    new.__dict__.update(instance.__dict__)
    new.__dict__.update(changes)
    return new


class Phase(StrEnum):
    """Phases of an instrument's life (their values are the names stored in the results)."""

    APPROACH = "approach"  # the tip is outside: tip contact with the surface
    INSERTION = "insertion"  # after puncture: insertion points along the path
    CUTTING = "cutting"  # after the cut start: the entry point, sliding and border rows of the cut


@dataclass(frozen=True)
class ChannelEnd:
    """Where a channel a tip cut ends: a material point of the tissue (``InstrumentState.channel_end``,
    ``Channel.end``).

    Attributes
    ----------
    tet, barycentric : The material point: the deepest point the tip reached, or, for a channel cut through
        to a far face (the event exit), the tip's last material point inside the tissue before it left;
        barycentric shape (4,).
    through : Whether the channel runs through the tissue to a far face: a tip on its line has nothing left
        to cut (no cutting row); off its line (the point farther than the needle's radius from the needle's
        line: turned out of the channel) it cuts intact tissue.
    """

    tet: int
    barycentric: np.ndarray
    through: bool = False


@dataclass(frozen=True)
class Channel:
    """A channel a needle cut into the tissue and left: a hole in its surface and the cut tissue behind it.

    It belongs to the tissue (``SimulationState.channels``), like the cut surface: it outlives the needle
    that made it, and every instrument meets it. Its points are material points (a tet and barycentric
    coordinates), so it moves with the tissue; the hole is found in rest coordinates (its entry's rest
    position), whatever the tissue's deformation since.

    Attributes
    ----------
    entry_tet, entry_barycentric : The entry material point (the path's first point, where the needle
        punctured), shape (4,) for the coordinates.
    end : Where it ends (:class:`ChannelEnd`): the deepest material point its tip reached, or the tip's last
        material point inside the tissue, marked through, when the tip cut through to a far face.
    radius : The radius of the needle that made it [m]: the hole's radius at the surface.
    step : The step at which the needle left it.
    """

    entry_tet: int
    entry_barycentric: np.ndarray
    end: ChannelEnd
    radius: float
    step: int

    def same_entry(self, other: Channel) -> bool:
        """Whether ``other`` enters the tissue at this channel's entry point (a needle re-entered it)."""
        return self.entry_tet == other.entry_tet and np.array_equal(
            self.entry_barycentric, other.entry_barycentric
        )


@dataclass(frozen=True)
class Crack:
    """A cut strip a needle left, with its crack tip: the tissue keeps it (``SimulationState.cracks``).

    A needle leaves its strip when it is withdrawn while cutting, moved back out of its cut behind the line it
    entered along (the event leave_cut), or pressed against its cut's faces until a new cut starts off them.
    The tissue between the strip's rear edge and its crack tip stays cut, and the crack tip stays where the
    uncut tissue begins: a needle later found inside the strip, in insertion (re-inserted along the cut, or
    moved back into it), slides in it and cuts on from its crack tip (the event cut_resume makes the strip
    the needle's again, `refsim.simulation.cut_events`), instead of being gripped by insertion points in
    tissue that is cut and cutting it a second time. The strip's layers index the tissue's cut surface,
    which only grows, and its crack tip is made of material points: it moves with the tissue.

    Attributes
    ----------
    strip : The strip, its last layer laid at the crack tip (:func:`refsim.cutting.strip.recorded_strip`).
    direction : ĉ, the direction it ran in when it was left (deformed), unit, shape (3,).
    step : The step at which it was left.
    """

    strip: CutStrip
    direction: np.ndarray
    step: int


@dataclass(frozen=True)
class InstrumentState:
    """Everything one instrument (today: a needle) changes during a run: its own story.

    Attributes
    ----------
    name : The instrument's name (the scene's; its body's name: the key of its Jacobian in a row block).
    phase : Its phase.
    needle : Its needle's configuration.
    path : Its insertion points (material points of the tissue), with the coupling ring each point's rows
        were last built on (``InsertionPath.rings``).
    cut_direction : ĉ, the unit direction its cut runs in the deformed state, shape (3,); None until it
        starts cutting.
    cut_strip : The structure of the cut it is making (its layers and crack tip); None outside its cutting
        phase (a withdrawn needle leaves the cut surface behind).
    tip_tet : The tissue tet its tip lies in after the step, −1 when the tip is outside the tissue (before
        puncture, after an exit through a far face or a withdrawal).
    tip_barycentric : The tip's barycentric coordinates in ``tip_tet``, shape (4,); None when outside.
    channel_end : The end of the channel its tip has cut in insertion, while the tip lies behind it (moved
        back along the channel): that material point (:class:`ChannelEnd`); the tip's cutting row acts
        there, so that the tip cuts again only beyond it. None while the tip is at the channel's end (its own
        material point is the end); marked through once the tip has cut through to a far face (the event
        exit: no tip row while the needle stays on that channel's line, until it is withdrawn). A needle that
        re-enters a channel of the tissue (``SimulationState.channels``) starts with that channel's end.
    entered_at : Where its tip entered the part of the tissue it is in (a puncture, or a re-entry into a
        hole): the material point its channel there starts from, recorded in the tissue's channels when the
        tip leaves that part (through a far face, or back out of an inner layer while the shaft stays in the
        tissue); None before puncture and once the tip has left that part.
    stretches : The stretches of its needle in the tissue in this state's configuration, (entry, end) arc
        lengths [m] from the base to the tip (:func:`refsim.constraints.inserted.inserted_stretches` at the
        cut's spacing: one per part of the tissue the needle is in), when the step's events located them
        (cutting, the strip extending down the shaft); None otherwise. The next step's cut rows, built on this
        configuration, read them instead of locating the needle again (the same inputs: the same bits).
    cut_face_stretch : The annulus stretch under its friction rows on the cut faces at the last solve
        (`refsim.constraints.friction.FaceStretch`), the next step's rows start from it; None without them.
    """

    name: str
    phase: Phase
    needle: NeedleState
    path: InsertionPath
    cut_direction: np.ndarray | None = None
    cut_strip: CutStrip | None = None
    tip_tet: int = -1
    tip_barycentric: np.ndarray | None = None
    channel_end: ChannelEnd | None = None
    entered_at: ChannelEnd | None = None
    stretches: tuple[tuple[float, float], ...] | None = None
    cut_face_stretch: FaceStretch | None = None

    def withdrawn(self) -> InstrumentState:
        """This instrument after the event withdrawal, its needle out of the tissue: back in approach with
        nothing of its time in the tissue (no insertion point, no cut strip, the tip outside, no channel end
        or entry). Its name, needle, cut direction and the step-scoped fields (:data:`KEPT_AT_WITHDRAWAL`) are
        kept."""
        return evolved(self, path=InsertionPath.empty(), **_WITHDRAWN)


#: What the event withdrawal sets in an instrument's state besides an empty path
#: (:meth:`InstrumentState.withdrawn`): the one place its time in the tissue is forgotten, whichever phase it
#: leaves from.
_WITHDRAWN = dict(
    phase=Phase.APPROACH,
    cut_strip=None,
    tip_tet=-1,
    tip_barycentric=None,
    channel_end=None,
    entered_at=None,
)
#: The fields of an instrument's state a withdrawal keeps: who it is and where its needle is, the direction
#: its last cut ran in, and what each step's events set again before reading (the inserted stretches,
#: the cut faces' stretch).
KEPT_AT_WITHDRAWAL = ("name", "needle", "cut_direction", "stretches", "cut_face_stretch")


@dataclass(frozen=True)
class SimulationState:
    """Everything that changes during a run: the tissue's part and each instrument's story.

    A step is a function of its state, the scene and the controls: a new :class:`refsim.simulation.Simulation`
    of the same scene continued from a state gives the bits of the run that made the state (what a simulation
    keeps across steps is either carried here, like the insertion points' coupling rings in each instrument's
    ``path`` and the tissue's stale factor, or a memo of the scene's models).

    Attributes
    ----------
    step : Steps done.
    time : Simulated time [s].
    tissue : Tissue positions [m] and velocities [m/s], each (n, 3).
    instruments : Each instrument's state, in the scene's order.
    cut : The cut surface of the tissue, None until the tissue is cut. It belongs to the tissue: every
        instrument's rows meet it.
    channels : The channels needles cut and left (:class:`Channel`, withdrawn from insertion), in the order
        they were left; one per hole (a needle that re-entered a hole and left it again replaces its record).
        They belong to the tissue: a needle of any instrument whose tip meets the surface within a hole
        enters it without puncture (the event reentry) and cuts only beyond the channel's end.
    cracks : The cut strips needles left, with their crack tips (:class:`Crack`), in the order they were
        left; a needle found inside one in insertion cuts on from its crack tip (the event cut_resume), which
        takes it off this list.
    tissue_factor : What the tissue compliance carries from step to step: the refreshed strategy's stale
        factor (the matrix A it last factorised and the steps since,
        :class:`refsim.fem.compliance.StaleFactor`), or the exact strategy's partial-solve marks on PARDISO
        (the DoFs its analysis marked, :class:`refsim.fem.compliance.PartialSolveMarks`), or the fast
        strategy's last free displacement and its image under the last operator (where its next conjugate
        gradients start, :class:`refsim.fem.compliance.FreeMotionStart`); None for the strategies that carry
        nothing, and before the first step.

    The one-instrument shortcuts ``phase``, ``needle``, ``path``, ``cut_direction``, ``cut_strip``,
    ``tip_tet`` and ``tip_barycentric`` read the only instrument's fields; on a state with several instruments
    they raise (use :meth:`instrument`).
    """

    step: int
    time: float
    tissue: TissueState
    instruments: tuple[InstrumentState, ...]
    cut: CutSurface | None = None
    channels: tuple[Channel, ...] = ()
    cracks: tuple[Crack, ...] = ()
    tissue_factor: StaleFactor | PartialSolveMarks | FreeMotionStart | None = None

    @property
    def instrument_names(self) -> tuple[str, ...]:
        """The instruments' names, in order."""
        return tuple(instrument.name for instrument in self.instruments)

    def instrument(self, name: str) -> InstrumentState:
        """The state of the instrument called ``name``."""
        for instrument in self.instruments:
            if instrument.name == name:
                return instrument
        raise KeyError(
            f"no instrument {name!r} in the state (instruments: {', '.join(self.instrument_names)})"
        )

    def with_instrument(self, instrument: InstrumentState) -> SimulationState:
        """The state with ``instrument`` in place of the instrument of the same name."""
        names = self.instrument_names
        if instrument.name not in names:
            raise KeyError(
                f"no instrument {instrument.name!r} in the state (instruments: {', '.join(names)})"
            )
        instruments = tuple(
            instrument if name == instrument.name else old
            for name, old in zip(names, self.instruments, strict=True)
        )
        return evolved(self, instruments=instruments)

    def body_state(self, name: str):
        """The state of the body called ``name``: the tissue's, or an instrument's needle."""
        return self.tissue if name == TISSUE else self.instrument(name).needle

    @property
    def sole(self) -> InstrumentState:
        """The only instrument's state; a state with several raises (name one: :meth:`instrument`)."""
        if len(self.instruments) != 1:
            raise AttributeError(
                f"the state has {len(self.instruments)} instruments ({', '.join(self.instrument_names)}): "
                "name one with state.instrument(name)"
            )
        return self.instruments[0]


def _sole_field(name: str) -> property:
    def read(self: SimulationState):
        return getattr(self.sole, name)

    read.__doc__ = (
        f"The only instrument's ``{name}`` (one-instrument states only; see :attr:`SimulationState.sole`)."
    )
    return property(read)


for _name in ("phase", "needle", "path", "cut_direction", "cut_strip", "tip_tet", "tip_barycentric"):
    setattr(SimulationState, _name, _sole_field(_name))
del _name
