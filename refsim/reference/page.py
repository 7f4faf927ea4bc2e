"""The reference set's page (docs/reference.md), written from a built package: nothing in it is typed by hand
except the fixed text below, so its numbers are those of the package's runs."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np

from refsim.reference.build import PROVENANCE, convergence_status, read_case_reference
from refsim.reference.cases import case_names, load_case

__all__ = ["write_page"]

INTRODUCTION = """\
# Reference set: canonical needle–tissue cases with converged answers

A handful of cases that another implementation (a SOFA plugin, a GPU or haptic simulator) can set up without
refsim, run in its own code and score against refsim's converged answers with `refsim compare`. Each case is
two plain TOML files in `refsim/reference/cases/`: `NAME.toml` (what it checks, its set-up in words, its
refinement levels, its quantities with their sampling points, units and modelling tolerances) and
`NAME.scene.toml` (an ordinary refsim scene with every value in SI units and a comment on each; the liver
cases use the scenes of `refsim/scenes/`, their mesh and trajectory files copied into the package). Code:
`refsim.reference` (DESIGN.md layer 6, above the study machinery it runs on).

This page is generated from a built package by `refsim reference page --package DIR -o docs/reference.md`; its
numbers hold for the code and the level of each case's build (below): its commit, and the digest of refsim's
numerics source its runs are keyed by (`refsim.sweep.worker.numerics_digest`: every source and data file of
the package but the command line, figures, viewer, study machinery, reference set, verification problems and
results readers; docs/studies.md, "Resuming"). A build in a folder that already holds complete runs reuses
those whose resolved scene, named files and numerics digest are the same, whatever the commit: a commit that
changes only documentation or tests runs nothing again. A build into a folder that holds a package adds its
cases to it and keeps the others with the provenance of the build that made them, so a package can hold some
cases at a finer level than the rest (`refsim reference build -o DIR --level fine --cases NAME ...` over a
`standard` package); the tables say each case's level. After a change to the physics, rebuild the package and
this page.

## The set, and why these cases

Each case isolates one thing another implementation must get right, in the order they build on each other:

- `cantilever`: the needle alone (beam stiffness, then geometric nonlinearity), with the elastica as a closed
  form;
- `puncture`: the tip's unilateral contact on a deformable surface (a flat tip acting over its face: the
  flat punch, with Sneddon's stiffness as the half-space limit) and the puncture event at f_p;
- `insertion`: the shaft's coupling along its axis: insertion constraints, Coulomb friction on the grip, the
  tip cutting force;
- `lateral_push`: the shaft's coupling across its axis, the tissue's lateral stiffness around an inserted
  needle (the quantity that the 1-D needle in a 3-D mesh gets wrong first);
- `laceration`, `laceration_paper_law`: the paper's cut: when it starts, the force while cutting, the area
  cut, by the energy law (refsim's default) and by the paper's equation 3;
- `withdrawal`: the laceration followed by pulling the needle back out through its cut: the force while
  pulling back, when the tip is out, and no force left once it is;
- `liver_rigid`, `liver_flexible`: the paper's liver with breathing and a robot-held beam needle, stiff
  (it cuts) and flexible (it does not): the force at stated times, whether and when the cut starts, on an
  unstructured organ mesh with a moving support.

Levels (each case's file gives its own, with a comment saying why): `coarse` (seconds to a minute a run: the
tests build it to check the machinery), `standard` (one machine, an hour), `fine` (a cluster's, or hours of
one machine per cube case; `laceration` and `lateral_push` are meant to be built at it, the other cases at
`standard`: the tables give the level each case of this page was built at). The cube cases refine mesh, d_i,
d_c and dt together on odd cell counts, 3/5/7, 5/7/9 and 13/17/21 cells, with d_i = d_c = 6.8 mm/cells and dt
= 0.05 s/cells: the 17 mm insertion is then n + 1/2 insertion spacings deep at every level (the last point
half a spacing above the tip), so the shaft's force, which grows by one point every d_i of depth, has the same
phase at every level, and every waypoint of the trajectory falls on a step. The standard level's h (20 to 11
mm) is above the needle's radius (8 mm) and the fine level's (7.7 to 4.8 mm) below it: each level stays in one
regime of the ring coupling (docs/coupling.md: rows on a ring of radius max(r, h)). The paper's law holds d_i
= d_c (they are parameters of its law). The puncture block (4 cm) refines 2–4, 8/12/16 and 16/24/32 cells. The
liver cases keep their organ mesh (the geometry) and refine dt with d_i, d_c and the needle's beam elements (h
= dt).

