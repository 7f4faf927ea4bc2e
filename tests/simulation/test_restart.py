"""A step is a function of its state (issue 23, item 4): a run restarted from a saved state gives the bits of
the uninterrupted run.

Each case runs a short scene once, keeping the state after chosen steps as a saved copy (a pickle round
trip, the in-memory form of a saved state); then a NEW :class:`Simulation` of the same scene continues from
each saved state to the end. Every array of the final state and of every record after the restart must equal
the uninterrupted run's bit for bit (``np.array_equal``, NaN equal to NaN); only wall-clock seconds are left
out.
The restart steps sit where something carried across steps is in use: the insertion points' coupling rings
(reused while the needle's tangent turns less than 1e-3 rad: a flexible needle turns a little every step), the
refreshed compliance strategy's stale factor (restarted part way between two factorisations), the fast
strategy's memo of rest compliance blocks, and the cut
(restarted just before the cut starts and after it, with tears in the steps that follow).
"""

from __future__ import annotations

import copy
import dataclasses
import pickle
import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp

from refsim.fem.compliance import Exact, FreeMotionStart, Refreshed
from refsim.fem.linear import available_linear_solvers
from refsim.fem.tissue import TissueModel, TissueState
from refsim.materials import HookeMaterial
from refsim.mesh.generators import box_mesh
from refsim.simulation import Simulation
from tests.simulation.cutting_cases import CuttingCase

COARSE = ("mesh.cells=[4, 4, 4]",)


def _differences(first, second, where: str = "") -> list[str]:
    """Where two values differ: arrays bit for bit (NaN equal to NaN), dataclasses, mappings and sequences
    field by field; a field whose name says ``seconds`` (wall clock) is left out."""
    if type(first) is not type(second):
        return [f"{where}: {type(first).__name__} against {type(second).__name__}"]
    if isinstance(first, np.ndarray):
        same = first.dtype == second.dtype and first.shape == second.shape
        same = same and np.array_equal(first, second, equal_nan=first.dtype.kind in "fc")
        return [] if same else [where]
    if sp.issparse(first):
        return _differences(
            (first.shape, first.indptr, first.indices, first.data),
            (second.shape, second.indptr, second.indices, second.data),
            where,
        )
    if dataclasses.is_dataclass(first):
        pairs = [(f.name, getattr(first, f.name), getattr(second, f.name)) for f in dataclasses.fields(first)]
    elif isinstance(first, dict):
        if first.keys() != second.keys():
            return [f"{where}: keys {sorted(first)} against {sorted(second)}"]
        pairs = [(str(key), first[key], second[key]) for key in first]
    elif isinstance(first, (list, tuple)):
        if len(first) != len(second):
            return [f"{where}: length {len(first)} against {len(second)}"]
        pairs = [(str(index), a, b) for index, (a, b) in enumerate(zip(first, second, strict=True))]
    elif isinstance(first, float):
        return [] if first == second or (np.isnan(first) and np.isnan(second)) else [where]
    else:
        return [] if first == second else [where]
    found = []
    for name, a, b in pairs:
        if "seconds" not in name:
            found += _differences(a, b, f"{where}.{name}")
    return found


def _check_restarts(scene, restarts: tuple[int, ...], total: int, watch=None) -> list:
    """Run ``total`` steps; from a saved copy of the state after each step of ``restarts``, continue with a
    new simulation to ``total``; assert that states and records are the uninterrupted run's. Returns the
    uninterrupted run's records; ``watch`` is called with each of its states."""
    simulation = Simulation(scene)
    state = simulation.initial_state()
    saved, records = {}, []
    for _ in range(total):
        state, record = simulation.step(state)
        records.append(record)
        if watch is not None:
            watch(state)
        if state.step in restarts:
            saved[state.step] = pickle.loads(pickle.dumps(state))
    assert not _differences(saved[restarts[0]], copy.deepcopy(saved[restarts[0]]))
    for step in restarts:
        restarted = Simulation(scene)
        resumed = saved[step]
        for index in range(step, total):
            resumed, record = restarted.step(resumed)
            assert not _differences(records[index], record, "record"), (step, record.step)
        assert not _differences(state, resumed, "state"), step
    return records


def _events(records) -> dict[str, list[int]]:
    found: dict[str, list[int]] = {}
    for record in records:
        for event in record.events:
            found.setdefault(event.name, []).append(record.step)
    return found


def test_restart_through_puncture_and_insertion_with_the_ring_coupling(cube_scene):
    scene = cube_scene(*COARSE)
    assert scene.insertion.coupling == "ring"
    records = _check_restarts(scene, restarts=(18, 30), total=34)
    # Puncture at step 21: the first restart goes through it, the second continues from insertion points.
    assert _events(records)["puncture"] == [21]
    assert records[29].insertion_point_count >= 2


