"""Where a needle is in the tissue: the stretches of its centreline inside the tissue mesh (one per part of
the tissue it is through: layers with a gap between them), located on a configuration of the tissue.

What the cut's rows are sampled along (:mod:`refsim.constraints.cut`), what the cut start's inserted length
L_in and the strip's columns are measured on (:mod:`refsim.simulation.cut_events`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["inserted_arc", "inserted_span", "inserted_stretches", "stretch_length", "stretch_span"]


def inserted_stretches(
    needle,
    locator,
    spacing: float,
    *,
    refinement: int = 16,
    tip_outside: bool = False,
    confirm_out: bool = False,
) -> tuple[tuple[float, float], ...]:
    """The stretches of the needle's centreline that lie in the tissue mesh (``locator``, a
    `refsim.geometry.TetLocator` on the configuration of ``needle``): (entry, end) arc lengths [m] of each,
    ordered from the needle's base to its tip, each end to ``spacing / refinement``; empty when no sample of
    the needle lies in the tissue.

    The needle is sampled every ``spacing`` from the tip to the base; a stretch is a run of samples in the
    tissue, so parts of the tissue closer than ``spacing`` along the needle may be read as one. The deepest
    stretch ends at the tip while the tip is in the tissue, else where the centreline leaves the tissue
    through a far face (the part beyond, in the air, is not inserted); each other one where the needle leaves
    its part of the tissue into a gap (a wall over an organ: the needle through both, a gap between them).

    ``tip_outside``: the tip is outside the tissue by the tip's rules (`InstrumentState.tip_tet` −1: a tip
    out of a far face pressed on the surface of another layer it has not punctured yet is held outside,
    wherever round-off locates it), so a stretch ending at the tip is its indentation of that surface, not a
    stretch of the needle in the tissue: it is left out.

    ``confirm_out``: when no sample lies in the tissue, the needle is sampled again every ``spacing /
    refinement`` before the answer is none: a part of it in the tissue shorter than ``spacing``, between two
    samples (a bent needle's shaft dipping into the surface), is no withdrawal (what the events read).
    """
    if confirm_out:
        found = inserted_stretches(needle, locator, spacing, refinement=refinement, tip_outside=tip_outside)
        if found:
            return found
        return inserted_stretches(
            needle, locator, spacing / refinement, refinement=refinement, tip_outside=tip_outside
        )
    length = needle.length
    arcs = np.arange(length, -0.5 * spacing, -spacing)  # from the tip to the base, every spacing
    found, _ = locator.locate(needle.points(np.clip(arcs, 0.0, length)))
    inside = found >= 0
    stretches = []
    start = 0  # where the search for the next stretch begins, among the samples from the tip
    while True:  # once per stretch (a part of the tissue the needle is in), from the tip's up
        deeper = np.flatnonzero(inside[start:])
        if deeper.size == 0:
            break
        last = start + int(deeper[0])  # the stretch's deepest sample; the one before it (deeper) is out
        if last == 0:
            end = float(length)
        else:
            fine = np.linspace(max(arcs[last], 0.0), arcs[last - 1], refinement + 1)
            located, _ = locator.locate(needle.points(fine))
            out = np.flatnonzero(located < 0)
            end = float(fine[max(int(out[0]) - 1, 0)]) if out.size else float(arcs[last - 1])
        outside = np.flatnonzero(~inside[last:])
        if outside.size == 0:
            stretches.append((0.0, end))
            break
        first = last + int(outside[0])
        # Refine between the first sample outside and the last inside.
        fine = np.linspace(max(arcs[first], 0.0), arcs[first - 1], refinement + 1)
        located, _ = locator.locate(needle.points(fine))
        outside_fine = np.flatnonzero(located < 0)
        lead = int(outside_fine[-1]) + 1 if outside_fine.size else 0
        stretches.append((float(fine[min(lead, refinement)]), end))
        start = first
    if tip_outside and stretches and stretches[0][1] >= length:
        stretches = stretches[1:]  # (the list runs from the tip's stretch up)
    return tuple(reversed(stretches))


def inserted_span(needle, locator, spacing: float, *, refinement: int = 16) -> tuple[float, float]:
    """Arc lengths [m] where the needle enters the tissue and where its inserted part ends
    (:func:`stretch_span` of :func:`inserted_stretches`).

    This, not the projection of the entry point, bounds the inserted part of the needle while it cuts: a
    tilted needle pushed sideways moves away from its entry point along the tissue surface, and the entry
    point's projection then lies up to stroke × tan(tilt) above the tissue (2.2 mm for a 30° needle and a 5 mm
    stroke; rows placed there pulled the needle onto the tissue surface: 10.8 N against 3.6 N). And a needle
    through a layer, its tip out of its far face, still cuts along the layer's thickness (ended at the tip,
    the span was empty once the tip left, and the needle crossed intact tissue with no force).
    """
    return stretch_span(inserted_stretches(needle, locator, spacing, refinement=refinement), needle.length)


def stretch_span(stretches, length: float) -> tuple[float, float]:
    """The entry of the first of ``stretches`` ((entry, end) arc lengths [m] from the base to the tip, as
    :func:`inserted_stretches` gives them) and the end of the deepest; (``length``, ``length``), the needle's
    length [m], when there is none (the needle is out of the tissue)."""
    if not stretches:
        return float(length), float(length)
    return stretches[0][0], stretches[-1][1]


def inserted_arc(needle, locator, spacing: float, *, refinement: int = 16) -> float:
    """Arc length [m] where the needle enters the tissue (:func:`inserted_span`'s first value)."""
    return inserted_span(needle, locator, spacing, refinement=refinement)[0]


def stretch_length(stretches, start: float = -np.inf, end: float = np.inf) -> float:
    """The needle's length in the tissue [m]: the sum of ``stretches`` ((entry, end) arc lengths, as
    :func:`inserted_stretches` gives them) within the arc lengths [start, end]."""
    return float(sum(max(min(b, end) - max(a, start), 0.0) for a, b in stretches))
