"""The events' and the step's cheap paths (refsim.simulation.events, refsim.simulation.state,
refsim.constraints.insertion) give what the plain ones give.

The tip's location solves its candidate tets in one batch and filters singular ones only when the batch
meets one (the determinant filter it replaces, kept here as the reference); the state's copies (``evolved``,
``InsertionPath._with``) are ``dataclasses.replace`` without the pass through ``__init__``; the path's
points handed to ``grow_path`` are those it would compute; one locator of the step serves every event.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from refsim.constraints import InsertionPath, grow_path
from refsim.geometry import TetLocator
from refsim.scene import load_scene
from refsim.simulation import Simulation
from refsim.simulation.events import TIP_TOLERANCE, LazyLocator
from refsim.simulation.state import evolved


def _reference_tip(rules, positions, tip, hint):
    """The tip's location as it was computed before: a determinant filter, then one solve."""
    tip = np.asarray(tip, dtype=float)
    if hint >= 0:
        candidates = rules._tets_around(hint)
        corners = positions[np.asarray(rules.tets)[candidates]]
        edges = np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1))
        valid = np.abs(np.linalg.det(edges)) > 0.0
        local = np.linalg.solve(edges[valid], (tip - corners[valid, 0])[:, :, None])[:, :, 0]
        barycentric = np.concatenate([1.0 - local.sum(axis=1, keepdims=True), local], axis=1)
        inside = np.flatnonzero(barycentric.min(axis=1) >= -TIP_TOLERANCE)
        if inside.size:
            best = inside[np.argmax(barycentric[inside].min(axis=1))]
            return int(candidates[valid][best]), barycentric[best]
    found, barycentric = TetLocator(positions, rules.tets).locate(tip[None, :])
    return (int(found[0]), barycentric[0]) if found[0] >= 0 else (-1, None)


def _same_location(found, expected):
    assert found[0] == expected[0]
    if expected[1] is None:
        assert found[1] is None
    else:
        np.testing.assert_array_equal(found[1], expected[1])


@pytest.fixture(scope="module")
def cube():
    simulation = Simulation(load_scene("cube", ["mesh.cells=[3, 3, 3]"]))
    return simulation, simulation.sole.event_rules


def test_the_tip_is_located_as_by_the_determinant_filter_on_a_deformed_mesh(cube):
    simulation, rules = cube
    rng = np.random.default_rng(7)
    rest = np.asarray(simulation.models.mesh.rest_positions)
    positions = rest + 1e-3 * rng.standard_normal(rest.shape)
    tets = np.asarray(simulation.tets)
    for hint in rng.choice(len(tets), 12, replace=False):
        centre = positions[tets[hint]].mean(axis=0)
        for tip in (centre, centre + 0.01 * rng.standard_normal(3), centre + np.array([0.0, 0.0, 1.0])):
            expected = _reference_tip(rules, positions, tip, int(hint))
            _same_location(rules.locate_tip(positions, tip, int(hint)), expected)
            shared = LazyLocator(positions, tets)
            _same_location(rules.locate_tip(positions, tip, int(hint), shared), expected)


def test_a_singular_candidate_is_left_out_as_by_the_determinant_filter(cube):
    simulation, rules = cube
    tets = np.asarray(simulation.tets)
    positions = np.array(simulation.models.mesh.rest_positions, dtype=float)
    hint = 40
    around = rules._tets_around(hint)
    # Flatten a neighbour of the hint (not the hint): its last node onto the plane z = its first node's z, its
    # other two nodes too, so its edge matrix has a zero row (an exact zero pivot, det = 0).
    flat = int(next(t for t in around if t != hint))
    moved = [n for n in tets[flat] if n not in tets[hint]]
    assert moved, "the flattened tet must have a node outside the hint"
    positions[tets[flat], 2] = positions[tets[flat][0], 2]
    edges = np.transpose(positions[tets[around]][:, 1:] - positions[tets[around]][:, :1], (0, 2, 1))
    assert np.any(np.linalg.det(edges) == 0.0)
    with pytest.raises(np.linalg.LinAlgError):
        np.linalg.solve(edges, np.ones((len(around), 3, 1)))
    centre = positions[tets[hint]].mean(axis=0)
    for tip in (centre, positions[tets[flat]].mean(axis=0), centre + 0.003):
        _same_location(rules.locate_tip(positions, tip, hint), _reference_tip(rules, positions, tip, hint))


def test_evolved_is_replace_without_init(cube):
    simulation, _ = cube
    state = simulation.initial_state()
    own = state.instruments[0]
    changed = evolved(own, tip_tet=5, stretches=((0.1, 0.2),))
    assert changed == dataclasses.replace(own, tip_tet=5, stretches=((0.1, 0.2),))
    assert own.tip_tet == -1 and own.stretches is None  # the original is untouched
    assert evolved(state, step=3) == dataclasses.replace(state, step=3)
    with pytest.raises(TypeError, match="no field"):
        evolved(own, tip=1)


def test_the_path_copies_are_replace_and_keep_their_check():
    path = InsertionPath(np.array([3, 4]), np.full((2, 4), 0.25), np.array([1, 2]))
    stored = path.with_multipliers(np.ones((2, 2)))
    np.testing.assert_array_equal(stored.multipliers, [[1, 1, 0], [1, 1, 0]])
    np.testing.assert_array_equal(stored.tets, path.tets)
    anchored = stored.with_stuck([True, False]).with_anchors([0.1, np.nan], [0.0, -1e-5])
    assert anchored.stuck.tolist() == [True, False] and anchored.stretch.tolist() == [0.0, -1e-5]
    assert path.multipliers.tolist() == [[0, 0, 0], [0, 0, 0]]  # the original is untouched
    assert anchored.point_count == 2

    class Rings:  # a ring layout's point count is what the check reads
        point_count = 3

    with pytest.raises(ValueError, match="rings for 3 points"):
        path.with_rings(Rings())


def test_grow_path_with_the_points_given_is_grow_path(cube):
    simulation, _ = cube
    tets = np.asarray(simulation.tets)
    positions = np.asarray(simulation.models.mesh.rest_positions)
    locator = TetLocator(positions, tets)
    start = positions[tets[40]].mean(axis=0)
    found, barycentric = locator.locate(start[None, :])
    path = InsertionPath.empty().appended(found, barycentric, 1)
    tip = start + np.array([0.0, 0.0, -0.012])
    options = dict(tip=tip, tissue_positions=positions, mesh_tets=tets, locator=locator, spacing=0.005)
    plain, added = grow_path(path, step=2, **options)
    given, added_given = grow_path(path, step=2, points=path.positions(positions, tets), **options)
    assert added == added_given == 2
    np.testing.assert_array_equal(plain.tets, given.tets)
    np.testing.assert_array_equal(plain.barycentric, given.barycentric)
