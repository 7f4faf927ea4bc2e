"""The tissue remembers the holes and channels needles leave in it (``SimulationState.channels``).

A needle inserted, pulled all the way back out and pushed in again through the same hole along the same line
meets the channel's friction alone, with no puncture and no tip cutting force, until its tip passes the old
channel's deepest point (Okamura, Simone and O'Leary, IEEE TBME 51(10), 2004, measured exactly this: no
puncture peak and no cutting force on re-insertion into the same hole). Each test runs the cube on 4³ cells
(or the 8 mm slab of the thin-layer tests) with a short trajectory (the helpers of ``test_life_cycle.py``).

The matrix (the cases beyond the first of each list are @slow):

- insert 6 mm, withdraw, re-insert to 10 mm through the same hole:
  ``test_a_needle_reinserted_into_its_hole_meets_its_channel_friction_alone`` (vertical and 30°; rigid and
  flexible; Gauss–Seidel, exact, the fast compliance; the entry inside a surface triangle, on a mesh edge,
  at a mesh vertex);
- the same, the second needle entering 2 needle radii beside the hole: punctures at f_p
  (``test_a_needle_beside_a_hole_punctures_the_surface``); entering 2 or 6 mm beside its old entry, within
  the hole: enters where it meets the surface, not pulled back to the old entry point
  (``test_a_needle_reentering_its_hole_off_its_old_axis_is_not_pulled_back_to_it``, rigid; flexible @slow);
- a hole through a thin layer (the needle left it through the far face): re-entered, no tip row at all
  (``test_a_channel_cut_through_a_layer_has_no_tip_row_when_reentered``);
- that hole re-entered at 30° from its line: the tip cuts the intact layer at f_cut
  (``test_a_channel_cut_through_a_layer_re_entered_at_another_angle_cuts_the_intact_tissue``);
- that layer entered from its far face through the exit hole by another needle: no puncture, no tip row
  (``test_a_layer_cut_through_is_entered_from_its_far_face_through_the_exit_hole``: vertical and 30°,
  Gauss–Seidel and exact);
- another instrument re-enters the hole the first one left (``test_another_needle_reenters_the_hole``);
- a run continued from a state saved between the withdrawal and the re-entry gives the uninterrupted bits
  (``test_restart_between_withdrawal_and_reentry``).
"""

from __future__ import annotations

import tomllib
from importlib import resources

import numpy as np
import pytest

from refsim.constraints import TIP
from refsim.scene import load_scene, scene_from_dict
from refsim.simulation import Phase, Simulation
from tests.simulation.test_life_cycle import (
    DIRECTIONS,
    ENTRIES,
    ENTRY,
    NEEDLES,
    SLAB,
    SLAB_BOTTOM,
    SLAB_SIDES,
    SOLVERS,
    TOP,
    _path_overrides,
    _run,
    assert_each_step_ends_with_the_rows_of_its_end_state,
)
from tests.simulation.test_restart import _check_restarts

VARIANTS = {**SOLVERS, "fast": ('compliance.strategy="fast"',)}
DEPTH = 0.006  # the first insertion's depth along the needle [m]


def _reinsertion(direction, entry_again=None, entry=ENTRY):
    """Knots: inserted 6 mm along the needle at 15 mm/s through ``entry`` on the top face, held 0.1 s, pulled
    out to 2 mm above the surface, held 0.3 s in the air (moved to ``entry_again`` there, ``entry`` when
    None), pushed in to 10 mm at 20 mm/s."""
    entry_again = entry if entry_again is None else entry_again
    return _path_overrides(
        [
            (0.0, entry, -0.002),
            (0.4, entry, DEPTH),
            (0.5, entry, DEPTH),
            (0.9, entry, -0.002),
            (1.2, entry_again, -0.002),
            (1.8, entry_again, 0.010),
        ],
        direction,
    )


def _named(records, *names):
    return [e.name for r in records for e in r.events if e.name in names]


def _tip(record) -> float:
    return float(record.row_forces[record.row_role == TIP].sum())