## Commands

    refsim reference list                                          # the cases
    refsim reference build -o DIR [--level standard] [--cases NAME ...] [--workers N] [--scheduler A]
    refsim reference page --package DIR -o docs/reference.md       # this page from a package
    refsim compare CASE THEIR.csv --reference DIR [-o FIG.png]     # score their results

`build` runs each case's refinement sequence through the study machinery (`refsim.sweep.run_study`: one zipped
sweep over the level's keys, every run an ordinary results file) on a Dask LocalCluster of `--workers`
processes, or on a cluster with `--scheduler tcp://HOST:8786` (set-up in docs/studies.md, "Running on several
machines"). Runs already complete in the folder are reused. The cantilever case is static and runs on the
client. `compare` exits 0 when every quantity passes, 1 when one fails, 2 for bad input (an unknown case, a
package without it, a CSV without the columns or quantities below).

### Building on several machines

One machine builds `standard` (its time is in "This build" below: the worker time of the runs, and the
build's own time, on one worker). The cube cases' `fine` level has (21/9)³ ≈ 13 times the cells and 2.3
times the steps of the finest standard run, and the factorisation grows faster than the node count: measured
on one worker of the 2-core machine this page was built on, the fine levels of `laceration` took 74, 286 and
1098 s (13, 17, 21 cells: 24 minutes) and of `lateral_push` 53, 273 and 1061 s (23 minutes, beside other
jobs), against 5 to 40 s for their standard runs; the finest run is three quarters of a case's time. So one
machine builds a cube case's fine level in about half an hour (the five cube cases in about three hours),
and the puncture's fine level (8 times the cells of its finest standard run: 32³ cells, about 105,000
free DoFs, 600 steps) is meant for a cluster.
Every run of a level is one Dask task, and a case's runs are independent, so the build uses as many workers
as a level has runs (3 per case):

    # every machine: the same refsim (pip install -e ".[study]" of the same commit), and the package
    # folder on a shared filesystem (NFS or similar) at the same path: workers write the run files, the
    # client reads them
    dask-scheduler --port 8786                                  # on one machine
    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 \
        dask-worker tcp://SCHEDULER:8786 --nworkers auto --nthreads 1    # on every compute machine
    refsim reference build -o /shared/refpkg --level fine --scheduler tcp://SCHEDULER:8786
    refsim reference page --package /shared/refpkg -o docs/reference.md

On one machine, a scheduler and two worker processes on the loopback interface run a build the same way
(the package folder is then simply local):

    dask scheduler --host 127.0.0.1 --port 8786 &
    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 \
        dask worker tcp://127.0.0.1:8786 --nworkers 2 --nthreads 1 &
    refsim reference build -o /tmp/refpkg --level coarse --scheduler tcp://127.0.0.1:8786

(`dask-scheduler` / `dask-worker` in older Dask.) The client runs each case's study in turn; start it again
after a lost worker or an interruption and only the missing runs are made (complete runs in the folder are
reused), then it writes the answers, figures and manifest. Give only the address of a scheduler you started,
on a network you control (docs/studies.md, "Security": whoever reaches it runs code as its workers' user).

## Running a case in another simulator

1. Read the case's set-up below and its scene file (every key, unit and valid range: docs/scenes.md). The
   needle's base follows the scene's `[trajectory]` (waypoints, linear in between); the tissue is linear
   co-rotational elastic on linear tetrahedra in refsim, but any discretisation of the same continuum is a
   valid implementation: the answers are extrapolated in the mesh (or, where no order is observed, the finest
   level's with its spread), not tied to refsim's mesh.
2. Record, at every step, the force of the tissue on the needle and the needle's base position (and the tip
   for the tip depth); the quantities are read from them:
   - `base_travel` [m]: the base's displacement along the needle's initial axis (from its initial position);
   - `tip_depth` [m]: the tip's position along the needle from the entry point (the surface point the tip
     touched at the puncture);
   - `lateral_stroke` [m]: the base's displacement across the initial axis;
   - `axial_force` [N]: minus the force's component along the needle's base segment (towards the tip):
     positive when the tissue resists insertion; `lateral_force` [N]: the norm of the rest;
   - `cut_area` [m²]: the area of the cut surface in the tissue's rest configuration.
   A curve is read over the steps of its window (`window = [t0, t1]` in the case file) or before an event
   (`until`), sampled at its `at` points by linear interpolation; a quantity with a `width` is, at each
   point, the mean of that piecewise-linear curve over [at − width/2, at + width/2] (its integral over the
   window divided by the width): a force that grows by one insertion point every d_i, or drops at each tear,
   is a staircase or a saw-tooth whose point samples land on a step at one level and between two at the
   next; its mean over a window is smooth in h. A scalar read at an event is the abscissa at its first step
   (none: NaN), or, with `crossing = true`, where the event's criterion (the tip force against f_p, the
   cut-start load against its threshold) reached its threshold, interpolated linearly between the step
   before the event and the event's step: the event's step alone snaps it to the time grid, an error of up
   to one step that is not smooth in h. An event alone (`cuts`) is 1 when it happens in the run, 0 when not.
