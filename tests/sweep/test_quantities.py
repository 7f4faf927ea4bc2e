"""Quantities of interest on small hand-made results (no simulation): cut area, stroke, displacement,
forces."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from refsim.io.reader import CutHistory, RecordedEvent
from refsim.sweep import force_history_error, quantity


def _results(**extra):
    steps = np.arange(1, 5)
    rest = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) * 0.01
    tets = np.array([[0, 1, 2, 3]])
    displacement = np.array([1e-4, -2e-4, 3e-4])  # a translation: the same at every point
    base = np.array([[0.0, 0, 0.4], [0, 0, 0.39], [0.002, 0, 0.39], [0.004, 0, 0.39]])
    forces = np.array([[0.0, 0, 0], [0, 0, 1.0], [-3.0, 0, 4.0], [-1.0, 0, 0]])
    results = SimpleNamespace(
        step=steps,
        time=0.01 * steps,
        step_count=4,
        needle_force=forces,
        profile_force=forces,
        base_position=base,
        needle_rest_nodes=np.array([[0.0, 0, 0.4], [0, 0, 0.3]]),
        rest_positions=rest,
        tets=tets,
        tissue_steps=np.array([4]),
        tissue_positions=(rest + displacement)[None],
        events=(RecordedEvent(2, 0.02, "puncture", 0.8), RecordedEvent(3, 0.03, "cut_start", 1.0)),
        **{"cut": None, **extra},
    )
    results.events_named = lambda name: [e for e in results.events if e.name == name]
    results.index_of = lambda step: int(np.flatnonzero(steps == step)[0])
    axis = np.array([0.0, 0, -1])
    results.axial_lateral_force = lambda: (
        forces @ axis,
        np.linalg.norm(forces - np.outer(forces @ axis, axis), axis=1),
    )
    return results


def test_forces_at_events():
    results = _results()
    assert quantity(results, "needle_force@puncture") == pytest.approx(1.0)
    assert quantity(results, "needle_force@cut_start") == pytest.approx(5.0)
    assert quantity(results, "needle_force@end") == pytest.approx(1.0)
    assert quantity(results, "axial_force@cut_start") == pytest.approx(
        4.0
    )  # resisting the insertion along -z
    assert quantity(results, "lateral_force@cut_start") == pytest.approx(3.0)
    assert quantity(results, "puncture_force") == pytest.approx(0.8)
    assert quantity(results, "time@cut_start") == pytest.approx(0.03)
    assert np.isnan(quantity(results, "time@tear"))
    assert np.isnan(quantity(results, "needle_force@tear"))  # no such event: NaN
    assert quantity(results, "needle_force@t=0.031") == pytest.approx(5.0)  # nearest step: 3 (t = 0.03 s)
    assert np.isnan(quantity(results, "needle_force@t=1.0"))  # after the run's end
    with pytest.raises(ValueError, match="t=SECONDS"):
        quantity(results, "needle_force@t=soon")


def test_lateral_stroke_at_cut_start():
    # the base moved 10 mm down the axis (not lateral) and then 2 mm along x by the cut start
    assert quantity(_results(), "lateral_stroke@cut_start") == pytest.approx(0.002)


def test_cut_area_from_rest_triangles():
    square = np.array([[0.0, 0, 0], [0.002, 0, 0], [0.002, 0.003, 0], [0, 0.003, 0], [0.01, 0.01, 0.01]])
    cut = CutHistory(
        points=square,
        point_step=np.zeros(5, dtype=int),
        triangles=np.array([[0, 1, 2], [0, 2, 3]]),
        triangle_step=np.zeros(2, dtype=int),
    )
    assert quantity(_results(cut=cut), "cut_area") == pytest.approx(6e-6)
    assert np.isnan(quantity(_results(), "cut_area"))


def test_displacement_at_a_point():
    results = _results()
    assert quantity(results, "displacement@0.002,0.002,0.002") == pytest.approx(np.sqrt(14) * 1e-4)
    assert quantity(results, "displacement_z@0.002,0.002,0.002") == pytest.approx(3e-4)
    with pytest.raises(ValueError, match="outside the tissue"):
        quantity(results, "displacement@1,1,1")
    with pytest.raises(ValueError, match="X,Y,Z"):
        quantity(results, "displacement@1,1")
    with pytest.raises(ValueError, match="unknown"):
        quantity(results, "stress@end")


def test_force_history_error_interpolates_in_time():
    reference = _results()
    assert force_history_error(reference, reference) == 0.0
    other = _results()
    other.needle_force = reference.needle_force * 1.1
    assert force_history_error(other, reference) == pytest.approx(0.1)
