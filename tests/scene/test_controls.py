"""Controls: the breathing law (Lujan et al. 1999), sampled motions, and their values at a time."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.scene import Controls, PeriodicBoundaryMotion, SampledBoundaryMotion
from refsim.scene.trajectory import Trajectory


def test_periodic_motion_is_zero_at_start_reaches_the_amplitude_and_repeats():
    motion = PeriodicBoundaryMotion(
        nodes=np.array([3, 1, 2]), amplitude=[0.0, 0.0, 0.005], period=4.0, exponent=2
    )
    np.testing.assert_array_equal(motion.nodes, [1, 2, 3])
    np.testing.assert_allclose(motion.displacement(0.0), 0.0, atol=1e-18)
    # 1 − cos⁴(π t / T) is 1 at t = T/2: the full amplitude.
    np.testing.assert_allclose(motion.displacement(2.0), [[0.0, 0.0, 0.005]] * 3, atol=1e-15)
    np.testing.assert_allclose(motion.displacement(1.3), motion.displacement(5.3), atol=1e-15)
    # Against the closed form at a generic time.
    assert motion.profile(0.7) == pytest.approx(1.0 - np.cos(np.pi * 0.7 / 4.0) ** 4, rel=1e-14)


def test_a_phase_keeps_the_start_at_rest():
    motion = PeriodicBoundaryMotion(nodes=np.array([0]), amplitude=[0.01, 0.0, 0.0], period=2.0, phase=0.4)
    np.testing.assert_allclose(motion.displacement(0.0), 0.0, atol=1e-18)
    assert abs(motion.profile(0.5)) > 0.0


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(nodes=np.array([], dtype=int), amplitude=[0, 0, 1], period=1.0), "non-empty"),
        (dict(nodes=np.array([1, 1]), amplitude=[0, 0, 1], period=1.0), "distinct"),
        (dict(nodes=np.array([0]), amplitude=[0, 0], period=1.0), "amplitude"),
        (dict(nodes=np.array([0]), amplitude=[0, 0, 1], period=0.0), "period"),
        (dict(nodes=np.array([0]), amplitude=[0, 0, 1], period=1.0, exponent=0), "exponent"),
    ],
)
def test_bad_periodic_motions_are_rejected_by_name(kwargs, message):
    with pytest.raises(ValueError, match=message):
        PeriodicBoundaryMotion(**kwargs)


def test_sampled_motion_interpolates_and_holds_after_the_last_sample():
    motion = SampledBoundaryMotion(
        nodes=np.array([4]),
        times=[0.0, 1.0, 2.0],
        displacements=[[0, 0, 0], [0, 0, 0.002], [0.001, 0, 0.002]],
    )
    np.testing.assert_allclose(motion.displacement(0.5), [[0.0, 0.0, 0.001]], atol=1e-18)
    np.testing.assert_allclose(motion.displacement(9.0), [[0.001, 0.0, 0.002]], atol=1e-18)
    with pytest.raises(ValueError, match="t = 0 must be zero"):
        SampledBoundaryMotion(nodes=np.array([4]), times=[0.0, 1.0], displacements=[[0, 0, 1e-3], [0, 0, 0]])


def test_controls_give_the_needle_pose_and_the_boundary_displacements():
    trajectory = Trajectory(
        np.array([0.0, 1.0]), np.array([[0, 0, 0.1], [0, 0, 0.09]]), np.array([[0, 0, -1.0]] * 2)
    )
    motion = PeriodicBoundaryMotion(nodes=np.array([7, 9]), amplitude=[0.0, 0.0, 0.004], period=2.0)
    values = Controls(trajectory, motion).at(0.5)
    np.testing.assert_allclose(values.base_position, [0, 0, 0.095], atol=1e-15)
    np.testing.assert_array_equal(values.boundary_nodes, [7, 9])
    np.testing.assert_allclose(values.boundary_displacements[:, 2], 0.004 * (1 - np.cos(np.pi / 4) ** 2))
    bare = Controls(trajectory).at(0.5)
    assert bare.boundary_nodes.size == 0 and bare.boundary_displacements.shape == (0, 3)


def test_a_trajectory_csv_may_start_with_comments_before_its_header(tmp_path):
    from refsim.scene.trajectory import read_trajectory_csv

    path = tmp_path / "robot.csv"
    path.write_text(
        "# made by a robot planner\n# second comment\nt,x,y,z,dx,dy,dz\n0,0,0,0.4,0,0,-1\n1,0,0,0.39,0,0,-1\n"
    )
    trajectory = read_trajectory_csv(path)
    np.testing.assert_allclose(trajectory.base_positions[:, 2], [0.4, 0.39])