# (direction, needle, variant, entry on the top face, slow). The entries on a mesh edge and at a mesh vertex
# put the closest surface point on an edge or a vertex of the surface (ENTRIES of test_life_cycle.py).
REINSERTED = [
    pytest.param(direction, needle, variant, entry, marks=[pytest.mark.slow] if slow else [])
    for direction, needle, variant, entry, slow in [
        ("0deg", "rigid", "gauss_seidel", "face", False),
        ("30deg", "rigid", "exact", "face", False),
        ("30deg", "rigid", "gauss_seidel", "face", True),
        ("0deg", "rigid", "exact", "face", True),
        ("0deg", "rigid", "fast", "face", True),
        ("30deg", "rigid", "fast", "face", False),
        ("0deg", "flexible", "gauss_seidel", "face", True),
        ("30deg", "flexible", "gauss_seidel", "face", True),
        ("0deg", "flexible", "exact", "face", True),
        ("30deg", "flexible", "exact", "face", True),
        ("0deg", "rigid", "gauss_seidel", "edge", True),
        ("30deg", "rigid", "gauss_seidel", "edge", True),
        ("0deg", "rigid", "gauss_seidel", "vertex", True),
        ("30deg", "rigid", "gauss_seidel", "vertex", True),
    ]
]


@pytest.mark.parametrize(("direction", "needle", "variant", "entry"), REINSERTED)
def test_a_needle_reinserted_into_its_hole_meets_its_channel_friction_alone(
    direction, needle, variant, entry
):
    # The cube on 4³ cells at dt = 20 ms (knots of _reinsertion). Reference (Okamura et al. 2004): the
    # capsule is torn at the hole and the channel behind it is cut, so the needle pushed in again through
    # its hole meets the channel's friction alone up to the old depth, and the tip's cutting force f_cut only
    # beyond it. Before, the tissue forgot the hole on withdrawal: a second puncture at f_p at the old entry
    # and f_cut again from the surface down. Expected: puncture, withdrawal, reentry (no second puncture);
    # after the re-entry the tip's row free (0) while the tip is in the old channel (up to 6 mm less a step's
    # travel) and at f_cut beyond 6 mm by two steps' travel; the force along the needle in the channel the
    # shaft's friction alone (below f_cut / 4), resisting the insertion.
    axis = np.asarray(DIRECTIONS[direction]) / np.linalg.norm(DIRECTIONS[direction])
    dt = 0.02
    scene, records = _run(
        f"time.dt={dt}",
        *NEEDLES[needle],
        *VARIANTS[variant],
        *_reinsertion(DIRECTIONS[direction], entry=ENTRIES[entry]),
    )
    names = _named(records, "puncture", "withdrawal", "reentry", "exit")
    assert names == ["puncture", "withdrawal", "reentry"], names
    f_cut, travel = scene.insertion.tip_cutting_force, 0.02 * dt
    depth = lambda r: float((r.needle_positions[-1] - np.array([*ENTRIES[entry], TOP])) @ axis)  # noqa: E731
    entered = next(r.step for r in records if any(e.name == "reentry" for e in r.events))
    # No capped contact in a hole, so no event located inside the step; the re-entry's step is solved again
    # with the channel's rows (STEP_SOLVED_AGAIN): the needle in the hole at its end is held from that step.
    assert records[entered - 1].instruments[0].within_step is None
    assert_each_step_ends_with_the_rows_of_its_end_state(records)
    again = [r for r in records if r.step > entered]
    channel = [r for r in again if depth(r) <= DEPTH - travel]
    beyond = [r for r in again if depth(r) >= DEPTH + 2 * travel]
    assert len(channel) >= 10 and len(beyond) >= 5
    assert all(r.phase == Phase.INSERTION for r in again)
    assert all(_tip(r) <= 1e-6 * f_cut for r in channel), [(depth(r), _tip(r)) for r in channel]
    assert all(_tip(r) == pytest.approx(f_cut, rel=1e-5) for r in beyond), [_tip(r) for r in beyond]
    pushed = np.array([r.needle_force @ axis for r in channel])
    assert np.all(pushed <= 0.0) and np.all(-pushed < 0.25 * f_cut), pushed
    assert np.any(pushed < 0.0)
    # The shaft's insertion points are laid again down the channel.
    assert channel[-1].insertion_point_count >= 0.5 * (DEPTH - 2 * travel) / scene.insertion.spacing


