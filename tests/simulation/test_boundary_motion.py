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
    for state, record in zip(states, records):
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
