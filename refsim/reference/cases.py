"""The reference cases: their specification files and the quantities of interest read from a run.

A case is two plain TOML files in ``refsim/reference/cases/``: ``NAME.toml`` (the case: what it checks, its
set-up in words, its refinement levels, its quantities with their sampling points, units and modelling
tolerances) and, for a simulated case, ``NAME.scene.toml`` (an ordinary refsim scene: geometry, supports,
materials, needle, trajectory and every parameter, in SI units, commented). Case file::

    [case]
    title = "..."
    scene = "NAME.scene.toml"      # or runner = "cantilever" (the needle alone, solved statically)
    set = ["section.key=value"]    # optional: overrides of the scene for every run (a variant of a scene)
    why = "..."                    # why another implementation needs this case
    setup = "..."                  # the set-up in words, enough to build it without refsim
    refine = "mesh.cells"          # the key whose value gives the refinement measure h
    measure = "inverse"            # optional: h = 1/value (a count, the default) or "value" (h = value: dt)
    formal_order = 1               # order of the discretisation refined together (1: implicit Euler's dt)
    note = "..."                   # optional: what the answers show about the model (for the page)

    [levels]                       # level name -> {key: values}; the i-th values form run i (coarsest first)
    coarse = { "mesh.cells" = [2, 3, 4], "time.dt" = [0.012, 0.008, 0.006] }

    [[quantity]]                   # a curve: y sampled at the abscissae ``at``
    name = "indentation_force"
    y = "axial_force"              # see CURVE_VALUES
    x = "base_travel"              # see ABSCISSAE
    at = [0.24e-3, 0.26e-3]
    width = 2e-3                   # optional: each sample is the mean of y over [at - width/2, at + width/2]
    window = [t0, t1]              # optional: only the steps with t0 <= time <= t1 [s]
    until = "puncture"             # optional: only the steps before the first such event
    unit = "N"
    x_unit = "m"
    tolerance = 0.01               # modelling tolerance, relative to the quantity's scale (see MODELLING)
    tolerance_note = "..."         # why this tolerance

    [[quantity]]                   # a scalar: a study quantity (refsim.sweep.quantities) ...
    name = "puncture_force"
    source = "puncture_force"
    [[quantity]]                   # ... or an abscissa at the first step of an event (NaN without one)
    name = "travel_at_puncture"
    x = "base_travel"
    event = "puncture"
    crossing = true                # optional: where the event's criterion met its threshold (between steps)
    [[quantity]]                   # ... or whether an event happens: 1 when it does, 0 when not
    name = "cuts"
    event = "cut_start"

Abscissae and curve values are read per step from a results file (:class:`refsim.io.Results`); a curve is
sampled by linear interpolation in its abscissa over the selected steps, which must not decrease. With
``width`` each sample is the mean of that piecewise-linear curve over a window of the abscissa
(:func:`sample_curve`): a quantity smooth in h where the curve is a staircase or a saw-tooth whose steps are
set by the discretisation (a friction force growing by one insertion point every d_i of depth, a cut force
dropping at each tear), so that a point sample would land on a step at one level and between two at the next.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

__all__ = [
    "ABSCISSAE",
    "CURVE_VALUES",
    "Case",
    "Quantity",
    "case_names",
    "case_values",
    "load_case",
    "results_values",
    "sample_curve",
]

#: Abscissae of curves [unit]: base travel along the initial needle axis, tip depth below the entry point,
#: lateral stroke of the base across the initial axis, time.
ABSCISSAE = {"base_travel": "m", "tip_depth": "m", "lateral_stroke": "m", "time": "s"}
#: Curve values per step [unit]: axial force (resisting insertion = positive), lateral force norm, force norm,
#: cut surface area in rest coordinates.
CURVE_VALUES = {"axial_force": "N", "lateral_force": "N", "needle_force": "N", "cut_area": "m^2"}
RUNNERS = ("scene", "cantilever")
#: How the refined key's value gives the refinement measure h (refsim.sweep.Sweep's measures).
MEASURES = ("inverse", "value")


def _folder():
    return resources.files("refsim.reference") / "cases"


def case_names() -> list[str]:
    """Names of the built-in cases, sorted."""
    return sorted(
        entry.name[: -len(".toml")]
        for entry in _folder().iterdir()
        if entry.name.endswith(".toml") and not entry.name.endswith(".scene.toml")
    )


@dataclass(frozen=True)
class Quantity:
    """One quantity of interest of a case.

    Attributes
    ----------
    name : Its name (a CSV ``quantity`` value).
    kind : "curve" (values at the abscissae ``at``) or "scalar".
    unit, x_unit : Units of the values and of the abscissa ("" for a scalar).
    at : Sampling points of a curve, in ``x_unit``, shape (k,); empty for a scalar.
    width : Averaging window of a curve's samples, in ``x_unit``: each is the mean of the curve over
        [at − width/2, at + width/2]; 0 for a point sample.
    y, x : Curve value and abscissa names (:data:`CURVE_VALUES`, :data:`ABSCISSAE`); a scalar read at an event
        has ``x`` and ``event``.
    source : A study quantity name (refsim.sweep.quantities) for a scalar read by the study machinery.
    event : Event name for a scalar abscissa at the event (with ``x``), or for whether it happens (1 or 0,
        without ``x``).
    crossing : For an abscissa at an event: read where the event's criterion (the run's ``criteria/``, e.g.
        the cut-start load against its threshold) reached its threshold, interpolated linearly between the
        step before the event and the event's step, instead of at the event's step (which snaps the event to
        the time grid: an error of up to one step that is not smooth in h).
    window : (t0, t1) [s]: the steps a curve is read from; None for all.
    until : Event before whose first step a curve stops; "" for none.
    tolerance : Modelling tolerance relative to the quantity's scale [-].
    tolerance_note, description, closed_form : Texts for the page.
    """

    name: str
    kind: str
    unit: str
    x_unit: str = ""
    at: tuple = ()
    width: float = 0.0
    y: str = ""
    x: str = ""
    source: str = ""
    event: str = ""
    crossing: bool = False
    window: tuple | None = None
    until: str = ""
    tolerance: float = 0.01
    tolerance_note: str = ""
    description: str = ""
    closed_form: str = ""


@dataclass(frozen=True)
class Case:
    """A reference case read from its file (see the module docstring)."""

    name: str
    title: str
    why: str
    setup: str
    runner: str
    refine: str
    formal_order: float
    levels: dict
    quantities: tuple
    path: Path
    scene_path: Path | None = None
    overrides: tuple = ()
    cantilever: dict = field(default_factory=dict)
    note: str = ""
    measure: str = "inverse"

    def level(self, level: str) -> dict:
        """{key: values} of a level.

        Raises
        ------
        ValueError
            For an unknown level (naming the valid ones).
        """
        if level not in self.levels:
            raise ValueError(
                f"{self.path}: case {self.name!r} has no level {level!r} (levels: {', '.join(self.levels)})"
            )
        return self.levels[level]

    def spacings(self, level: str) -> np.ndarray:
        """Refinement measure h of each run of a level (1/value of the refined key, or its value for
        ``measure = "value"``), shape (L,)."""
        values = np.asarray(self.level(level)[self.refine], dtype=float)
        return values if self.measure == "value" else 1.0 / values

    def quantity(self, name: str) -> Quantity:
        """The quantity called ``name``; a ValueError naming the known ones otherwise."""
        for quantity in self.quantities:
            if quantity.name == name:
                return quantity
        known = ", ".join(q.name for q in self.quantities)
        raise ValueError(f"case {self.name!r}: no quantity {name!r} (quantities: {known})")


def _fail(path, where: str, message: str):
    raise ValueError(f"{path}: {where}: {message}")


def _quantity(path: Path, index: int, table: dict) -> Quantity:
    where = f"[[quantity]] {index + 1}"
    known = {
        "name",
        "y",
        "x",
        "at",
        "width",
        "window",
        "until",
        "unit",
        "x_unit",
        "tolerance",
        "tolerance_note",
        "description",
        "source",
        "event",
        "crossing",
        "closed_form",
    }
    unknown = sorted(set(table) - known)
    if unknown:
        _fail(path, where, f"unknown key {unknown[0]!r} (keys: {', '.join(sorted(known))})")
    if "name" not in table or "unit" not in table:
        _fail(path, where, "needs name and unit")
    tolerance = table.get("tolerance", 0.01)
    if not (isinstance(tolerance, (int, float)) and 0.0 <= tolerance < 1.0):
        _fail(path, where, f"tolerance = {tolerance!r}: expected a relative tolerance in [0, 1)")
    common = dict(
        name=str(table["name"]),
        unit=str(table["unit"]),
        tolerance=float(tolerance),
        tolerance_note=str(table.get("tolerance_note", "")),
        description=str(table.get("description", "")),
        closed_form=str(table.get("closed_form", "")),
    )
    if "y" in table:
        if table["y"] not in CURVE_VALUES:
            _fail(path, where, f"y = {table['y']!r}: expected one of {', '.join(CURVE_VALUES)}")
        if table.get("x") not in ABSCISSAE:
            _fail(path, where, f"x = {table.get('x')!r}: expected one of {', '.join(ABSCISSAE)}")
        at = table.get("at", [])
        if not at or not all(isinstance(v, (int, float)) for v in at) or np.any(np.diff(at) <= 0.0):
            _fail(path, where, f"at = {at!r}: expected increasing sampling points")
        window = table.get("window")
        if window is not None and (len(window) != 2 or not window[0] < window[1]):
            _fail(path, where, f"window = {window!r}: expected [t0, t1] with t0 < t1 [s]")
        width = table.get("width", 0.0)
        if not (isinstance(width, (int, float)) and math.isfinite(width) and width >= 0.0):
            _fail(path, where, f"width = {width!r}: expected an averaging window >= 0 in the abscissa's unit")
        return Quantity(
            kind="curve",
            x_unit=str(table.get("x_unit", ABSCISSAE[table["x"]])),
            at=tuple(float(v) for v in at),
            width=float(width),
            y=table["y"],
            x=table["x"],
            window=None if window is None else (float(window[0]), float(window[1])),
            until=str(table.get("until", "")),
            **common,
        )
    if "source" in table:
        return Quantity(kind="scalar", source=str(table["source"]), **common)
    if "x" in table and "event" in table:
        if table["x"] not in ABSCISSAE:
            _fail(path, where, f"x = {table['x']!r}: expected one of {', '.join(ABSCISSAE)}")
        crossing = table.get("crossing", False)
        if not isinstance(crossing, bool):
            _fail(path, where, f"crossing = {crossing!r}: expected true or false")
        return Quantity(kind="scalar", x=table["x"], event=str(table["event"]), crossing=crossing, **common)
    if "event" in table:
        return Quantity(kind="scalar", event=str(table["event"]), **common)
    return _fail(path, where, "expected y and x (a curve), source, x and event, or event alone (a scalar)")


def load_case(name_or_path) -> Case:
    """Read a case by built-in name or path.

    Raises
    ------
    ValueError
        For an unknown case (naming the built-in ones) or a malformed file (naming the file and key).
    """
    text = str(name_or_path)
    if text.endswith(".toml"):
        path = Path(text)
    else:
        if text not in case_names():
            raise ValueError(f"unknown reference case {text!r}; cases: {', '.join(case_names())}")
        path = Path(str(_folder() / f"{text}.toml"))
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ValueError(f"{path}: no such case file") from None
    except tomllib.TOMLDecodeError as error:
        raise ValueError(f"{path}: not valid TOML: {error}") from None
    head = data.get("case", {})
    for key in ("title", "why", "setup", "refine", "formal_order"):
        if key not in head:
            _fail(path, "[case]", f"missing key {key!r}")
    runner = str(head.get("runner", "scene"))
    if runner not in RUNNERS:
        _fail(path, "[case] runner", f"{runner!r}: expected one of {', '.join(RUNNERS)}")
    scene_path = None
    if runner == "scene":
        if "scene" not in head:
            _fail(path, "[case]", "missing key 'scene' (the case's scene file)")
        scene_path = (path.parent / head["scene"]).resolve()
        if not scene_path.is_file():
            _fail(path, "[case] scene", f"{scene_path}: no such scene file")
    measure = str(head.get("measure", "inverse"))
    if measure not in MEASURES:
        _fail(path, "[case] measure", f"{measure!r}: expected one of {', '.join(MEASURES)}")
    formal_order = head["formal_order"]
    if not (isinstance(formal_order, (int, float)) and 0.0 < formal_order <= 4.0):
        _fail(path, "[case] formal_order", f"{formal_order!r}: expected a number in (0, 4]")
    overrides = head.get("set", [])
    if not isinstance(overrides, list) or not all(isinstance(v, str) for v in overrides):
        _fail(path, "[case] set", f"{overrides!r}: expected a list of 'section.key=value' strings")
    levels = data.get("levels", {})
    if not levels:
        _fail(path, "[levels]", "no level")
    for level, keys in levels.items():
        counts = {len(v) for v in keys.values()}
        if head["refine"] not in keys or len(counts) != 1 or counts.pop() < 3:
            _fail(
                path,
                f"[levels] {level}",
                f"expected at least three values of {head['refine']!r} and as many of every other key",
            )
        refined = np.asarray(keys[head["refine"]], dtype=float)
        spacing = refined if measure == "value" else 1.0 / refined
        if not np.all(refined > 0.0) or np.any(np.diff(spacing) >= 0.0):
            expected = "decreasing" if measure == "value" else "increasing"
            _fail(
                path,
                f"[levels] {level}",
                f"{head['refine']} = {keys[head['refine']]}: expected positive, {expected} (coarsest first)",
            )
    quantities = tuple(_quantity(path, i, t) for i, t in enumerate(data.get("quantity", [])))
    if not quantities:
        _fail(path, "[[quantity]]", "no quantity")
    return Case(
        name=path.stem,
        title=str(head["title"]),
        why=" ".join(str(head["why"]).split()),
        setup=" ".join(str(head["setup"]).split()),
        runner=runner,
        refine=str(head["refine"]),
        formal_order=float(formal_order),
        levels={k: {key: list(v) for key, v in keys.items()} for k, keys in levels.items()},
        quantities=quantities,
        path=path,
        scene_path=scene_path,
        overrides=tuple(overrides),
        cantilever=dict(data.get("cantilever", {})),
        note=" ".join(str(head.get("note", "")).split()),
        measure=measure,
    )


# ---------------------------------------------------------------------- reading a run


def _abscissa(results, name: str) -> np.ndarray:
    """Abscissa ``name`` at every step of a run, shape (s,)."""
    if name == "time":
        return np.asarray(results.time, dtype=float)
    if name == "tip_depth":
        return results.tip_depth()
    rest = results.needle_rest_nodes
    axis = (rest[1] - rest[0]) / np.linalg.norm(rest[1] - rest[0])
    moved = results.base_position - rest[0]
    along = moved @ axis
    if name == "base_travel":
        return along
    return np.linalg.norm(moved - along[:, None] * axis, axis=1)  # lateral_stroke


def _curve_value(results, name: str) -> np.ndarray:
    """Curve value ``name`` at every step of a run, shape (s,)."""
    if name == "cut_area":
        area = np.zeros(results.step_count)
        if results.cut is not None and results.cut.triangles.shape[0]:
            from refsim.sweep.quantities import triangle_areas

            areas = triangle_areas(results.cut.points, results.cut.triangles)
            created = np.searchsorted(results.step, results.cut.triangle_step)  # first step holding it
            area = np.cumsum(np.bincount(created, weights=areas, minlength=results.step_count + 1))
            area = area[: results.step_count]
        return area
    if name == "needle_force":
        return np.linalg.norm(results.profile_force, axis=1)
    axial, lateral = results.axial_lateral_force()
    return -axial if name == "axial_force" else lateral


def _steps(results, quantity: Quantity) -> np.ndarray:
    """Mask of the steps a curve is read from, shape (s,)."""
    keep = np.ones(results.step_count, dtype=bool)
    if quantity.window is not None:
        keep &= (results.time >= quantity.window[0] - 1e-12) & (results.time <= quantity.window[1] + 1e-12)
    if quantity.until:
        found = results.events_named(quantity.until)
        if found:
            keep &= results.step < found[0].step
    return keep


def event_crossing(results, event: str, abscissa: np.ndarray) -> float:
    """The abscissa at which the first ``event``'s criterion reached its threshold: linear in the criterion's
    value between the step before the event and the event's step, from the run's ``criteria/``; the abscissa
    at the event's step when the criterion was not evaluated at the step before; NaN without the event.

    Raises
    ------
    ValueError
        When the run records no criterion ``event`` (naming the file): the crossing cannot be read.
    """
    found = results.events_named(event)
    if not found:
        return math.nan
    step = found[0].step
    at_event = float(abscissa[results.index_of(step)])
    criteria = results.criteria
    rows = np.zeros(0, dtype=int)
    if criteria is not None:
        rows = np.flatnonzero((np.asarray(criteria.name) == event) & (np.asarray(criteria.step) <= step))
    if rows.size == 0 or int(criteria.step[rows[-1]]) != step:
        raise ValueError(
            f"{results.path}: no criterion {event!r} recorded at the step of the event {event!r}; its "
            "crossing cannot be read (crossing = true needs the run's criteria/)"
        )
    if rows.size < 2 or int(criteria.step[rows[-2]]) != step - 1 or results.step[0] > step - 1:
        return at_event
    before, after = float(criteria.value[rows[-2]]), float(criteria.value[rows[-1]])
    threshold = float(criteria.threshold[rows[-1]])
    if not before < threshold <= after:
        return at_event
    fraction = (threshold - before) / (after - before)
    previous = float(abscissa[results.index_of(step - 1)])
    return previous + fraction * (at_event - previous)


def sample_curve(x: np.ndarray, y: np.ndarray, at, *, where: str, width: float = 0.0) -> np.ndarray:
    """y interpolated linearly at the points ``at`` of a non-decreasing abscissa x; NaN outside x's range.

    With ``width`` > 0 each sample is the mean of the piecewise-linear curve over [at − width/2,
    at + width/2] (its exact integral, the trapezoid rule on the curve's own points and the window's ends,
    divided by ``width``); NaN where the window leaves x's range.

    Raises
    ------
    ValueError
        When x decreases anywhere (naming ``where``): the curve is not a function of its abscissa.
    """
    x, y, at = np.asarray(x, dtype=float), np.asarray(y, dtype=float), np.asarray(at, dtype=float)
    finite = np.isfinite(x) & np.isfinite(y)
    x, y = x[finite], y[finite]
    if x.size < 2:
        return np.full(at.shape, np.nan)
    scale = max(np.max(np.abs(x)), np.finfo(float).tiny)
    if np.any(np.diff(x) < -1e-9 * scale):
        raise ValueError(f"{where}: the abscissa decreases; expected a non-decreasing abscissa")
    if width > 0.0:
        low, high = at - 0.5 * width, at + 0.5 * width
        # the curve's cumulative integral at its points; at any s it is that at the point before plus the
        # trapezoid from that point to s (y linear in between)
        cumulative = np.concatenate([[0.0], np.cumsum(0.5 * (y[1:] + y[:-1]) * np.diff(x))])

        def integral(s):
            index = np.clip(np.searchsorted(x, s, side="right") - 1, 0, x.size - 2)
            ys = np.interp(s, x, y)
            return cumulative[index] + 0.5 * (y[index] + ys) * (s - x[index])

        values = (integral(high) - integral(low)) / width
        outside = (low < x[0] - 1e-12 * scale) | (high > x[-1] + 1e-12 * scale)
    else:
        values = np.interp(at, x, y)
        outside = (at < x[0] - 1e-12 * scale) | (at > x[-1] + 1e-12 * scale)
    values[outside] = np.nan
    return values


def results_values(case: Case, results) -> dict[str, np.ndarray]:
    """Every quantity of ``case`` read from a run's results: {name: values}, shape (k,) for a curve (NaN at
    a sampling point outside what the run covers), () for a scalar (NaN when the run does not have it)."""
    from refsim.sweep.quantities import quantity as study_quantity

    out = {}
    for quantity in case.quantities:
        if quantity.kind == "curve":
            keep = _steps(results, quantity)
            out[quantity.name] = sample_curve(
                _abscissa(results, quantity.x)[keep],
                _curve_value(results, quantity.y)[keep],
                quantity.at,
                where=f"{results.path}: case {case.name}, quantity {quantity.name}",
                width=quantity.width,
            )
        elif quantity.source:
            out[quantity.name] = np.asarray(study_quantity(results, quantity.source), dtype=float)
        elif not quantity.x:
            out[quantity.name] = np.asarray(1.0 if results.events_named(quantity.event) else 0.0)
        elif quantity.crossing:
            out[quantity.name] = np.asarray(
                event_crossing(results, quantity.event, _abscissa(results, quantity.x))
            )
        else:
            found = results.events_named(quantity.event)
            value = math.nan
            if found:
                value = float(_abscissa(results, quantity.x)[results.index_of(found[0].step)])
            out[quantity.name] = np.asarray(value)
    return out


def case_values(case: Case, path) -> dict[str, np.ndarray]:
    """:func:`results_values` of a results file."""
    from refsim.io import read_results

    return results_values(case, read_results(path))
