"""[[instruments]]: several needles in one scene, each with its name, trajectory, [needle] overrides and
whether it cuts; every bad value named with the file, the key, the value and what is allowed (exit 2
from the CLI)."""

from __future__ import annotations

import tomllib
from importlib import resources

import numpy as np
import pytest

from refsim.cli import main
from refsim.scene import InstrumentsOverlap, SceneError, load_scene, scene_from_dict


def _two_needles() -> dict:
    path = resources.files("refsim") / "scenes" / "two_needles.toml"
    return tomllib.loads(path.read_text(encoding="utf-8"))


def test_the_two_needle_scene_resolves_each_instrument():
    scene = load_scene("two_needles")
    specs = scene.instrument_specs
    assert [spec.name for spec in specs] == ["cutter", "holder"]
    assert [spec.cuts for spec in specs] == [True, False]  # the cutter by cutting.enabled, the holder set
    assert scene.trajectory == specs[0].trajectory
    assert specs[0].trajectory.base_positions[0][0] != specs[1].trajectory.base_positions[0][0]
    assert specs[1].needle == scene.needle  # no override: the scene's [needle]


def test_a_one_needle_scene_is_one_instrument_named_needle():
    scene = load_scene("cube")
    (only,) = scene.instrument_specs
    assert (only.name, only.cuts, only.needle, only.trajectory) == (
        "needle",
        scene.cutting.enabled,
        scene.needle,
        scene.trajectory,
    )
    assert "instruments" not in scene.to_dict()


def test_needle_overrides_and_the_round_trip_through_to_dict():
    data = _two_needles()
    data["instruments"][1]["radius"] = 0.004
    scene = scene_from_dict(data, source="two.toml")
    assert scene.instrument_specs[1].needle.radius == 0.004
    assert scene.instrument_specs[0].needle.radius == scene.needle.radius
    again = scene_from_dict(scene.to_dict(), source="again.toml")
    assert again.instrument_specs == scene.instrument_specs


def _changed(change) -> dict:
    data = _two_needles()
    change(data)
    return data


@pytest.mark.parametrize(
    ("change", "fragments"),
    [
        (lambda d: d["instruments"][1].update(name="cutter"), ["instruments[1].name", "'cutter'", "unique"]),
        (lambda d: d["instruments"][0].update(name="tissue"), ["instruments[0].name", "'tissue'"]),
        (lambda d: d["instruments"][1].update(name="cut"), ["instruments[1].name", "'cut'", "reserved"]),
        (lambda d: d["instruments"][0].update(name="a/b"), ["instruments[0].name", "'a/b'", "letters"]),
        (lambda d: d.update(trajectory=d["instruments"][0]["trajectory"]), ["[trajectory] and [["]),
        (lambda d: d["instruments"][1].update(colour=1), ["unknown key instruments[1].colour"]),
        (lambda d: d["instruments"][1].update(radius=-1.0), ["instruments[1].radius", "-1.0", "(0.0, inf]"]),
        (lambda d: d["instruments"][0].update(cuts="yes"), ["instruments[0].cuts", "'yes'", "true or false"]),
        (lambda d: d["instruments"][0].pop("trajectory"), ["missing key instruments[0].trajectory"]),
        (
            lambda d: d["instruments"][0]["trajectory"].update(times=[0.0, 0.5]),
            ["instruments[0].trajectory.base_positions", "2 rows of 3"],
        ),
        (lambda d: d.update(instruments=[]), ["expected an array of tables [[instruments]]"]),
        (
            lambda d: (d["cutting"].update(enabled=False), d["instruments"][1].update(cuts=True)),
            ["instruments[1].cuts", "cutting.enabled is false"],
        ),
    ],
)
def test_bad_instruments_are_named(change, fragments):
    with pytest.raises(SceneError) as raised:
        scene_from_dict(_changed(change), source="two.toml")
    message = str(raised.value)
    assert "two.toml" in message
    for fragment in fragments:
        assert fragment in message, message


def test_the_cli_exits_2_on_a_bad_instrument(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    text = (resources.files("refsim") / "scenes" / "two_needles.toml").read_text(encoding="utf-8")
    path.write_text(text.replace('name = "holder"', 'name = "cutter"'), encoding="utf-8")
    output = tmp_path / "out.h5"
    code = main(["run", str(path), "-o", str(output)])
    error = capsys.readouterr().err
    assert code == 2 and "instruments[1].name" in error and "Traceback" not in error
    assert not output.exists()


def test_segment_distances_against_a_dense_search():
    # Reference: the least distance over a 801 × 801 grid of (s, t), which is at most the true minimum plus
    # half a grid step along each segment (|u| h/2 + |v| h/2), and never below it.
    from refsim.scene.build import segment_distances

    rng = np.random.default_rng(7)
    m = 40
    p, u, q, v = (rng.standard_normal((m, 3)) for _ in range(4))
    u[:5] = 2.0 * v[:5]  # parallel
    q[5:10] = p[5:10] + 0.3 * u[5:10]  # crossing (distance 0 where the segments meet)
    v[5:10] = rng.standard_normal((5, 3))
    p[10:12], u[10:12] = q[10:12], v[10:12]  # the same segment
    got = segment_distances(p, u, q, v)
    grid = np.linspace(0.0, 1.0, 801)
    h = grid[1] - grid[0]
    for k in range(m):
        a = p[k][None, None, :] + grid[:, None, None] * u[k]
        b = q[k][None, None, :] + grid[None, :, None] * v[k]
        brute = np.linalg.norm(a - b, axis=-1).min()
        assert got[k] <= brute + 1e-12
        assert got[k] >= brute - 0.5 * h * (np.linalg.norm(u[k]) + np.linalg.norm(v[k])) - 1e-12
    np.testing.assert_allclose(got[10:12], 0.0, atol=1e-15)


@pytest.mark.parametrize(
    ("holder_x", "radius", "overlap"),
    [(0.02123, 0.008, False), (-0.01977, 0.008, True), (-0.00377, 0.008, True), (-0.00377, 0.002, False)],
)
def test_instruments_whose_shafts_overlap_are_refused(holder_x, radius, overlap):
    # two_needles with the holder moved in x: onto the cutter's line (the same spot), or within the cutter's
    # stroke (the cutter reaches x = -1.177 cm at 2.8 s: 0.8 cm from x = -0.377 cm, less than 2 × 0.8 cm, but
    # more than two 2 mm radii).
    from refsim.scene.build import build_models

    data = _two_needles()
    data["needle"]["radius"] = radius
    trajectory = data["instruments"][1]["trajectory"]
    trajectory["base_positions"] = [[holder_x, *position[1:]] for position in trajectory["base_positions"]]
    scene = scene_from_dict(data, source="two.toml")
    if not overlap:
        assert len(build_models(scene).instruments) == 2
        return
    with pytest.raises(InstrumentsOverlap) as raised:  # a SceneError of its own type
        build_models(scene)
    assert isinstance(raised.value, SceneError)
    message = str(raised.value)
    for fragment in ("two.toml", "'cutter'", "'holder'", "overlap", "sum of their radii"):
        assert fragment in message, message
