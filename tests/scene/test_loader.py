"""Scene files: every built-in scene loads; every bad input names the file, the key, the value and the
range."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from refsim.scene import SceneError, builtin_scenes, load_scene, scene_from_dict, scene_to_json
from refsim.scene.trajectory import Trajectory, read_trajectory_csv


def test_builtin_scenes_load():
    names = builtin_scenes()
    assert "cube" in names
    for name in names:
        scene = load_scene(name)
        assert scene.name == name
        assert scene.time.step_count >= 1


def test_cube_has_the_papers_values():
    # DESIGN.md, "The paper's scenes": every number the paper gives, as a key of the scene file.
    scene = load_scene("cube")
    assert scene.mesh.size == (0.1, 0.1, 0.1) and scene.mesh.cells == (8, 8, 8)
    assert scene.tissue.youngs_modulus == 500e3 and scene.tissue.poisson_ratio == 0.4
    assert scene.needle.length == 0.32 and scene.needle.radius == 0.008 and scene.needle.element_count == 16
    assert scene.needle.youngs_modulus == 100e9 and scene.needle.poisson_ratio == 0.4
    assert scene.insertion.puncture_force == 0.8 and scene.insertion.spacing == 0.5e-3
    assert scene.cutting.point_spacing == 0.5e-3
    # f_c and f_t belong to the paper's law, whose defaults are the paper's values (cube: the energy law).
    paper = load_scene("cube", ['cutting.law="paper"']).cutting
    assert paper.cutting_force == 1.0 and paper.tearing_force == 1.0


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ("needle.radius=-1", ["cube.toml", "radius", "-1", "(0.0, inf]"]),
        ("needle.colour=1", ["cube.toml", "needle.colour", "keys of [needle]"]),
        ('solver.method="newton"', ["cube.toml", "method", "newton", "gauss_seidel"]),
        ("tissue.poisson_ratio=0.5", ["poisson_ratio", "0.5", "(-1.0, 0.5)"]),
        ("mesh.cells=[8, 8]", ["cells", "3 integers"]),
        ("needle.rigid=1", ["rigid", "true or false"]),
        ("time.dt=0", ["dt", "(0.0, 1.0]"]),
        ('mesh.fixed_faces=["top"]', ["fixed_faces", "top", "zmin"]),
        ("trajectory.times=[0, 2, 1]", ["times", "increasing"]),
        ("insertion.spacing=nan", ["spacing", "finite"]),
    ],
)
def test_bad_values_are_named(override, expected):
    with pytest.raises(SceneError) as caught:
        load_scene("cube", [override])
    message = str(caught.value)
    for fragment in expected:
        assert fragment in message, (fragment, message)


def test_missing_key_and_section_are_named(tmp_path: Path):
    text = (Path(load_scene("cube").source)).read_text()
    broken = tmp_path / "broken.toml"
    broken.write_text(text.replace("puncture_force = 0.8", ""))
    with pytest.raises(SceneError, match=r"broken.toml: missing key insertion.puncture_force"):
        load_scene(broken)
    data = {"name": "x"}
    with pytest.raises(SceneError, match=r"missing section \[mesh\]"):
        scene_from_dict(data, source="memory.toml")


def test_unknown_scene_and_bad_toml(tmp_path: Path):
    with pytest.raises(SceneError, match="neither a scene file nor a built-in scene"):
        load_scene("no_such_scene")
    bad = tmp_path / "bad.toml"
    bad.write_text("[mesh\n")
    with pytest.raises(SceneError, match="bad.toml: not valid TOML"):
        load_scene(bad)


def test_override_changes_value_and_json_round_trip():
    scene = load_scene("cube", ["needle.radius=0.001", "time.duration=0.5"])
    assert scene.needle.radius == 0.001 and scene.time.step_count == 50
    assert '"radius": 0.001' in scene_to_json(scene)


def test_an_override_of_the_mesh_file_replaces_a_generated_mesh(tmp_path: Path):
    # A built-in scene on one's own mesh: --set mesh.file=... replaces the scene's box (its generator, size,
    # cells and origin dropped; its fixed faces kept), and the models are built from the file. The other way
    # round, --set mesh.generator="box" with its size and cells replaces a scene's file. Both kinds set
    # together are still refused, naming both. (Before: "give exactly one of generator or file", and no
    # override could unset the scene's generator.)
    import meshio

    from refsim.mesh.generators import box_mesh
    from refsim.scene.build import build_mesh

    mesh = box_mesh(size=(0.02, 0.03, 0.04), cells=(1, 2, 1))
    path = tmp_path / "mine.vtu"
    meshio.write(path, meshio.Mesh(mesh.rest_positions, [("tetra", mesh.tets)]))
    scene = load_scene("cube", [f'mesh.file="{path}"'])
    assert scene.mesh.file == str(path) and scene.mesh.generator is None and scene.mesh.size is None
    assert scene.mesh.cells is None and scene.mesh.fixed_faces == ("zmin",)
    built = build_mesh(scene.mesh, scene.base_directory)
    assert built.rest_positions.shape == mesh.rest_positions.shape
    boxed = load_scene(
        "liver_rigid", ['mesh.generator="box"', "mesh.size=[0.1, 0.1, 0.1]", "mesh.cells=[2, 2, 2]"]
    )
    assert boxed.mesh.generator == "box" and boxed.mesh.file is None and boxed.mesh.cells == (2, 2, 2)
    with pytest.raises(SceneError, match="give exactly one of generator or file") as error:
        load_scene("cube", [f'mesh.file="{path}"', 'mesh.generator="box"'])
    assert "override --set" in str(error.value)


def test_trajectory_interpolates_and_normalises():
    trajectory = Trajectory(
        np.array([0.0, 1.0]),
        np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]),
        np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]),
    )
    base, direction = trajectory.pose(0.5)
    np.testing.assert_allclose(base, [0.0, 0.0, 0.5])
    np.testing.assert_allclose(np.linalg.norm(direction), 1.0)
    base, _ = trajectory.pose(5.0)  # constant after the last sample
    np.testing.assert_allclose(base, [0.0, 0.0, 0.0])


def test_trajectory_csv(tmp_path: Path):
    good = tmp_path / "robot.csv"
    good.write_text("t,x,y,z,dx,dy,dz\n0,0,0,0.3,0,0,-2\n0.5,0,0,0.29,0,0,-1\n")
    trajectory = read_trajectory_csv(good)
    np.testing.assert_allclose(trajectory.directions[0], [0.0, 0.0, -1.0])
    bad = tmp_path / "bad.csv"
    bad.write_text("0,0,0,0.3,0,0,-1\n0,0,0,0.29,0,0,-1\n")
    with pytest.raises(ValueError, match="bad.csv: times must start at 0 s and increase"):
        read_trajectory_csv(bad)
    with pytest.raises(ValueError, match="missing.csv: trajectory file not found"):
        read_trajectory_csv(tmp_path / "missing.csv")
