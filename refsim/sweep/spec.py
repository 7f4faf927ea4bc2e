"""A study: a scene, sweeps over its keys (a product or a zip), extra cases, quantities and a reference run.

A study file (TOML)::

    name = "cube_spacing"                      # optional; the file's stem by default
    scene = "cube"                             # built-in name or a path (relative to the study file)
    set = ["mesh.cells=[4, 4, 4]"]             # overrides applied to every run
    combine = "product"                        # or "zip": the i-th values of every sweep together
    quantities = ["needle_force@end", "puncture_force"]

    [[sweep]]
    key = "insertion.spacing"
    values = [2e-3, 1e-3, 5e-4]
    measure = "value"                          # refinement measure h: "value", "inverse" (1/value) or "none"

    [[case]]                                   # explicit runs added after the sweep's (a Pareto study's
    options) label = "GS tol 1e-4"
    set = ["solver.tolerance=1e-4"]

    [reference]                                # optional: errors of every run are taken against this run
    label = "exact"
    set = ["solver.method=\"exact\""]

On the command line the same is ``refsim study SCENE --sweep key=v1,v2,v3 [--sweep ...] [--zip]``. A scalar
given for a key that takes a fixed-length list (``mesh.cells=4,8``) is repeated (``[4, 4, 4]``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from refsim.sweep.quantities import check_quantity

__all__ = [
    "DEFAULT_QUANTITIES",
    "RunSpec",
    "StudySpec",
    "Sweep",
    "load_study",
    "parse_sweep",
    "study_from_options",
]

#: Quantities recorded when a study names none.
DEFAULT_QUANTITIES = (
    "needle_force@end",
    "axial_force@end",
    "lateral_force@end",
    "puncture_force",
    "cut_area",
    "lateral_stroke@cut_start",
)

#: Refinement measure of a key when the study does not give one: h = 1/value for cell counts, h = value else.
DEFAULT_MEASURES = {"mesh.cells": "inverse"}
MEASURES = ("value", "inverse", "none")


def _field(key: str) -> dataclasses.Field:
    from refsim.scene.spec import SECTIONS

    section, _, name = key.partition(".")
    if section not in SECTIONS or not name:
        raise ValueError(f"sweep key {key!r}: expected section.key with a section of {', '.join(SECTIONS)}")
    fields = {f.name: f for f in dataclasses.fields(SECTIONS[section])}
    if name not in fields:
        raise ValueError(f"sweep key {key!r}: [{section}] has no key {name!r} (keys: {', '.join(fields)})")
    return fields[name]


def _normalise(key: str, value):
    """A sweep value as the scene expects it (a scalar repeated for a fixed-length key)."""
    length = _field(key).metadata.get("length")
    if length and not isinstance(value, (list, tuple)):
        return [value] * length
    if isinstance(value, tuple):
        return list(value)
    return value


def toml_value(value) -> str:
    """A value in TOML syntax (for a ``section.key=value`` override)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return repr(value)


@dataclass(frozen=True)
class Sweep:
    """Values of one scene key; ``measure`` says how a value gives the refinement measure h."""

    key: str
    values: tuple
    measure: str = "value"

    def __post_init__(self) -> None:
        _field(self.key)
        if len(self.values) == 0:
            raise ValueError(f"sweep {self.key}: no values")
        if self.measure not in MEASURES:
            raise ValueError(f"sweep {self.key}: measure = {self.measure!r}; valid: {', '.join(MEASURES)}")
        object.__setattr__(self, "values", tuple(_normalise(self.key, v) for v in self.values))

    def spacing(self, value) -> float:
        """The refinement measure h of ``value`` (NaN for measure "none" or a non-numeric value)."""
        scalar = value[0] if isinstance(value, (list, tuple)) else value
        if self.measure == "none" or isinstance(scalar, (bool, str)):
            return float("nan")
        return float(scalar) if self.measure == "value" else 1.0 / float(scalar)


@dataclass(frozen=True)
class RunSpec:
    """One run of a study: its id (stable, from its scene and overrides), label, swept values and
    overrides."""

    id: str
    label: str
    values: dict
    overrides: tuple

    @property
    def file_name(self) -> str:
        """Name of the run's results file inside the study's run folder."""
        return f"{self.id}.h5"