def test_a_needle_beside_a_hole_punctures_the_surface():
    # As above, vertical, but re-inserted 2 needle radii (16 mm) beside the hole along x: the surface there
    # is intact. Expected: a second puncture at f_p (the capped tip contact), no reentry, and the tip cutting
    # at f_cut from the puncture on.
    scene = load_scene("cube", ["mesh.cells=[4, 4, 4]"])
    beside = (ENTRY[0] + 2 * scene.needle.radius, ENTRY[1])
    scene, records = _run("time.dt=0.02", *_reinsertion(DIRECTIONS["0deg"], beside))
    punctures = [(r, e) for r in records for e in r.events if e.name == "puncture"]
    assert _named(records, "puncture", "withdrawal", "reentry") == ["puncture", "withdrawal", "puncture"]
    for _, event in punctures:
        assert event.force == pytest.approx(scene.insertion.puncture_force, rel=1e-6)
    second = punctures[1][0].step
    later = [r for r in records if r.step > second + 1]
    assert later and all(_tip(r) == pytest.approx(scene.insertion.tip_cutting_force, rel=1e-5) for r in later)


OFF_AXIS = [
    pytest.param(0.002, "rigid", id="2mm-rigid"),
    pytest.param(0.006, "rigid", id="6mm-rigid"),
    pytest.param(0.002, "flexible", id="2mm-flexible", marks=pytest.mark.slow),
    pytest.param(0.006, "flexible", id="6mm-flexible", marks=pytest.mark.slow),
]


@pytest.mark.parametrize(("offset", "needle"), OFF_AXIS)
def test_a_needle_reentering_its_hole_off_its_old_axis_is_not_pulled_back_to_it(offset, needle):
    # As the first test, vertical, but re-inserted `offset` beside the old entry along x, within the hole's
    # radius (the needle's, 8 mm). Reference: the surface is open over the hole, so the needle enters where
    # it meets it (no puncture) and has no tissue to push aside there: its lateral force is the channel's
    # friction's, as on its old axis (2.4 mN at 0 offset). When the re-entry's first insertion point was the
    # old entry point, its rows pulled the needle back to it, the energy law's cut start leaving them out:
    # 2.9 N at 2 mm and 16.5 N at 6 mm, to the end of the run.
    scene, records = _run(
        "time.dt=0.02", *NEEDLES[needle], *_reinsertion(DIRECTIONS["0deg"], (ENTRY[0] + offset, ENTRY[1]))
    )
    assert _named(records, "puncture", "withdrawal", "reentry") == ["puncture", "withdrawal", "reentry"]
    entered = next(r.step for r in records if any(e.name == "reentry" for e in r.events))
    lateral = [float(np.linalg.norm(r.needle_force[:2])) for r in records if r.step >= entered]
    assert max(lateral) < 0.05 * scene.insertion.puncture_force, lateral


def test_a_channel_cut_through_a_layer_has_no_tip_row_when_reentered():
    # The 8 mm slab at dt = 10 ms: crossed at 20 mm/s to 11 mm (the tip 3 mm out through the far face),
    # pulled back out to 2 mm above the top face, pushed through again to 11 mm. Reference: the layer is cut
    # through along the channel (Okamura et al. 2004), so the re-entered needle meets neither a puncture nor
    # a tip cutting force, only the shaft's friction. Expected: puncture, exit, withdrawal, reentry, exit; no
    # tip row after the re-entry; the force along the needle below f_cut / 4 (the friction).
    knots = [
        (0.0, ENTRY, -0.002),
        (0.65, ENTRY, 0.011),
        (1.3, ENTRY, -0.002),
        (1.4, ENTRY, -0.002),
        (2.05, ENTRY, 0.011),
    ]
    scene, records = _run(*SLAB, "time.dt=0.01", *_path_overrides(knots, (0.0, 0.0, -1.0)))
    names = _named(records, "puncture", "exit", "withdrawal", "reentry")
    assert names == ["puncture", "exit", "withdrawal", "reentry", "exit"], names
    entered = next(r.step for r in records if any(e.name == "reentry" for e in r.events))
    after = [r for r in records if r.step >= entered]
    assert any(SLAB_BOTTOM < r.needle_positions[-1, 2] < TOP - 0.002 for r in after)  # the tip in the layer
    assert not any(np.any(r.row_role == TIP) for r in after)
    along = [abs(r.needle_force[2]) for r in after]
    assert max(along) < 0.25 * scene.insertion.tip_cutting_force, max(along)
    assert_each_step_ends_with_the_rows_of_its_end_state(records)


