"""Several instruments in one tissue (issue 23, item 5): refsim/scenes/two_needles.toml on the coarse cube.

Every instrument owns its story (phase, path, cut strip, events) and its rows carry its index; all rows are
solved in one constraint problem, coupled through the tissue's compliance. Nothing is special-cased for two: a
run of three needles is checked the same way.
"""

from __future__ import annotations

import copy
import tomllib
from importlib import resources

import numpy as np
import pytest

from refsim.scene import load_scene, scene_from_dict
from refsim.simulation import Simulation
from refsim.simulation.events import PUNCTURE_TOLERANCE

COARSE = {"cells": [4, 4, 4]}


def _two_needles(**time) -> dict:
    data = tomllib.loads((resources.files("refsim") / "scenes" / "two_needles.toml").read_text("utf-8"))
    data["mesh"].update(COARSE)
    data["time"].update(time)
    return data


def _run(data: dict, source: str = "two_needles.toml") -> tuple[Simulation, object, list]:
    simulation = Simulation(scene_from_dict(data, source=source))
    records = []
    state = simulation.run(on_step=lambda state, record: records.append(record))
    return simulation, state, records


def _events(records, name: str) -> dict[str, list[int]]:
    """Instrument ``name``'s events: event name -> steps."""
    found: dict[str, list[int]] = {}
    for record in records:
        part = next(part for part in record.instruments if part.name == name)
        for event in part.events:
            found.setdefault(event.name, []).append(record.step)
    return found


@pytest.fixture(scope="module")
def two():
    return _run(_two_needles())


@pytest.fixture(scope="module")
def two_exact():
    data = _two_needles()
    data["solver"]["method"] = "exact"
    return _run(data)


def _check_own_rows(records, count: int) -> None:
    """Every row belongs to one of the ``count`` instruments, and each instrument's force is Σ λ n over its
    rows (read by the rows' instrument field)."""
    for record in records:
        assert len(record.instruments) == count
        assert record.row_instrument.shape == record.row_forces.shape
        assert set(np.unique(record.row_instrument)) <= set(range(count))
        for index, part in enumerate(record.instruments):
            mine = record.row_instrument == index
            own = (record.row_directions[mine] * record.row_forces[mine, None]).sum(axis=0)
            np.testing.assert_array_equal(part.needle_force, own)


def _check_punctures(scene, records) -> None:
    """Each needle punctures once, at f_p: its own tip contact (its penetration normal rows, capped at f_p by
    insertion.puncture_within_step) carries f_p to the puncture test's tolerance when it gives way (the
    puncture step's within-step state)."""
    f_p = scene.insertion.puncture_force
    for index, spec in enumerate(scene.instrument_specs):
        steps = _events(records, spec.name).get("puncture")
        assert steps is not None and len(steps) == 1, spec.name
        record = records[steps[0] - 1]
        (event,) = [e for e in record.instruments[index].events if e.name == "puncture"]
        # The give-way: the step's end has the entry point's rows, its within-step state the tip's.
        within = record.instruments[index].within_step
        assert within is not None and within.event == "puncture"
        assert event.force == pytest.approx(within.normal_force, abs=0.0)
        assert f_p * (1.0 - PUNCTURE_TOLERANCE) <= event.force <= f_p * (1.0 + PUNCTURE_TOLERANCE)


def test_both_needles_puncture_at_f_p_insert_and_one_cuts(two):
    simulation, state, records = two
    scene = simulation.scene
    _check_own_rows(records, 2)
    _check_punctures(scene, records)
    cutter, holder = (_events(records, name) for name in ("cutter", "holder"))
    assert cutter["puncture"][0] < holder["puncture"][0]  # the holder starts 0.5 s later
    assert "cut_start" in cutter and "tear" in cutter
    assert set(holder) == {"puncture"}  # it inserts and holds: no cut
    assert [p.phase for p in records[-1].instruments] == ["cutting", "insertion"]
    assert state.instrument("holder").path.point_count > 10 and state.instrument("holder").cut_strip is None
    assert state.cut is not None and state.cut.triangle_count