def _run_id(scene: str, overrides: tuple) -> str:
    """12 hex digits of the SHA-1 of the scene and the overrides: the same run has the same id in any
    study."""
    return hashlib.sha1("\n".join((str(scene),) + tuple(overrides)).encode()).hexdigest()[:12]


# A study name: it becomes a file name (<name>_study.h5) in the working folder, never a path.
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,99}")


def _default_name(stem: str) -> str:
    """A valid study name from a file's stem (other characters become '_')."""
    name = re.sub(r"[^A-Za-z0-9._-]", "_", stem).lstrip("._-")[:100]
    return name or "study"


@dataclass(frozen=True)
class StudySpec:
    """A whole study (see the module docstring for the file format)."""

    name: str
    scene: str
    sweeps: tuple = ()
    combine: str = "product"
    overrides: tuple = ()
    cases: tuple = ()  # ((label, (override, ...)), ...)
    quantities: tuple = DEFAULT_QUANTITIES
    reference: tuple | None = None  # (label, (override, ...))
    source: str = "<command line>"
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not _NAME.fullmatch(self.name):
            raise ValueError(
                f"{self.source}: name = {self.name!r}: a study name must be a plain file name of at most "
                "100 letters, digits, '.', '-' or '_', starting with a letter or a digit (no folder, no "
                "'..'): it names the study file <name>_study.h5 in the working folder when -o is not given"
            )
        if self.combine not in ("product", "zip"):
            raise ValueError(f"{self.source}: combine = {self.combine!r}; valid: 'product', 'zip'")
        keys = [s.key for s in self.sweeps]
        if len(set(keys)) != len(keys):
            raise ValueError(f"{self.source}: key swept twice in {keys}")
        if self.combine == "zip" and len({len(s.values) for s in self.sweeps}) > 1:
            lengths = ", ".join(f"{s.key}: {len(s.values)}" for s in self.sweeps)
            raise ValueError(f"{self.source}: zip needs sweeps of equal length, got {lengths}")
        if not self.sweeps and not self.cases:
            raise ValueError(f"{self.source}: a study needs at least one sweep or case")
        for name in self.quantities:
            check_quantity(name)

    def runs(self) -> list[RunSpec]:
        """Every run of the study, in order: the sweep's combinations, then the cases."""
        runs = []
        if self.sweeps:
            columns = [s.values for s in self.sweeps]
            rows = zip(*columns, strict=True) if self.combine == "zip" else itertools.product(*columns)
            for row in rows:
                values = {s.key: v for s, v in zip(self.sweeps, row, strict=True)}
                overrides = tuple(self.overrides) + tuple(f"{k}={toml_value(v)}" for k, v in values.items())
                label = ", ".join(f"{k}={toml_value(v)}" for k, v in values.items())
                runs.append(RunSpec(_run_id(self.scene, overrides), label, values, overrides))
        for label, case in self.cases:
            overrides = tuple(self.overrides) + tuple(case)
            runs.append(RunSpec(_run_id(self.scene, overrides), label, {}, overrides))
        ids = [run.id for run in runs]
        if len(set(ids)) != len(ids):
            raise ValueError(f"{self.source}: two runs have the same overrides (the same run twice)")
        return runs

    def reference_run(self) -> RunSpec | None:
        """The reference run, or None."""
        if self.reference is None:
            return None
        label, case = self.reference
        overrides = tuple(self.overrides) + tuple(case)
        return RunSpec(_run_id(self.scene, overrides), label, {}, overrides)

    def to_json(self) -> str:
        """The study as JSON (stored in the study file)."""
        return json.dumps(
            {
                "name": self.name,
                "scene": self.scene,
                "combine": self.combine,
                "set": list(self.overrides),
                "sweep": [
                    {"key": s.key, "values": list(s.values), "measure": s.measure} for s in self.sweeps
                ],
                "case": [{"label": label, "set": list(case)} for label, case in self.cases],
                "quantities": list(self.quantities),
                "reference": None
                if self.reference is None
                else {"label": self.reference[0], "set": list(self.reference[1])},
                "source": self.source,
                **self.extra,
            },
            sort_keys=True,
        )


