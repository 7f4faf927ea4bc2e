"""Declarative, validated fields for the scene dataclasses.

Each field of a scene section carries its unit, its valid range and a one-line description; `check_fields`
validates a dataclass instance against them and raises a `ValueError` that names the field, the value and the
valid range. The TOML loader turns that into a `SceneError` that also names the file and the section.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

__all__ = ["spec", "check_fields", "describe_field"]


def spec(
    default: Any = dataclasses.MISSING,
    *,
    unit: str = "",
    doc: str,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    choices: tuple | None = None,
    length: int | None = None,
) -> Any:
    """A dataclass field with validation metadata (unit, range, choices, vector length)."""
    metadata = dict(
        unit=unit, doc=doc, low=low, high=high, low_open=low_open, high_open=high_open, choices=choices, length=length
    )
    if isinstance(default, (list, dict)):
        raise TypeError("use tuples for defaults")
    return dataclasses.field(default=default, metadata=metadata)


def describe_field(field: dataclasses.Field) -> str:
    """The valid range of a field, in words, e.g. "a number in (0, 0.5) [-]"."""
    meta = field.metadata
    if meta.get("choices"):
        return "one of " + ", ".join(repr(c) for c in meta["choices"])
    low, high = meta.get("low"), meta.get("high")
    left = "(" if meta.get("low_open") else "["
    right = ")" if meta.get("high_open") else "]"
    interval = f"{left}{'-inf' if low is None else low}, {'inf' if high is None else high}{right}"
    unit = f" [{meta['unit']}]" if meta.get("unit") else ""
    if meta.get("length"):
        return f"{meta['length']} numbers in {interval}{unit}"
    return f"a number in {interval}{unit}"


def _check_number(name: str, value: Any, field: dataclasses.Field) -> None:
    meta = field.metadata
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} = {value!r}: expected {describe_field(field)}")
    if not math.isfinite(value):
        raise ValueError(f"{name} = {value!r}: expected a finite number, {describe_field(field)}")
    low, high = meta.get("low"), meta.get("high")
    too_low = low is not None and (value <= low if meta.get("low_open") else value < low)
    too_high = high is not None and (value >= high if meta.get("high_open") else value > high)
    if too_low or too_high:
        raise ValueError(f"{name} = {value!r} is out of range: expected {describe_field(field)}")


def check_fields(instance: Any) -> None:
    """Validate every field of a dataclass instance that has `spec` metadata.

    Raises
    ------
    ValueError
        Naming the field, its value and the valid range.
    """
    for field in dataclasses.fields(instance):
        meta = field.metadata
        if "doc" not in meta:
            continue
        value = getattr(instance, field.name)
        if value is None:
            continue
        if meta.get("choices"):
            if value not in meta["choices"]:
                raise ValueError(f"{field.name} = {value!r}: expected {describe_field(field)}")
            continue
        if meta.get("length"):
            if not isinstance(value, tuple) or len(value) != meta["length"]:
                raise ValueError(f"{field.name} = {value!r}: expected {describe_field(field)}")
            for item in value:
                _check_number(field.name, item, field)
            continue
        if isinstance(value, (tuple, str, bool)):
            continue  # tuples of varying length and strings are checked by the section's own validate()
        if meta.get("low") is not None or meta.get("high") is not None or meta.get("unit"):
            _check_number(field.name, value, field)
