"""Building the reference set: each case's refinement sequence on Dask, its converged answers and the package.

:func:`build_reference` runs every case at a level through the study machinery
(:func:`refsim.sweep.run_study`: one zipped sweep over the level's keys, a LocalCluster or
``--scheduler``), reads each run's quantities (:func:`refsim.reference.cases.results_values`), and gives each
quantity at each sampling point a reference value with an uncertainty (:func:`reference_value`).
It writes the versioned data package (layout in ``docs/reference.md``)::

    DIR/manifest.json                      format, schema version, the last build's refsim version, git
                                           commit, numerics digest (what the runs are keyed by:
                                           refsim.sweep.worker.numerics_digest), command, level and seconds;
                                           per case: its level, its own build's provenance (the same fields:
                                           cases are built one invocation at a time), levels, quantities
                                           (worst uncertainty); SHA-256 of every file

A build into a folder that holds a package adds its cases to it: the cases it builds replace theirs (at the
level it builds), the others stay with the provenance of the build that made them. So one package can hold
each case at the finest level it was built at (``refsim reference build -o DIR --level fine --cases ...``
over a ``standard`` package), and says so per case.
    DIR/cases/NAME/reference.h5            the answers (format "refsim-reference-case")
    DIR/cases/NAME/reference.csv           the same as CSV (the columns ``refsim compare`` reads, and more)
    DIR/cases/NAME/case.toml, scene.toml   the specification, as built
    DIR/cases/NAME/study.h5, study_runs/   the study file and every run's results file
    DIR/cases/NAME/problems.h5, fclib/     20 of the finest run's constraint problems (evenly spaced steps)
                                           with exact solutions; up to 10 FCLib files of the steps FCLib holds
                                           (refsim.io.export.coulomb_contacts: the loaded tip contact before
                                           puncture), evenly spaced
    DIR/figures/NAME.png                   each quantity against refinement, with the reference band
"""

from __future__ import annotations

import datetime
import hashlib
import json
import logging
import math
import shutil
import time
from pathlib import Path

import numpy as np

from refsim.reference.cases import Case, case_names, case_values, load_case

__all__ = [
    "CASE_FORMAT",
    "MANIFEST_FORMAT",
    "PROVENANCE",
    "build_reference",
    "check_manifest",
    "convergence_status",
    "read_case_reference",
    "reference_value",
]

logger = logging.getLogger(__name__)

CASE_FORMAT = "refsim-reference-case"
MANIFEST_FORMAT = "refsim-reference"
SCHEMA_VERSION = 2  # 2: each case carries its level and its build's provenance (a package grows by case)
#: Columns of a case's reference.csv (``refsim compare`` reads quantity, x, value; the rest is for people).
CSV_COLUMNS = (
    "quantity",
    "x",
    "value",
    "uncertainty",
    "band",
    "method",
    "order",
    "order_used",
    "gci",
    "unit",
    "x_unit",
)


