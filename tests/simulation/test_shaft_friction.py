"""Static and dynamic shaft friction (issue 9, item 3): a point that stuck holds up to μ_s times its normal
force, one that slips carries μ_d times it.

Closed form: a thin needle with an interference grip and no lateral load, so each point's normal force is the
grip 2π r p₀ d_i (p₀ from Lamé, :func:`refsim.constraints.channel.grip_preload`). Inserted, held (every point
stuck, the tissue keeping the friction load the insertion left), then pulled out: the axial force jumps to
μ_s n 2π r p₀ d_i on the first step of the pull (every point stuck, each gives way at its static bound) and
drops to μ_d n 2π r p₀ d_i from the next (every point slips), n the points coupled in that step.
"""

from __future__ import annotations

import numpy as np
import pytest

from refsim.constraints import BILATERAL, FRICTION, INSERTION
from refsim.constraints.channel import grip_preload
from refsim.scene.fields import FieldError
from refsim.simulation import Simulation

STATIC, DYNAMIC, INTERFERENCE = 0.25, 0.1, 2e-5
HOLD_START, PULL_START = 1.2, 1.6  # [s]: inserted 10 mm by 1.2 s, held 0.4 s, pulled 3 mm back until 1.9 s
SCENE = (
    "mesh.cells=[4, 4, 4]",
    "needle.radius=0.0005",
    f"insertion.interference={INTERFERENCE}",
    # friction alone: the cube's tip cutting force would add f_cut to the hold
    "insertion.tip_cutting_force=0",
    f"insertion.shaft_friction_coefficient={DYNAMIC}",
    f"insertion.shaft_static_friction_coefficient={STATIC}",
    "trajectory.times=[0.0, 1.2, 1.6, 1.9]",
    "trajectory.base_positions=[[0.00123, 0.00231, 0.422], [0.00123, 0.00231, 0.410], "
    "[0.00123, 0.00231, 0.410], [0.00123, 0.00231, 0.413]]",
    "trajectory.directions=[[0, 0, -1], [0, 0, -1], [0, 0, -1], [0, 0, -1]]",
    "time.duration=1.9",
)


def test_pull_out_force_peaks_at_static_and_drops_to_dynamic_friction(cube_scene):
    scene = cube_scene(*SCENE)
    records = []
    Simulation(scene).run(on_step=lambda state, record: records.append(record))
    tissue = scene.tissue
    shear = tissue.youngs_modulus / (2.0 * (1.0 + tissue.poisson_ratio))
    grip = grip_preload(
        shear_modulus=shear,
        poisson_ratio=tissue.poisson_ratio,
        radius=scene.needle.radius,
        interference=INTERFERENCE,
        spacing=scene.insertion.spacing,
    )
    first = next(i for i, r in enumerate(records) if r.time > PULL_START + 1e-9)
    pull = records[first : first + 12]
    for k, record in enumerate(pull):
        insertion = record.row_source == INSERTION
        count = int(np.count_nonzero(insertion & (record.row_kind == FRICTION)))
        lateral = record.row_forces[insertion & (record.row_kind == BILATERAL)].reshape(-1, 2)
        mu = STATIC if k == 0 else DYNAMIC
        expected = mu * grip * count
        # The bound of each point is μ max(grip, ‖λ_lateral‖) (the lateral reactions of a mesh not symmetric
        # about the needle, with the grip's preload less the last step's lateral force: channel_preload):
        # within μ Σ‖λ_lateral‖ of μ grip; the solver's residual 1e-8 is far below.
        tolerance = mu * np.linalg.norm(lateral, axis=1).sum() + 1e-6 * expected
        pulled = record.needle_force[2]  # the tissue holds the needle back: −z while pulled up (+z)
        assert count >= 10
        assert abs(-pulled - expected) <= tolerance, (k, -pulled, expected, tolerance)
    # Before the pull the needle is held: every point sticks and keeps the load the insertion left (the stick
    # anchors of refsim.constraints.friction; a static elastic body held by Coulomb stick keeps its load).
    # From 0.1 s after the stop (10 times the damping time β = 0.01 s) to the pull the force is constant to
    # 1e-6 of itself, and it is the insertion's friction (the points slipped at μ_d, the newest once at μ_s):
    # at least half of μ_d times the points' normal forces (it decayed below 1 % of one point's bound when
    # the stuck rows crept), at most μ_s times them.
    hold = [r for r in records if HOLD_START + 0.1 < r.time <= PULL_START + 1e-9]
    held = np.array([r.needle_force[2] for r in hold])
    assert len(hold) >= 20
    assert np.ptp(held) <= 1e-6 * abs(held[-1]), np.ptp(held)
    last = hold[-1]
    insertion = last.row_source == INSERTION
    count = int(np.count_nonzero(insertion & (last.row_kind == FRICTION)))
    lateral = last.row_forces[insertion & (last.row_kind == BILATERAL)].reshape(-1, 2)
    # (+z: the tissue holds back the needle it was resisting while inserted down, −z)
    normal = grip * count + np.linalg.norm(lateral, axis=1).sum()
    assert 0.5 * DYNAMIC * normal <= held[-1] <= STATIC * normal


def test_static_coefficient_below_the_dynamic_one_is_refused(cube_scene):
    with pytest.raises((FieldError, ValueError), match="shaft_static_friction_coefficient"):
        cube_scene(
            "insertion.shaft_friction_coefficient=0.2", "insertion.shaft_static_friction_coefficient=0.1"
        )
