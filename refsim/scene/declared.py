"""Section fields generated from declarations: a section whose keys depend on a choice (the cutting law, the
boundary motion) gets one dataclass field per key each choice declares, with the declaration's unit, range and
meaning, so a new law or motion adds its keys without touching the section."""

from __future__ import annotations

import dataclasses

from refsim.cutting.laws import CUTTING_LAWS
from refsim.scene.controls import BOUNDARY_MOTIONS
from refsim.scene.fields import spec

__all__ = ["boundary_motion_keys", "cutting_law_keys", "declared_section"]


def declared_section(base: type, declared: list[tuple[str, str, dataclasses.Field]]) -> type:
    """The section's dataclass: ``base`` (named ``_Name``) with one field per key its choices declare
    ``(name, annotation, field with spec metadata)``, named ``Name``; a key declared twice (a key several
    choices read) must be the same declaration."""
    fields: dict[str, tuple[str, str, dataclasses.Field]] = {}
    for name, annotation, field in declared:
        if name in fields and fields[name][2] is not field:
            raise TypeError(f"{base.__name__}: the key {name!r} is declared twice, differently")
        fields.setdefault(name, (name, annotation, field))
    section = dataclasses.make_dataclass(
        base.__name__.lstrip("_"),
        list(fields.values()),
        bases=(base,),
        frozen=True,
        kw_only=True,
        namespace={"__module__": base.__module__, "__doc__": base.__doc__},
    )
    section.__qualname__ = section.__name__
    return section


def cutting_law_keys() -> list[tuple[str, str, dataclasses.Field]]:
    """One ``[cutting]`` field per key a cutting law declares (``refsim.cutting.laws.law_key``): unset (none)
    by default, its range and unit from the declaration; the chosen law's left-out keys take its defaults."""
    declared = []
    for name, law in CUTTING_LAWS.items():
        for field in dataclasses.fields(law):
            if field.name in law.keys:
                meta = dict(field.metadata)
                doc = f"{meta.pop('doc')}; {name} law only"
                declared.append((field.name, f"{field.type} | None", spec(None, doc=doc, **meta)))
    return declared


def boundary_motion_keys() -> list[tuple[str, str, dataclasses.Field]]:
    """One ``[boundary]`` field per key a boundary motion declares (``keys`` of each class of
    ``BOUNDARY_MOTIONS``: name -> (annotation, field))."""
    return [
        (name, annotation, field)
        for motion in BOUNDARY_MOTIONS.values()
        for name, (annotation, field) in motion.keys.items()
    ]
