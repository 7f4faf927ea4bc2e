"""Pareto figures of the speed-against-error study, one per scene, from its study files (run.py writes them).

    python studies/pareto/plot.py [--output studies/pareto/output] [--docs docs]

x: mean wall time per step [ms]; y: relative error of the needle force history against the exact mode of the
same scene. One marker per option family; the line joins the Pareto front (no other option is both faster and
more accurate); the dashed line is the exact mode's time per step.
"""

from __future__ import annotations

import argparse
import json
import tomllib
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
OPTIONS = HERE / "options.toml"  # (run.py's option table: the families' order)


def pareto_front(times, errors) -> np.ndarray:
    """Indices of the non-dominated points (no other point has both a smaller time and a smaller error), by
    increasing time."""
    times, errors = np.asarray(times, dtype=float), np.asarray(errors, dtype=float)
    order = [i for i in np.argsort(times, kind="stable") if np.isfinite(times[i]) and np.isfinite(errors[i])]
    front, best = [], np.inf
    for index in order:
        if errors[index] < best:
            front.append(index)
            best = errors[index]
    return np.array(front, dtype=np.int64)


def step_times(runs) -> tuple[np.ndarray, str]:
    """Time per step of each run [ms] and what it is: the process CPU time when every run has it (robust to
    other processes sharing the cores), else the mean wall time."""
    cpu = np.asarray(runs.get("cpu_ms_per_step", []), dtype=float)
    if cpu.size and np.all(np.isfinite(cpu) | np.array([s != "complete" for s in runs["status"]])):
        return cpu, "CPU ms per step (process time, one BLAS thread)"
    return np.asarray(runs["ms_per_step"], dtype=float), "ms per step (mean wall time)"


def place_labels(axis, labels, xs, ys, *, avoid=(), fontsize: float = 6.0) -> list:
    """Label each point (xs[i], ys[i]) with labels[i], placing each label where it overlaps no other
    label, no marker, nor the artists of ``avoid`` (the legend), and stays inside the axes: the first free
    place among offsets tried nearest first (beside the point, then further away with a thin leader line).
    Labels are placed from the most crowded point out. Returns the annotations."""
    from matplotlib.transforms import Bbox

    figure = axis.figure
    figure.canvas.draw()
    renderer = figure.canvas.get_renderer()
    to_points = 72.0 / figure.dpi
    frame = axis.get_window_extent(renderer)
    centres = axis.transData.transform(np.column_stack([xs, ys]))
    marker = 4.0 / to_points * 0.75  # a 6-point marker's half width [px], and a little
    taken = [Bbox.from_extents(x - marker, y - marker, x + marker, y + marker) for x, y in centres]
    taken += [artist.get_window_extent(renderer) for artist in avoid]
    sizes = []
    for label in labels:
        probe = axis.text(0.0, 0.0, label, fontsize=fontsize)
        extent = probe.get_window_extent(renderer)
        sizes.append((extent.width, extent.height))
        probe.remove()
    crowding = [np.sum(np.hypot(*(centres - c).T) < 40.0) for c in centres]
    annotations = []
    for i in sorted(range(len(labels)), key=lambda k: -crowding[k]):
        width, height = sizes[i]
        x, y = centres[i]
        chosen = None
        for distance in (3.0, 9.0, 16.0, 26.0, 40.0, 60.0):
            for dx, dy in (
                (distance, distance - 2.0),
                (distance, -distance - height + 2.0),
                (-distance - width, distance - 2.0),
                (-distance - width, -distance - height + 2.0),
                (-0.5 * width, distance + 2.0),
                (-0.5 * width, -distance - height - 2.0),
                (distance + 2.0, -0.5 * height),
                (-distance - width - 2.0, -0.5 * height),
            ):
                box = Bbox.from_bounds(x + dx, y + dy, width, height)
                inside = frame.containsx(box.x0) and frame.containsx(box.x1)
                inside &= frame.containsy(box.y0) and frame.containsy(box.y1)
                if inside and not any(box.overlaps(other) for other in taken):
                    chosen = (dx, dy, distance)
                    break
            if chosen is not None:
                break
        if chosen is None:  # no free place: beside the point, as before
            chosen = (3.0, 3.0, 3.0)
        dx, dy, distance = chosen
        taken.append(Bbox.from_bounds(x + dx, y + dy, width, height))
        annotations.append(
            axis.annotate(
                labels[i],
                (xs[i], ys[i]),
                xytext=(dx * to_points, dy * to_points),
                textcoords="offset points",
                fontsize=fontsize,
                ha="left",
                va="bottom",
                arrowprops=None if distance < 9.0 else {"arrowstyle": "-", "lw": 0.4, "color": "0.4"},
            )
        )
    return annotations


