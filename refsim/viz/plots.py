"""Force plots of a run with matplotlib (Agg backend, no display), read from the results file only.

The force shown is the force on the needle base, taken quasi-statically as the opposite of the force of the
tissue on the needle: F_base = −F, with F the force profile (``Results.profile_force``: each step's end force,
``steps/needle_force`` = Σ λ n, except in a puncture step, where it is the force at the tip contact's give-way
within the step, ``steps/event_needle_force``, the profile's peak). It is split along the unit direction t of
the base segment (base towards tip): axial F_base·t (positive when the tissue resists insertion) and lateral
‖F_base − (F_base·t) t‖.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

__all__ = [
    "plot_result",
    "event_rows",
    "force_figure",
    "force_panels",
    "base_force_components",
    "lateral_stroke",
    "EVENT_STYLES",
    "LATERAL_STROKE_MIN",
]

logger = logging.getLogger(__name__)

#: Colour and line style of each event's marker; other events get a grey dotted line.
EVENT_STYLES = {
    "puncture": ("#2ca02c", "--"),
    "cut_start": ("#d62728", "--"),
    "tear": ("#ff7f0e", ":"),
    "retraction": ("#9467bd", ":"),
    "withdrawal": ("#8c564b", "--"),
    "reentry": ("#17becf", "--"),
}


def base_force_components(results) -> tuple[np.ndarray, np.ndarray]:
    """Axial and lateral components [N] of the force on the needle base, each shape (s,) (see module
    notes)."""
    axial, lateral = results.axial_lateral_force()
    return -axial, lateral


def lateral_stroke(results) -> np.ndarray:
    """Lateral stroke of the needle base [m], shape (s,): the norm of the base displacement from its first
    recorded position, perpendicular to the needle's initial base axis t₀: ‖(I − t₀ t₀ᵀ)(b − b₀)‖."""
    axis = results.needle_axis(at="base")[0]
    moved = results.base_position - results.base_position[0]
    return np.linalg.norm(moved - np.outer(moved @ axis, axis), axis=1)


#: A motion is lateral when the base moves at least this far sideways [m] (an insertion guided along its
#: axis moves it by round-off only).
LATERAL_STROKE_MIN = 1e-4


def _mark_events(axis, results, positions: np.ndarray) -> None:
    """Vertical lines at the events, one colour and style per kind (``EVENT_STYLES``); ``positions`` maps
    each step index to the abscissa. No text on the data: the kinds are named once, in the figure's legend,
    and their values listed in the event table beside the panels (:func:`event_rows`)."""
    for event in results.events:
        where = np.flatnonzero(results.step == event.step)
        if where.size == 0 or not np.isfinite(positions[where[0]]):
            continue
        color, style = EVENT_STYLES.get(event.name, ("0.5", ":"))
        axis.axvline(positions[where[0]], color=color, linestyle=style, linewidth=1.0)


