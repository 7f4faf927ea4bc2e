"""Validation at load (issue 10): types and ranges of every key, overrides blamed, consistency across
sections, and the checks against the mesh and the trajectory before a run (needle outside the tissue, units,
radius)."""

from __future__ import annotations

import dataclasses
import logging

import pytest

from refsim.scene import SceneError, load_scene
from refsim.scene.build import build_models
from refsim.scene.spec import SECTIONS

SMALL = ["mesh.cells=[3, 3, 3]", "time.duration=0.1"]


def _message(*overrides: str) -> str:
    with pytest.raises(SceneError) as caught:
        load_scene("cube", list(overrides))
    return str(caught.value)


def _numeric_keys():
    for section, cls in SECTIONS.items():
        for field in dataclasses.fields(cls):
            kind = str(field.type).split("|")[0].strip()
            if kind in ("float", "int"):
                yield section, field.name


@pytest.mark.parametrize(("section", "key"), list(_numeric_keys()))
def test_a_string_in_any_numeric_key_is_refused_and_blamed_on_the_override(section, key):
    override = f'{section}.{key}="soft"'
    message = _message(override)
    assert f"override --set {override!r}" in message  # the override, not the file, is blamed
    assert f"{section}.{key} = 'soft'" in message and "got a string" in message


@pytest.mark.parametrize(
    ("override", "fragments"),
    [
        ('needle.youngs_modulus="soft"', ["needle.youngs_modulus", "(0.0, 1e+13]"]),
        ("insertion.spacing=abc", ["insertion.spacing = 'abc'"]),
        ('time.dt="0.01"', ["time.dt = '0.01'"]),
        ("tissue.density=1e300", ["tissue.density", "out of range", "100000.0"]),
        ("tissue.youngs_modulus=1e308", ["tissue.youngs_modulus", "out of range"]),
        ("tissue.gravity=[0, 0, -1e300]", ["tissue.gravity"]),
        ("needle.element_count=16.0", ["needle.element_count", "an integer"]),
        ("needle.rigid=1", ["needle.rigid", "true or false"]),
        ("output.tissue_every=0", ["output.tissue_every", "[1, 1e+06]"]),
        ("insertion.puncture_force=0", ["insertion.puncture_force", "(0.0, inf]"]),
        ("time.duration=2.205", ["time.duration", "not a whole number", "2.2 or 2.21"]),
        ("time.dt=1", ["dt = 1 s"]),  # blamed on the override of dt although duration is the key checked
        ("insertion.spacing=1", ["insertion.spacing = 1", "needle.length = 0.32"]),
        ("insertion.interference=0.008", ["insertion.interference = 0.008", "needle.radius = 0.008"]),
        (
            "trajectory.directions=[[0, 0, -1], [0, 0, 1], [0, 0, 1]]",
            ["trajectory.directions", "180.0 degrees"],
        ),
        (
            "trajectory.directions=[[0, 0, -1], [1, 0, 0.1], [1, 0, 0.1]]",
            ["trajectory.directions", "less than 90"],
        ),
        ('solver.backend="nosuch"', ["solver.backend = 'nosuch'", "clarabel"]),
        ('mesh.fixed_faces="zmin"', ["mesh.fixed_faces", "expected a list"]),
        ("trajectory.times=abc", ["trajectory.times"]),
        ("needle.radius=0.5", ["needle.radius", "length"]),
    ],
)
def test_bad_values_name_the_override_the_key_and_the_range(override, fragments):
    message = _message(override)
    assert "override --set" in message, message
    for fragment in fragments:
        assert fragment in message, (fragment, message)


def test_dt_against_the_contact_distance():
    # 10 mm/s: one step of 0.25 s moves the tip 2.5 mm, beyond the 2 mm contact distance.
    message = _message("time.dt=0.25", "time.duration=2.0")
    assert "time.dt" in message and "contact_distance" in message and "dt <= 0.2 s" in message


def test_dt_beyond_d_i_is_a_warning(caplog):
    with caplog.at_level(logging.WARNING, logger="refsim.scene"):
        load_scene("cube", ["time.dt=0.1", "time.duration=2.2"])  # 1 mm per step, d_i 0.5 mm
    assert any("several insertion points" in record.message for record in caplog.records)


def test_needle_inside_the_tissue_at_t0_is_refused():
    scene = load_scene(
        "cube",
        SMALL
        + [
            "trajectory.base_positions=[[0.00123, 0.00231, 0.39], "
            "[0.00123, 0.00231, 0.39], [0.00123, 0.00231, 0.39]]"
        ],
    )
    with pytest.raises(SceneError, match="at t = 0 the needle is inside the tissue"):
        build_models(scene)


def test_mesh_in_millimetres_warns_with_the_likely_scale(caplog):
    scene = load_scene("cube", SMALL + ["mesh.size=[100, 100, 100]", "mesh.origin=[-50, -50, -100.3]"])
    with caplog.at_level(logging.WARNING, logger="refsim.scene"):
        build_models(scene)
    assert any("millimetres (mesh.scale = 0.001)" in record.message for record in caplog.records)


def test_needle_wider_than_the_tissue_is_refused():
    scene = load_scene("cube", SMALL + ["needle.radius=0.06"])
    with pytest.raises(SceneError, match="not thinner than the tissue"):
        build_models(scene)


def test_the_builtin_scenes_pass_every_check(caplog):
    with caplog.at_level(logging.WARNING, logger="refsim.scene"):
        for name in ("cube", "cube_cut"):
            build_models(load_scene(name, ["mesh.cells=[4, 4, 4]"]))
    assert not caplog.records
