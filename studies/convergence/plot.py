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
MEASURE_LABEL = {"mesh.cells": "h = 1/cells", "insertion.spacing": "d_i [m]", "cutting.point_spacing": "d_c [m]"}


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
        if row is not None and math.isfinite(row["extrapolated"]):
            top.axhline(row["extrapolated"], color="k", ls="--", lw=0.8, label="f_ext")
            if math.isfinite(row["uncertainty"]):
                f1 = row["f"][0]
                top.axhspan(f1 - row["uncertainty"], f1 + row["uncertainty"], color="C1", alpha=0.2,
                            label="f1 ± GCI")
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
        for axis in (top, bottom):
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
    lines = [f"| {key} | status | ms/step | " + " | ".join(spec["quantities"]) + " |",
             "|---" * (3 + len(spec["quantities"])) + "|"]
    for index in range(len(runs["label"])):
        value = runs["values"][key][index]
        cells = [f"{runs['quantities'][name][index]:.5g}" for name in spec["quantities"]]
        lines.append(f"| {value} | {runs['status'][index]} | {runs['ms_per_step'][index]:.1f} | "
                     + " | ".join(cells) + " |")
    lines += ["", "| quantity | type | observed order p (3 finest) | fitted slope (all levels) | f_ext (Richardson) | "
              "GCI (finest) | f1 ± |", "|---|---|---|---|---|---|---|"]
    for row in study["convergence"]:
        lines.append(f"| {row['quantity']} | {row['kind']} | {row['order']:.3f} | {row['fitted_order']:.3f} | "
                     f"{row['extrapolated']:.6g} | {100 * row['gci']:.3g} % | {row['uncertainty']:.3g} |")
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
        "# Convergence study: d_i, d_c and mesh on cube and cube_cut", "",
        "Generated by `studies/convergence/plot.py` from the study files of `studies/convergence/run.py` "
        "(regenerate: `python studies/convergence/run.py && python studies/convergence/plot.py`; the sweeps are "
        "the `studies/convergence/*.toml` study files). Method: `refsim.sweep.convergence` — observed order from "
        "the three finest levels p = ln(ε32/ε21)/ln r (Celik et al. 2008 for unequal ratios), Richardson "
        "extrapolation f_ext = f1 + (f1 − f2)/(r^p − 1), Roache's GCI = 1.25 |(f1 − f2)/f1|/(r^p − 1). "
        "The fitted slope is the least-squares slope of log|f − f_ext| against log h over all levels. "
        "An order is given only for a monotone sequence.", "",
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