def reference_value(spacings, values, formal_order: float, *, scale: float | None = None) -> dict:
    """The reference value of one quantity at one sampling point from its refinement sequence.

    The GCI follows Roy's rule (Oberkampf and Roy 2010, "Verification and Validation in Scientific Computing",
    section 8.7): when the observed order p is within 10 % of the formal order p_f, Fs = 1.25 and p; otherwise
    Fs = 3 and p̂ = min(max(0.5, p), p_f), so that an order far from the asymptotic one (a pre-asymptotic or
    noisy sequence) widens the band instead of shrinking it. A difference at round-off is not an observation
    (:mod:`refsim.sweep.convergence`, floor δ = ROUNDOFF · scale).

    Parameters
    ----------
    spacings : Refinement measure h of each level, shape (L,), L ≥ 3.
    values : The quantity at each level, shape (L,).
    formal_order : p_f of the discretisation refined together (1 when the implicit Euler step is refined with
        the mesh, 2 for the static Timoshenko beam) [-].
    scale : Magnitude the round-off floor is relative to (a curve's largest |value|, so that a sample near
        zero is judged against the curve); max(|f1|, |f2|, |f3|) when None.

    Returns
    -------
    dict with ``value``, ``uncertainty`` (half-width U of the band, in the quantity's unit), ``method``,
    ``order`` (observed; NaN where not observable), ``order_used``, ``safety_factor``, ``gci``:

    - "richardson": monotone over the three finest levels: the Richardson value with p̂, U = GCI |f1|,
      GCI = Fs |(f1 − f2)/f1| / (r21^p̂ − 1);
    - "converged": converged to round-off (|f1 − f2| ≤ δ): f1, U = δ, no order (not observable);
    - "oscillatory" (ε21/ε32 < 0) or "divergent" (differences not shrinking, or f3 = f2 ≠ f1): no order is
      claimed; f1 with Roache's GCI for an order not observed: Fs = 3 at the formal order,
      U = 3 |f1 − f2| / (r21^p_f − 1);
    - "missing": a level lacks the quantity: NaN.
    """
    from refsim.sweep.convergence import convergence, grid_convergence_index, richardson, roundoff_floor

    h, f = np.asarray(spacings, dtype=float), np.asarray(values, dtype=float)
    nan = float("nan")
    answer = {"order": nan, "order_used": nan, "safety_factor": nan, "gci": nan}
    if not np.all(np.isfinite(f)):
        return {**answer, "value": nan, "uncertainty": nan, "method": "missing"}
    finest = f[np.argsort(h)[:3]]
    noise = roundoff_floor(finest if scale is None or not math.isfinite(scale) else [scale])
    result = convergence(h, f, noise=noise)
    f1, f2 = result.values[0], result.values[1]
    if result.kind == "converged":
        converged = {"value": f1, "uncertainty": result.uncertainty, "method": "converged", "gci": result.gci}
        return {**answer, **converged}
    if result.kind == "monotone":
        p = result.order
        if abs(p - formal_order) <= 0.1 * formal_order:
            used, factor = p, 1.25
        else:
            used, factor = min(max(0.5, p), formal_order), 3.0
        method, value = "richardson", richardson(f1, f2, result.ratio_fine, used)
    else:  # oscillatory or divergent: no order observed
        p, used, factor = nan, float(formal_order), 3.0
        method, value = result.kind, f1
    uncertainty = factor * abs(f1 - f2) / (result.ratio_fine**used - 1.0)
    gci = nan
    if f1 != 0.0:
        gci = grid_convergence_index(f1, f2, result.ratio_fine, used, safety_factor=factor)
        uncertainty = gci * abs(f1)
    return {
        "value": value,
        "uncertainty": uncertainty,
        "method": method,
        "order": p,
        "order_used": used,
        "safety_factor": factor,
        "gci": gci,
    }


#: What a sample's answer says about its convergence, best first (:func:`convergence_status`).
STATUSES = ("converged", "asymptotic", "pre-asymptotic", "not converged", "missing")


def convergence_status(method: str, safety_factor: float) -> str:
    """What a sample's answer (:func:`reference_value`) says about its convergence, for the page:

    - "converged": to round-off (method "converged");
    - "asymptotic": Richardson with the observed order within 10 % of the formal one (Fs = 1.25): the levels
      are in the asymptotic range and U is a demonstrated band;
    - "pre-asymptotic": Richardson with an observed order far from the formal one (Fs = 3): monotone, but not
      shown to be asymptotic; U is Roy's conservative estimate;
    - "not converged": oscillatory or divergent, no order observed: U is Roache's estimate at the formal
      order, not a band the levels demonstrate;
    - "missing": a level lacks the quantity.
    """
    if method == "converged":
        return "converged"
    if method == "richardson":
        return "asymptotic" if safety_factor < 2.0 else "pre-asymptotic"
    if method in ("oscillatory", "divergent"):
        return "not converged"
    return "missing"


def worst_status(statuses) -> str:
    """The least converged of some statuses (:data:`STATUSES`)."""
    return max(statuses, key=STATUSES.index)


# ---------------------------------------------------------------------- running the levels


def _study(case: Case, level: str):
    from refsim.sweep import StudySpec, Sweep

    keys = case.level(level)
    count = len(keys[case.refine])
    sweeps = [
        Sweep(key, tuple(values), case.measure if key == case.refine else "value")
        for key, values in keys.items()
    ]
    # only the finest run records its constraint problems (exported with exact solutions)
    sweeps.append(Sweep("output.record_problems", tuple([False] * (count - 1) + [True]), "none"))
    return StudySpec(
        name=f"{case.name}_{level}",
        scene=str(case.scene_path),
        sweeps=tuple(sweeps),
        combine="zip",
        overrides=("output.tissue_every=1000000", *case.overrides),
        quantities=tuple(q.source for q in case.quantities if q.source) or ("needle_force@end",),
        source=str(case.path),
    )


