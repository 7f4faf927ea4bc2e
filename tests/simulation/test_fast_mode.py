"""The fast compliance strategy in a whole run (issue 26, item 2): the same events as the exact strategy and
needle forces close to its forces.

Tolerance: issue 26's acceptance, the force within 2 % of the run's peak force (stated, not derived: the
strategy's per-step errors are bounded in tests/fem/test_compliance.py, W by ‖H‖² ‖A⁻¹‖ ‖Ã⁻¹‖ ‖A − Ã‖ and the
free motion by κ(A) times its PCG tolerance; through the constraint problem and many steps they compose into
no closed-form bound). The scene is the cube with 4 cells per axis through puncture and insertion.
"""

from __future__ import annotations

import numpy as np
import pytest

from refsim.simulation import Simulation

COARSE = ("mesh.cells=[4, 4, 4]", "time.duration=0.45")


def _run(scene):
    simulation = Simulation(scene)
    state = simulation.initial_state()
    forces, events = [], []
    for _ in range(scene.time.step_count):
        state, record = simulation.step(state)
        forces.append(record.needle_force)
        events += [(record.step, event.name) for event in record.events]
    return np.array(forces), events


@pytest.mark.parametrize("youngs_modulus", [5e4, 5e5, 5e6])
def test_fast_mode_has_the_exact_events_and_forces_within_two_percent_of_the_peak(cube_scene, youngs_modulus):
    # Over the stiffness range where the fast mode holds issue 26's acceptance on the cube (the scene's
    # 500 kPa, ten times softer and ten times stiffer; docs/fast_stiffness.md: softer still, its tip
    # punctures early).
    coarse = (*COARSE, f"tissue.youngs_modulus={youngs_modulus!r}")
    exact_forces, exact_events = _run(cube_scene(*coarse))
    fast_forces, fast_events = _run(cube_scene(*coarse, 'compliance.strategy="fast"'))
    assert fast_events == exact_events
    assert [name for _, name in exact_events][:1] == ["puncture"]
    peak = np.linalg.norm(exact_forces, axis=1).max()
    error = np.linalg.norm(fast_forces - exact_forces, axis=1).max()
    assert peak > 0.0
    assert error <= 0.02 * peak
    # It is an approximation: the forces are not the exact ones (a strategy that silently fell back to exact
    # would pass the bound above).
    assert error > 1e-9 * peak


def test_fast_mode_has_the_exact_events_through_a_reversal_a_withdrawal_and_a_second_insertion(cube_scene):
    # The life beyond the insertion (tests/simulation/test_life_cycle.py): tilted 30° in the xz plane,
    # inserted 6 mm along the needle at dt = 20 ms, pulled back 4 mm (its tip back along its channel),
    # pushed in to 8 mm (the tip cuts again beyond 6 mm), pulled out to 2 mm above the surface, moved 25 mm
    # along x in the air and inserted 6 mm again. Expected as above: the exact strategy's events at the same
    # steps (puncture, retractions, withdrawal, the second puncture) and forces within 2 % of the peak.
    axis = np.array([0.5, 0.0, -np.sqrt(3.0) / 2.0])
    entry = np.array([0.00123, 0.00231, 0.1])
    knots = [(0.0, 0.0, -0.002), (0.4, 0.0, 0.006), (0.6, 0.0, 0.002), (0.9, 0.0, 0.008), (1.4, 0.0, -0.002)]
    knots += [(1.8, 0.025, -0.002), (2.2, 0.025, 0.006)]
    bases = [entry + [shift, 0.0, 0.0] + (depth - 0.32) * axis for _, shift, depth in knots]
    fmt = lambda v: "[" + ", ".join(repr(float(c)) for c in v) + "]"  # noqa: E731
    path = (
        "mesh.cells=[4, 4, 4]",
        "time.dt=0.02",
        f"trajectory.times={fmt([t for t, _, _ in knots])}",
        "trajectory.base_positions=[" + ", ".join(fmt(b) for b in bases) + "]",
        "trajectory.directions=[" + ", ".join(fmt(axis) for _ in knots) + "]",
        f"time.duration={knots[-1][0]}",
    )
    exact_forces, exact_events = _run(cube_scene(*path))
    fast_forces, fast_events = _run(cube_scene(*path, 'compliance.strategy="fast"'))
    names = [name for _, name in exact_events if name != "retraction"]
    assert names == ["puncture", "withdrawal", "puncture"], names
    assert fast_events == exact_events
    peak = np.linalg.norm(exact_forces, axis=1).max()
    assert np.linalg.norm(fast_forces - exact_forces, axis=1).max() <= 0.02 * peak