3. Write one CSV (format below) and run `refsim compare CASE THEIR.csv --reference DIR -o FIG.png`.

## The uncertainty and the pass band

Each quantity at each sampling point gets its reference value from the case's refinement sequence (mesh, d_i,
d_c and dt refined together, h = 1/cells, or h = dt for the liver; the exact solver at a natural residual of
1e-10), with `refsim.sweep.convergence` on the three finest levels:

- `richardson`: monotone convergence: the Richardson value, U = GCI·|f1|, GCI = Fs·|(f1 − f2)/f1|/(r21^p̂ − 1)
  with Roy's rule (Oberkampf and Roy 2010, section 8.7): Fs = 1.25 and p̂ = p when the observed order p is
  within 10 % of the formal order p_f (the case's `formal_order`: 1 where implicit Euler's dt is refined with
  the mesh, 2 for the static beam), otherwise Fs = 3 and p̂ = min(max(0.5, p), p_f);
- `oscillatory` (ε21/ε32 < 0) or `divergent` (the differences do not shrink): no order is observed, none is
  claimed: the finest value f1 with Roache's GCI for an unobserved order, Fs = 3 at the formal order,
  U = 3·|f1 − f2|/(r21^p_f − 1);
- `converged`: converged to round-off, |f1 − f2| ≤ δ with δ = 1e-12 times the quantity's largest |value|
  (`refsim.sweep.convergence.ROUNDOFF`; a difference below it is round-off, not an observation): f1, U = δ,
  order not observable.

`compare` reports per sample the error in units of the uncertainty, |theirs − ref|/U, and passes a sample when
|theirs − ref| ≤ U + T. T is the case's modelling tolerance: a stated fraction of the quantity's scale (its
largest |ref| over the samples), for what the specification leaves open between two correct implementations
(each quantity's note says what). A quantity passes when all its samples do. A quantity whose U is large
against its scale has no converged answer at the built level: its band says so, and so does the table.

The column `convergence` says, per sample (and, in the summary, for the least converged sample of each
quantity), what the levels show: `converged` (to round-off), `asymptotic` (Richardson, the observed order
within 10 % of the formal one: U is a band the levels demonstrate), `pre-asymptotic` (monotone, but the
observed order is far from the formal one: the levels are not shown to be in the asymptotic range and U is
Roy's conservative Fs = 3 estimate, not a demonstrated band), `not converged` (oscillatory or divergent: no
order, U is Roache's estimate at the formal order; the value is the finest level's and the band is a guess of
its error, not a converged answer). A quantity that is not `asymptotic` or `converged` has no converged
answer at the built level; a finer level is what would give one.

## Their results: the CSV format

One row per sample, a header with the columns `quantity`, `x`, `value` (other columns are ignored), SI units
as in the tables below; curves at any abscissae covering the reference's sampling points (interpolated
linearly; for a quantity with a `width`, the window means at the sampling points, computed from their curve:
`refsim.reference.sample_curve(x, y, at, width=w, where=...)` does it), scalars with `x` empty:

    quantity,x,value
    indentation_force,0.00020,0.512
    indentation_force,0.00025,0.655
    puncture_force,,0.8