def _run_scene_case(case: Case, level: str, folder: Path, client) -> tuple[list[dict], list[str], dict]:
    """Run the levels on Dask; per level {quantity: values}, the run files (relative to ``folder``), study
    attributes."""
    from refsim.sweep import run_study
    from refsim.sweep.study import check_study_output

    spec, output = _study(case, level), folder / "study.h5"
    try:
        check_study_output(spec, output)
    except ValueError:
        # the case at another level (or an unreadable study file): its study is replaced by this level's; the
        # run files stay in study_runs/ (reused if that level is built again)
        output.unlink()
    study = run_study(spec, output, client=client, progress=False, warm_up=False)
    runs = study["runs"]
    failed = [
        f"{label}: {error}"
        for label, status, error in zip(runs["label"], runs["status"], runs["error"], strict=True)
        if status != "complete"
    ]
    if failed:
        raise RuntimeError(f"case {case.name}, level {level}: runs did not complete: {'; '.join(failed)}")
    values = [case_values(case, folder / name) for name in runs["file"]]
    seconds = float(np.nansum(np.asarray(runs["seconds"], dtype=float)))
    return values, list(runs["file"]), {"run_seconds": seconds, "ms_per_step": list(runs["ms_per_step"])}


def _run_cantilever_case(case: Case, level: str) -> tuple[list[dict], list[str], dict]:
    """The needle alone, static (:func:`refsim.verification.needle.needle_cantilever`), at each element count;
    closed forms for the cross-check."""
    from refsim.fem.needle import NeedleModel
    from refsim.verification.needle import elastica_tip_displacement, needle_cantilever

    spec = case.cantilever
    length, radius = float(spec["length"]), float(spec["radius"])
    modulus, ratio = float(spec["youngs_modulus"]), float(spec["poisson_ratio"])
    section = NeedleModel(
        length=length,
        radius=radius,
        element_count=1,
        youngs_modulus=modulus,
        poisson_ratio=ratio,
        density=1.0,
    ).section
    bending = modulus * section.second_moment
    start = time.perf_counter()
    values = []
    for count in case.level(level)[case.refine]:
        row = {}
        for name, parameter in spec["load_parameters"].items():
            force = float(parameter) * bending / length**2
            tip = needle_cantilever(
                [0.0, -force, 0.0],
                length=length,
                radius=radius,
                youngs_modulus=modulus,
                poisson_ratio=ratio,
                element_count=int(count),
            ).tip_displacement
            row[f"deflection@{name}"] = -tip[1]
            row[f"shortening@{name}"] = -tip[0]
        values.append({q.name: np.asarray(row[q.source]) for q in case.quantities})
    closed = {}
    shear_modulus = modulus / (2.0 * (1.0 + ratio))
    for name, parameter in spec["load_parameters"].items():
        force = float(parameter) * bending / length**2
        axial = bending / (modulus * section.area * length**2)
        shear = bending / (section.shear_coefficient * shear_modulus * section.area * length**2)
        dx, dy = elastica_tip_displacement(
            float(parameter), length, axial_compliance=axial, shear_compliance=shear
        )
        closed[f"shortening@{name}"], closed[f"deflection@{name}"] = -dx, -dy
        # Timoshenko's linear closed form, the small-load limit of the elastica
        closed[f"linear_deflection@{name}"] = force * length**3 / (3.0 * bending) + force * length / (
            section.shear_coefficient * shear_modulus * section.area
        )
    info = {
        "run_seconds": time.perf_counter() - start,
        "closed_form": {q.name: closed[q.source] for q in case.quantities if q.source in closed},
    }
    return values, [], info


