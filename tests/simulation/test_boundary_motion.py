"""A tissue boundary motion as a control: the moving nodes follow it exactly, the tissue follows them, and
the needle meets the moving tissue earlier."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.scene import Controls, PeriodicBoundaryMotion, load_scene
from refsim.simulation import Simulation


def _scene(**overrides):
    sets = ["mesh.cells=[4,4,4]", "time.duration=0.6", *[f"{k}={v}" for k, v in overrides.items()]]
    return load_scene("cube", overrides=sets)


def _run(scene, motion_of=None):
    simulation = Simulation(scene)
    controls = None
    if motion_of is not None:
        controls = Controls(simulation.models.trajectory, motion_of(simulation.tissue.fixed_nodes))
        simulation = Simulation(scene, simulation.models, controls)
    records, states = [], []
    simulation.run(on_step=lambda state, record: (states.append(state), records.append(record)))
    return simulation, states, records


def test_the_moving_nodes_follow_the_prescribed_displacement_exactly():
    # Dirichlet condition: the bottom face moves up by a (1 − cos²(πt/T)), a = 5 mm, T = 1.2 s.
    def motion(nodes):
        return PeriodicBoundaryMotion(nodes=nodes, amplitude=[0.0, 0.0, 0.005], period=1.2)

    simulation, states, records = _run(_scene(), motion)
    rest = simulation.tissue.rest_positions
    law = motion(simulation.tissue.fixed_nodes)
    for state, record in zip(states, records, strict=False):
        moved = state.tissue.positions[law.nodes] - rest[law.nodes]
        np.testing.assert_allclose(moved, law.displacement(state.time), atol=1e-15)
        np.testing.assert_allclose(record.boundary_displacements, law.displacement(state.time), atol=0)
    # The tissue follows its base: the top face has moved up by most of the base's 5 mm at t = T/2 = 0.6 s.
    top = np.flatnonzero(np.isclose(rest[:, 2], rest[:, 2].max()))
    lift = states[-1].tissue.positions[top, 2] - rest[top, 2]
    assert np.all(lift > 0.5 * 0.005)


def test_a_tissue_moving_towards_the_needle_is_punctured_earlier():
    def puncture_step(records):
        steps = [r.step for r in records if any(e.name == "puncture" for e in r.events)]
        return steps[0] if steps else None

    _, _, still = _run(_scene())
    _, _, moving = _run(
        _scene(),
        lambda nodes: PeriodicBoundaryMotion(nodes=nodes, amplitude=[0.0, 0.0, 0.004], period=1.2),
    )
    assert puncture_step(still) is not None and puncture_step(moving) is not None
    assert puncture_step(moving) < puncture_step(still)


def test_moving_nodes_that_are_not_fixed_are_rejected():
    scene = _scene()
    simulation = Simulation(scene)
    free_node = int(np.setdiff1d(np.arange(simulation.tissue.node_count), simulation.tissue.fixed_nodes)[0])
    controls = Controls(
        simulation.models.trajectory,
        PeriodicBoundaryMotion(nodes=np.array([free_node]), amplitude=[0.0, 0.0, 0.001], period=1.0),
    )
    simulation = Simulation(scene, simulation.models, controls)
    with pytest.raises(ValueError, match="not fixed"):
        simulation.step(simulation.initial_state())


def test_a_scene_file_boundary_section_moves_the_tissue_and_the_results_record_it(tmp_path):
    # The [boundary] section: the bottom face (a box around z = 0) breathes up by 4 mm over T = 1.2 s; the
    # results hold the moving nodes and their prescribed displacement at every step, so the file stands alone.
    from refsim.io import read_results
    from refsim.io.driver import run_scene

    scene = load_scene(
        "cube",
        [
            "mesh.cells=[4,4,4]",
            "time.duration=0.3",
            'boundary.motion="periodic"',
            "boundary.box=[[-0.06, -0.06, -0.001], [0.06, 0.06, 0.001]]",
            "boundary.amplitude=[0, 0, 0.004]",
            "boundary.period=1.2",
            "boundary.exponent=2",
        ],
    )
    path = tmp_path / "moving.h5"
    run_scene(scene, path, overwrite=True)
    results = read_results(path)
    law = PeriodicBoundaryMotion(
        nodes=results.boundary_nodes, amplitude=[0, 0, 0.004], period=1.2, exponent=2
    )
    assert results.boundary_nodes.size == 25  # the 5 × 5 nodes of the bottom face
    assert set(results.boundary_nodes) <= set(results.fixed_nodes)
    for index, time in enumerate(results.time):
        np.testing.assert_allclose(results.boundary_displacement[index], law.displacement(time), atol=1e-15)


@pytest.mark.parametrize(
    "overrides, message",
    [
        (['boundary.motion="periodic"', "boundary.amplitude=[0, 0, 0.004]"], "exactly one of"),
        (['boundary.motion="periodic"', "boundary.nodes=[0, 1]"], "amplitude"),
        (['boundary.motion="file"', "boundary.nodes=[0]"], "file"),
        (
            [
                'boundary.motion="periodic"',
                "boundary.patch_point=[0, 0, 0.1]",
                "boundary.amplitude=[0, 0, 1e-3]",
            ],
            "patch_distance",
        ),
        (
            ['boundary.motion="periodic"', "boundary.facing=[0, 0, 0]", "boundary.facing_angle=45"],
            "facing.*direction is zero",
        ),
        (['boundary.motion="periodic"', "boundary.facing=[0, 0, 1]"], "facing_angle"),
        (['boundary.motion="periodic"', "boundary.nodes=[0]", "boundary.facing_angle=45"], "facing"),
        (['boundary.motion="periodic"', "boundary.facing=[0, 0, 1]", "boundary.facing_angle=180"], "180"),
        (['boundary.motion="periodic"', "boundary.facing=[0, 1]", "boundary.facing_angle=45"], "facing"),
    ],
)
def test_bad_boundary_sections_are_refused_naming_the_key(overrides, message):
    from refsim.scene import SceneError

    with pytest.raises(SceneError, match=message):
        load_scene("cube", overrides)


def test_a_selection_that_catches_no_node_is_refused():
    from refsim.scene import SceneError

    scene = load_scene(
        "cube",
        [
            "mesh.cells=[4,4,4]",
            'boundary.motion="periodic"',
            "boundary.amplitude=[0, 0, 1e-3]",
            "boundary.box=[[1, 1, 1], [2, 2, 2]]",
        ],
    )
    with pytest.raises(SceneError, match="boundary.box selects no node"):
        Simulation(scene)


@pytest.mark.parametrize("direction, axis, side", [([0, 0, -1], 2, "min"), ([1, 0, 0], 0, "max")])
def test_a_facing_selection_takes_the_face_turned_towards_its_direction(direction, axis, side):
    # facing = d, facing_angle = 30°: the surface nodes whose outward normal is within 30° of d. On a 4×4×4
    # cube the nodes inside a face have that face's normal (angle 0), a node of another face or of the
    # opposite one is at 90° or 180°; a node on the face's rim has a mean of two or three faces' normals
    # (weighted by the areas of its triangles), which may fall on either side of 30°. So: the 3×3 nodes
    # inside the face are all taken, and nothing off the face is.
    scene = load_scene(
        "cube",
        [
            "mesh.cells=[4,4,4]",
            'boundary.motion="periodic"',
            "boundary.amplitude=[0, 0, 1e-3]",
            f"boundary.facing={direction}",
            "boundary.facing_angle=30",
        ],
    )
    simulation = Simulation(scene)
    rest = simulation.models.mesh.rest_positions
    nodes = simulation.controls.boundary.nodes
    face = getattr(rest[:, axis], side)()
    lower, upper = rest.min(axis=0), rest.max(axis=0)
    others = [k for k in range(3) if k != axis]
    inside = (
        np.isclose(rest[:, axis], face)
        & np.all(rest[:, others] > lower[others] + 1e-9, axis=1)
        & np.all(rest[:, others] < upper[others] - 1e-9, axis=1)
    )
    assert np.all(np.isclose(rest[nodes, axis], face))
    assert set(np.flatnonzero(inside)) <= set(nodes.tolist()) and inside.sum() == 9


def test_facing_surface_refuses_bad_values_naming_them():
    from refsim.mesh import box_mesh, facing_surface

    mesh = box_mesh(size=(0.01, 0.01, 0.01), cells=(2, 2, 2))
    for arguments, message in [
        (dict(direction=(0, 0, 0), angle=45.0), "direction is zero"),
        (dict(direction=(0, 0, 1), angle=0.0), "angle = 0.0"),
        (dict(direction=(0, 0, 1), angle=float("nan")), "angle = nan"),
        (dict(direction=(0, 1), angle=45.0), "direction"),
    ]:
        with pytest.raises(ValueError, match=message):
            facing_surface(mesh.rest_positions, mesh.boundary_faces, **arguments)