def test_restart_of_a_flexible_needle_keeps_the_points_rings(cube_scene):
    scene = cube_scene(*COARSE, "needle.rigid=false")
    states = []
    _check_restarts(scene, restarts=(28,), total=32, watch=states.append)
    # The needle bends, so the tangent at the entry point turns, yet the point keeps the ring it got first
    # (turned by less than 1e-3 rad): a ring rebuilt on a restart would differ.
    built = next(state.path.rings.tangents[0] for state in states if state.path.rings is not None)
    state = states[-1]
    simulation = Simulation(scene)
    geometry = simulation.needle.geometry(state.needle)
    arc_length, _ = geometry.project(state.path.positions(state.tissue.positions, simulation.tets)[:1])
    assert np.array_equal(state.path.rings.tangents[0], built)
    assert not np.array_equal(geometry.tangents(arc_length)[0], built)


def test_restart_between_factorisations_of_the_refreshed_strategy(cube_scene):
    scene = cube_scene(*COARSE, 'compliance.strategy="refreshed"', "compliance.refresh_every=4")
    states = []
    _check_restarts(scene, restarts=(18, 26), total=30, watch=states.append)
    # Factorised at steps 1, 5, 9, ...: both restarts carry a factor used for 2 steps already.
    assert [states[step - 1].tissue_factor.age for step in (18, 26)] == [2, 2]


def test_restart_of_the_fast_strategy_recomputes_its_node_blocks_with_the_same_bits(cube_scene):
    # The fast strategy carries its last free displacement and its image under the last operator (the next
    # CG's start) in the state; its C₀ node blocks are a memo of the model, each solved alone the first time a
    # row touches its node, so a restarted run (which solves only the blocks it needs from then on) has the
    # uninterrupted run's bits. At 1e-4 the CG iterates in some steps of this run.
    scene = cube_scene(*COARSE, 'compliance.strategy="fast"', "compliance.tolerance=1e-4")
    states = []
    records = _check_restarts(scene, restarts=(18, 26, 30), total=34, watch=states.append)
    assert _events(records)["puncture"] == [21]
    for step in (18, 26, 30):
        carried = states[step - 1].tissue_factor
        assert isinstance(carried, FreeMotionStart)
        assert not carried.displacement.flags.writeable and not carried.load.flags.writeable
        assert np.abs(carried.displacement).max() > 0.0 and np.abs(carried.load).max() > 0.0


@pytest.fixture(scope="module")
def cut_scene():
    return CuttingCase(cells=4, depth=0.006, stroke=(0.003, 0.0)).scene()


def test_restart_through_the_cut_start_and_tears(cut_scene):
    records = _check_restarts(cut_scene, restarts=(41, 45), total=48)
    events = _events(records)
    # The cut starts at step 42 and tears at 44 and 47: the first restart goes through both, the second
    # continues a cut.
    assert events["cut_start"] == [42]
    assert [step for step in events["tear"] if step > 45]
    assert records[44].cut_triangle_count > 0


# The pieces: the compliance's carried factor and its memo of W, on a small clamped box.


@pytest.fixture(scope="module")
def box():
    mesh = box_mesh(size=(0.1, 0.1, 0.1), cells=(3, 3, 3))
    rest = np.asarray(mesh.rest_positions, dtype=float)
    material = HookeMaterial(youngs_modulus=5.0e5, poisson_ratio=0.4, density=1000.0)
    return TissueModel(
        rest,
        np.asarray(mesh.tets),
        material,
        rayleigh_stiffness=0.01,
        fixed_nodes=np.flatnonzero(rest[:, 2] < 1e-12),
    )


def _box_system(model, amplitude: float):
    rest = model.rest_positions
    positions = rest + amplitude * np.sin(20.0 * rest)
    positions[model.fixed_nodes] = rest[model.fixed_nodes]
    return model.assemble_step(TissueState(positions=positions, velocities=np.zeros_like(rest)), 0.01)


def _box_rows(model, count: int = 5) -> sp.csr_matrix:
    rng = np.random.default_rng(2)
    free = np.setdiff1d(np.arange(model.dof_count), 3 * model.fixed_nodes[:, None] + np.arange(3))
    columns = rng.choice(free, (count, 6), replace=False)
    rows = np.repeat(np.arange(count), 6)
    return sp.csr_matrix(
        (rng.standard_normal(rows.size), (rows, columns.ravel())), shape=(count, model.dof_count)
    )


