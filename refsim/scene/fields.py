"""Declarative, validated fields for the scene dataclasses.

Each field of a scene section carries its unit, its valid range and a one-line description; `check_fields`
validates a dataclass instance against them: the type first (a number, an integer, true/false, a string, a
list, from the field's annotation), then the range or the choices, and raises a :class:`FieldError` that names
the field, the value and what is allowed. The TOML loader turns that into a `SceneError` that also names the
file (or the ``--set`` override that gave the value) and the section.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

__all__ = ["FieldError", "spec", "check_fields", "describe_field", "field_kind"]


class FieldError(ValueError):
    """A bad value of one field; ``key`` is the field's name (the loader prefixes the section and the source).

    Parameters
    ----------
    key : Field name, e.g. "youngs_modulus".
    message : What is wrong, starting with ``key = value``.
    related : Other keys of the same section the check involves (an override of one of them is blamed).
    """

    def __init__(self, key: str, message: str, related: tuple[str, ...] = ()):
        super().__init__(message)
        self.key = key
        self.related = tuple(related)


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
    integer: bool = False,
) -> Any:
    """A dataclass field with validation metadata (unit, range, choices, vector length, integer items)."""
    metadata = dict(
        unit=unit,
        doc=doc,
        low=low,
        high=high,
        low_open=low_open,
        high_open=high_open,
        choices=choices,
        length=length,
        integer=integer,
    )
    if isinstance(default, (list, dict)):
        raise TypeError("use tuples for defaults")
    return dataclasses.field(default=default, metadata=metadata)


def field_kind(field: dataclasses.Field) -> tuple[str, bool]:
    """The field's value kind from its annotation ("float", "int", "bool", "str", "tuple") and whether None is
    allowed (annotation ``X | None``)."""
    annotation = (
        field.type if isinstance(field.type, str) else getattr(field.type, "__name__", str(field.type))
    )
    parts = [part.strip() for part in annotation.split("|")]
    optional = "None" in parts
    kinds = [part for part in parts if part != "None"]
    return (kinds[0] if kinds else "str"), optional


def describe_field(field: dataclasses.Field) -> str:
    """The valid values of a field, in words, e.g. "a number in (0, 0.5) [-]"."""
    meta = field.metadata
    kind, _ = field_kind(field)
    if meta.get("choices"):
        return "one of " + ", ".join(repr(c) for c in meta["choices"])
    if kind == "bool":
        return "true or false"
    low, high = meta.get("low"), meta.get("high")
    left = "(" if meta.get("low_open") else "["
    right = ")" if meta.get("high_open") else "]"
    interval = (
        f"{left}{'-inf' if low is None else _bound(low)}, {'inf' if high is None else _bound(high)}{right}"
    )
    unit = f" [{meta['unit']}]" if meta.get("unit") else ""
    if meta.get("length"):
        what = "integers" if meta.get("integer") else "numbers"
        return f"{meta['length']} {what} in {interval}{unit}"
    if kind == "tuple" and meta.get("integer"):
        return f"a list of integers in {interval}"
    if kind == "int":
        return f"an integer in {interval}"
    if kind == "str":
        return "a string"
    if kind == "tuple":
        return "a list, see the key's meaning"
    return f"a number in {interval}{unit}"


def _bound(value: float) -> str:
    return repr(value) if abs(value) < 1e6 else f"{value:g}"


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _check_number(name: str, value: Any, field: dataclasses.Field, *, integer: bool = False) -> None:
    meta = field.metadata
    if integer:
        if isinstance(value, bool) or not isinstance(value, int):
            raise FieldError(
                name, f"{name} = {value!r}: expected {describe_field(field)} (got {_type_name(value)})"
            )
    elif not _is_number(value):
        raise FieldError(
            name, f"{name} = {value!r}: expected {describe_field(field)} (got {_type_name(value)})"
        )
    if not math.isfinite(value):
        raise FieldError(name, f"{name} = {value!r}: expected a finite number, {describe_field(field)}")
    low, high = meta.get("low"), meta.get("high")
    too_low = low is not None and (value <= low if meta.get("low_open") else value < low)
    too_high = high is not None and (value >= high if meta.get("high_open") else value > high)
    if too_low or too_high:
        raise FieldError(name, f"{name} = {value!r} is out of range: expected {describe_field(field)}")


def _type_name(value: Any) -> str:
    return {
        bool: "true/false",
        int: "an integer",
        float: "a number",
        str: "a string",
        tuple: "a list",
        dict: "a table",
    }.get(type(value), type(value).__name__)


def check_fields(instance: Any) -> None:
    """Validate every field of a dataclass instance that has `spec` metadata: its type, then its range.

    Raises
    ------
    FieldError
        Naming the field, its value and what is allowed.
    """
    for field in dataclasses.fields(instance):
        meta = field.metadata
        if "doc" not in meta:
            continue
        value = getattr(instance, field.name)
        kind, optional = field_kind(field)
        if value is None:
            if optional:
                continue
            raise FieldError(field.name, f"{field.name} is required: expected {describe_field(field)}")
        name = field.name
        if kind == "bool":
            if not isinstance(value, bool):
                raise FieldError(
                    name, f"{name} = {value!r}: expected true or false (got {_type_name(value)})"
                )
        elif kind == "str":
            if not isinstance(value, str):
                raise FieldError(
                    name, f"{name} = {value!r}: expected {describe_field(field)} (got {_type_name(value)})"
                )
            if meta.get("choices") and value not in meta["choices"]:
                raise FieldError(name, f"{name} = {value!r}: expected {describe_field(field)}")
        elif kind == "tuple":
            if not isinstance(value, tuple):
                raise FieldError(
                    name,
                    f"{name} = {value!r}: expected a list (got {_type_name(value)}); "
                    f"{describe_field(field) if meta.get('length') else meta['doc']}",
                )
            if meta.get("length") or meta.get("integer"):  # a list of numbers: every item checked
                if meta.get("length") and len(value) != meta["length"]:
                    raise FieldError(name, f"{name} = {value!r}: expected {describe_field(field)}")
                for item in value:
                    try:
                        _check_number(name, item, field, integer=bool(meta.get("integer")))
                    except FieldError:
                        raise FieldError(
                            name,
                            f"{name} = {list(value)!r}: expected {describe_field(field)} (item {item!r})",
                        ) from None
        elif kind == "int":
            _check_number(name, value, field, integer=True)
        else:
            _check_number(name, value, field)
