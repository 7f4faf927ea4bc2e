"""Scene keys declared where they are read: each cutting law's keys (``refsim.cutting.laws.law_key``) and each
boundary motion's (``keys`` of its class) are fields of their section generated from the declaration (unit,
range, default, meaning), and the insertion row builders' options are built from ``[insertion]`` by their
field names."""

from __future__ import annotations

import dataclasses

import pytest

from refsim.constraints.insertion import InsertionOptions
from refsim.cutting.laws import CUTTING_LAWS
from refsim.scene import load_scene
from refsim.scene.controls import BOUNDARY_MOTIONS
from refsim.scene.fields import FieldError
from refsim.scene.spec import BoundarySpec, CuttingSpec

RANGE = ("unit", "low", "high", "low_open", "high_open")


def test_each_cutting_law_key_is_a_cutting_field_of_its_declaration():
    fields = {field.name: field for field in dataclasses.fields(CuttingSpec)}
    for name, law in CUTTING_LAWS.items():
        assert law.keys and set(law.keys) == {field.name for field in dataclasses.fields(law)}
        for declared in dataclasses.fields(law):
            field = fields[declared.name]
            assert {key: field.metadata[key] for key in RANGE} == {
                key: declared.metadata[key] for key in RANGE
            }
            assert field.default is None and field.metadata["doc"].endswith(f"; {name} law only")
            assert law.defaults()[declared.name] == declared.default


def test_each_boundary_motion_key_is_a_boundary_field_of_its_declaration():
    fields = {field.name: field for field in dataclasses.fields(BoundarySpec)}
    for motion in BOUNDARY_MOTIONS.values():
        for name, (_, declared) in motion.keys.items():
            assert fields[name].metadata == declared.metadata
            assert fields[name].default == declared.default


@pytest.mark.parametrize(
    ("key", "value", "law"), [("fracture_energy", 0.0, "energy"), ("extent", -1e-3, "paper")]
)
def test_a_declared_key_out_of_its_declared_range_is_refused(key, value, law):
    with pytest.raises(FieldError, match=f"{key} = {value!r} is out of range"):
        CuttingSpec(enabled=True, point_spacing=1e-3, law=law, **{key: value})


def test_insertion_options_are_the_sections_fields_of_their_names():
    section = load_scene("cube", ["insertion.shaft_static_friction_coefficient=0.4"]).insertion
    options = InsertionOptions.from_section(section)
    assert options.static_friction_coefficient == 0.4  # μ_s (an attribute of the section: a property)
    for field in dataclasses.fields(InsertionOptions):
        assert getattr(options, field.name) == getattr(section, field.name)