# slow: the exact solver over the whole two-needle run (about 20 s alone); the instrument matrix's
# test_gauss_seidel_and_exact_agree_on_every_case compares both solvers on small cases in the default suite.
@pytest.mark.slow
def test_gauss_seidel_and_exact_agree_on_the_whole_two_needle_run(two, two_exact):
    # As for one needle (tests/simulation/test_cutting.py, test_gauss_seidel_and_exact_agree_on_the_events):
    # each solver converged to the natural residual 1e-8 on a positive definite problem finds the same
    # multipliers, so the same events at the same steps for each instrument, and each needle's force within a
    # thousandth of its peak (the coupling matrix's bound, tests/simulation/test_coupling_matrix.py).
    _, _, iterative = two
    _, _, exact = two_exact
    for name in ("cutter", "holder"):
        assert _events(iterative, name) == _events(exact, name), name
    for run in (iterative, exact):
        assert all(r.solver is None or r.solver.converged for r in run)
    for index in range(2):
        forces = [np.stack([r.instruments[index].needle_force for r in run]) for run in (iterative, exact)]
        assert np.abs(forces[0] - forces[1]).max() <= 1e-3 * np.abs(forces[1]).max(), index


def test_the_second_needle_changes_the_first_needles_force(two):
    # The coupling is the tissue's: the holder's rows and the cutter's are in one problem, W's off-diagonal
    # block H_cutter A⁻¹ H_holderᵀ couples them. Without the holder, the cutter's force differs from the first
    # step the holder has rows; 4 cm apart, by less than the holder's own load (what reaches the cutter is
    # part of it, carried through the tissue: its puncture at f_p = 0.8 N moves the cutter's force by about
    # 1 %).
    simulation, _, records = two
    data = _two_needles()
    data["instruments"] = data["instruments"][:1]
    _, _, alone = _run(data, "cutter_alone.toml")
    cut_start = _events(records, "cutter")["cut_start"][0]
    puncture = _events(records, "holder")["puncture"][0]
    first_rows = next(r.step for r in records if np.any(r.row_instrument == 1))
    differences, holder_forces, touching = [], [], []
    for together, single in zip(records, alone, strict=True):
        difference = np.linalg.norm(together.instruments[0].needle_force - single.needle_force)
        if together.step < first_rows:
            # Until the holder has a row (its tip within the contact distance) the problem is the cutter's
            # alone: the same bits.
            assert difference == 0.0, together.step
        elif together.step < puncture:
            touching.append(difference)
        elif together.step < cut_start:
            differences.append(difference)
            holder = together.instruments[1]  # its force profile: at its puncture, the give-way
            within = holder.within_step
            force = holder.needle_force if within is None else within.needle_force
            holder_forces.append(np.linalg.norm(force))
    differences, holder_forces = np.array(differences), np.array(holder_forces)
    # The holder's tip touching the surface (at most f_p = 0.8 N, reached at the puncture step only) moves
    # the cutter's force by much less than that.
    assert max(touching) < 1e-3 * simulation.scene.insertion.puncture_force
    assert differences.max() > 0.0
    assert np.all(differences <= np.maximum.accumulate(holder_forces)), (
        differences.max(),
        holder_forces.max(),
    )


@pytest.mark.slow
def test_three_needles_each_puncture_and_insert():
    data = _two_needles(duration=1.2)
    third = copy.deepcopy(data["instruments"][1])
    third.update(name="third")
    trajectory = third["trajectory"]
    trajectory["times"] = [0.0, 0.2, 1.2]
    trajectory["base_positions"] = [
        [0.00123, -0.02231, 0.422],
        [0.00123, -0.02231, 0.422],
        [0.00123, -0.02231, 0.412],
    ]
    trajectory["directions"] = [[0.0, 0.0, -1.0]] * 3
    data["instruments"].append(third)
    simulation, state, records = _run(data, "three.toml")
    assert state.instrument_names == ("cutter", "holder", "third")
    _check_own_rows(records, 3)
    _check_punctures(simulation.scene, records)
    assert all(instrument.phase == "insertion" for instrument in state.instruments)
    assert len(simulation.bodies) == 4


def test_one_instrument_in_instruments_gives_the_bits_of_the_needle_scene():
    from tests.simulation.test_restart import _differences

    scene = load_scene("cube", ["mesh.cells=[4, 4, 4]", "time.duration=0.4"])
    data = scene.to_dict()
    trajectory = data.pop("trajectory")
    data["instruments"] = [{"name": "needle", "trajectory": trajectory}]
    converted = scene_from_dict(data, source="cube_instruments.toml")
    assert len(converted.instruments) == 1
    runs = []
    for each in (scene, converted):
        records = []
        final = Simulation(each).run(on_step=lambda state, record, records=records: records.append(record))
        runs.append((final, records))
    assert _events(runs[0][1], "needle") == {"puncture": [21]}
    assert not _differences(runs[0][0], runs[1][0], "state")
    for first, second in zip(runs[0][1], runs[1][1], strict=True):
        assert not _differences(first, second, "record"), first.step