def _instrument(name, knots, direction=(0.0, 0.0, -1.0)):
    """An [[instruments]] table of the cube's needle through ``knots`` (as _path_overrides')."""
    direction = np.asarray(direction, dtype=float)
    length = 0.32
    return {
        "name": name,
        "cuts": False,
        "trajectory": {
            "times": [t for t, _, _ in knots],
            "base_positions": [
                [float(c) for c in np.array([x, y, TOP]) + (d - length) * direction] for _, (x, y), d in knots
            ],
            "directions": [[float(c) for c in direction] for _ in knots],
        },
    }


def test_another_needle_reenters_the_hole():
    # Two needles of the cube's on 4³ cells (refsim/scenes/two_needles.toml's tissue): "first" inserts 6 mm,
    # is pulled back out to 2 mm above the surface and moved 20 mm aside; "second" waits 4 mm above the
    # surface 20 mm to the other side, moves over the hole once the first has left it and is pushed to 10 mm
    # along the first's line (their shafts stay more than the sum of their radii apart: refsim models no
    # contact between instruments). The hole belongs to the tissue: expected, the first punctures and is
    # withdrawn, the second re-enters (no puncture) and meets no tip cutting force up to the first's depth,
    # f_cut beyond it.
    data = tomllib.loads((resources.files("refsim") / "scenes" / "two_needles.toml").read_text("utf-8"))
    data["mesh"]["cells"] = [4, 4, 4]
    data["time"].update(dt=0.02, duration=2.0)
    data["cutting"]["enabled"] = False
    data["insertion"]["tip_cutting_force"] = 0.5  # the cube's f_cut (two_needles has none)
    left, right = (ENTRY[0] - 0.02, ENTRY[1]), (ENTRY[0] + 0.02, ENTRY[1])
    data["instruments"] = [
        _instrument(
            "first", [(0.0, ENTRY, -0.002), (0.4, ENTRY, DEPTH), (0.8, ENTRY, -0.002), (1.1, right, -0.002)]
        ),
        _instrument(
            "second", [(0.0, left, -0.004), (1.1, left, -0.004), (1.4, ENTRY, -0.004), (2.0, ENTRY, 0.010)]
        ),
    ]
    simulation = Simulation(scene_from_dict(data, source="two_needles.toml"))
    records = []
    simulation.run(on_step=lambda state, record: records.append(record))

    def events(name):
        parts = [(r.step, part) for r in records for part in r.instruments if part.name == name]
        return [(step, e.name) for step, part in parts for e in part.events]

    first = [name for _, name in events("first") if name in ("puncture", "withdrawal", "reentry")]
    second = [name for _, name in events("second") if name in ("puncture", "withdrawal", "reentry")]
    assert first == ["puncture", "withdrawal"] and second == ["reentry"], (first, second)
    f_cut = simulation.scene.insertion.tip_cutting_force
    assert f_cut > 0.0
    index = next(i for i, instrument in enumerate(simulation.instruments) if instrument.name == "second")

    def tip(record):
        mine = (record.row_role == TIP) & (record.row_instrument == index)
        return float(record.row_forces[mine].sum())

    def depth(record):
        part = next(part for part in record.instruments if part.name == "second")
        return float(TOP - part.needle_positions[-1, 2])

    entered = next(step for step, name in events("second") if name == "reentry")
    channel = [r for r in records if r.step > entered and depth(r) <= DEPTH - 0.0004]
    beyond = [r for r in records if r.step > entered and depth(r) >= DEPTH + 0.0008]
    assert channel and beyond
    assert all(tip(r) <= 1e-6 * f_cut for r in channel)
    assert all(tip(r) == pytest.approx(f_cut, rel=1e-5) for r in beyond)


FAR_FACE = [
    pytest.param(direction, solver, marks=[pytest.mark.slow] if slow else [])
    for direction, solver, slow in [
        ("0deg", (), False),
        ("30deg", (), False),
        ("0deg", SOLVERS["exact"], True),
    ]
]