def test_a_body_resumed_from_a_carried_stale_factor_gives_the_bits_of_the_body_that_kept_it(box):
    strategy = Refreshed(refresh_every=3)
    kept = strategy.bind()
    kept.step(_box_system(box, 0.001))
    kept.step(_box_system(box, 0.002))
    carried = pickle.loads(pickle.dumps(kept.carried()))
    assert carried.age == 2
    resumed = strategy.bind()
    resumed.resume(carried)
    system = _box_system(box, 0.003)  # A has changed since the factorisation: PCG on the stale factor
    first, second = kept.step(system), resumed.step(system)
    assert not first.report["refactorised"] and not second.report["refactorised"]
    rows = _box_rows(box)
    multipliers = np.linspace(-1.0, 1.0, rows.shape[0])
    assert np.array_equal(first.free_displacement, second.free_displacement)
    assert np.array_equal(first.delassus(rows), second.delassus(rows))
    assert np.array_equal(first.correction(rows, multipliers), second.correction(rows, multipliers))
    # The factor is due after refresh_every steps; resumed from None (a run's start), at once.
    assert kept.step(system).report["refactorised"]
    resumed.resume(None)
    assert resumed.step(system).report["refactorised"]


def test_the_memo_of_w_is_keyed_on_the_rows_by_value(box):
    system = _box_system(box, 0.001)
    step = Exact().bind().step(system)
    rows = _box_rows(box)
    before = step.delassus(rows)
    rows.data *= 2.0  # the same object, changed in place: not the rows W was computed for
    fresh = Exact().bind().step(system)
    assert np.array_equal(step.delassus(rows), fresh.delassus(rows))
    assert not np.array_equal(step.delassus(rows), before)


def test_restart_of_two_needles_through_both_punctures_and_the_cut():
    # Each instrument carries its own story (phase, path with its rings, cut strip, tip) in the state; the
    # cut surface is the tissue's. Restarts: while the cutter inserts and the holder approaches, after the
    # holder's puncture, and in the cutter's cut (tears follow).
    import tomllib
    from importlib import resources

    from refsim.scene import scene_from_dict

    data = tomllib.loads((resources.files("refsim") / "scenes" / "two_needles.toml").read_text("utf-8"))
    data["mesh"]["cells"] = [4, 4, 4]
    scene = scene_from_dict(data, source="two_needles.toml")
    records = _check_restarts(scene, restarts=(60, 80, 206), total=215)
    names = [
        (record.step, part.name, event.name)
        for record in records
        for part in record.instruments
        for event in part.events
    ]
    assert (21, "cutter", "puncture") in names and (71, "holder", "puncture") in names
    assert any(name == "cut_start" and step < 206 for step, _, name in names)
    assert any(name == "tear" and step > 206 for step, _, name in names)


_SAME_SIMULATION_AGAIN = """
import pickle
import numpy as np
from refsim.scene.loader import load_scene
from refsim.simulation import Simulation
from tests.simulation.test_restart import _differences

scene = load_scene("cube", ["mesh.cells=[4, 4, 4]", *{overrides!r}])
assert scene.compliance.strategy == "exact"
simulation = Simulation(scene)
runs, saved = [], None
for run in range(2):
    records = []
    state = simulation.run(steps=34, on_step=lambda state, record: records.append(record))
    runs.append((state, records))
    if run == 0:
        saved = pickle.loads(pickle.dumps(state))
first, second = runs
print("again", not _differences(first, second))
# a restart on the same simulation: from the first run's step 18, continued to 34
restart = Simulation(scene)
state = restart.run(steps=18)
resumed = simulation.run(steps=16, state=pickle.loads(pickle.dumps(state)))
print("resumed", not _differences(first[0], resumed, "state"))
"""


@pytest.mark.parametrize("overrides", [(), ("solver.method=exact",)], ids=["gauss-seidel", "exact-solver"])
def test_a_second_run_of_the_same_simulation_gives_the_first_runs_bits(overrides):
    # The exact compliance strategy on PARDISO re-analyses its factor when the partial-solve marks change;
    # a second run of the same Simulation (and a restart on it) resumes without marks, then marks again.
    # That sequence once corrupted the C heap and aborted the process, so the runs go in a child process:
    # it must exit cleanly, its second run (through the puncture at step 21) must equal its first bit for
    # bit, and a run resumed on it from another simulation's state must reach the same final state.
    if "pardiso" not in available_linear_solvers():
        pytest.skip("pardiso not available on this machine")
    code = _SAME_SIMULATION_AGAIN.format(overrides=list(overrides))
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["again", "True", "resumed", "True"]
