"""Aiming helpers (trajectory.entry and its keys) and the fixed-set report of a scene at load.

References: the geometry of a straight insertion. The entry is the closest point of the boundary surface to
trajectory.entry; the needle makes the angle θ = entry_angle with the inward normal n, tilted towards the part
of tilt_towards along the surface, so d = cos θ n + sin θ t̂; the tip starts ``standoff`` before the entry and
ends ``depth`` past it, reached at t = (standoff + depth) / speed. A rigid needle follows its trajectory
exactly, so its tip at the end of a run is entry + depth d to round-off.
"""

from __future__ import annotations

import logging
import tomllib
from pathlib import Path

import numpy as np
import pytest

from refsim.scene import SceneError, scene_from_dict
from refsim.scene.build import build_mesh, build_models, check_held, fixed_nodes

SCENES = Path(__file__).resolve().parents[2] / "refsim" / "scenes"


def _cube(trajectory: dict, **mesh) -> dict:
    with open(SCENES / "cube.toml", "rb") as handle:
        data = tomllib.load(handle)
    data["mesh"]["cells"] = [4, 4, 4]
    data["mesh"].update(mesh)
    data["trajectory"] = trajectory
    data["time"]["duration"] = 0.4
    return data


def _scene(trajectory: dict, **mesh):
    return scene_from_dict(_cube(trajectory, **mesh), source="aim.toml")


def test_the_needle_enters_along_the_inward_normal_at_the_closest_surface_point():
    # A target 5 mm under the top face (z = 0.1 m): the closest surface point is straight above it.
    scene = _scene({"entry": [0.01, 0.02, 0.095], "depth": 0.004, "speed": 0.01, "standoff": 0.001})
    trajectory = build_models(scene).trajectory
    direction = trajectory.directions[0]
    np.testing.assert_allclose(direction, [0.0, 0.0, -1.0], atol=1e-12)
    tips = trajectory.base_positions + scene.needle.length * trajectory.directions
    np.testing.assert_allclose(tips[0], [0.01, 0.02, 0.101], atol=1e-12)
    np.testing.assert_allclose(tips[1], [0.01, 0.02, 0.096], atol=1e-12)
    np.testing.assert_allclose(trajectory.times, [0.0, 0.005 / 0.01], rtol=1e-12)


def test_an_angle_tilts_the_needle_towards_the_given_direction():
    scene = _scene(
        {
            "entry": [0.0, 0.0, 0.12],
            "entry_angle": 30.0,
            "tilt_towards": [1.0, 1.0, 5.0],  # its part along the top face: (1, 1, 0) / √2
            "depth": 0.01,
            "speed": 0.01,
        }
    )
    direction = build_models(scene).trajectory.directions[0]
    theta = np.radians(30.0)
    expected = np.cos(theta) * np.array([0, 0, -1.0]) + np.sin(theta) * np.array([1.0, 1.0, 0]) / np.sqrt(2)
    np.testing.assert_allclose(direction, expected, atol=1e-12)


def test_a_side_face_gives_its_own_normal_and_an_explicit_direction_is_kept():
    scene = _scene({"entry": [0.08, 0.01, 0.05], "entry_direction": [-1.0, 0.0, -1.0], "depth": 0.005,
                    "speed": 0.01})  # fmt: skip
    trajectory = build_models(scene).trajectory
    np.testing.assert_allclose(trajectory.directions[0], np.array([-1.0, 0.0, -1.0]) / np.sqrt(2), atol=1e-12)
    tip_end = trajectory.base_positions[1] + scene.needle.length * trajectory.directions[1]
    np.testing.assert_allclose(tip_end, [0.05, 0.01, 0.05] + 0.005 * trajectory.directions[1], atol=1e-12)


@pytest.mark.parametrize(
    "trajectory, key",
    [
        ({"entry": [0, 0, 0.12], "entry_direction": [0, 0, 1.0], "depth": 0.01, "speed": 0.01},
         "entry_direction"),
        ({"entry": [0, 0, 0.12], "entry_angle": 20.0, "depth": 0.01, "speed": 0.01}, "tilt_towards"),
        ({"entry": [0, 0, 0.12], "entry_angle": 20.0, "tilt_towards": [0, 0, 1.0], "depth": 0.01,
          "speed": 0.01}, "tilt_towards"),
        ({"entry": [0, 0, 0.12], "speed": 0.01}, "depth"),
        ({"entry": [0, 0, 0.12], "depth": 0.01, "speed": 0.01, "times": [0.0]}, "entry"),
        ({"entry": [0, 0, 0.12], "entry_angle": 95.0, "tilt_towards": [1, 0, 0], "depth": 0.01,
          "speed": 0.01}, "entry_angle"),
        ({"times": [0.0], "base_positions": [[0, 0, 0.5]], "directions": [[0, 0, -1]], "depth": 0.01},
         "depth"),
    ],
)  # fmt: skip
def test_bad_aims_name_their_key(trajectory, key):
    with pytest.raises(SceneError, match=rf"trajectory\.{key}|\[trajectory\] {key}\b"):
        build_models(_scene(trajectory))


def test_an_aimed_run_punctures_and_ends_with_the_tip_at_its_depth(tmp_path):
    from refsim.simulation import Simulation

    scene = _scene({"entry": [0.00123, 0.00231, 0.1], "depth": 0.002, "speed": 0.01, "standoff": 0.001})
    records = []
    Simulation(scene).run(on_step=lambda state, record: records.append(record))
    assert [e.name for r in records for e in r.events][:1] == ["puncture"]
    np.testing.assert_allclose(records[-1].needle_positions[-1], [0.00123, 0.00231, 0.098], atol=1e-12)


def test_the_fixed_set_is_reported_and_a_cube_clamped_at_its_base_is_held(caplog):
    with caplog.at_level(logging.INFO, logger="refsim.scene"):
        build_models(_scene({"entry": [0, 0, 0.12], "depth": 0.01, "speed": 0.01}))
    assert "25 fixed tissue nodes of 125, within [-0.05, -0.05, 0.0] .. [0.05, 0.05, 0.0] m" in caplog.text


def test_an_organ_held_by_one_node_is_refused():
    scene = _scene({"entry": [0, 0, 0.12], "depth": 0.01, "speed": 0.01}, fixed_faces=[], fixed_nodes=[0])
    with pytest.raises(SceneError, match=r"the tissue \(125 nodes.*only 1 held node"):
        build_models(scene)


def test_fixed_nodes_on_one_line_and_the_liver_phantom_held_on_zmin_by_one_node_are_refused():
    scene = _scene({"entry": [0, 0, 0.12], "depth": 0.01, "speed": 0.01})
    mesh = build_mesh(scene.mesh)
    rest = mesh.rest_positions
    edge = np.flatnonzero((np.abs(rest[:, 0] + 0.05) < 1e-12) & (np.abs(rest[:, 2]) < 1e-12))
    assert edge.size == 5
    with pytest.raises(SceneError, match="only 5 held node.s. on one line"):
        check_held(scene, mesh, edge)
    check_held(scene, mesh, fixed_nodes(scene.mesh, rest))  # the bottom face holds the box
    from refsim.scene import load_scene

    liver = load_scene("liver_rigid", ['mesh.fixed_faces=["zmin"]'])
    import dataclasses

    spec = dataclasses.replace(liver.mesh, fixed_box=None)
    organ = build_mesh(spec, liver.base_directory)
    held = fixed_nodes(spec, organ.rest_positions)
    assert held.size == 1
    with pytest.raises(SceneError, match=f"the tissue \\({organ.node_count} nodes.*only 1 held node"):
        check_held(liver, organ, held)