# ---------------------------------------------------------------------- writing


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _answers(case: Case, spacings: np.ndarray, values: list[dict]) -> dict:
    """{quantity: {at, levels (L, k), value, uncertainty, method, order, gci, band, scale}}."""
    answers = {}
    for quantity in case.quantities:
        levels = np.array([np.atleast_1d(v[quantity.name]) for v in values], dtype=float)  # (L, k)
        finite = np.abs(levels[np.isfinite(levels)])
        magnitude = float(finite.max()) if finite.size else None
        rows = [
            reference_value(spacings, levels[:, j], case.formal_order, scale=magnitude)
            for j in range(levels.shape[1])
        ]
        value = np.array([r["value"] for r in rows])
        uncertainty = np.array([r["uncertainty"] for r in rows])
        finite = value[np.isfinite(value)]
        scale = float(np.max(np.abs(finite))) if finite.size else float("nan")
        answers[quantity.name] = {
            "at": np.asarray(quantity.at, dtype=float),
            "levels": levels,
            "value": value,
            "uncertainty": uncertainty,
            "method": [r["method"] for r in rows],
            "order": np.array([r["order"] for r in rows]),
            "order_used": np.array([r["order_used"] for r in rows]),
            "safety_factor": np.array([r["safety_factor"] for r in rows]),
            "gci": np.array([r["gci"] for r in rows]),
            "scale": scale,
            "modelling": quantity.tolerance * scale,
            "band": uncertainty + quantity.tolerance * scale,
        }
    return answers


def _write_case_h5(path: Path, case: Case, level: str, spacings, answers, files, info, meta) -> None:
    import h5py

    strings = h5py.string_dtype()
    with h5py.File(path, "w") as handle:
        handle.attrs.update(
            {
                "format": CASE_FORMAT,
                "schema_version": SCHEMA_VERSION,
                "case": case.name,
                "title": case.title,
                "level": level,
                "refine": case.refine,
                "formal_order": case.formal_order,
                "levels": json.dumps(case.level(level)),
                **meta,
            }
        )
        handle.create_dataset("h", data=np.asarray(spacings, dtype=float)).attrs["units"] = "1/value"
        handle.create_dataset("runs", data=np.array(files, dtype=object), dtype=strings)
        for quantity in case.quantities:
            answer = answers[quantity.name]
            group = handle.create_group(f"quantities/{quantity.name}")
            group.attrs.update(
                {
                    "kind": quantity.kind,
                    "unit": quantity.unit,
                    "x_unit": quantity.x_unit,
                    "description": quantity.description,
                    "tolerance_relative": quantity.tolerance,
                    "tolerance_note": quantity.tolerance_note,
                    "modelling_tolerance": answer["modelling"],
                    "scale": answer["scale"],
                    "closed_form": float(info.get("closed_form", {}).get(quantity.name, np.nan)),
                    "closed_form_text": quantity.closed_form,
                }
            )
            group.create_dataset("at", data=answer["at"]).attrs["units"] = quantity.x_unit
            for name in ("value", "uncertainty", "band"):
                group.create_dataset(name, data=answer[name]).attrs["units"] = quantity.unit
            group.create_dataset("levels", data=answer["levels"]).attrs["units"] = quantity.unit
            group.create_dataset("order", data=answer["order"]).attrs["units"] = "1"
            group.create_dataset("order_used", data=answer["order_used"]).attrs["units"] = "1"
            group.create_dataset("safety_factor", data=answer["safety_factor"]).attrs["units"] = "1"
            group.create_dataset("gci", data=answer["gci"]).attrs["units"] = "1"
            group.create_dataset("method", data=np.array(answer["method"], dtype=object), dtype=strings)


def _write_case_csv(path: Path, case: Case, answers) -> None:
    lines = [",".join(CSV_COLUMNS)]
    for quantity in case.quantities:
        answer = answers[quantity.name]
        xs = answer["at"] if quantity.kind == "curve" else [None]
        for j, x in enumerate(xs):
            lines.append(
                ",".join(
                    [
                        quantity.name,
                        "" if x is None else f"{x:.12g}",
                        f"{answer['value'][j]:.12g}",
                        f"{answer['uncertainty'][j]:.6g}",
                        f"{answer['band'][j]:.6g}",
                        answer["method"][j],
                        f"{answer['order'][j]:.4g}",
                        f"{answer['order_used'][j]:.4g}",
                        f"{answer['gci'][j]:.4g}",
                        quantity.unit,
                        quantity.x_unit,
                    ]
                )
            )
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _level_label(case: Case, h: float) -> str:
    """One level's legend: its refined value (h = dt) or the count it is the reciprocal of (h = 1/cells)."""
    return f"h = {h:.3g}" if case.measure == "value" else f"h = 1/{1 / h:.3g}"


