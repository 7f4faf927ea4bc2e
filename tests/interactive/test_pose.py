"""The commanded pose: the speed and turn bounds, exact arrival, moves below resolution, keys (a tilt pivots
about the tip), pose messages, and directions of norm exactly 1."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.interactive.pose import (
    KEYS,
    SMALLEST_MOVE,
    PoseError,
    PoseTarget,
    exact_unit,
    lateral_axes,
    parse_pose,
)

BASE = np.array([0.00123, 0.00231, 0.422])
DOWN = np.array([0.0, 0.0, -1.0])
LENGTH = 0.32


def _target(**bounds) -> PoseTarget:
    return PoseTarget(BASE, DOWN, needle_length=LENGTH, max_speed=0.05, max_turn=np.radians(30.0), **bounds)


def test_the_base_moves_at_most_max_speed_dt_and_arrives_exactly():
    target = _target()
    goal = BASE + [0.0, 0.0, -0.01]  # 10 mm: 20 steps of 0.5 mm at 0.05 m/s and dt = 0.01 s
    target.set(goal, DOWN)
    positions = [target.advance(0.01)[0] for _ in range(25)]
    travel = np.linalg.norm(np.diff(np.vstack([BASE, positions]), axis=0), axis=1)
    np.testing.assert_allclose(travel[:19], 5e-4, rtol=1e-9)
    assert np.array_equal(positions[19], goal) and all(np.array_equal(p, goal) for p in positions[20:])


def test_the_direction_turns_at_most_max_turn_dt():
    target = _target()
    turned = exact_unit([np.sin(np.radians(3.0)), 0.0, -np.cos(np.radians(3.0))])
    target.set(BASE, turned)
    # the base is already there: the turn bounds the fraction (0.3 degrees per step at 30 deg/s)
    directions = [target.advance(0.01)[1] for _ in range(12)]
    angles = np.degrees(np.arccos(np.clip(np.vstack([DOWN, directions]) @ DOWN, -1.0, 1.0)))
    np.testing.assert_allclose(np.diff(angles)[:9], 0.3, rtol=1e-6)
    assert np.array_equal(directions[-1], turned)


def test_a_move_below_the_smallest_move_is_not_made():
    target = _target()
    target.set(BASE + [0.0, 0.0, 0.1 * SMALLEST_MOVE], DOWN)
    base, direction = target.advance(0.01)
    assert np.array_equal(base, BASE) and np.array_equal(direction, DOWN)


def test_latest_pose_wins_and_superseded_poses_are_counted():
    target = _target()
    for depth in (1e-4, 2e-4, 3e-4):
        target.set(BASE + [0.0, 0.0, -depth], DOWN)
    base, _ = target.advance(0.01)
    assert np.array_equal(base, BASE + [0.0, 0.0, -3e-4])
    assert target.received == 3 and target.superseded == 2


def test_keys_translate_along_the_needle_and_sideways():
    target = _target()
    a, b = lateral_axes(DOWN)
    np.testing.assert_allclose(np.cross(a, b), DOWN, atol=1e-15)
    target.key(KEYS["Up"], distance=1e-3, angle=0.0)
    target.key(KEYS["Right"], distance=2e-3, angle=0.0)
    target.key(KEYS["Prior"], distance=3e-3, angle=0.0)
    goal, direction = target.target()
    np.testing.assert_allclose(goal, BASE + 1e-3 * DOWN + 2e-3 * a + 3e-3 * b, atol=1e-15)
    assert np.array_equal(direction, DOWN)


@pytest.mark.parametrize("key", ["i", "j", "k", "l"])
def test_a_tilt_pivots_about_the_tip(key):
    target = _target()
    angle = np.radians(2.0)
    target.key(KEYS[key], distance=0.0, angle=angle)
    base, direction = target.target()
    np.testing.assert_allclose(base + LENGTH * direction, BASE + LENGTH * DOWN, atol=1e-15)
    np.testing.assert_allclose(np.arccos(direction @ DOWN), angle, rtol=1e-9)
    action = KEYS[key]
    axis = dict(zip("ab", lateral_axes(DOWN), strict=True))[action.axis]
    assert action.sign * ((base - BASE) @ axis) > 0.0  # the base swings towards sign * axis


def test_parse_pose_accepts_a_pose_and_normalises_its_direction():
    base, direction = parse_pose({"t": 0.5, "base": [0.0, 0.0, 0.4], "direction": [0, 0, -2]}, reach=1.0)
    assert np.array_equal(base, [0.0, 0.0, 0.4]) and np.array_equal(direction, DOWN)


@pytest.mark.parametrize(
    ("message", "expected"),
    [
        ({"base": [0, 0, 0], "direction": [0, 0, 1e-15]}, "is zero"),
        ({"base": [0, 0, True], "direction": [0, 0, 1]}, "expected 3 numbers"),
        ({"base": [0, 0, float("inf")], "direction": [0, 0, 1]}, "finite"),
        ({"base": [5, 0, 0], "direction": [0, 0, 1]}, "beyond the 1 m"),
        ({"direction": [0, 0, 1]}, "'base': expected a list of 3 numbers, got None"),
        ("pose", "expected a JSON object"),
    ],
)
def test_parse_pose_names_the_defect(message, expected):
    with pytest.raises(PoseError, match=expected):
        parse_pose(message, reach=1.0)


def test_exact_unit_gives_norm_exactly_one_in_both_norm_forms():
    rng = np.random.default_rng(26)
    for vector in rng.normal(size=(2000, 3)) * rng.lognormal(size=(2000, 1)):
        unit = exact_unit(vector)
        assert np.linalg.norm(unit) == 1.0 and np.linalg.norm(unit[None], axis=1)[0] == 1.0
        np.testing.assert_allclose(unit, vector / np.linalg.norm(vector), rtol=0.0, atol=1e-15)
        assert np.array_equal(unit / np.linalg.norm(unit), unit)


@pytest.mark.parametrize("bound", [0.0, -1.0, float("nan"), float("inf")])
def test_bounds_must_be_positive_and_finite(bound):
    with pytest.raises(ValueError, match="valid range"):
        PoseTarget(BASE, DOWN, needle_length=LENGTH, max_speed=bound, max_turn=1.0)
