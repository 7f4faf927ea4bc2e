"""Reading scene files (TOML) into validated :class:`~refsim.scene.spec.Scene` objects."""

from __future__ import annotations

import dataclasses
import json
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from refsim.scene.fields import FieldError, describe_field
from refsim.scene.spec import SECTIONS, ConsistencyError, InstrumentSpec, NeedleSpec, Scene, TrajectorySpec

__all__ = ["SceneError", "load_scene", "scene_from_dict", "scene_to_json", "builtin_scenes", "parse_override"]


class SceneError(ValueError):
    """A scene file or override is invalid; the message names the file, the key, the value and what is
    allowed."""


class InstrumentsOverlap(SceneError):
    """Two instruments' commanded shafts come closer than the sum of their radii
    (:func:`refsim.scene.build.check_instruments_apart`): a :class:`SceneError` a caller drawing trajectories
    can tell from the others by its type (and draw again)."""


def builtin_scenes() -> list[str]:
    """Names of the scenes shipped in ``refsim/scenes/`` (usable as ``refsim run NAME``)."""
    folder = resources.files("refsim") / "scenes"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def _resolve(path_or_name: str | Path) -> Path:
    path = Path(path_or_name)
    if path.suffix == ".toml" or path.exists():
        if path.is_dir():
            raise SceneError(f"{path}: is a directory; expected a scene file (.toml) or a built-in scene")
        if not path.is_file():
            raise SceneError(f"{path}: scene file not found")
        return path
    candidate = Path(str(resources.files("refsim") / "scenes" / f"{path_or_name}.toml"))
    if candidate.is_file():
        return candidate
    raise SceneError(
        f"{path_or_name!r} is neither a scene file nor a built-in scene "
        f"(built-in: {', '.join(builtin_scenes())})"
    )


def _tuples(value: Any) -> Any:
    if isinstance(value, list):
        return tuple(_tuples(v) for v in value)
    return value


def parse_override(text: str) -> tuple[str, str, Any]:
    """Parse ``section.key=value`` (value in TOML syntax; bare words are strings).

    Returns
    -------
    (section, key, value)
    """
    if "=" not in text or "." not in text.split("=", 1)[0]:
        raise SceneError(f"override {text!r}: expected section.key=value, e.g. needle.radius=0.001")
    dotted, raw = text.split("=", 1)
    section, key = (part.strip() for part in dotted.strip().split(".", 1))
    if not section or not key or "." in key:
        raise SceneError(f"override {text!r}: expected section.key=value, e.g. needle.radius=0.001")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return section, key, value


def check_overrides(texts) -> dict[tuple[str, str], str]:
    """The command line's ``--set`` overrides, each key once: ``{(section, key): text}``.

    A key given twice is ambiguous (one of the two values would be dropped without a word), so it is an error
    naming both.

    Raises
    ------
    SceneError
        A malformed override (:func:`parse_override`), or a key given twice.
    """
    seen: dict[tuple[str, str], str] = {}
    for text in texts:
        section, key, _ = parse_override(text)
        if (section, key) in seen:
            raise SceneError(
                f"override --set {text!r}: {section}.{key} is already set by --set {seen[(section, key)]!r}; "
                "give each key once"
            )
        seen[(section, key)] = text
    return seen


def _origin(source: str, overrides: dict, section: str, key: str | None, related=()) -> str:
    """Who gave the value of section.key (or of a related key the check involves): the ``--set`` override when
    there is one, else the file."""
    for candidate in [(section, key), *related]:
        text = overrides.get(candidate)
        if text is not None:
            return f"override --set {text!r} (scene {source})"
    return source


def _qualified(section: str, key: str, message: str) -> str:
    """The message with its leading key named as section.key."""
    return f"{section}.{message}" if message.startswith(key) else f"[{section}] {message}"


def scene_from_dict(
    data: dict, *, source: str = "<memory>", base_directory: str = ".", overrides: dict | None = None
) -> Scene:
    """Build a validated scene from plain data (the TOML document).

    Parameters
    ----------
    data : The TOML document as plain data.
    source : The file it came from (named in messages).
    base_directory : Relative paths in the scene are relative to this folder.
    overrides : ``{(section, key): "section.key=value"}`` for values given by ``--set``: an error in such a
        value is blamed on the override, not on the file.

    Raises
    ------
    SceneError
        Naming the file or the override, section.key, the value and what is allowed.
    """
    overrides = overrides or {}
    unknown = sorted(set(data) - set(SECTIONS) - {"name", "instruments"})
    if unknown:
        raise SceneError(f"{source}: unknown section or key {unknown[0]!r} (sections: {', '.join(SECTIONS)})")
    if not isinstance(data.get("name", ""), str):
        raise SceneError(f"{source}: name = {data['name']!r}: expected a string")
    sections = {}
    for name, cls in SECTIONS.items():
        table = data.get(name)
        if name == "trajectory" and "instruments" in data:
            if table is not None:
                raise SceneError(
                    f"{source}: [trajectory] and [[instruments]] are both given: a scene has either one "
                    "needle ([needle] and [trajectory]) or [[instruments]], each with its own trajectory"
                )
            continue
        if table is None:
            if name in ("output", "compliance", "boundary"):
                table = {}
            else:
                raise SceneError(f"{source}: missing section [{name}]")
        if not isinstance(table, dict):
            raise SceneError(f"{source}: [{name}] must be a table, got {table!r}")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        for key in table:
            if key not in fields:
                raise SceneError(
                    f"{_origin(source, overrides, name, key)}: unknown key {name}.{key} "
                    f"(keys of [{name}]: {', '.join(fields)})"
                )
        for key, field in fields.items():
            required = field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING
            if required and key not in table:
                raise SceneError(
                    f"{source}: missing key {name}.{key} ({field.metadata.get('doc', '')}; "
                    f"{describe_field(field)})"
                )
        try:
            sections[name] = cls(**{k: _tuples(v) for k, v in table.items()})
        except FieldError as error:
            raise SceneError(
                f"{_origin(source, overrides, name, error.key, [(name, k) for k in error.related])}: "
                f"{_qualified(name, error.key, str(error))}"
            ) from None
        except (ValueError, TypeError) as error:
            raise SceneError(f"{source}: [{name}] {error}") from None
    if "instruments" in data:
        sections["instruments"] = _instruments(data["instruments"], sections["needle"], source)
        sections["trajectory"] = sections["instruments"][0].trajectory
    try:
        return Scene(
            name=data.get("name", Path(source).stem), source=source, base_directory=base_directory, **sections
        )
    except ConsistencyError as error:
        raise SceneError(
            f"{_origin(source, overrides, error.section, error.key, error.related_keys)}: "
            f"{_qualified(error.section, error.key, str(error))}"
        ) from None