def _figure(path: Path, case: Case, spacings, answers) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    count = len(case.quantities)
    figure, axes = plt.subplots(1, count, figsize=(4.2 * count, 3.4), squeeze=False)
    for axis, quantity in zip(axes[0], case.quantities, strict=True):
        answer = answers[quantity.name]
        if quantity.kind == "curve":
            x = answer["at"]
            for row, h in zip(answer["levels"], spacings, strict=True):
                axis.plot(x, row, "o-", ms=3, lw=0.8, label=_level_label(case, h))
            value, band, u = answer["value"], answer["band"], answer["uncertainty"]
            axis.fill_between(x, value - band, value + band, color="0.85", label="reference ± (U + T)")
            axis.fill_between(x, value - u, value + u, color="0.6", label="reference ± U")
            axis.plot(x, value, "k-", lw=1.2, label="reference")
            axis.set_xlabel(f"{quantity.x} [{quantity.x_unit}]")
        else:
            axis.plot(spacings, answer["levels"][:, 0], "o-", label="levels")
            value, band, u = answer["value"][0], answer["band"][0], answer["uncertainty"][0]
            axis.axhspan(value - band, value + band, color="0.85", label="reference ± (U + T)")
            axis.axhspan(value - u, value + u, color="0.6", label="reference ± U")
            axis.axhline(value, color="k", lw=1.2, label="reference")
            axis.set_xlim(0.0, 1.1 * float(np.max(spacings)))
            axis.set_xlabel(f"h = {case.refine}" if case.measure == "value" else f"h = 1/{case.refine}")
            levels = answer["levels"][:, 0]
            scale = max(abs(float(value)), 1e-300)
            if max(float(np.ptp(levels)), float(band)) < 1e-9 * scale:
                # a converged answer (an event that happens, a threshold): on the answer's own scale, not on
                # an axis of its round-off
                axis.set_ylim(value - 0.1 * scale, value + 0.1 * scale)
        axis.set_title(quantity.name, fontsize=9)
        axis.ticklabel_format(axis="both", style="sci", scilimits=(-2, 3), useOffset=False)
        axis.tick_params(labelsize=7)
        axis.set_ylabel(f"[{quantity.unit}]")
        axis.legend(fontsize=6)
    figure.suptitle(case.title, fontsize=9)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


#: Constraint problems kept per case: evenly spaced over the finest run's recorded steps.
PROBLEM_STEPS = 20
#: FCLib files kept per case: evenly spaced over the finest run's steps that FCLib's format holds.
FCLIB_STEPS = 10


def _evenly(count: int, keep: int) -> np.ndarray:
    """Indices of ``keep`` of ``count`` items, evenly spaced, first and last included (all when fewer)."""
    if count == 0:
        return np.zeros(0, dtype=int)
    return np.unique(np.linspace(0, count - 1, min(keep, count)).round().astype(int))