def _value_range(values: np.ndarray, unit: str) -> str:
    """A value, or the range of several, with 4 significant digits of the largest and the same decimals."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return "-"
    largest = float(np.abs(finite).max())
    decimals = max(0, 3 - int(np.floor(np.log10(largest)))) if largest > 0 else 0
    if np.ptp(finite) == 0.0:
        return f"{finite[0]:.{decimals}f} {unit}"
    return f"{finite.min():.{decimals}f} - {finite.max():.{decimals}f} {unit}"


def event_rows(results) -> list[tuple[str, str, str, str]]:
    """One row per event kind, in order of first occurrence: (kind, count, steps, triggering value with its
    unit, the recorded event's ``unit``: N, or N/m for the energy law's cut_start)."""
    kinds: dict[str, list] = {}
    for event in results.events:
        kinds.setdefault(event.name, []).append(event)
    rows = []
    for name, events in kinds.items():
        steps = [e.step for e in events]
        where = f"{steps[0]}" if len(steps) == 1 else f"{steps[0]} - {steps[-1]}"
        units = {getattr(e, "unit", "N") for e in events}
        values = ", ".join(
            _value_range(np.array([e.force for e in events if getattr(e, "unit", "N") == u]), u)
            for u in sorted(units)
        )
        rows.append((name, str(len(events)), where, values))
    return rows


def plot_result(path, output_png, *, dpi: int = 120) -> Path:
    """Plot the force on the needle base, with the events marked, in panels chosen by what the run did.

    Panels (:func:`force_figure`): when the base moves sideways (the lateral stroke, :func:`lateral_stroke`,
    reaches ``LATERAL_STROKE_MIN``), against time and against the lateral stroke [mm] from the start of the
    lateral motion; otherwise against the tip depth from the puncture point [mm] (when the needle punctured)
    and against time, the phases shaded. Events (puncture, cut_start, tear, ...) are vertical lines, one
    colour per kind named once in the legend below the panels; the table at the right lists each kind's
    count, steps and triggering values with their unit.

    Parameters
    ----------
    path : Results file.
    output_png : PNG to write (parent folders are created).
    dpi : Resolution of the PNG.

    Returns
    -------
    The PNG's path.
    """
    from refsim.io import read_results

    results = read_results(path)
    figure = force_figure(results)
    output_png = Path(output_png)
    output_png.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(output_png, dpi=dpi)
    logger.info("plotted %s to %s", results.path, output_png)
    return output_png


def force_panels(results) -> tuple[str, ...]:
    """The panels of the force figure for what the run did: ("time", "stroke") for a lateral motion,
    ("depth", "time") after a puncture, ("time",) otherwise."""
    if lateral_stroke(results).max() >= LATERAL_STROKE_MIN:
        return ("time", "stroke")
    if np.any(np.isfinite(results.tip_depth())):
        return ("depth", "time")
    return ("time",)


def force_figure(results, figure=None):
    """The figure of :func:`plot_result` for a :class:`refsim.io.Results` (a matplotlib Figure, Agg canvas):
    the panels of :func:`force_panels`, an event table at the right, one legend below the panels. A run of
    several instruments gets one such row per instrument (its own force, events and phases), in order.
    ``figure``: draw one instrument's row into this (sub)figure.

    Raises
    ------
    ValueError
        When the results hold no step.
    """
    # A bare Figure renders with the Agg canvas and never touches pyplot's global state or a display.
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    if results.step_count == 0:
        raise ValueError(f"{results.path}: the file holds no step to plot")
    names = tuple(getattr(results, "instrument_names", ("needle",)))
    if figure is None and len(names) > 1:
        views = results.instruments
        width = max(5.2 * len(force_panels(view)) + 3.6 for view in views)
        figure = Figure(figsize=(width, 4.8 * len(views)), layout="constrained")
        for view, part in zip(views, figure.subfigures(len(views), 1), strict=True):
            force_figure(view, figure=part)
        return figure
    axial, lateral = base_force_components(results)
    panels = force_panels(results)
    if figure is None:
        figure = Figure(figsize=(5.2 * len(panels) + 3.6, 4.8), layout="constrained")
    grid = figure.add_gridspec(1, len(panels) + 1, width_ratios=[1.0] * len(panels) + [0.62])
    for column, panel in enumerate(panels):
        axis = figure.add_subplot(grid[0, column])
        if panel == "depth":
            abscissa = 1e3 * results.tip_depth()
            axis.set_xlabel("tip depth from the puncture point [mm]")
            axis.set_title("against depth")
        elif panel == "time":
            abscissa = results.time
            _shade_phases(axis, results)
            axis.set_xlabel("time [s]")
            axis.set_title("against time")
        else:  # the steps from the start of the lateral motion (1 % of its largest value)
            stroke = lateral_stroke(results)
            start = int(np.argmax(stroke >= 0.01 * stroke.max()))
            abscissa = np.where(np.arange(stroke.size) >= start, 1e3 * stroke, np.nan)
            axis.set_xlabel("lateral stroke of the needle base [mm]")
            axis.set_title("against the lateral stroke")
        axis.plot(abscissa, axial, color="#1f77b4")
        axis.plot(abscissa, lateral, color="#ff7f0e")
        _mark_events(axis, results, abscissa)
        axis.set_ylabel("force on the needle base [N]")
        axis.grid(True, alpha=0.3)

    handles = [
        Line2D([], [], color="#1f77b4", label="axial force"),
        Line2D([], [], color="#ff7f0e", label="lateral force"),
    ]
    if "time" in panels:
        present = {results.phase_names[code] for code in np.unique(results.phase)}
        handles += [
            Patch(color=color, alpha=0.15, label=f"{name} phase")
            for name, color in _PHASE_COLORS.items()
            if name in present
        ]
    rows = event_rows(results)
    for name, count, _, _ in rows:
        color, style = EVENT_STYLES.get(name, ("0.5", ":"))
        handles.append(Line2D([], [], color=color, linestyle=style, label=f"{name} ({count})"))
    figure.legend(handles=handles, loc="outside lower center", ncols=min(len(handles), 7), fontsize=8)

    table = figure.add_subplot(grid[0, -1])
    table.set_axis_off()
    table.set_title("events", fontsize=10)
    if rows:
        cells = table.table(
            cellText=[list(row) for row in rows],
            colLabels=["kind", "count", "step", "triggering value"],
            loc="upper center",
            cellLoc="left",
            colLoc="left",
        )
        cells.auto_set_font_size(False)
        cells.set_fontsize(7.5)
        cells.auto_set_column_width(list(range(4)))
        cells.scale(1.0, 1.3)
    else:
        table.text(0.5, 0.9, "none", ha="center", va="top", transform=table.transAxes)
    if np.isfinite(results.event_needle_force).all(axis=1).any():
        table.text(
            0.5,
            0.02,
            "puncture step: the force at the\ntip contact's give-way in the step",
            ha="center",
            va="bottom",
            fontsize=7.5,
            transform=table.transAxes,
        )
    status = "" if results.complete else "  (interrupted run)"
    whose = "the needle" if len(names) == 1 and names[0] == "needle" else f"{names[0]}'s needle"
    figure.suptitle(f"{results.scene_name}: force on {whose} base{status}")
    return figure


_PHASE_COLORS = {"insertion": "#2ca02c", "cutting": "#d62728"}


def _shade_phases(axis, results) -> None:
    """Light background bands for the insertion and cutting phases (named in the figure's legend)."""
    phase = results.phase
    changes = np.flatnonzero(np.diff(phase)) + 1
    starts = np.concatenate([[0], changes])
    ends = np.concatenate([changes, [phase.size]])
    dt = float(np.median(np.diff(results.time))) if results.time.size > 1 else 0.0
    for start, end in zip(starts, ends, strict=False):
        name = results.phase_names[phase[start]]
        if name in _PHASE_COLORS:
            axis.axvspan(
                results.time[start] - dt, results.time[end - 1], color=_PHASE_COLORS[name], alpha=0.07
            )