# The built-in scenes and what users vary (the needle's model, two instruments, a cut, a breathing liver
# held by a robot), each run in full in both modes: the same events at the same steps and the needle forces
# within 2 % of the peak (issue 26's acceptance, as above), at the fast mode's default CG tolerance and at a
# tight one.
MATRIX = [
    ("cube_cut", ()),
    ("cube", ("needle.rigid=false",)),
    ("cube", ("time.dt=0.02", "time.duration=2.2")),
    ("two_needles", ()),
    ("liver_flexible", ("time.duration=1.5",)),
    ("liver_rigid", ("time.duration=1.5",)),
]


@pytest.mark.slow
@pytest.mark.parametrize("tolerance", [None, 1e-6], ids=["default", "cg1e-6"])
@pytest.mark.parametrize(("name", "overrides"), MATRIX, ids=[f"{n}:{' '.join(o)}" for n, o in MATRIX])
def test_fast_mode_over_the_built_in_scenes(cube_scene, name, overrides, tolerance):
    exact_forces, exact_events = _run(cube_scene(*overrides, name=name))
    fast = (*overrides, 'compliance.strategy="fast"')
    if tolerance is not None:
        fast = (*fast, f"compliance.tolerance={tolerance}")
    fast_forces, fast_events = _run(cube_scene(*fast, name=name))
    assert exact_events and fast_events == exact_events
    peak = np.linalg.norm(exact_forces, axis=1).max()
    error = np.linalg.norm(fast_forces - exact_forces, axis=1).max()
    assert 1e-9 * peak < error <= 0.02 * peak


@pytest.mark.parametrize("strategy", ["fast", "precomputed"])
def test_the_rest_factor_is_made_with_the_simulation_and_no_step_factorises(cube_scene, strategy):
    # The strategies that keep the rest matrix's factor for the run make it when the simulation is built
    # (BodyCompliance.prepare), so no step pays it (the first step of an interactive session would hitch by a
    # factorisation); the run is the same bit for bit as one whose body prepares at its first step.
    from refsim.fem.compliance import make_strategy
    from refsim.simulation.bodies import TissueBody

    scene = cube_scene(*COARSE, f'compliance.strategy="{strategy}"')
    simulation = Simulation(scene)
    assert simulation.tissue_compliance.linear_counts()[0] == 1
    forces, events = _run(scene)
    assert simulation.tissue_compliance.linear_counts()[0] == 1  # the built one, untouched by _run's own
    lazy = Simulation(scene)
    lazy.tissue_compliance = make_strategy(strategy).bind()
    lazy.tissue_body = TissueBody(lazy.tissue, lazy.tissue_compliance)
    lazy.bodies = (lazy.tissue_body, *lazy.bodies[1:])
    assert lazy.tissue_compliance.linear_counts()[0] == 0
    state, lazy_forces, lazy_events = lazy.initial_state(), [], []
    for _ in range(scene.time.step_count):
        state, record = lazy.step(state)
        lazy_forces.append(record.needle_force)
        lazy_events += [(record.step, event.name) for event in record.events]
    assert lazy.tissue_compliance.linear_counts()[0] == 1
    assert lazy_events == events and np.array_equal(np.array(lazy_forces), forces)