def _export_problems(
    run_file: Path, folder: Path, count: int = PROBLEM_STEPS, fclib_count: int = FCLIB_STEPS
):
    """Export the finest run's constraint problems with their exact solutions (refsim.io.export), keeping
    ``count`` steps evenly spaced over the run in ``problems.h5``, and ``fclib_count`` FCLib files in
    ``fclib/`` evenly spaced over the steps FCLib's format holds (:func:`refsim.io.export.coulomb_contacts`;
    chosen among those, not among the kept problems: they are the few steps before puncture). Returns
    {count, recorded, fclib, fclib_steps}."""
    import h5py

    from refsim.io.export import coulomb_contacts, export_problems, is_pure_contact
    from refsim.io.reader import read_problems, read_results

    reused = _exported_problems(run_file, folder)
    if reused is not None:
        return reused
    fclib = folder / "fclib"
    shutil.rmtree(fclib, ignore_errors=True)
    # Only the kept steps are solved (a fine run records thousands): the problems evenly spaced over the
    # recorded steps, and for FCLib the steps whose rows have its form (structure alone, no solve), of
    # which the export keeps those it can write (a loaded contact, every cap inactive at the solution).
    names = [int(step) for step in read_results(run_file).problem_steps]
    chosen = [names[i] for i in _evenly(len(names), count)]
    holdable_form = []
    for start in range(0, len(names), 200):  # read in batches: a fine run's W's do not fit in memory at once
        for step, problem in read_problems(run_file, steps=names[start : start + 200]):
            if is_pure_contact(problem) or coulomb_contacts(problem) is not None:
                holdable_form.append(step)
    partial = folder / "problems.h5.tmp"
    summary = export_problems(run_file, partial, fclib_folder=fclib, steps=chosen, fclib_steps=holdable_form)
    with h5py.File(partial, "a") as target:
        target.attrs["selection"] = f"{len(chosen)} of the {len(names)} recorded steps, evenly spaced"
    partial.replace(folder / "problems.h5")
    files = sorted(summary["fclib"])
    kept = [files[i] for i in _evenly(len(files), fclib_count)]
    for path in set(files) - set(kept):
        path.unlink()
    if not kept and fclib.is_dir():
        fclib.rmdir()
    with h5py.File(folder / "problems.h5", "a") as target:
        target.attrs["recorded_steps"] = len(names)
        target.attrs["fclib_holdable"] = len(files)
    return {
        "count": len(chosen),
        "recorded": len(names),
        "fclib": len(kept),
        "fclib_steps": [int(path.stem.split("_")[1]) for path in kept],
        "fclib_holdable": len(files),
    }


def _exported_problems(run_file: Path, folder: Path) -> dict | None:
    """The summary of the problems already exported from ``run_file`` into ``folder`` (a build run again
    over complete runs: the export, which solves every recorded problem exactly, is the longest part of it),
    or None when they must be exported: no ``problems.h5``, one exported from another file, or older than
    the run file (the run was made again since). ``fclib_holdable`` is None for a file written before it was
    recorded."""
    import h5py

    path = folder / "problems.h5"
    if not path.is_file() or path.stat().st_mtime < Path(run_file).stat().st_mtime:
        return None
    try:
        with h5py.File(path, "r") as handle:
            attributes = dict(handle.attrs)
    except OSError:
        return None
    if str(attributes.get("source", "")) != str(run_file):
        return None
    recorded = attributes.get("recorded_steps")
    if recorded is None:  # "20 of the 710 recorded steps, evenly spaced"
        recorded = int(str(attributes.get("selection", "")).split(" of the ")[1].split()[0])
    kept = sorted((folder / "fclib").glob("*.hdf5")) if (folder / "fclib").is_dir() else []
    holdable = attributes.get("fclib_holdable")
    return {
        "count": int(attributes["problem_count"]),
        "recorded": int(recorded),
        "fclib": len(kept),
        "fclib_steps": [int(path.stem.split("_")[1]) for path in kept],
        "fclib_holdable": None if holdable is None else int(holdable),
    }


def read_case_reference(folder, case_name: str) -> dict:
    """The answers of one case from a package: attributes, ``h``, and ``quantities`` {name: {kind, unit,
    x_unit, at, value, uncertainty, band, levels, order, gci, method, ...}}.

    Raises
    ------
    ValueError
        When the package has no such case (naming the cases it has) or the file is not a case file.
    """
    import h5py

    folder = Path(folder)
    path = folder / "cases" / case_name / "reference.h5"
    if not path.is_file():
        held = sorted(p.name for p in (folder / "cases").glob("*")) if (folder / "cases").is_dir() else []
        raise ValueError(
            f"{folder}: no reference for case {case_name!r} (cases in the package: "
            f"{', '.join(held) or 'none'}; build it with: refsim reference build -o DIR)"
        )

    def plain(value):
        if isinstance(value, bytes):
            return value.decode()
        if isinstance(value, np.generic):
            return value.item()
        return value

    with h5py.File(path, "r") as handle:
        if plain(handle.attrs.get("format")) != CASE_FORMAT:
            raise ValueError(f"{path}: not a reference case file (format {handle.attrs.get('format')!r})")
        out = {
            "attributes": {k: plain(v) for k, v in handle.attrs.items()},
            "h": handle["h"][()],
            "path": path,
        }
        quantities = {}
        for name, group in handle["quantities"].items():
            entry = {k: plain(v) for k, v in group.attrs.items()}
            for key in ("at", "value", "uncertainty", "band", "levels", "order", "order_used", "gci"):
                entry[key] = group[key][()]
            entry["safety_factor"] = group["safety_factor"][()]
            entry["method"] = [plain(v) for v in group["method"][()]]
            quantities[name] = entry
        out["quantities"] = quantities
    return out


