"""Reading scene files (TOML) into validated :class:`~refsim.scene.spec.Scene` objects."""

from __future__ import annotations

import dataclasses
import json
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from refsim.scene.fields import describe_field
from refsim.scene.spec import SECTIONS, Scene

__all__ = ["SceneError", "load_scene", "scene_from_dict", "scene_to_json", "builtin_scenes", "parse_override"]


class SceneError(ValueError):
    """A scene file or override is invalid; the message names the file, the key, the value and what is allowed."""


def builtin_scenes() -> list[str]:
    """Names of the scenes shipped in ``refsim/scenes/`` (usable as ``refsim run NAME``)."""
    folder = resources.files("refsim") / "scenes"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def _resolve(path_or_name: str | Path) -> Path:
    path = Path(path_or_name)
    if path.suffix == ".toml" or path.exists():
        if not path.is_file():
            raise SceneError(f"{path}: scene file not found")
        return path
    candidate = Path(str(resources.files("refsim") / "scenes" / f"{path_or_name}.toml"))
    if candidate.is_file():
        return candidate
    raise SceneError(
        f"{path_or_name!r} is neither a scene file nor a built-in scene (built-in: {', '.join(builtin_scenes())})"
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
    section, key = dotted.strip().split(".", 1)
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    return section, key, value


def scene_from_dict(data: dict, *, source: str = "<memory>", base_directory: str = ".") -> Scene:
    """Build a validated scene from plain data (the TOML document).

    Raises
    ------
    SceneError
        Naming ``source``, the key, the value and what is allowed.
    """
    unknown = sorted(set(data) - set(SECTIONS) - {"name"})
    if unknown:
        raise SceneError(f"{source}: unknown section or key {unknown[0]!r} (sections: {', '.join(SECTIONS)})")
    if not isinstance(data.get("name", ""), str):
        raise SceneError(f"{source}: name = {data['name']!r}: expected a string")
    sections = {}
    for name, cls in SECTIONS.items():
        table = data.get(name)
        if table is None:
            if name in ("output", "compliance"):
                table = {}
            else:
                raise SceneError(f"{source}: missing section [{name}]")
        if not isinstance(table, dict):
            raise SceneError(f"{source}: [{name}] must be a table, got {table!r}")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        for key in table:
            if key not in fields:
                raise SceneError(f"{source}: unknown key {name}.{key} (keys of [{name}]: {', '.join(fields)})")
        for key, field in fields.items():
            required = field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING
            if required and key not in table:
                raise SceneError(
                    f"{source}: missing key {name}.{key} ({field.metadata.get('doc', '')}; {describe_field(field)})"
                )
        try:
            sections[name] = cls(**{k: _tuples(v) for k, v in table.items()})
        except (ValueError, TypeError) as error:
            raise SceneError(f"{source}: [{name}] {error}") from None
    return Scene(
        name=data.get("name", Path(source).stem), source=source, base_directory=base_directory, **sections
    )


def load_scene(path_or_name: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> Scene:
    """Load a scene file, or a built-in scene by name, applying ``section.key=value`` overrides.

    Parameters
    ----------
    path_or_name : A path to a TOML file, or the name of a built-in scene (``cube``, ``cube_cut``, ...).
    overrides : Strings ``section.key=value`` (TOML values), applied after reading.
    """
    path = _resolve(path_or_name)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"{path}: not valid TOML: {error}") from None
    except (OSError, UnicodeDecodeError) as error:
        raise SceneError(f"{path}: cannot read the scene file: {error}") from None
    for text in overrides:
        section, key, value = parse_override(text)
        if section not in SECTIONS:
            raise SceneError(f"override {text!r}: unknown section {section!r} (sections: {', '.join(SECTIONS)})")
        data.setdefault(section, {})[key] = value
    return scene_from_dict(data, source=str(path), base_directory=str(path.parent))


def scene_to_json(scene: Scene) -> str:
    """The full scene as JSON (stored in the results file's root attributes)."""
    return json.dumps({"source": scene.source, **scene.to_dict()}, sort_keys=True)