@pytest.mark.parametrize(("direction", "solver"), FAR_FACE)
def test_a_layer_cut_through_is_entered_from_its_far_face_through_the_exit_hole(direction, solver):
    # The 8 mm slab (side faces clamped, both faces free) at dt = 10 ms: "first" crosses it along
    # ``direction`` (vertical, or 30° from it) at 20 mm/s until its tip is 3 mm past the bottom face and is
    # pulled back out above the top face; "second" points back up that line, waits 4 mm beyond the exit
    # 20 mm aside, moves onto the line once the first has left the layer and is pushed 5 mm into the layer
    # along it. Reference: the layer is cut through along the first's line (Okamura et al. 2004), so its
    # exit is a hole as its entry is: the second needle meets no puncture there and no tip cutting force on
    # that line, only the shaft's friction. Expected: first puncture, exit, withdrawal; second reentry alone;
    # no tip row of the second; its force along the needle below f_cut / 4. (Before, only the entry was a
    # hole: the second punctured the bottom face at f_p and cut at f_cut.)
    axis = np.asarray(DIRECTIONS[direction]) / np.linalg.norm(DIRECTIONS[direction])
    through = (TOP - SLAB_BOTTOM) / -axis[2]  # the channel's length along the line [m]
    data = tomllib.loads((resources.files("refsim") / "scenes" / "two_needles.toml").read_text("utf-8"))
    data["mesh"].update(
        cells=[4, 4, 2], size=[0.1, 0.1, 0.008], origin=[-0.05, -0.05, SLAB_BOTTOM], fixed_faces=SLAB_SIDES
    )
    data["needle"]["radius"] = 0.0005
    data["time"].update(dt=0.01, duration=2.2)
    data["cutting"]["enabled"] = False
    data["insertion"]["tip_cutting_force"] = 0.5  # the cube's f_cut (two_needles has none)
    if solver:
        data["solver"]["method"] = "exact"
    aside = (ENTRY[0] - 0.02, ENTRY[1])
    beyond, inside = -(through + 0.004), -(through - 0.005)  # the second's tip along -axis from the entry
    data["instruments"] = [
        _instrument(
            "first", [(0.0, ENTRY, -0.002), (0.65, ENTRY, through + 0.003), (1.3, ENTRY, -0.002)], axis
        ),
        _instrument(
            "second",
            [(0.0, aside, beyond), (1.3, aside, beyond), (1.6, ENTRY, beyond), (2.05, ENTRY, inside)],
            -axis,
        ),
    ]
    simulation = Simulation(scene_from_dict(data, source="slab.toml"))
    records = []
    simulation.run(on_step=lambda state, record: records.append(record))

    def events(name):
        parts = [(r.step, part) for r in records for part in r.instruments if part.name == name]
        return [e.name for _, part in parts for e in part.events if e.name in NAMED]

    assert events("first") == ["puncture", "exit", "withdrawal"], events("first")
    assert events("second") == ["reentry"], events("second")
    f_cut = simulation.scene.insertion.tip_cutting_force
    index = next(i for i, instrument in enumerate(simulation.instruments) if instrument.name == "second")
    second = [(r, next(part for part in r.instruments if part.name == "second")) for r in records]
    entered = [(r, part) for r, part in second if part.phase == Phase.INSERTION]
    assert any(part.needle_positions[-1, 2] > SLAB_BOTTOM + 0.004 for _, part in entered)  # 4 mm in
    assert not any(np.any((r.row_role == TIP) & (r.row_instrument == index)) for r, _ in entered)
    along = [abs(part.needle_force @ axis) for _, part in entered]
    assert max(along) < 0.25 * f_cut, max(along)


NAMED = ("puncture", "exit", "withdrawal", "reentry")


def test_restart_between_withdrawal_and_reentry():
    # A step is a function of its state: the tissue's channels are carried in it, so a run continued from a
    # state saved after the withdrawal (step 46, the needle in the air) re-enters the hole at the step the
    # uninterrupted run does, with its bits.
    scene = load_scene("cube", ["mesh.cells=[4, 4, 4]", "time.dt=0.02", *_reinsertion(DIRECTIONS["0deg"])])
    states = []
    records = _check_restarts(scene, restarts=(46,), total=72, watch=states.append)
    withdrawn = next(r.step for r in records if any(e.name == "withdrawal" for e in r.events))
    entered = next(r.step for r in records if any(e.name == "reentry" for e in r.events))
    assert withdrawn < 46 < entered
    assert len(states[45].channels) == 1 and states[45].phase == "approach"