def check_manifest(folder) -> list[str]:
    """Files of a package whose SHA-256 differs from its manifest's, or that are missing ([] when intact)."""
    folder = Path(folder)
    manifest = json.loads((folder / "manifest.json").read_text(encoding="utf-8"))
    bad = []
    for name, digest in manifest["files"].items():
        path = folder / name
        if not path.is_file() or _sha256(path) != digest:
            bad.append(name)
    return bad


def build_reference(
    output,
    *,
    level: str = "coarse",
    cases=None,
    scheduler: str | None = None,
    workers: int | None = None,
    client=None,
    command: str = "",
    figures: bool = True,
) -> dict:
    """Build the reference set (or some of its cases) at a level into the folder ``output`` and return the
    package's manifest: a folder that already holds a package keeps the cases this build does not make.

    Parameters
    ----------
    output : Package folder (created; runs already complete inside it are reused, like a study's).
    level : "coarse" (seconds per case: the machinery), "standard" (one machine) or "fine" (a cluster, or
        one machine for some cases: docs/reference.md).
    cases : Case names (all built-in cases when None).
    scheduler, workers, client : Where the runs go (:func:`refsim.sweep.run_study`): a Dask scheduler address,
        or a LocalCluster of ``workers`` processes, or an open ``distributed.Client``.
    command : The command line, recorded in the manifest.
    figures : Write the figures.

    Raises
    ------
    ValueError
        For an unknown case or level, or a folder whose manifest.json is not a reference package's, before
        anything runs.
    RuntimeError
        When a run of a case did not complete (naming it).
    """
    from refsim import __version__
    from refsim.io import git_commit
    from refsim.sweep.worker import numerics_digest

    names = list(cases) if cases else case_names()
    loaded = [load_case(name) for name in names]
    for case in loaded:
        case.level(level)
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    meta = {
        "refsim_version": __version__,
        "git_commit": git_commit(),
        "numerics_digest": numerics_digest(),
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": command or f"build_reference({str(output)!r}, level={level!r}, cases={names!r})",
    }
    from refsim.sweep.study import start_client, stop_client

    kept = _kept_cases(output, names)
    own = client is None and any(case.runner == "scene" for case in loaded)
    if own:
        client, cluster = start_client(scheduler, workers)
    start = time.perf_counter()
    built = {}
    try:
        for case in loaded:
            built[case.name] = {
                **_build_case(case, level, output, client, meta, figures),
                "level": level,
                "build": dict(meta),
            }
    finally:
        if own:
            stop_client(client, cluster)  # also removes a LocalCluster's scratch folder
    every = {**kept, **built}
    order = {name: index for index, name in enumerate(case_names())}
    manifest = {
        "format": MANIFEST_FORMAT,
        "schema_version": SCHEMA_VERSION,
        "level": level,
        **meta,
        "seconds": time.perf_counter() - start,
        "cases": {name: every[name] for name in sorted(every, key=lambda n: (order.get(n, len(order)), n))},
    }
    _write_manifest(output, manifest)
    return manifest


def _kept_cases(output: Path, building) -> dict:
    """The manifest entries of the cases a package in ``output`` already holds and this build does not make
    (their answers still in the folder), each with its level and its build's provenance (a schema-1
    manifest's, which has them once for all its cases); {} for a folder without a package.

    Raises
    ------
    ValueError
        When ``output`` holds a manifest.json that is not a reference package's (naming it).
    """
    path = output / "manifest.json"
    if not path.is_file():
        return {}
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as error:
        raise ValueError(f"{path}: not a readable reference manifest ({error})") from error
    if manifest.get("format") != MANIFEST_FORMAT or manifest.get("schema_version") not in (1, SCHEMA_VERSION):
        raise ValueError(
            f"{path}: format {manifest.get('format')!r}, schema version {manifest.get('schema_version')!r}; "
            f"a reference package is {MANIFEST_FORMAT!r}, schema 1 or {SCHEMA_VERSION}"
        )
    provenance = {key: manifest.get(key) for key in PROVENANCE}
    kept = {}
    for name, entry in manifest.get("cases", {}).items():
        if name in building or not (output / "cases" / name / "reference.h5").is_file():
            continue
        kept[name] = {"level": manifest.get("level"), "build": provenance, **entry}
    return kept


