"""The reference cases' levels and quantity definitions: window means of a curve (exact on a staircase), the
alignment of the cube cases' levels with their insertion, the refinement measure h = dt, a scalar for whether
an event happens, and the liver scenes copied into a package with their files. No runs (fast)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from refsim.reference import case_names, load_case, sample_curve
from refsim.reference.build import _copy_scene
from refsim.scene import load_scene

#: The cube cases' tip starts 2 mm above the top face (their set-up text); the insertion ends at t = 1.9 s.
GAP, STOP = 2e-3, 1.9
CUBE_CASES = ("insertion", "lateral_push", "laceration", "laceration_paper_law", "withdrawal")


def _staircase(start: float, step: float, slope: float, end: float, jump: float = 1e-12):
    """Points of F(s) = slope · step · ceil((s − start)/step) on [start, end]: each jump drawn over ``jump``
    (a piecewise-linear curve that is the staircase but on those intervals)."""
    edges = start + step * np.arange(0, int(np.ceil((end - start) / step)) + 1)
    x = np.sort(np.concatenate([edges, edges + jump, [end]]))
    y = slope * step * np.ceil((x - start - 0.5 * jump) / step)
    keep = x <= end
    return x[keep], y[keep]


def test_window_mean_of_a_line_is_its_value_and_of_a_staircase_its_mean():
    """The window mean of a piecewise-linear curve is its exact integral over the window / width: a line's is
    its value at the centre; a staircase's over a whole number of steps, wherever the steps fall, is the
    staircase's mean, slope · (s − start) + slope · step / 2 at the centre (each ramp of width ε loses
    slope · step · ε / 2 of area per step: the tolerance)."""
    x = np.linspace(0.0, 10.0, 37)
    at = np.array([2.0, 5.0, 8.9])
    np.testing.assert_allclose(
        sample_curve(x, 3.0 * x - 1.0, at, where="t", width=2.0), 3.0 * at - 1.0, rtol=1e-12
    )
    assert np.isnan(sample_curve(x, x, [9.5], where="t", width=2.0)[0])  # the window leaves the curve
    slope, width, jump = 4.5, 6.8e-3, 1e-12
    at = np.array([4e-3, 6e-3, 13e-3])
    for cells, start in ((5, 0.11e-3), (7, 0.013e-3), (9, 0.5e-3)):
        step = 6.8e-3 / cells
        x, y = _staircase(start, step, slope, 17e-3, jump)
        mean = sample_curve(x, y, at, where="t", width=width)
        expected = slope * (at - start) + 0.5 * slope * step
        np.testing.assert_allclose(mean, expected, rtol=0.0, atol=slope * jump + 1e-15)
        # the point samples of the same staircase are off its mean by up to half a step, set by where the
        # steps fall: the quantity the window removes
        assert np.max(np.abs(sample_curve(x, y, at, where="t") - expected)) > 0.1 * slope * step


@pytest.mark.parametrize("name", CUBE_CASES)
def test_cube_levels_end_the_insertion_half_a_spacing_past_a_point(name):
    """At every level of the cube cases the 17 mm insertion is n + 1/2 insertion spacings deep (so the
    last point's phase is the same at every level), the windows of a window-mean quantity on depth are whole
    numbers of spacings, and every waypoint of the trajectory falls on a step."""
    case = load_case(name)
    scene = load_scene(case.scene_path, list(case.overrides))
    times = np.asarray(scene.trajectory.times, dtype=float)
    positions = np.asarray(scene.trajectory.base_positions, dtype=float)
    depth = np.linalg.norm(positions[0] - positions[np.searchsorted(times, STOP)]) - GAP
    assert depth == pytest.approx(17e-3, abs=1e-12)
    for level in case.levels:
        keys = case.level(level)
        for spacing in keys["insertion.spacing"]:
            assert (depth / spacing) % 1.0 == pytest.approx(0.5, abs=1e-9), (level, spacing)
            for quantity in case.quantities:
                if quantity.width and quantity.x == "tip_depth":
                    ratio = quantity.width / spacing
                    assert ratio == pytest.approx(round(ratio), abs=1e-9), (level, quantity.name)
        for dt in keys["time.dt"]:
            steps = times / dt
            np.testing.assert_allclose(steps, np.round(steps), atol=1e-9)


def test_liver_cases_refine_dt_and_copy_their_files(tmp_path):
    """h = dt for the liver (measure = "value": coarsest first, decreasing), and the package's copy of the
    scene loads on its own: its mesh and trajectory copied beside it, byte for byte."""
    for name in ("liver_rigid", "liver_flexible"):
        case = load_case(name)
        for level in case.levels:
            np.testing.assert_array_equal(case.spacings(level), case.level(level)["time.dt"])
            assert np.all(np.diff(case.spacings(level)) < 0.0)
        folder = tmp_path / name
        folder.mkdir()
        copied = _copy_scene(case.scene_path, folder)
        assert sorted(copied) == ["liver_phantom_coarse.vtu", "liver_robot.csv"]
        original = load_scene(case.scene_path)
        copy = load_scene(folder / "scene.toml")
        assert copy.mesh.file == "liver_phantom_coarse.vtu" and copy.trajectory.file == "liver_robot.csv"
        for file_name, source in (
            ("liver_phantom_coarse.vtu", case.scene_path.parent / original.mesh.file),
            ("liver_robot.csv", case.scene_path.parent / original.trajectory.file),
        ):
            assert (folder / file_name).read_bytes() == source.read_bytes()
    assert load_case("liver_rigid").quantity("cuts").kind == "scalar"
    assert {"liver_rigid", "liver_flexible"} <= set(case_names())


def test_case_file_keys_of_levels_and_windows_are_validated(tmp_path):
    head = '[case]\ntitle = "t"\nwhy = "w"\nsetup = "s"\nformal_order = 1\nrunner = "cantilever"\n'
    quantity = '[[quantity]]\nname = "q"\nunit = "N"\ny = "axial_force"\nx = "time"\nat = [1.0]\n'
    path = tmp_path / "case.toml"
    path.write_text(
        head + 'refine = "time.dt"\nmeasure = "value"\n[levels]\nc = { "time.dt" = [0.01, 0.02, 0.04] }\n'
    )
    with pytest.raises(
        ValueError, match=r"\[levels\] c: time.dt = \[0.01, 0.02, 0.04\]: expected positive, decreasing"
    ):
        load_case(path)
    path.write_text(
        head + 'refine = "time.dt"\nmeasure = "log"\n[levels]\nc = { "time.dt" = [0.04, 0.02, 0.01] }\n'
    )
    with pytest.raises(ValueError, match=r"\[case\] measure: 'log': expected one of inverse, value"):
        load_case(path)
    levels = 'refine = "n"\n[levels]\nc = { "n" = [2, 3, 4] }\n'
    path.write_text(head + levels + quantity + "width = -1.0\n")
    with pytest.raises(
        ValueError, match=r"\[\[quantity\]\] 1: width = -1.0: expected an averaging window >= 0"
    ):
        load_case(path)
    path.write_text(head + levels + '[[quantity]]\nname = "cuts"\nunit = "1"\nevent = "cut_start"\n')
    case = load_case(path)
    assert case.quantity("cuts").kind == "scalar" and not case.quantity("cuts").x
    assert math.isclose(case.spacings("c")[0], 0.5)


class _Run:
    """What event_crossing reads of a run: steps 0..9, an abscissa 0.1·step, a criterion 0.5·step with
    threshold 2.2 from step 1 on (crossed between steps 4 and 5), the event at step 5."""

    path = "run.h5"
    step = np.arange(10)

    def __init__(self, criteria=True):
        from refsim.simulation.margins import CriterionSeries

        steps = np.arange(1, 10)
        self.criteria = None
        if criteria:
            self.criteria = CriterionSeries(
                step=steps,
                name=np.array(["cut_start"] * steps.size, dtype=object),
                value=0.5 * steps,
                threshold=np.full(steps.size, 2.2),
                accuracy=np.zeros(steps.size),
                unit=np.array(["N"] * steps.size, dtype=object),
            )

    def events_named(self, name):
        from types import SimpleNamespace

        return [SimpleNamespace(step=5, name=name)] if name == "cut_start" else []

    def index_of(self, step):
        return int(step)


def test_event_crossing_interpolates_the_criterion_between_steps():
    """The criterion 0.5·step reaches 2.2 at step 4.4: the abscissa 0.1·step is 0.44 there, where the event's
    step alone would give 0.5; no event: NaN; no criterion recorded: an error naming the file."""
    from refsim.reference.cases import event_crossing

    abscissa = 0.1 * np.arange(10)
    assert event_crossing(_Run(), "cut_start", abscissa) == pytest.approx(0.44, abs=1e-12)
    assert math.isnan(event_crossing(_Run(), "tear", abscissa))
    with pytest.raises(ValueError, match="run.h5: no criterion 'cut_start' recorded"):
        event_crossing(_Run(criteria=False), "cut_start", abscissa)


def test_a_curve_read_until_an_event_has_no_window_across_it():
    """A curve read ``until`` an event (a force before the cut starts) keeps the steps before the
    event's first step (steps 0 to 4 of the run above, time 0.1·step): a window inside them is the curve's
    mean (y = time, linear: its mean is its value at the window's centre); a window that reaches the event's
    step has no sample (NaN), so a level whose event falls inside a window cannot mix the two sides of it."""
    from refsim.reference.cases import Quantity, _steps, sample_curve

    class Run(_Run):
        step_count = 10
        time = 0.1 * np.arange(10)

    quantity = Quantity(name="f", kind="curve", unit="N", x="time", y="needle_force", until="cut_start")
    keep = _steps(Run(), quantity)
    np.testing.assert_array_equal(np.flatnonzero(keep), np.arange(5))
    values = sample_curve(Run.time[keep], Run.time[keep], [0.2, 0.45], where="run.h5", width=0.1)
    assert values[0] == pytest.approx(0.2, abs=1e-12)
    assert math.isnan(values[1])
