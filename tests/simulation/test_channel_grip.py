"""The grip of a closed channel is the normal force of its shaft friction: a lateral force redistributes the
interference pressure around the needle, it does not add to it (refsim.constraints.channel.channel_preload).

Reference: the reference case ``insertion`` (the paper's 8 mm needle, δ_r = 20 µm, μ = 0.1, f_cut = 0.5 N)
refined as its levels are (d_i = 6.8 mm/cells, dt = 0.05 s/cells). Every point slips during the insertion,
so the shaft's friction is μ g n (g = 2π r p₀ d_i, Lamé's p₀ = 2 G δ_r / r; n the points), the Coulomb force
of the grip. Its lateral multipliers are the mesh's lateral error of a straight symmetric insertion: the sum
of their norms grows under refinement (μ Σ‖λ_lat‖ at 8 mm deep: 0.4 %, 0.6 %, 1.0 % of the friction on 5, 7,
9 cells; Σ‖λ_lat‖ per metre of shaft 0.18, 0.26, 0.46, 0.81, 1.44, 2.87 N/m on 5 … 17 cells). Counted in
the bound on top of the grip (μ (‖λ_lat‖ + g), before), they made the shaft friction grow with the mesh and
the fine level of the case diverge.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from refsim.constraints import AXIAL_FRICTION, LATERAL_FIRST, LATERAL_SECOND
from refsim.constraints.channel import channel_preload
from refsim.scene import load_scene
from refsim.simulation import Simulation

CASE = Path(__file__).resolve().parents[2] / "refsim" / "reference" / "cases" / "insertion.scene.toml"


def test_channel_preload_is_the_grip_less_the_last_lateral_force():
    lateral = np.array([0.0, 0.01, 0.03, 0.05])
    assert channel_preload(0.04, lateral).tolist() == pytest.approx([0.04, 0.03, 0.01, 0.0])
    # no grip: the paper's law, μ ‖λ_lat‖ (a scalar 0, the bound unchanged)
    assert channel_preload(0.0, lateral) == 0.0
    # the bound μ (‖λ_lat‖ + p) is then μ max(g, ‖λ_lat‖) for the same lateral force
    grip = 0.04
    assert (lateral + channel_preload(grip, lateral)).tolist() == pytest.approx(np.maximum(grip, lateral))


@pytest.mark.parametrize("cells", [5, 7, 9])
def test_shaft_friction_is_the_grip_under_refinement(cells):
    scene = load_scene(
        CASE,
        [
            f"mesh.cells=[{cells}, {cells}, {cells}]",
            f"insertion.spacing={6.8e-3 / cells!r}",
            f"time.dt={0.05 / cells!r}",
        ],
    )
    simulation = Simulation(scene)
    state = simulation.initial_state()
    for _ in range(round(1.0 / scene.time.dt)):  # 8 mm deep at 1.0 s, inserting at 10 mm/s
        state, record = simulation.step(state)
    detector = simulation.detector
    grip, mu = detector.preload, scene.insertion.shaft_friction_coefficient
    role, forces = record.row_role, record.row_forces
    axial = np.abs(forces[role == AXIAL_FRICTION])
    lateral = np.hypot(forces[role == LATERAL_FIRST], forces[role == LATERAL_SECOND])
    expected = mu * grip * axial.size
    assert axial.size >= 5
    # the lateral multipliers exist (and are not negligible: μ Σ‖λ_lat‖ ≥ 0.2 % of the friction) ...
    assert mu * lateral.sum() >= 2e-3 * expected
    assert np.all(lateral < grip)  # the channel stays closed
    # ... but the shaft friction is the grip's: μ g per slipping point, to 1e-4 of it (before: 0.4 … 1.0 %)
    assert axial.sum() == pytest.approx(expected, rel=1e-4)
    assert np.allclose(axial, mu * grip, rtol=1e-3)