def _built(cls, table: dict, where: str, source: str):
    """``cls(**table)``, a bad value named as ``where.key`` with the file."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for key in table:
        if key not in fields:
            raise SceneError(f"{source}: unknown key {where}.{key} (keys: {', '.join(fields)})")
    try:
        return cls(**{k: _tuples(v) for k, v in table.items()})
    except FieldError as error:
        raise SceneError(f"{source}: {where}.{error}") from None
    except (ValueError, TypeError) as error:
        raise SceneError(f"{source}: {where}: {error}") from None


def _instruments(tables: Any, needle: NeedleSpec, source: str) -> tuple[InstrumentSpec, ...]:
    """The [[instruments]] array: each table's name, cuts, trajectory sub-table and [needle] overrides."""
    if not isinstance(tables, list) or not tables or not all(isinstance(t, dict) for t in tables):
        raise SceneError(
            f"{source}: instruments = {tables!r}: expected an array of tables [[instruments]] (at least "
            "one), each with name and a [instruments.trajectory] sub-table"
        )
    needle_keys = {f.name for f in dataclasses.fields(NeedleSpec)}
    allowed = ("name", "cuts", "trajectory", *needle_keys)
    found = []
    for index, table in enumerate(tables):
        where = f"instruments[{index}]"
        for key in table:
            if key not in allowed:
                raise SceneError(
                    f"{source}: unknown key {where}.{key} (keys: name, cuts, trajectory and the keys of "
                    f"[needle]: {', '.join(sorted(needle_keys))})"
                )
        for key in ("name", "trajectory"):
            if key not in table:
                raise SceneError(f"{source}: missing key {where}.{key}")
        if not isinstance(table["trajectory"], dict):
            raise SceneError(f"{source}: {where}.trajectory must be a table ([{where}.trajectory] keys)")
        trajectory = _built(TrajectorySpec, table["trajectory"], f"{where}.trajectory", source)
        overrides = {key: value for key, value in table.items() if key in needle_keys}
        own_needle = _built(NeedleSpec, {**dataclasses.asdict(needle), **overrides}, where, source)
        found.append(
            _built(
                InstrumentSpec,
                {
                    "name": table["name"],
                    **({"cuts": table["cuts"]} if "cuts" in table else {}),
                    "trajectory": trajectory,
                    "needle": own_needle,
                },
                where,
                source,
            )
        )
    return tuple(found)


def load_scene(path_or_name: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> Scene:
    """Load a scene file, or a built-in scene by name, applying ``section.key=value`` overrides.

    Parameters
    ----------
    path_or_name : A path to a TOML file, or the name of a built-in scene (``cube``, ``cube_cut``, ...).
    overrides : Strings ``section.key=value`` (TOML values), applied after reading; an error in one of them is
        blamed on it (``override --set '...'``), not on the file.
    """
    path = _resolve(path_or_name)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"{path}: not valid TOML: {error}") from None
    except (OSError, UnicodeDecodeError) as error:
        raise SceneError(f"{path}: cannot read the scene file: {error}") from None
    origins = {}
    for text in overrides:
        section, key, value = parse_override(text)
        if section not in SECTIONS:
            raise SceneError(
                f"override {text!r}: unknown section {section!r} (sections: {', '.join(SECTIONS)})"
            )
        if not isinstance(data.get(section, {}), dict):
            raise SceneError(f"{path}: [{section}] must be a table")
        data.setdefault(section, {})[key] = value
        origins[(section, key)] = text
    _replace_mesh_source(data, origins)
    return scene_from_dict(data, source=str(path), base_directory=str(path.parent), overrides=origins)


#: The keys of each kind of mesh source in [mesh]: a generated box, or a file.
_MESH_SOURCES = {"generator": ("generator", "size", "cells", "origin"), "file": ("file", "scale")}


def _replace_mesh_source(data: dict, origins: dict) -> None:
    """An override of ``mesh.file`` on a scene whose mesh is generated (or of ``mesh.generator`` on a scene
    whose mesh is a file) replaces the scene's mesh source: the other kind's keys the file gives are dropped,
    unless an override sets them too (then the section's own check names the conflict). The rest of [mesh]
    (fixed faces, box or nodes) stays."""
    mesh = data.get("mesh")
    if not isinstance(mesh, dict):
        return
    for kind, other in (("file", "generator"), ("generator", "file")):
        if ("mesh", kind) in origins and ("mesh", other) not in origins and other in mesh:
            for key in _MESH_SOURCES[other]:
                if ("mesh", key) not in origins:
                    mesh.pop(key, None)


def scene_to_json(scene: Scene) -> str:
    """The full scene as JSON (stored in the results file's root attributes)."""
    return json.dumps({"source": scene.source, **scene.to_dict()}, sort_keys=True)
