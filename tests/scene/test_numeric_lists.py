"""Lists of numbers in a scene (trajectory waypoints, boxes, planes): a string item is refused like a string
in a numeric key (before: numpy read "0" as 0.0, so `times = ["0", 1, 2]` ran)."""

from __future__ import annotations

import pytest

from refsim.scene import SceneError, load_scene


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ('trajectory.times=["0", 1.9, 2.2]', "trajectory.times"),
        (
            'trajectory.base_positions=[[0, 0, "0.422"], [0, 0, 0.403], [0, 0, 0.403]]',
            "trajectory.base_positions",
        ),
        ('trajectory.directions=[[0, 0, -1], [0, 0, -1], [0, "0", -1]]', "trajectory.directions"),
        ('mesh.fixed_box=[[-1, -1, -1], [1, 1, "0.001"]]', "mesh.fixed_box"),
    ],
)
def test_a_string_in_a_list_of_numbers_is_named(override, key):
    with pytest.raises(SceneError) as error:
        load_scene("cube", [override])
    message = str(error.value)
    assert f"override --set {override!r}" in message
    assert key in message and "expected numbers, not the string" in message