def test_a_hole_is_found_in_rest_coordinates_wherever_the_tissue_moved():
    # The hole belongs to the tissue's material: the tissue moved 12 mm along x since it was made (a
    # breathing organ), so the hole now lies 12 mm from where it was made. Expected: a tip above the moved
    # hole meets it (its closest surface point's rest position lies at the hole's rest entry); a tip above
    # the place the hole was made, now 12 mm (1.5 needle radii) beside it in the tissue's material, meets
    # intact surface. Compared in the deformed configuration, both answers would be the other way round.
    from refsim.constraints import find_surface_contact
    from refsim.geometry import SurfaceProjector
    from refsim.simulation.events import locate_under_surface
    from refsim.simulation.state import Channel, ChannelEnd

    simulation = Simulation(load_scene("cube", ["mesh.cells=[4, 4, 4]"]))
    rest, tets, faces = simulation.models.mesh.rest_positions, simulation.tets, simulation.faces
    entry = np.array([[*ENTRY, TOP]])
    tet, barycentric = locate_under_surface(rest, tets, entry, inward=np.array([0.0, 0.0, -1.0]))
    radius = simulation.scene.needle.radius
    hole = Channel(int(tet[0]), barycentric[0], ChannelEnd(int(tet[0]), barycentric[0]), radius, 1)
    shift = np.array([1.5 * radius, 0.0, 0.0])
    moved = rest + shift
    projector, down = SurfaceProjector(moved, faces), np.array([0.0, 0.0, -1.0])
    detector = simulation.detector

    def found(tip):
        contact = find_surface_contact(projector, faces, tip, down)
        return detector.hole(contact, (hole,), tets)

    assert found(entry[0] + shift + [0.0, 0.0, 0.001]) is hole
    assert found(entry[0] + [0.0, 0.0, 0.001]) is None
    # Within the radius of the moved entry, and not beyond it.
    assert found(entry[0] + shift + [0.9 * radius, 0.0, 0.001]) is hole
    assert found(entry[0] + shift + [0.0, 1.1 * radius, 0.001]) is None


def test_a_channel_cut_through_a_layer_re_entered_at_another_angle_cuts_the_intact_tissue():
    # The 8 mm slab at dt = 10 ms: crossed vertically to 11 mm (out through the far face), pulled back out to
    # 10 mm above the top face, turned to 30° in the air and pushed in again through the same hole, 6 mm
    # along the needle (5.2 mm deep: inside the layer). Reference: the tissue is cut along the vertical
    # channel only; on the turned line the layer is intact beyond the hole, so the tip cuts it at f_cut (the
    # channel's exit point lies 8 sin 30° = 4 mm off the needle's line, 8 times its 0.5 mm radius).
    # Expected: puncture, exit, withdrawal, reentry; after the re-entry the tip has a row, and it reaches
    # f_cut (a through channel once had no end point, and its re-entered needle no tip row on any line).
    tilted = np.asarray(DIRECTIONS["30deg"]) / np.linalg.norm(DIRECTIONS["30deg"])
    vertical = np.array([0.0, 0.0, -1.0])
    top = np.array([*ENTRY, TOP])
    # Turned about the tip, 10 mm above the hole, 5° per 0.4 s (slow enough for the tip's
    # speed check on the base's motion; the base's chord keeps the tip within 0.5 mm).
    turns = [
        (1.5 + 0.4 * k, np.array([np.sin(a), 0.0, -np.cos(a)]), -0.010)
        for k, a in enumerate(np.radians(np.arange(0, 31, 5)))
    ]
    knots = [
        (0.0, vertical, -0.002),
        (0.65, vertical, 0.011),
        (1.3, vertical, -0.010),
        *turns,
        (4.3, tilted, -0.002),
        (4.7, tilted, 0.006),
    ]
    fmt = lambda v: "[" + ", ".join(repr(float(c)) for c in v) + "]"  # noqa: E731
    bases = [top + (d - 0.32) * axis for _, axis, d in knots]
    overrides = (
        f"trajectory.times={fmt([t for t, _, _ in knots])}",
        "trajectory.base_positions=[" + ", ".join(fmt(b) for b in bases) + "]",
        "trajectory.directions=[" + ", ".join(fmt(axis) for _, axis, _ in knots) + "]",
        f"time.duration={knots[-1][0]}",
    )
    scene, records = _run(*SLAB, "time.dt=0.01", *overrides)
    names = _named(records, "puncture", "exit", "withdrawal", "reentry")
    assert names == ["puncture", "exit", "withdrawal", "reentry"], names
    entered = next(r.step for r in records if any(e.name == "reentry" for e in r.events))
    tip = [_tip(r) for r in records if r.step > entered]
    assert any(np.any(r.row_role == TIP) for r in records if r.step > entered)
    f_cut = scene.insertion.tip_cutting_force
    assert max(tip) >= (1.0 - 1e-3) * f_cut, (max(tip), f_cut)
