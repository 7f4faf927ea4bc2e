"""Validation at load (issue 10): types and ranges of every key, overrides blamed, consistency across
sections, and the checks against the mesh and the trajectory before a run (needle outside the tissue, units,
radius)."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from refsim.scene import SceneError, load_scene
from refsim.scene.build import _warn_unreachable, build_models
from refsim.scene.spec import SECTIONS
from refsim.scene.trajectory import Trajectory

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


def _scene_length_keys():
    from refsim.scene.spec import scene_lengths

    scene = load_scene("cube_cut")
    return sorted({(section, key) for section, key, _ in scene_lengths(scene)})


def test_the_scene_lengths_are_the_strictly_positive_length_keys():
    """The class is found from the fields' metadata (unit m, range (0, ...]), so a new length key joins it;
    the keys of issue 25 are in it."""
    keys = _scene_length_keys()
    expected = [("needle", "radius"), ("cutting", "point_spacing"), ("insertion", "spacing")]
    expected.append(("mesh", "size"))
    assert set(expected) <= set(keys)
    assert ("mesh", "face_tolerance") not in keys  # may be 0: not a length the geometry divides by


@pytest.mark.parametrize("key", ["needle.radius", "cutting.point_spacing", "insertion.contact_distance"])
def test_a_scene_length_below_round_off_is_refused_with_its_floor(key):
    """1000 float64 epsilons of cube_cut's largest coordinate: the base starts at z = 0.422 m and the needle
    is 0.32 m long, so 0.742 m and a floor of 1000 × 2.22e-16 × 0.742 = 1.65e-13 m; 1e-13 is below it,
    2e-13 above (and then refused, if at all, by another check that does not name the floor)."""
    import numpy as np

    floor = 1e3 * np.finfo(float).eps * 0.742
    with pytest.raises(SceneError) as caught:
        load_scene("cube_cut", [f"{key}=1e-13"])
    message = str(caught.value)
    assert f"override --set '{key}=1e-13'" in message and f"{key} = 1e-13 m" in message
    assert f"expected a length >= {floor:.3g} m" in message and "0.742 m" in message
    try:
        load_scene("cube_cut", [f"{key}=2e-13"])
    except SceneError as error:
        assert "expected a length >=" not in str(error)


def test_a_scene_length_beyond_the_largest_coordinate_is_refused():
    message = _message("insertion.contact_distance=1e300")
    assert "insertion.contact_distance = 1e+300 m: expected a length <= 1000 m" in message


def test_the_mesh_sets_the_scale_of_the_scene_lengths():
    """A mesh file's coordinates are only known when it is read: a 2 km mesh raises the floor to
    1000 ε × 2000 m = 4.4e-10 m, and a radius of 1e-10 m, accepted at load (cube: floor 1e-13 m), is refused
    against the mesh, naming the scene file."""
    import numpy as np

    from refsim.mesh import box_mesh
    from refsim.scene.build import check_mesh_lengths

    scene = load_scene("cube", ["needle.radius=1e-10", "insertion.interference=0.0"])
    check_mesh_lengths(scene, box_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1)))
    with pytest.raises(SceneError) as caught:
        check_mesh_lengths(scene, box_mesh(size=(2000.0, 2000.0, 2000.0), cells=(1, 1, 1)))
    floor = 1e3 * np.finfo(float).eps * 2000.0
    message = str(caught.value)
    assert "cube.toml: needle.radius = 1e-10 m" in message and f">= {floor:.3g} m" in message


@pytest.mark.parametrize(
    ("overrides", "fragment"),
    [
        (["trajectory.standoff=1e300"], "trajectory.standoff = 1e+300 m: expected a length <= 1000 m"),
        (["mesh.origin=[0.0, 0.0, 1e300]"], "mesh.origin = [0.0, 0.0, 1e+300]: expected coordinates within"),
    ],
)
def test_a_huge_length_or_coordinate_is_named_not_the_lengths_it_dwarfs(overrides, fragment):
    """The bounds of lengths and coordinates are checked before the floor that is relative to them: a huge
    value is named itself, not a normal length that looks short beside it."""
    assert fragment in _message(*overrides)


def _closest_tip_gap_one_pose_at_a_time(scene, trajectory, bounds) -> float:
    """The tip's closest distance to the bounding box, as the check computed it before it was vectorised:
    the waypoints and 20 points a segment, one ``Trajectory.pose`` call each."""
    length = scene.needle.length
    tips = list(trajectory.base_positions + length * trajectory.directions)
    times = trajectory.times
    for i in range(times.size - 1):
        for t in times[i] + np.linspace(0.0, 1.0, 21) * (times[i + 1] - times[i]):
            base, direction = trajectory.pose(t)
            tips.append(base + length * direction)
    gaps = np.maximum(np.maximum(bounds[0] - np.array(tips), np.array(tips) - bounds[1]), 0.0)
    return float(np.linalg.norm(gaps, axis=1).min())


def test_a_tip_that_never_reaches_the_tissue_warns_as_the_pose_by_pose_check(caplog):
    # The needle turns about its base from +x to +y; halfway, its tip passes L (1, 1, 0)/√2, which only the
    # points between the waypoints see. A box there is reached (no warning); moved out along the diagonal
    # by 3 reaches, it is not, and the warning names the pose-by-pose check's closest distance.
    scene = load_scene("cube", SMALL)
    length = scene.needle.length
    reach = scene.insertion.contact_distance + scene.needle.radius
    trajectory = Trajectory(
        np.array([0.0, 1.0, 1.5]), np.zeros((3, 3)), np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 1.0, 0]])
    )
    base, direction = trajectory.poses(np.linspace(0.0, 1.5, 31))
    for k, t in enumerate(np.linspace(0.0, 1.5, 31)):
        assert np.array_equal(base[k], trajectory.pose(t)[0])
        assert np.array_equal(direction[k], trajectory.pose(t)[1])
    middle = length * np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    half = np.full(3, 0.5 * reach)
    diagonal = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    for shift, warns in ((0.0, False), (3.0 * reach, True)):
        bounds = np.stack([middle - half, middle + half]) + shift * diagonal
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="refsim.scene"):
            _warn_unreachable(scene, trajectory, bounds)
        found = [r.getMessage() for r in caplog.records if "never comes within" in r.getMessage()]
        if not warns:
            assert found == []
            continue
        closest = _closest_tip_gap_one_pose_at_a_time(scene, trajectory, bounds)
        assert closest > reach
        assert len(found) == 1 and f"(closest {closest:.3g} m from its bounding box)" in found[0]
