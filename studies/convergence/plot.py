"""Figures and page of the convergence study, from its study files only (run.py writes them).

    python studies/convergence/plot.py [--output studies/convergence/output] [--docs docs]

One figure per study (docs/figures/convergence_NAME.png): per quantity, the values against the refinement
measure h with the Richardson-extrapolated value and its GCI band (top), and |f − f_ext| against h on log-log
axes with the least-squares fitted slope (bottom). The page docs/convergence.md tabulates the observed orders,
extrapolated values and GCIs.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
MEASURE_LABEL = {
    "mesh.cells": "h = 1/cells",
    "insertion.spacing": "d_i [m]",
    "cutting.point_spacing": "d_c [m]",
}

# : Values theory gives for a quantity of a scene, (value, label, what it is): drawn in the figure and
# tabulated. : cube_cut: the needle is inserted to L = 17 mm (base at z = 0.403 m, needle 0.32 m, top face z =
# 0.1 m), then : moved 8 mm sideways; the energy law's steady cut needs F = G_c L (G_c = 200 J/m²), and the
# cut swept by the : shaft from the cut start (0.4 mm of stroke) to the end is about L × 7.6 mm (in rest
# coordinates).
REFERENCES = {
    ("cube_cut", "lateral_force@end"): (200.0 * 0.017, "G_c L", "G_c L, energy balance of a steady cut"),
    ("cube_cut", "cut_area"): (0.017 * 0.0076, "swept rectangle", "L × (8 mm − 0.4 mm), the swept rectangle"),
}

# : What each study's quantities are and what theory says of their order (text of the page; no measured
# numbers, : which the tables give).
NOTES = {
    "cube_spacing": (
        "The cube is punctured within the step of the first contact (0.1 mm of travel per step reaches f_p), "
        "so "
        "`puncture_force` is the threshold f_p itself under any refinement. After the puncture the tip cuts "
        "at "
        "f_cut = 0.5 N and the shaft's friction on the channel's grip (Lamé, δ_r = 20 µm) adds μ 2π r p₀ per "
        "metre inserted (docs/coupling.md): `axial_force@t=1.9` (the base stops) is about 0.58 N, and "
        "`needle_force@end` is the load the stuck shaft holds after the base stops (static friction, stick "
        "anchors: docs/coupling.md). Each insertion point carries the grip of a length d_i, with "
        "full "
        "weights at both ends of the inserted length (a rectangle rule): O(d_i) in theory."
    ),
    "cube_mesh": (
        "As for cube_spacing, on 3–8 cells per axis. With the paper's thick needle (r = 8 mm) the ring "
        "radius "
        "max(r, h) of the coupling is h on all these meshes, above r: the levels are not in the asymptotic "
        "range of the ring on the needle's surface (docs/coupling.md), and the differences between levels do "
        "not decrease (divergent in the table) although they stay below 0.5 %."
    ),
    "cube_cut_spacing": (
        "`lateral_force@t=2.03` is the shaft's lateral load 0.3 mm into the stroke, before the cut starts: "
        "the "
        "coupling rows are a quadrature of the shaft's distributed coupling with weight d_i per point and "
        "full "
        "weights at both ends (a rectangle rule), whose error is O(d_i); `tests/sweep/"
        "test_insertion_spacing_order.py` asserts p = 1 ± 0.1 on 4 and 6 cells and two entry points (slow). "
        "`needle_force@cut_start` and `lateral_stroke@cut_start` are read at the first step where the "
        "lateral load per inserted length reaches G_c, a step solved again with the cut's rows "
        '(docs/cutting.md, "When an event takes effect"): its force lies between '
        "the step before's and G_c L. The stroke advances 0.1 mm per step, so both are quantised by the step "
        "and converge only with dt: an order in d_i is not defined for them. The quantities after the cut "
        "start inherit that quantisation (and the tears, discrete events)."
    ),
    "cube_cut_point_spacing": (
        "d_c acts only after the cut start: the quantities before it are the same in every run (converged). "
        "The cut area and the final lateral load are compared with the energy balance and the swept "
        "rectangle "
        "(dotted lines in the figure; the table's last columns)."
    ),
    "cube_cut_mesh": (
        "The mesh changes the tissue's stiffness and the cut start step. P1 elements give O(h) in energy and "
        "O(h²) in L² for smooth solutions (asserted in `tests/sweep/test_mesh_convergence.py`); a needle "
        "load is "
        "a line load, singular at the shaft, for which no such order holds, and the coupling's sub-grid "
        "compliance depends on h by design (docs/coupling.md). With the paper's thick needle (r = 8 mm) the "
        "ring radius max(r, h) of the coupling is h = 100 mm/cells up to 8 cells and about r from 12 cells "
        "on: "
        "the two regimes show as a jump of the loads between 8 and 12 cells, so no three levels here are in "
        "one asymptotic range."
    ),
    "liver_rigid_spacing": (
        "Coarse phantom (1,735 tets), the whole 6 s trajectory: about 1 min a run on one core, so no part of "
        "the trajectory had to be cut off. The puncture force is the threshold (0.5 N). The forces at t = "
        "0.9 s "
        "(the insertion; at G_c = 30.5 J/m², the study's, the cut starts between 0.89 and 1.03 s across the "
        "levels, so at the finest level t = 0.9 s is a step after it and its force is no longer the "
        "insertion's alone: the sequence is then not monotone) are of the coupling's quadrature, first order "
        "in d_i in theory. "
        "The cut starts earlier as d_i is refined; `time@cut_start` is a multiple of dt = 10 ms, so its "
        "order "
        "is measurable only while the levels differ by several steps (see the table), and the force and "
        "stroke at the cut start are read at that step. The cut area and the force at 4 s (the end of the "
        "insertion) follow the cut; the force at the end follows the breathing and the tears after it "
        "(discrete events)."
    ),
    "liver_rigid_point_spacing": (
        "As liver_rigid_spacing, d_c swept: the quantities before the cut start do not depend on d_c."
    ),
    "liver_flexible_spacing": (
        "The flexible needle bends and does not cut: every quantity is of the insertion (the coupling's "
        "quadrature in d_i, first order in theory) and of the breathing after it."
    ),
}


def _relative_change(row: dict) -> str:
    """|f1 − f2|/|f1| of a convergence row, as text (an order from differences this small is not
    asymptotic)."""
    f1, f2 = row["f"][0], row["f"][1]
    return f"{abs(f1 - f2) / abs(f1):.2e}" if f1 != 0 and math.isfinite(f1) and math.isfinite(f2) else "nan"


def _reference(spec: dict, name: str):
    return REFERENCES.get((spec["scene"], name))


def _figure(study: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    runs = study["runs"]
    spec = json.loads(study["attributes"]["study"])
    key = spec["sweep"][0]["key"]
    rows = {row["quantity"]: row for row in study["convergence"]}
    names = spec["quantities"]
    h = np.asarray(runs["spacing"][key], dtype=float)
    complete = np.array([status == "complete" for status in runs["status"]])
    figure, axes = plt.subplots(2, len(names), figsize=(3.3 * len(names), 5.6), squeeze=False)
    for column, name in enumerate(names):
        f = np.asarray(runs["quantities"][name], dtype=float)
        keep = complete & np.isfinite(f) & np.isfinite(h)
        top, bottom = axes[0, column], axes[1, column]
        top.semilogx(h[keep], f[keep], "o-")
        top.set_title(name, fontsize=9)
        top.set_xlabel(MEASURE_LABEL.get(key, key), fontsize=8)
        row = rows.get(name)
        reference = _reference(spec, name)
        if reference is not None:
            top.axhline(reference[0], color="C2", ls=":", lw=1.0, label=reference[1])
            top.legend(fontsize=7)
        if row is not None and math.isfinite(row["extrapolated"]):
            top.axhline(row["extrapolated"], color="k", ls="--", lw=0.8, label="f_ext")
            if math.isfinite(row["uncertainty"]):
                f1 = row["f"][0]
                top.axhspan(
                    f1 - row["uncertainty"], f1 + row["uncertainty"], color="C1", alpha=0.2, label="f1 ± GCI"
                )
            if row["kind"] == "converged":  # agreed to round-off: show the value, not a 1e-12 band
                span = max(1e-3 * abs(f1), row["uncertainty"], 1e-300)
                top.set_ylim(f1 - span, f1 + span)
            top.ticklabel_format(axis="y", useOffset=False)
            top.legend(fontsize=7)
        if row is not None and row["kind"] == "monotone":
            error = np.abs(f[keep] - row["extrapolated"])
            positive = error > 0
            bottom.loglog(h[keep][positive], error[positive], "o")
            if math.isfinite(row["fitted_order"]):
                slope, intercept = np.polyfit(np.log(h[keep][positive]), np.log(error[positive]), 1)
                grid = np.geomspace(h[keep].min(), h[keep].max(), 20)
                bottom.loglog(grid, np.exp(intercept) * grid**slope, "-", lw=0.8)
            bottom.set_title(f"p = {row['order']:.2f} (3 finest), fit {row['fitted_order']:.2f}", fontsize=8)
            bottom.set_ylabel("|f − f_ext|", fontsize=8)
        else:
            kind = row["kind"] if row is not None else "fewer than 3 levels"
            bottom.text(0.5, 0.5, f"{kind}:\nno order", ha="center", va="center", transform=bottom.transAxes)
            bottom.set_xticks([])
            bottom.set_yticks([])
        bottom.set_xlabel(MEASURE_LABEL.get(key, key), fontsize=8)
        levels = np.unique(h[complete & np.isfinite(h)])
        for axis in (top, bottom):
            if (
                levels.size and axis.has_data()
            ):  # ticks at the levels (a sweep often spans less than a decade)
                axis.set_xticks(levels, labels=[f"{v:.3g}" for v in levels])
                axis.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
            else:
                axis.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            axis.tick_params(labelsize=7)
            axis.grid(True, which="both", alpha=0.3)
    figure.suptitle(f"{spec['name']}: scene {spec['scene']}, sweep of {key}", fontsize=10)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def _table(study: dict) -> list[str]:
    runs = study["runs"]
    spec = json.loads(study["attributes"]["study"])
    key = spec["sweep"][0]["key"]
    lines = [
        f"| {key} | status | ms/step | " + " | ".join(spec["quantities"]) + " |",
        "|---" * (3 + len(spec["quantities"])) + "|",
    ]
    for index in range(len(runs["label"])):
        value = runs["values"][key][index]
        cells = [f"{runs['quantities'][name][index]:.5g}" for name in spec["quantities"]]
        lines.append(
            f"| {value} | {runs['status'][index]} | {runs['ms_per_step'][index]:.1f} | "
            + " | ".join(cells)
            + " |"
        )
    lines += [
        "",
        "| quantity | type | observed order p (3 finest) | fitted slope (all levels) | f_ext (Richardson) | "
        "GCI (finest) | f1 ± | \\|f1 − f2\\|/\\|f1\\| | theory's value | f1 against it |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in study["convergence"]:
        reference = _reference(spec, row["quantity"])
        theory = (
            f"{reference[0]:.6g} ({reference[2]}) | {100 * (row['f'][0] / reference[0] - 1):+.2f} %"
            if reference is not None
            else " | "
        )
        lines.append(
            f"| {row['quantity']} | {row['kind']} | {row['order']:.3f} | {row['fitted_order']:.3f} | "
            f"{row['extrapolated']:.6g} | {100 * row['gci']:.3g} % | {row['uncertainty']:.3g} | "
            f"{_relative_change(row)} | {theory} |"
        )
    note = NOTES.get(spec["name"])
    if note:
        lines += ["", note]
    return lines


def main(argv: list[str] | None = None) -> None:
    from refsim.sweep import read_study

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", default=str(HERE / "output"))
    parser.add_argument("--docs", default=str(HERE.parents[1] / "docs"))
    args = parser.parse_args(argv)
    docs = Path(args.docs)
    (docs / "figures").mkdir(parents=True, exist_ok=True)
    lines = [
        "# Convergence study: d_i, d_c and mesh on cube, cube_cut and the liver",
        "",
        "Generated by `studies/convergence/plot.py` from the study files of `studies/convergence/run.py`. "
        "Regenerate (one line; 11 min on 2 workers sharing the 2 cores with other users, load 4 to 7):",
        "",
        "    PYTHONPATH=. python studies/convergence/run.py --liver && PYTHONPATH=. python "
        "studies/convergence/plot.py",
        "",
        "It runs the cube and cube_cut sweeps (`studies/convergence/*.toml`, 20 runs) and the liver's "
        "(`studies/convergence/liver/*.toml`, 12 runs); without `--liver` only the former, and the page "
        "shows "
        "every study file of the output folder. A run already complete and current is not run again; "
        "one whose scene, the files it names, overrides or refsim's numerics (version or source digest, "
        "docs/studies.md) changed is run again. "
        "Method: `refsim.sweep.convergence` — observed order from "
        "the three finest levels p = ln(ε32/ε21)/ln r (Celik et al. 2008 for unequal ratios), Richardson "
        "extrapolation f_ext = f1 + (f1 − f2)/(r^p − 1), Roache's GCI = 1.25 |(f1 − f2)/f1|/(r^p − 1). "
        "The fitted slope is the least-squares slope of log|f − f_ext| against log h over all levels. "
        'An order is given only for a monotone sequence; "converged" means the two finest levels agree to '
        "round-off (1e-12 of the quantity's scale: the uncertainty shown is that floor). "
        "|f1 − f2|/|f1| is the change between the two finest levels: an order computed from changes near the "
        "solver's or the events' resolution (say below 1e-3) is not an asymptotic order. "
        "An order is meaningful only for a quantity that depends smoothly on the parameter: the notes under "
        "each table say which do.",
        "",
    ]
    for path in sorted(Path(args.output).glob("*.h5")):
        study = read_study(path)
        name = study["attributes"]["name"]
        figure = docs / "figures" / f"convergence_{name}.png"
        _figure(study, figure)
        lines += [f"## {name}", "", *_table(study), "", f"![{name}](figures/{figure.name})", ""]
    (docs / "convergence.md").write_text("\n".join(lines) + "\n", encoding="utf-8")
    print(f"wrote {docs / 'convergence.md'} and its figures")


if __name__ == "__main__":
    main()