#: The fields of a build's provenance (the manifest's top level, and each case's "build").
PROVENANCE = ("refsim_version", "git_commit", "numerics_digest", "created", "command")


#: Scene keys that name a file, relative to the scene's folder (copied into the package with the scene).
SCENE_FILES = (("mesh", "file"), ("trajectory", "file"), ("boundary", "file"))


def _copy_scene(scene_path: Path, folder: Path) -> list[str]:
    """Copy the scene to ``folder/scene.toml`` with the files it names (a mesh, a trajectory, a boundary
    motion; :data:`SCENE_FILES`) beside it, its paths rewritten to the copies' names; returns those names."""
    import tomllib

    text = scene_path.read_text(encoding="utf-8")
    data = tomllib.loads(text)
    copied = []
    for section, key in SCENE_FILES:
        name = data.get(section, {}).get(key)
        if not name:
            continue
        source = Path(name) if Path(name).is_absolute() else scene_path.parent / name
        shutil.copyfile(source, folder / source.name)
        text = text.replace(f'"{name}"', f'"{source.name}"')
        copied.append(source.name)
    (folder / "scene.toml").write_text(text, encoding="utf-8")
    return copied


def _build_case(case: Case, level: str, output: Path, client, meta: dict, figures: bool) -> dict:
    """Run one case's levels, write its answers (HDF5, CSV), problems and figure into the package, and return
    its manifest entry."""
    case_start = time.perf_counter()
    folder = output / "cases" / case.name
    folder.mkdir(parents=True, exist_ok=True)
    if case.runner == "scene":
        # the scene the runs are made from, before they are (an interrupted build keeps it)
        _copy_scene(case.scene_path, folder)
        values, files, info = _run_scene_case(case, level, folder, client)
    else:
        values, files, info = _run_cantilever_case(case, level)
    shutil.copyfile(case.path, folder / "case.toml")
    spacings = case.spacings(level)
    answers = _answers(case, spacings, values)
    _write_case_h5(folder / "reference.h5", case, level, spacings, answers, files, info, meta)
    _write_case_csv(folder / "reference.csv", case, answers)
    problems = _export_problems(folder / files[-1], folder) if files else None
    if figures:
        (output / "figures").mkdir(exist_ok=True)
        _figure(output / "figures" / f"{case.name}.png", case, spacings, answers)
    return {
        "title": case.title,
        "runner": case.runner,
        "refine": case.refine,
        "formal_order": case.formal_order,
        "levels": case.level(level),
        "h": spacings.tolist(),
        "seconds": time.perf_counter() - case_start,
        "run_seconds": info["run_seconds"],
        "problems": problems,
        "quantities": {
            q.name: {
                "kind": q.kind,
                "unit": q.unit,
                "methods": sorted(set(answers[q.name]["method"])),
                "status": worst_status(
                    convergence_status(m, f)
                    for m, f in zip(answers[q.name]["method"], answers[q.name]["safety_factor"], strict=True)
                ),
                "largest_relative_uncertainty": _largest_relative(answers[q.name]),
                "modelling_tolerance_relative": q.tolerance,
            }
            for q in case.quantities
        },
    }


def _write_manifest(output: Path, manifest: dict) -> None:
    """Add the SHA-256 of every file of the package to ``manifest`` and write it (atomically)."""
    manifest["files"] = {
        str(path.relative_to(output)): _sha256(path)
        for path in sorted(output.rglob("*"))
        if path.is_file() and path.name != "manifest.json" and not path.name.endswith(".tmp")
    }
    temporary = output / "manifest.json.tmp"
    temporary.write_text(
        json.dumps(manifest, indent=1, sort_keys=True, default=float) + "\n", encoding="utf-8"
    )
    temporary.replace(output / "manifest.json")


def _largest_relative(answer) -> float:
    """max U/scale over the samples of a quantity [-] (NaN when it has no finite value)."""
    if not math.isfinite(answer["scale"]) or answer["scale"] == 0.0:
        return float("nan")
    return float(np.nanmax(answer["uncertainty"]) / answer["scale"])