def _figure(study: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = study["runs"]
    spec = json.loads(study["attributes"]["study"])
    families = spec.get("families", {})
    times, measure = step_times(runs)
    errors = np.asarray(runs["errors"]["force_history"], dtype=float)
    valid = np.isfinite(errors) & np.isfinite(times) & np.array([s == "complete" for s in runs["status"]])
    errors = np.where(valid, errors, np.nan)  # a failed run has no error; it is listed under the axes
    floor = np.nanmin(errors[errors > 0]) / 10 if np.any(errors > 0) else 1e-16
    shown = np.where(errors > 0, errors, floor)  # an error of exactly 0 is drawn at the floor
    figure, axis = plt.subplots(figsize=(6.4, 4.6))
    markers = "osD^v<>p*hX"
    # A family's marker and colour by its place in options.toml (then the study's other families), the same
    # in every scene's figure whichever families that scene has.
    listed = [option["family"] for option in tomllib.loads(OPTIONS.read_text(encoding="utf-8"))["option"]]
    styles = {family: number for number, family in enumerate(dict.fromkeys([*listed, *families.values()]))}
    for family in dict.fromkeys(families.get(label, "other") for label in runs["label"]):
        members = [
            i for i, label in enumerate(runs["label"]) if families.get(label, "other") == family and valid[i]
        ]
        if not members:
            continue
        number = styles.setdefault(family, len(styles))
        axis.loglog(
            times[members],
            shown[members],
            markers[number % len(markers)],
            color=f"C{number % 10}",
            label=family,
            ms=6,
        )
    front = pareto_front(times, errors)
    axis.loglog(times[front], shown[front], "k-", lw=0.8, alpha=0.6, label="Pareto front")
    reference = study["reference"]
    reference_time = (
        reference.get("cpu_ms_per_step" if measure.startswith("CPU") else "ms_per_step", np.nan)
        if reference
        else np.nan
    )
    if np.isfinite(reference_time):
        axis.axvline(reference_time, color="k", ls="--", lw=0.8, label="exact mode")
    failed = [label for i, label in enumerate(runs["label"]) if not valid[i]]
    xlabel = measure
    if failed:
        xlabel += f"\nnot shown, run failed: {', '.join(failed)}"
    axis.set_xlabel(xlabel)
    axis.set_ylabel("relative error of the needle force history")
    axis.set_title(
        f"{spec['scene']}: speed against error (reference: {reference['label'] if reference else '-'})",
        fontsize=10,
    )
    axis.grid(True, which="both", alpha=0.3)
    legend = axis.legend(fontsize=7)
    figure.tight_layout()
    shown_runs = np.flatnonzero(valid)
    place_labels(
        axis, [runs["label"][i] for i in shown_runs], times[shown_runs], shown[shown_runs], avoid=[legend]
    )
    figure.savefig(path, dpi=110)
    plt.close(figure)


def solve_share(study_path: Path, file: str) -> float:
    """Share of the constraint solve in the wall time of a step of a run [-] (its stage_seconds)."""
    from refsim.io import read_results

    seconds = read_results(Path(study_path).parent / file).stage_seconds
    total = sum(float(np.nansum(values)) for values in seconds.values())
    return float(np.nansum(seconds["solve"])) / total if total > 0 and "solve" in seconds else float("nan")


def timing_noise(runs, times) -> tuple[list[str], float]:
    """Labels of the runs with the same force history as the first ("paper") one (relative error equal to
    1e-9: the same iterations, the same work) and the spread (max − min)/min of their times [-]."""
    errors = np.asarray(runs["errors"]["force_history"], dtype=float)
    same = [
        i
        for i in range(len(errors))
        if np.isfinite(errors[i])
        and np.isfinite(times[i])
        and abs(errors[i] - errors[0]) <= 1e-9 * max(abs(errors[0]), 1e-300)
    ]
    if len(same) < 2:
        return [runs["label"][i] for i in same], float("nan")
    chosen = np.asarray(times, dtype=float)[same]
    return [runs["label"][i] for i in same], float((chosen.max() - chosen.min()) / chosen.min())


def main(argv: list[str] | None = None) -> None:
    from refsim.sweep import read_study

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", default=str(HERE / "output"))
    parser.add_argument("--docs", default=str(HERE.parents[1] / "docs"))
    args = parser.parse_args(argv)
    docs = Path(args.docs)
    (docs / "figures").mkdir(parents=True, exist_ok=True)
    lines = [
        "# Speed against error: the Pareto study",
        "",
        "",  # the generation line, with the number of runs: filled in below
        "",
        "    PYTHONPATH=. python studies/pareto/run.py && PYTHONPATH=. python studies/pareto/plot.py",
        "",
        "A run already complete is not run again: delete `studies/pareto/output/` after changing the code. "
        "Every fast option of "
        "`studies/pareto/options.toml` is one run of the scene; the error is the relative L2 difference of "
        'the needle force history from the exact mode of the same scene (`solver.method = "exact"`, '
        "tolerance 1e-10), ‖F − F_exact‖/‖F_exact‖ over all steps; time is the process CPU time per step "
        "of the worker that ran it (one BLAS thread; measured from the first to the last step, after an "
        "untimed warm-up run that compiles the kernels), which other processes sharing the cores do not "
        "inflate as they do the wall time (also given). Add an option by adding an `[[option]]` to "
        "options.toml.",
        "",
        "The family *compliance strategy* (`compliance.strategy`, docs/speed.md) trades the tissue's "
        "compliance: `precomputed` and `fast` use the rest compliance rotated per node, H R C₀ Rᵀ Hᵀ, for"
        " W and the correction instead of the current H A⁻¹ Hᵀ. That is exact for rigid motions of the "
        "rest shape and its error grows with the tissue's strain, so it costs little while the needle "
        "only indents or inserts (cube) and more once the tissue is cut and pulled (cube_cut), with the "
        "same events in both. `fast` computes that same W without assembling or factorising any matrix "
        "during the run (free motion by CG on the co-rotated operator, preconditioned by the rotated rest"
        " factor), so its errors are `precomputed`'s to the CG tolerance and it takes a fraction of its "
        "time; the constraint solve's options (tolerance, cap) act on another share of the step and "
        "combine with it.",
        "",
    ]
    run_count = 0
    for path in sorted(Path(args.output).glob("*.h5")):
        study = read_study(path)
        run_count += len(study["runs"]["label"]) + 1  # the options' runs and the exact reference
        spec = json.loads(study["attributes"]["study"])
        figure = docs / "figures" / f"{study['attributes']['name']}.png"
        _figure(study, figure)
        runs = study["runs"]
        names = spec["quantities"]
        times, measure = step_times(runs)
        reference = study["reference"]
        same, spread = timing_noise(runs, times)
        shares = {
            label: solve_share(path, file)
            for label, file in (("exact mode", reference["file"]), (runs["label"][0], runs["file"][0]))
        }
        lines += [
            f"## {spec['scene']}",
            "",
            f"Exact mode: {reference.get('cpu_ms_per_step', np.nan):.1f} CPU ms, "
            f"{reference['ms_per_step']:.1f} wall ms per step. Time axis: {measure}. "
            "The constraint solve takes "
            + ", ".join(f"{100 * v:.1f} % of a step ({k})" for k, v in shares.items())
            + " (wall time of the stages): the tolerance and the cap act on that share only. "
            f"Timing noise: {', '.join(same)} gave the same force history (the same work) and their times "
            f"spread by {100 * spread:.0f} %; smaller differences are not measured.",
            "",
            "| option | family | CPU ms/step | wall ms/step | force history error | "
            + " | ".join(f"error {n}" for n in names)
            + " |",
            "|---" * (5 + len(names)) + "|",
        ]
        front = set(pareto_front(times, runs["errors"]["force_history"]).tolist())
        for i, label in enumerate(runs["label"]):
            mark = " **(front)**" if i in front else ""
            cells = " | ".join(f"{runs['errors'][n][i]:.2e}" for n in names)
            if runs["status"][i] != "complete":
                mark = f" (failed: {runs['error'][i][:120]})"
            lines.append(
                f"| {label}{mark} | {spec.get('families', {}).get(label, '')} | "
                f"{runs.get('cpu_ms_per_step', [np.nan] * len(times))[i]:.1f} | {runs['ms_per_step'][i]:.1f} "
                f"| "
                f"{runs['errors']['force_history'][i]:.2e} | {cells} |"
            )
        lines += ["", f"![{spec['scene']}](figures/{figure.name})", ""]
    lines[2] = (
        "Generated by `studies/pareto/plot.py` from `studies/pareto/run.py`. Regenerate (one line; "
        f"{run_count} runs, one worker per core by default, `--workers 1` for one; each option's time is its "
        "own worker's process CPU time):"
    )
    (docs / "pareto.md").write_text("\n".join(lines) + "\n", encoding="utf-8")
    print(f"wrote {docs / 'pareto.md'} and its figures")


if __name__ == "__main__":
    main()