def _split_values(text: str) -> list[str]:
    """Split ``v1,v2,[a, b],v3`` on the commas outside brackets."""
    parts, depth, current = [], 0, ""
    for char in text:
        if char in "[{":
            depth += 1
        elif char in "]}":
            depth -= 1
        if char == "," and depth == 0:
            parts.append(current)
            current = ""
        else:
            current += char
    parts.append(current)
    return [p.strip() for p in parts if p.strip()]


def _toml(raw: str):
    try:
        return tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        return raw


def parse_sweep(text: str, measure: str | None = None) -> Sweep:
    """A sweep from ``section.key=v1,v2,...`` (values in TOML syntax; bare words are strings)."""
    if "=" not in text:
        raise ValueError(
            f"--sweep {text!r}: expected section.key=v1,v2,..., e.g. insertion.spacing=2e-3,1e-3"
        )
    key, raw = text.split("=", 1)
    key = key.strip()
    values = [_toml(v) for v in _split_values(raw)]
    if not values:
        raise ValueError(f"--sweep {text!r}: no values after '='")
    return Sweep(key, tuple(values), measure or DEFAULT_MEASURES.get(key, "value"))


def study_from_options(
    scene: str,
    sweeps: list[str],
    *,
    combine: str = "product",
    overrides=(),
    quantities=None,
    reference=None,
    name: str | None = None,
) -> StudySpec:
    """A study from command-line options (``reference``: overrides of the reference run, or None)."""
    return StudySpec(
        name=name or _default_name(Path(str(scene)).stem),
        scene=str(scene),
        sweeps=tuple(parse_sweep(s) for s in sweeps),
        combine=combine,
        overrides=tuple(overrides or ()),
        quantities=tuple(quantities) if quantities else DEFAULT_QUANTITIES,
        reference=None if reference is None else ("reference", tuple(reference)),
    )


def load_study(path) -> StudySpec:
    """Read a study file (TOML).

    Raises
    ------
    ValueError
        Naming the file and the key for every error.
    """
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: study file not found") from None
    except tomllib.TOMLDecodeError as error:
        raise ValueError(f"{path}: not valid TOML: {error}") from None
    known = {"name", "scene", "set", "combine", "quantities", "sweep", "case", "reference", "plot"}
    if {"mesh", "tissue", "needle"} & set(data):
        raise ValueError(
            f"{path}: a scene file, not a study file; sweep it with: refsim study {path} "
            "--sweep section.key=v1,v2,..."
        )
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"{path}: unknown key {unknown[0]!r} (keys: {', '.join(sorted(known))})")
    if "scene" not in data:
        raise ValueError(f"{path}: missing key 'scene' (a built-in scene name or a scene file)")
    scene = str(data["scene"])
    if scene.endswith(".toml") and not Path(scene).is_absolute():
        scene = str((path.parent / scene).resolve())

    def overrides(table, where: str) -> tuple:
        value = table.get("set", [])
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ValueError(
                f"{path}: {where}set = {value!r}: expected a list of 'section.key=value' strings"
            )
        return tuple(value)

    try:
        sweeps = []
        for index, table in enumerate(data.get("sweep", [])):
            if "key" not in table or "values" not in table:
                raise ValueError(f"[[sweep]] {index + 1}: needs key and values")
            sweeps.append(
                Sweep(
                    table["key"],
                    tuple(table["values"]),
                    table.get("measure", DEFAULT_MEASURES.get(table["key"], "value")),
                )
            )
        cases = tuple(
            (str(t.get("label", f"case {i + 1}")), overrides(t, f"[[case]] {i + 1}: "))
            for i, t in enumerate(data.get("case", []))
        )
        reference = data.get("reference")
        if reference is not None:
            reference = (str(reference.get("label", "reference")), overrides(reference, "[reference] "))
        return StudySpec(
            name=str(data.get("name", _default_name(path.stem))),
            scene=scene,
            sweeps=tuple(sweeps),
            combine=str(data.get("combine", "product")),
            overrides=overrides(data, ""),
            cases=cases,
            quantities=tuple(data.get("quantities", DEFAULT_QUANTITIES)),
            reference=reference,
            source=str(path),
            extra={"plot": data.get("plot", {})},
        )
    except ValueError as error:
        message = str(error)
        raise ValueError(message if message.startswith(str(path)) else f"{path}: {message}") from None
