"""Force plots of a run with matplotlib (Agg backend, no display), read from the results file only.

The force shown is the force on the needle base, taken quasi-statically as the opposite of the force of the
tissue on the needle (``steps/needle_force`` = Σ λ n): F_base = −F. It is split along the unit direction t of
the base segment (base towards tip): axial F_base·t (positive when the tissue resists insertion) and lateral
‖F_base − (F_base·t) t‖.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

__all__ = [
    "plot_result",
    "force_figure",
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


def _mark_events(axis, results, positions: np.ndarray, *, label: bool, annotate: bool = True) -> None:
    """Vertical lines at the events; ``positions`` maps each step index to the abscissa. Each event with a
    force gets its own label beside its line ("tear 2.27 N"), so every tear shows its own force."""
    seen: set[str] = set()
    transform = axis.get_xaxis_transform()
    for number, event in enumerate(results.events):
        where = np.flatnonzero(results.step == event.step)
        if where.size == 0 or not np.isfinite(positions[where[0]]):
            continue
        color, style = EVENT_STYLES.get(event.name, ("0.5", ":"))
        axis.axvline(
            positions[where[0]],
            color=color,
            linestyle=style,
            linewidth=1.0,
            label=event.name if label and event.name not in seen else None,
        )
        seen.add(event.name)
        if annotate:
            text = event.name if np.isnan(event.force) else f"{event.name} {event.force:.2f} N"
            # Staggered heights so that labels of close events do not overlap.
            axis.text(
                positions[where[0]],
                0.97 - 0.09 * (number % 4),
                text,
                transform=transform,
                rotation=90,
                ha="right",
                va="top",
                fontsize=7,
                color=color,
                bbox={"facecolor": "white", "alpha": 0.75, "edgecolor": "none", "pad": 0.6},
            )


def plot_result(path, output_png, *, dpi: int = 120) -> Path:
    """Plot the force on the needle base against tip depth, time and, when the base moves sideways, the
    lateral stroke, with the events marked.

    Left: axial and lateral force against the tip depth along the needle from the puncture point [mm]
    (omitted, with a note, when the needle never punctured). Middle: the same against time [s], with the
    phases shaded. Right, when the lateral stroke (:func:`lateral_stroke`) reaches ``LATERAL_STROKE_MIN``: the
    same against the lateral stroke [mm], from the start of the lateral motion. Events (puncture, cut_start,
    tear, ...) are vertical lines, each labelled with its own triggering force.

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


def force_figure(results):
    """The figure of :func:`plot_result` for a :class:`refsim.io.Results` (a matplotlib Figure, Agg canvas).

    Raises
    ------
    ValueError
        When the results hold no step.
    """
    # A bare Figure renders with the Agg canvas and never touches pyplot's global state or a display.
    from matplotlib.figure import Figure

    if results.step_count == 0:
        raise ValueError(f"{results.path}: the file holds no step to plot")
    axial, lateral = base_force_components(results)
    depth_mm = 1e3 * results.tip_depth()

    stroke = lateral_stroke(results)
    lateral_motion = bool(stroke.max() >= LATERAL_STROKE_MIN)
    panels = 3 if lateral_motion else 2
    figure = Figure(figsize=(6.0 * panels, 4.6), layout="constrained")
    axes = figure.subplots(1, panels)
    by_depth, by_time = axes[0], axes[1]

    if np.all(np.isnan(depth_mm)):
        by_depth.text(
            0.5, 0.5, "no puncture: depth undefined", ha="center", va="center", transform=by_depth.transAxes
        )
    else:
        by_depth.plot(depth_mm, axial, color="#1f77b4", label="axial")
        by_depth.plot(depth_mm, lateral, color="#ff7f0e", label="lateral")
        _mark_events(by_depth, results, depth_mm, label=False, annotate=not lateral_motion)
    by_depth.set_xlabel("tip depth from the puncture point [mm]")
    by_depth.set_ylabel("force on the needle base [N]")
    by_depth.set_title("against depth")
    by_depth.grid(True, alpha=0.3)
    by_depth.legend(loc="upper left", fontsize=8)

    by_time.plot(results.time, axial, color="#1f77b4", label="axial")
    by_time.plot(results.time, lateral, color="#ff7f0e", label="lateral")
    _shade_phases(by_time, results)
    _mark_events(by_time, results, results.time, label=True)
    by_time.set_xlabel("time [s]")
    by_time.set_ylabel("force on the needle base [N]")
    by_time.set_title("against time")
    by_time.grid(True, alpha=0.3)
    by_time.legend(loc="upper left", fontsize=8)

    if lateral_motion:
        # Against the lateral stroke: the steps from the start of the lateral motion (1 % of its largest
        # value).
        by_stroke = axes[2]
        moving = stroke >= 0.01 * stroke.max()
        start = int(np.argmax(moving))
        stroke_mm = np.where(np.arange(stroke.size) >= start, 1e3 * stroke, np.nan)
        by_stroke.plot(stroke_mm, axial, color="#1f77b4", label="axial")
        by_stroke.plot(stroke_mm, lateral, color="#ff7f0e", label="lateral")
        _mark_events(by_stroke, results, stroke_mm, label=False)
        by_stroke.set_xlabel("lateral stroke of the needle base [mm]")
        by_stroke.set_ylabel("force on the needle base [N]")
        by_stroke.set_title("against the lateral stroke")
        by_stroke.grid(True, alpha=0.3)
        by_stroke.legend(loc="upper left", fontsize=8)

    status = "" if results.complete else "  (interrupted run)"
    figure.suptitle(f"{results.scene_name}: force on the needle base{status}")
    return figure


def _shade_phases(axis, results) -> None:
    """Light background bands for the insertion and cutting phases."""
    colors = {"insertion": "#2ca02c", "cutting": "#d62728"}
    phase = results.phase
    changes = np.flatnonzero(np.diff(phase)) + 1
    starts = np.concatenate([[0], changes])
    ends = np.concatenate([changes, [phase.size]])
    dt = float(np.median(np.diff(results.time))) if results.time.size > 1 else 0.0
    labelled: set[str] = set()
    for start, end in zip(starts, ends, strict=False):
        name = results.phase_names[phase[start]]
        if name in colors:
            axis.axvspan(
                results.time[start] - dt,
                results.time[end - 1],
                color=colors[name],
                alpha=0.07,
                label=None if name in labelled else f"{name} phase",
            )
            labelled.add(name)