def test_several_instruments_refuse_the_one_needle_shortcuts(two):
    simulation, state, _ = two
    with pytest.raises(AttributeError, match="2 instruments"):
        _ = state.needle
    with pytest.raises(AttributeError, match="2 instruments"):
        _ = simulation.needle
    assert state.instrument("holder").name == "holder"
    with pytest.raises(KeyError, match="no instrument 'nobody'"):
        state.instrument("nobody")


@pytest.mark.parametrize("crossing", [False, True], ids=["apart", "crossing"])
def test_two_needles_that_both_cut_each_cut_at_g_c_per_unit_length(crossing):
    # two_needles on 4³ cells, r = 2 mm, both instruments cutting: the first inserted 17 mm at (−12, 1) mm
    # and moved 15 mm along x, then the second 17 mm at (−4, 9) mm moved 16 mm along −y, across the first's
    # cut (``crossing``, 7 mm behind the first needle), or at (20, 9) mm, beside it. Reference: the energy
    # law: each needle cuts with G_c per unit inserted length, G_c × 17 mm = 3.4 N, in steady cutting (the
    # last 0.3 s of each stroke, the other needle held still: the second's 5 mm after it crossed). Each cut
    # is its own strip of the one surface, which the other needle meets as a cut it is not cutting; at its
    # own front a cutting needle meets no other cut (the tissue ahead resists it, which its front cuts at
    # G_c per unit length), so crossing the first cut the second needle cuts at G_c × 17 mm all the way, as
    # in the steady windows (from 0.2 s after its cut start, when its stroke has begun); every step keeps
    # the random lives' invariants.
    from refsim.verification.invariants import life_violations

    data = _two_needles(duration=7.2)
    data["needle"]["radius"] = 0.002
    data["compliance"] = {"strategy": "fast"}

    def trajectory(start, stroke, start_time):
        x, y = start
        times = [0.0, start_time, start_time + 1.9, start_time + 1.9 + 100.0 * np.linalg.norm(stroke), 7.2]
        bases = [[x, y, 0.422], [x, y, 0.422], [x, y, 0.403]] + [[x + stroke[0], y + stroke[1], 0.403]] * 2
        directions = [[0.0, 0.0, -1.0]] * 5
        return {"times": [round(t, 2) for t in times], "base_positions": bases, "directions": directions}

    first, second = data["instruments"]
    first["trajectory"] = trajectory((-0.012, 0.001), (0.015, 0.0), 0.1)
    second["trajectory"] = trajectory((-0.004 if crossing else 0.02, 0.009), (0.0, -0.016), 3.6)
    second["cuts"] = True
    scene = scene_from_dict(data, source="two cutters")
    records, states = [], []
    Simulation(scene).run(on_step=lambda state, record: (records.append(record), states.append(state)))
    assert all("cut_start" in _events(records, name) for name in ("cutter", "holder"))
    forces = np.array([[np.linalg.norm(i.needle_force) for i in r.instruments] for r in records])
    g_c, depth = scene.cutting.fracture_energy, 0.017
    for index, stroke_end in ((0, 3.5), (1, 7.1)):  # (the strokes' ends)
        steady = forces[round((stroke_end - 0.3) / 0.01) : round(stroke_end / 0.01), index]
        assert steady == pytest.approx(g_c * depth, rel=0.01), (index, steady.min(), steady.max())
    second_start = _events(records, "holder")["cut_start"][0]
    stroke = forces[second_start + 20 : round(7.1 / 0.01), 1]  # (record i is step i + 1)
    assert stroke == pytest.approx(g_c * depth, rel=0.01), (stroke.min(), stroke.max())
    final = states[-1]
    own = [final.instrument(name).cut_strip.own_triangles(final.cut) for name in ("cutter", "holder")]
    assert own[0].any() and own[1].any() and not np.any(own[0] & own[1])
    assert life_violations(records, scene) == []