Every value and every curve's `x` must be a finite number and a scalar's `x` empty; a defect is named with its
line and column. A UTF-8 byte-order mark (a spreadsheet's export) is read. A refsim results file (`.h5`) is
read directly instead. From Python, `refsim.reference.write_their_csv(case, {quantity: values}, path)` writes
this format for a case's sampling points.

## The data package

    DIR/manifest.json                      format, schema version (2), the last build's refsim version,
                                           git commit, numerics digest (what the runs are keyed by),
                                           command, level; per case: its level and its build's provenance
                                           ("build": the same fields), levels, h, seconds, quantities
                                           (methods, convergence, largest U/scale);
                                           the SHA-256 of every file (`refsim.reference.check_manifest(DIR)`
                                           lists the files that differ or are missing)
    DIR/cases/NAME/reference.h5            answers (format "refsim-reference-case"): /h; /quantities/Q/{at,
                                           value, uncertainty, band, levels (L, k), order, gci, method}
    DIR/cases/NAME/reference.csv           the same as CSV (quantity, x, value, uncertainty, band, method,
                                           order, gci, unit, x_unit)
    DIR/cases/NAME/case.toml, scene.toml   the specification as built
    DIR/cases/NAME/study.h5, study_runs/   the study file and each run's results file
    DIR/cases/NAME/problems.h5, fclib/     20 constraint problems of the finest run (steps evenly spaced)
                                           with their exact solutions (the problem-set format of
                                           refsim/io/export.py); fclib/: up to 10 steps FCLib's local
                                           format holds (the tip contact before puncture, loaded, its f_p cap
                                           inactive), evenly spaced, with FCLib's Coulomb cone on the step's
                                           W, q, mu and the exact solution of that problem (each file's
                                           /fclib_local/info/description says so)
    DIR/figures/NAME.png                   each quantity against refinement with the reference band
"""


def _format(value: float) -> str:
    return "—" if not math.isfinite(value) else f"{value:.5g}"


def _order(value: float) -> str:
    """An observed order, or "not observable" (round-off, oscillatory or divergent sequences)."""
    return "not observable" if not math.isfinite(value) else f"{value:.5g}"


def _scene_name(path: Path) -> str:
    """The scene's path relative to the repository (``refsim/...``) when it is refsim's, else its name."""
    import refsim

    root = Path(refsim.__file__).resolve().parent
    try:
        return "refsim/" + path.resolve().relative_to(root).as_posix()
    except ValueError:
        return path.name


def _case_section(case, reference: dict, manifest_case: dict, level: str, figure: str | None) -> list[str]:
    lines = [f"## {case.name}: {case.title}", "", f"**Why.** {case.why}", "", f"**Set-up.** {case.setup}", ""]
    if case.note:
        lines += [f"**Note.** {case.note}", ""]
    if case.runner == "scene":
        changed = "".join(f", with `{text}`" for text in case.overrides)
        lines.append(f"Scene file: `{_scene_name(case.scene_path)}`{changed}; case file: `{case.path.name}`.")
    else:
        lines.append(f"Case file: `{case.path.name}` (solved statically, `refsim.verification.needle`).")
    levels = manifest_case["levels"]
    lines += ["", "| level | " + " | ".join(levels) + " |", "|---" * (len(levels) + 1) + "|"]
    for index in range(len(next(iter(levels.values())))):
        lines.append(f"| {index + 1} | " + " | ".join(str(v[index]) for v in levels.values()) + " |")
    lines += [
        "",
        f"Built at the `{level}` level; run time: {manifest_case['run_seconds']:.1f} s (the sum over the "
        "levels' runs).",
        "",
        "| quantity | x | reference | U | U + T | method | convergence | observed order | order used "
        "| unit |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for quantity in case.quantities:
        entry = reference["quantities"][quantity.name]
        at = np.atleast_1d(entry["at"])
        value, u, band = (np.atleast_1d(entry[k]) for k in ("value", "uncertainty", "band"))
        order, used = np.atleast_1d(entry["order"]), np.atleast_1d(entry["order_used"])
        factor = np.atleast_1d(entry["safety_factor"])
        for j in range(value.size):
            x = f"{at[j]:.4g} {quantity.x_unit}" if quantity.kind == "curve" else ""
            lines.append(
                f"| {quantity.name} | {x} | {_format(value[j])} | {_format(u[j])} | {_format(band[j])} | "
                f"{entry['method'][j]} | {convergence_status(entry['method'][j], factor[j])} | "
                f"{_order(order[j])} | {_format(used[j])} | {quantity.unit} |"
            )
    lines += ["", "Quantities:", ""]
    for quantity in case.quantities:
        entry = reference["quantities"][quantity.name]
        text = f"- `{quantity.name}` [{quantity.unit}]: {quantity.description}."
        if quantity.kind == "curve":
            text += f" Sampled at {quantity.x} = {', '.join(f'{v:g}' for v in quantity.at)} {quantity.x_unit}"
            if quantity.width:
                text += f", each the mean over {quantity.width:g} {quantity.x_unit} around the point"
            text += "."
        text += f" T = {100 * quantity.tolerance:g} % of its scale: {quantity.tolerance_note}."
        if quantity.closed_form:
            text += f" Cross-check: {quantity.closed_form}"
            closed = float(entry.get("closed_form", math.nan))
            text += f" = {closed:.6g} {quantity.unit}." if math.isfinite(closed) else "."
        lines.append(text)
    if figure:
        lines += ["", f"![{case.name}]({figure})"]
    return lines + [""]


def _case_level(manifest: dict, case: dict) -> str:
    """A case's level (schema 2 records it per case; schema 1 once for the package)."""
    return case.get("level", manifest["level"])


def _builds(manifest: dict) -> list[str]:
    """One paragraph per build that made some of the package's cases (a package grows case by case): its
    level, refsim version, commit, numerics digest, date, command, its cases and their worker time."""
    groups: dict[tuple, list[str]] = {}
    for name, case in manifest["cases"].items():
        build = case.get("build") or {key: manifest.get(key) for key in PROVENANCE}
        key = (_case_level(manifest, case), *(build.get(field) for field in PROVENANCE))
        groups.setdefault(key, []).append(name)
    lines = []
    if len(groups) > 1:
        lines += [
            f"The package was built by {len(groups)} invocations, each of some of its cases (a build into a "
            "package adds its cases to it and keeps the others, with the provenance of the build that made "
            "them):",
            "",
        ]
    for (level, version, commit, digest, created, command), names in groups.items():
        seconds = sum(manifest["cases"][name]["run_seconds"] for name in names)
        cases = ", ".join(f"`{name}`" for name in names)
        last = (
            f" (the last invocation took {manifest['seconds']:.0f} s; runs already complete in the folder "
            "are reused)."
        )
        lines.append(
            ("- " if len(groups) > 1 else "")
            + f"Level `{level}`, refsim {version}, commit `{commit}`, numerics digest "
            f"`{digest or 'unrecorded'}` (the runs are keyed by it, not by the commit), built {created} with "
            f"`{command}`: {seconds:.0f} s of worker time for the runs of {cases}"
            + (last if len(groups) == 1 else ".")
        )
    return lines


def write_page(package, output) -> Path:
    """Write the page from the package folder ``package``; figures are copied to ``figures/reference/``
    beside the page. Returns the page's path.

    Raises
    ------
    ValueError
        When the folder holds no manifest (naming it).
    """
    package, output = Path(package), Path(output)
    manifest_path = package / "manifest.json"
    if not manifest_path.is_file():
        raise ValueError(
            f"{package}: no manifest.json; build the package with: refsim reference build -o DIR"
        )
    manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
    figures = output.parent / "figures" / "reference"
    lines = [INTRODUCTION, "## This build", ""]
    lines += _builds(manifest)
    lines += [
        "",
        "| case | level | quantity | method | convergence | largest U / scale | T / scale |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, case in manifest["cases"].items():
        for quantity, row in case["quantities"].items():
            lines.append(
                f"| {name} | {_case_level(manifest, case)} | {quantity} | {', '.join(row['methods'])} | "
                f"{row.get('status', '—')} | "
                f"{_format(row['largest_relative_uncertainty'])} | {row['modelling_tolerance_relative']:g} |"
            )
    absent = [name for name in case_names() if name not in manifest["cases"]]
    if absent:
        lines += [
            "",
            f"Not in this build: {', '.join(f'`{name}`' for name in absent)} (build them with "
            "`refsim reference build --cases NAME ...`; their set-up is in their case files).",
        ]
    lines.append("")
    for name, manifest_case in manifest["cases"].items():
        case = load_case(name)
        figure = None
        source = package / "figures" / f"{name}.png"
        if source.is_file():
            figures.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, figures / f"{name}.png")
            figure = f"figures/reference/{name}.png"
        level = _case_level(manifest, manifest_case)
        lines += _case_section(case, read_case_reference(package, name), manifest_case, level, figure)
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text("\n".join(lines), encoding="utf-8")
    return output
