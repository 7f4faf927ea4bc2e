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
