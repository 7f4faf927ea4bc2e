"""The detection's and the events' kept values (refsim.simulation.detection, refsim.simulation.events,
refsim.constraints.rows, refsim.constraints.coupling) change no bit of a run.

What is kept between steps: the probe sort of each set of row patterns (``rows._SORT_ORDERS``) and the
summation plan of each set of rows' nodes (``rows._PLANS``), the 2-D
sub-grid compliance of the last insertion rows (``Detector._compliance``, by the bytes of the rows' kinds
and the points' mesh sizes), the tets around each tet the tip was in (``EventRules._tets_around``), the
ring angles per point count (``coupling._ring_angles``) and the rest entries of the tissue's holes
(``Detector._holes_memo``, by the channels' tuple), and the last deformed-mesh locators, whose grid of the
tets' boxes the next step's locator takes over while each tet's box still lies in its box there
(``EventRules._last_locator``, ``Detector._cut_locator``). Each is a function of its key alone; a run whose
every store is emptied before each step must give the same bits as one that keeps them, through a puncture,
insertion (points added), a withdrawal out of the tissue and a re-entry into its hole (points removed, a
hole kept, the rings and patterns of a new path), and through a cut (cube_cut: its rows, the cut surface
changing every step).
"""

from __future__ import annotations

import numpy as np
import pytest

from refsim.constraints import coupling
from refsim.constraints import rows as rows_module
from refsim.scene import load_scene
from refsim.simulation import Simulation

TOP = 0.1
LENGTH = 0.32


def _in_out_in(entry=(0.00123, 0.00231)):
    """Overrides of the 4³ cube: the tip 2 mm above the top face, 8 mm in, back 1 mm above it (withdrawal),
    6 mm in again through the same hole (a re-entry)."""
    times, depths = [0.0, 0.8, 1.2, 1.6], [-0.002, 0.008, -0.001, 0.006]
    fmt = lambda v: "[" + ", ".join(repr(float(x)) for x in v) + "]"  # noqa: E731
    bases = [[entry[0], entry[1], TOP - d + LENGTH] for d in depths]
    return [
        "mesh.cells=[4, 4, 4]",
        f"trajectory.times={fmt(times)}",
        "trajectory.base_positions=[" + ", ".join(fmt(b) for b in bases) + "]",
        "trajectory.directions=[" + ", ".join("[0.0, 0.0, -1.0]" for _ in times) + "]",
        f"time.duration={times[-1]}",
    ]


def _cut_sideways():
    """Overrides of cube_cut on 4³ cells: the needle inserted 17 mm, then moved 8 mm along +x (it cuts)."""
    times, xs, zs = [0.0, 1.9, 2.0, 2.8], [0.00123, 0.00123, 0.00123, 0.00923], [0.422, 0.403, 0.403, 0.403]
    bases = "[" + ", ".join(f"[{x!r}, 0.00231, {z!r}]" for x, z in zip(xs, zs, strict=True)) + "]"
    return [
        "mesh.cells=[4, 4, 4]",
        f"trajectory.times={times!r}",
        f"trajectory.base_positions={bases}",
        "trajectory.directions=[" + ", ".join(["[0, 0, -1]"] * len(times)) + "]",
        f"time.duration={times[-1]}",
    ]


def _forget(simulation: Simulation) -> None:
    """Empty every store of kept values."""
    rows_module._SORT_ORDERS.clear()
    rows_module._PLANS.clear()
    coupling._ring_angles.cache_clear()
    for instrument in simulation.instruments:
        instrument.detector._compliance_memo = None
        instrument.detector._holes_memo = None
        instrument.detector._cut_locator = None
        instrument.event_rules._last_locator = None
        instrument.event_rules._around.clear()
        instrument.event_rules._around_nodes.clear()


def _run(scene, forget: bool):
    simulation = Simulation(scene)
    state = simulation.initial_state()
    records = []
    for _ in range(scene.time.step_count):
        if forget:
            _forget(simulation)
        state, record = simulation.step(state)
        records.append(record)
    return state, records


@pytest.mark.parametrize(
    ("name", "overrides", "expected"),
    [
        ("cube", _in_out_in(), {"puncture": 1, "withdrawal": 1, "reentry": 1}),
        ("cube_cut", _cut_sideways(), {"puncture": 1, "cut_start": 1}),
    ],
)
def test_kept_values_change_no_bit_of_a_run(name, overrides, expected):
    scene = load_scene(name, overrides)
    kept_state, kept = _run(scene, forget=False)
    fresh_state, fresh = _run(scene, forget=True)
    events = [event.name for record in kept for event in record.events]
    for event, count in expected.items():
        assert events.count(event) == count, events  # the run goes through what the test is about
    assert events == [event.name for record in fresh for event in record.events]
    for a, b in zip(kept, fresh, strict=True):
        np.testing.assert_array_equal(a.row_forces, b.row_forces)
        np.testing.assert_array_equal(a.needle_positions, b.needle_positions)
        np.testing.assert_array_equal(a.needle_force, b.needle_force)
    np.testing.assert_array_equal(kept_state.tissue.positions, fresh_state.tissue.positions)
    np.testing.assert_array_equal(kept_state.tissue.velocities, fresh_state.tissue.velocities)


def test_the_tets_around_a_tet_are_those_sharing_a_node_with_it():
    scene = load_scene("cube", ["mesh.cells=[3, 3, 3]"])
    simulation = Simulation(scene)
    rules = simulation.sole.event_rules
    tets = np.asarray(simulation.tets)
    for tet in (0, 17, len(tets) - 1):
        expected = np.flatnonzero(np.isin(tets, tets[tet]).any(axis=1))
        np.testing.assert_array_equal(rules._tets_around(tet), expected)
        assert rules._tets_around(tet) is rules._tets_around(tet)  # kept


def test_the_kept_compliance_follows_its_inputs():
    # The memo answers for the same kinds and mesh sizes only: other mesh sizes (a point added, a new ring)
    # or other kinds give their own values, and the first inputs again give the first values.
    scene = load_scene("cube", ["mesh.cells=[3, 3, 3]"])
    detector = Simulation(scene).sole.detector
    kinds = np.tile(np.array([0, 0, 2], dtype=np.int8), 4)  # BILATERAL, BILATERAL, FRICTION per point

    class Rows:  # the two fields insertion_compliance reads
        kind = kinds
        row_count = kinds.size

    def fresh(mesh_size):
        return coupling.insertion_compliance(
            Rows,
            shear_modulus=detector.shear_modulus,
            poisson_ratio=detector.poisson_ratio,
            needle_radius=detector.needle_radius,
            mesh_size=mesh_size,
            spacing=detector.insertion.spacing,
        )

    first, second = np.full(4, 0.03), np.array([0.03, 0.03, 0.03, 0.02])
    for mesh_size in (first, first, second, first):
        got = detector._compliance(Rows, mesh_size, None)
        np.testing.assert_array_equal(got, fresh(mesh_size))
    assert not np.array_equal(fresh(first), fresh(second))
