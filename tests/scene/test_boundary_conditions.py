"""Boundary conditions are what the scene says (issue 25): fixed-node indices checked against the mesh as
read and renumbered with it, every part of the tissue held, boundary motions checked like the needle's
trajectory (per-step travel, sampling, size).

The scenes are the paper's cube on 3³ cells (0.1 m, dt = 10 ms, insertion.contact_distance = 2 mm), built
without running (build_models, build_controls: a fraction of a second each).
"""

from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np
import pytest

import refsim
from refsim.mesh import box_mesh
from refsim.scene import SceneError, load_scene
from refsim.scene.build import build_controls, build_models

SMALL = ["mesh.cells=[3, 3, 3]", "time.duration=0.5"]


def _build(scene):
    models = build_models(scene)
    return models, build_controls(scene, models)


def _scene_with_mesh(tmp_path, positions, tets, *overrides):
    """The cube scene reading its tissue from a .vtu file of these arrays."""
    path = tmp_path / "tissue.vtu"
    meshio.write(path, meshio.Mesh(positions, [("tetra", tets)]))
    text = (Path(refsim.__file__).parent / "scenes" / "cube.toml").read_text()
    scene_file = tmp_path / "scene.toml"
    scene_file.write_text(text.replace('generator = "box"', f'file = "{path}"'))
    return load_scene(scene_file, ["time.duration=0.5", *overrides])


# ---------------------------------------------------------------------- fixed-node indices


@pytest.mark.parametrize(
    ("value", "expected"),
    [("[-1, 3]", r"mesh.fixed_nodes.*-1"), ("[1.5, 3]", r"mesh.fixed_nodes.*1.5"), ("[true]", "fixed_nodes")],
)
def test_fixed_node_indices_must_be_non_negative_integers(value, expected):
    """Before: -1 pinned the last node (Python's indexing) and 1.5 was truncated to node 1."""
    with pytest.raises(ValueError, match=expected):
        load_scene("cube", [*SMALL, f"mesh.fixed_nodes={value}"])


def test_a_fixed_node_index_beyond_the_mesh_is_refused():
    scene = load_scene("cube", [*SMALL, "mesh.fixed_nodes=[64]"])
    with pytest.raises(SceneError, match=r"mesh.fixed_nodes contains 64.* 64 nodes"):
        _build(scene)


def test_fixed_nodes_follow_the_file_numbering_after_renumbering(tmp_path):
    """The file lists an unused node first: the reader drops it and renumbers. mesh.fixed_nodes in the file's
    numbering must still fix the same points (before: the node after each one was fixed)."""
    cube = box_mesh(size=(0.1, 0.1, 0.1), cells=(3, 3, 3), origin=(-0.05, -0.05, 0.0))
    positions = np.vstack([[[1.0, 1.0, 1.0]], cube.rest_positions])
    bottom = np.flatnonzero(np.abs(positions[:, 2]) < 1e-12)
    listed = ", ".join(str(i) for i in bottom)
    scene = _scene_with_mesh(
        tmp_path, positions, np.asarray(cube.tets) + 1, "mesh.fixed_faces=[]", f"mesh.fixed_nodes=[{listed}]"
    )
    models, _ = _build(scene)
    held = models.mesh.rest_positions[models.tissue.fixed_nodes]
    np.testing.assert_array_equal(held, positions[bottom])
    with pytest.raises(SceneError, match="node 0 .* used by no tetrahedron"):
        _build(_scene_with_mesh(tmp_path, positions, np.asarray(cube.tets) + 1, "mesh.fixed_nodes=[0]"))


# ---------------------------------------------------------------------- every part held


def test_a_loose_part_is_refused_with_its_size(tmp_path):
    """Two cubes, the second 5 cm higher: mesh.fixed_faces = ["zmin"] holds only the first. Before, the second
    floated free (or fell under gravity) and the run exited 0."""
    cube = box_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2), origin=(-0.05, -0.05, 0.0))
    positions = np.vstack([cube.rest_positions, cube.rest_positions + [0.2, 0.0, 0.05]])
    tets = np.vstack([cube.tets, np.asarray(cube.tets) + cube.node_count])
    scene = _scene_with_mesh(tmp_path, positions, tets)
    with pytest.raises(SceneError, match=r"part 2 of 2 \(27 nodes, 48 tetrahedra.* no held node"):
        _build(scene)


@pytest.mark.parametrize(
    ("fixed", "how"),
    [("[0]", r"only 1 held node"), ("[0, 1, 2, 3]", r"only 4 held node\(s\) on one line")],
)
def test_a_tissue_held_by_a_point_or_a_line_is_refused(fixed, how):
    """One node leaves three rotations free; nodes on one line (the box's first edge: nodes 0..3 along x)
    leave the rotation about it."""
    scene = load_scene("cube", [*SMALL, "mesh.fixed_faces=[]", f"mesh.fixed_nodes={fixed}"])
    positions = box_mesh(size=(0.1, 0.1, 0.1), cells=(3, 3, 3)).rest_positions
    if "line" in how:
        line = positions[[0, 1, 2, 3]] - positions[0]
        assert np.linalg.matrix_rank(line, tol=1e-12) == 1  # the premise: they are collinear
    with pytest.raises(SceneError, match=f"the tissue .* has {how}"):
        _build(scene)


# ---------------------------------------------------------------------- boundary motions

BOX = "boundary.box=[[-1, -1, -1], [1, 1, 0.001]]"


def _periodic(*extra):
    return load_scene("cube", [*SMALL, "mesh.fixed_faces=[]", 'boundary.motion="periodic"', BOX, *extra])


def test_a_periodic_motion_the_steps_resolve_is_accepted():
    """1 mm at T = 4 s: at most a·π/T·dt = 7.9e-6 m per step."""
    _, controls = _build(_periodic("boundary.amplitude=[0, 0, 0.001]", "boundary.period=4.0"))
    assert controls.boundary is not None


def test_a_period_of_one_step_is_refused():
    """T = dt sampled at the steps is exactly zero motion (aliasing); before, the run said nothing."""
    with pytest.raises(SceneError, match=r"boundary.period = 0.01 s.*Nyquist.*period >= 0.04"):
        _build(_periodic("boundary.amplitude=[0, 0, 0.001]", "boundary.period=0.01"))


def test_a_boundary_jump_beyond_the_contact_distance_is_refused():
    """2 cm at T = 0.2 s: up to a·π/T·dt = 3.1 mm per step, above the 2 mm contact distance."""
    with pytest.raises(SceneError, match=r"in one step .* more than insertion.contact_distance = 0.002"):
        _build(_periodic("boundary.amplitude=[0, 0, 0.02]", "boundary.period=0.2"))


def test_a_displacement_larger_than_the_tissue_is_refused():
    """0.5 m at T = 10 s over 5 s (the peak is reached; 1.6 mm per step at most): more than the cube's 0.17 m
    diagonal."""
    with pytest.raises(SceneError, match=r"by up to 0.5 m, more than the tissue's size \(0.173 m"):
        _build(_periodic("boundary.amplitude=[0, 0, 0.5]", "boundary.period=10.0", "time.duration=5.0"))


def test_an_amplitude_without_a_range_is_refused_at_load():
    """1e300 used to end in an IndexError (exit 3) instead of naming the key."""
    with pytest.raises(ValueError, match=r"boundary.amplitude|amplitude"):
        _periodic("boundary.amplitude=[0, 0, 1e300]")


def _file_motion(tmp_path, rows):
    path = tmp_path / "motion.csv"
    path.write_text("t,dx,dy,dz\n" + "\n".join(",".join(str(v) for v in row) for row in rows) + "\n")
    return load_scene(
        "cube",
        [*SMALL, "mesh.fixed_faces=[]", 'boundary.motion="file"', BOX, f'boundary.file="{path}"'],
    )


def test_a_file_that_moves_the_clamped_face_in_one_step_is_refused(tmp_path):
    """The issue's case: 5 cm in one step (before: 1,153 N and 66 insertion points in that step, exit 0)."""
    with pytest.raises(SceneError, match=r"0.05 m in one step \(from t = 0.1 s"):
        _build(_file_motion(tmp_path, [(0, 0, 0, 0), (0.1, 0, 0, 0), (0.11, 0, 0, 0.05)]))


def test_a_file_oscillating_faster_than_the_steps_is_refused(tmp_path):
    """±2.5 cm every 5 ms while dt = 10 ms: the steps see only the zeros, the file's peaks fall between."""
    times = np.arange(101) * 0.005  # ends on a zero, at the run's last step
    rows = [(t, 0.0, 0.0, 0.0 if i % 2 == 0 else 0.025) for i, t in enumerate(times)]
    with pytest.raises(SceneError, match=r"boundary.file: the motion changes faster than the steps"):
        _build(_file_motion(tmp_path, rows))


def test_a_boundary_file_without_its_motion_is_refused():
    """Issue 24 item 9: `[boundary] file = ...` with the default motion = "none" ran with no motion and no
    message. Now the key is named with the motion that reads it, blamed on the override that gave it."""
    with pytest.raises(SceneError) as caught:
        load_scene("cube", [*SMALL, 'boundary.file="breathing.csv"'])
    message = str(caught.value)
    assert "override --set 'boundary.file=\"breathing.csv\"'" in message
    assert "boundary.file = 'breathing.csv' is given but motion = 'none' does not read it" in message
    assert "set motion = 'file'" in message


@pytest.mark.parametrize(
    ("overrides", "key", "readers"),
    [
        (
            ['boundary.motion="periodic"', "boundary.box=[[0,0,0],[1,1,1]]", 'boundary.file="b.csv"'],
            "file",
            "'file'",
        ),
        (
            [
                'boundary.motion="file"',
                "boundary.box=[[0,0,0],[1,1,1]]",
                'boundary.file="b.csv"',
                "boundary.period=2.0",
            ],
            "period",
            "'periodic'",
        ),
        (["boundary.box=[[0,0,0],[1,1,1]]"], "box", "'periodic' or 'file'"),
    ],
)
def test_a_boundary_key_the_chosen_motion_does_not_read_is_refused(overrides, key, readers):
    with pytest.raises(SceneError) as caught:
        load_scene("cube", [*SMALL, *overrides])
    message = str(caught.value)
    assert f"boundary.{key} = " in message and f"set motion = {readers}" in message


def test_every_boundary_motion_lists_the_keys_it_reads():
    import dataclasses

    from refsim.scene.spec import BoundarySpec

    motion = next(field for field in dataclasses.fields(BoundarySpec) if field.name == "motion")
    assert set(BoundarySpec.MOTION_KEYS) == set(motion.metadata["choices"])
    keys = {name for names in BoundarySpec.MOTION_KEYS.values() for name in names}
    names = {field.name for field in dataclasses.fields(BoundarySpec)} - {"motion"}
    assert keys | set(BoundarySpec.SELECTION_KEYS) == names
