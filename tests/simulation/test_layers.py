"""A needle through two layers of tissue with a gap between them (a wall over an organ): the tip punctures
each layer at f_p, and each layer keeps its own channel over the needle's life.

The tissue is two slabs in one mesh: an 8 mm layer (z from 92 to 100 mm, 4 x 4 x 2 cells over 10 x 10 cm)
above a 20 mm one, ``gap`` below it; both are held on their sides, the lower one on its bottom too. A needle
of the thin-layer tests (r = 0.5 mm) is pushed through the upper layer and 5 mm into the lower one, pulled
back until its tip is in the gap, pushed in again short of its first depth, pulled out of the tissue, and
pushed through both once more.

Reference (what the model says of a tip, whichever layer): a tip outside the tissue meets the surface ahead
of it as a contact it punctures at f_p (the paper's rule; capped within the step, or the plain one), and a
hole it cut as a hole (no puncture); its channel ends where it cut to (no tip cutting force short of that end,
Okamura et al. 2004), and a channel cut through a layer has no tip row on its line. Checked over the gap
(above and below the contact distance, 2 mm: the lower layer is within reach of the tip as it leaves the upper
one), the needle's direction (vertical, 30°) and the puncture rule, and on single cases the needle (a beam,
a thick one), the fast compliance, the exact solver and the entry point (a grid edge, a vertex). A needle
through both layers cuts both: each holds it at G_c per unit length of needle in it while it cuts, and each
has its own cut. The tip's rules do not depend on what holds the shaft: a needle pushed through the gap while
it cuts punctures the lower layer at f_p, or re-enters a hole there, as an inserting needle does; and a tip
backed out of the lower layer into the gap and moved sideways away from its hole punctures that layer again
at its new place.
"""

from __future__ import annotations

import math

import meshio
import numpy as np
import pytest

from refsim.constraints import TIP
from refsim.mesh.generators import box_mesh
from refsim.scene import load_scene
from refsim.simulation import Simulation
from refsim.simulation.detection import Detector
from tests.simulation.waypoints import times_at_speed, trajectory_overrides

TOP, UPPER_THICKNESS, LOWER_THICKNESS = 0.1, 0.008, 0.02
ENTRY = (0.00123, 0.00231)
NEEDLE_LENGTH = 0.32
SPEED = 0.02  # m/s along the needle
DIRECTIONS = {"0deg": (0.0, 0.0, -1.0), "30deg": (0.5, 0.0, -math.sqrt(3.0) / 2.0)}


def _layers_file(tmp_path, gap: float) -> str:
    upper = box_mesh(
        size=(0.1, 0.1, UPPER_THICKNESS), cells=(4, 4, 2), origin=(-0.05, -0.05, TOP - UPPER_THICKNESS)
    )
    lower_top = TOP - UPPER_THICKNESS - gap
    lower = box_mesh(
        size=(0.1, 0.1, LOWER_THICKNESS), cells=(4, 4, 4), origin=(-0.05, -0.05, lower_top - LOWER_THICKNESS)
    )
    points = np.vstack([upper.rest_positions, lower.rest_positions])
    tets = np.vstack([upper.tets, lower.tets + upper.rest_positions.shape[0]])
    path = tmp_path / f"layers_{gap:g}.vtu"
    meshio.write(path, meshio.Mesh(points, [("tetra", tets)]))
    return str(path)


def _scene_on_layers(tmp_path, name, gap, *overrides):
    """The built-in scene ``name`` on the two layers ``gap`` [m] apart (its mesh replaced by the file's)."""
    held = '["xmin", "xmax", "ymin", "ymax", "zmin"]'
    return load_scene(
        name, [f'mesh.file="{_layers_file(tmp_path, gap)}"', f"mesh.fixed_faces={held}", *overrides]
    )


def _run(tmp_path, gap, direction, *overrides, radius=0.0005, entry=ENTRY):
    """The two-layer scene and its step records for the needle's life of the module's docstring (a needle of
    ``radius`` [m])."""
    direction = np.asarray(DIRECTIONS[direction], dtype=float)
    cos = -direction[2]
    # depths of the tip below the top face along the needle [m]
    through = (UPPER_THICKNESS + gap + 0.005) / cos  # 5 mm into the lower layer
    in_gap = (UPPER_THICKNESS + 0.5 * gap) / cos
    short = through - 0.001 / cos
    depths = [-0.002, through, through, in_gap, short, -0.002, through]
    entry = np.array([entry[0], entry[1], TOP])
    bases = [entry + (d - NEEDLE_LENGTH) * direction for d in depths]
    times = times_at_speed(bases, SPEED)  # (the base moves along the needle: the tip's speed)
    scene = _scene_on_layers(
        tmp_path,
        "cube",
        gap,
        f"needle.radius={radius!r}",
        "time.dt=0.01",
        *trajectory_overrides(times, bases, direction, duration=times[-1]),
        *overrides,
    )
    records = []
    Simulation(scene).run(on_step=lambda state, record: records.append(record))
    return scene, records, times


# Pushed in again from the gap, the tip is in the lower layer's channel's mouth (it backed out of the face it
# entered by): located there with its channel's end, no event; from the air, each layer's hole is re-entered.
LIFE = ["puncture", "exit", "puncture", "withdrawal", "reentry", "exit", "reentry"]


# What else a user varies, on one case each: the needle (beam, thick), the compliance (fast mode), the
# solver, the entry point.
VARIANTS = {
    "rigid": (),
    "flexible": ("needle.rigid=false",),
    "fast": ('compliance.strategy="fast"',),
    "exact_solver": ('solver.method="exact"',),
    # the cube's needle, r = 8 mm: the upper layer's exit hole lies within its radius of the lower layer's
    # surface (3 mm below; the holes of another surface were once taken for that surface's)
    "thick": (),
    # entries on the 4 x 4 grid of both layers' top faces (lines every 25 mm): on a grid edge, at a vertex
    "edge": (),
    "vertex": (),
}
RADII = {"thick": 0.008}
ENTRIES = {"edge": (0.0, ENTRY[1]), "vertex": (0.0, 0.0)}
CASES = [
    *(
        (gap, direction, rule, "rigid")
        for gap in (0.003, 0.001)
        for direction in DIRECTIONS
        for rule in ("capped", "plain")
    ),
    (0.003, "0deg", "capped", "flexible"),
    (0.001, "30deg", "capped", "fast"),
    (0.001, "0deg", "plain", "exact_solver"),
    (0.003, "0deg", "capped", "thick"),
    (0.003, "30deg", "capped", "edge"),
    (0.001, "0deg", "plain", "vertex"),
]


@pytest.mark.parametrize(
    ("gap", "direction", "rule", "variant"),
    CASES,
    ids=[f"gap{g * 1e3:g}mm-{d}-{r}-{v}" for g, d, r, v in CASES],
)
def test_a_needle_through_two_layers_punctures_each_and_keeps_their_channels(
    tmp_path, gap, direction, rule, variant
):
    within = "true" if rule == "capped" else "false"
    scene, records, times = _run(
        tmp_path,
        gap,
        direction,
        f"insertion.puncture_within_step={within}",
        *VARIANTS[variant],
        radius=RADII.get(variant, 0.0005),
        entry=ENTRIES.get(variant, ENTRY),
    )
    named = [(r.step, e) for r in records for e in r.events if e.name in set(LIFE)]
    assert [e.name for _, e in named] == LIFE, " ".join(f"{s}:{e.name}" for s, e in named)
    f_p, f_cut = scene.insertion.puncture_force, scene.insertion.tip_cutting_force
    # Each layer is punctured at f_p by the tip's contact (the lower one too: before, its tip went through it
    # with no contact and no puncture).
    punctures = [e for _, e in named if e.name == "puncture"]
    for event in punctures:
        if rule == "capped":
            assert event.force == pytest.approx(f_p, rel=1e-6)
        else:
            assert event.force >= f_p * (1.0 - 1e-6)
    # Pushed in again along its channel in the lower layer, short of where it cut to: no tip cutting force.
    steps = [s for s, _ in named]
    again = [r for r in records if times[3] < r.time <= times[4]]
    assert again and all(r.step < steps[3] for r in again)
    assert max(float(r.row_forces[r.row_role == TIP].sum()) for r in again) < 0.05 * f_cut
    # Through both once more: no tip row on the upper layer's line (cut through), none short of the lower
    # channel's end.
    last = [r for r in records if steps[4] < r.step < steps[6]]
    assert last and not any(np.any(r.row_role == TIP) for r in last)


def test_a_tip_moved_back_out_of_a_far_face_meets_no_surface():
    # The detector's rule behind the cases above: a tip outside the tissue that moves back along the needle
    # meets no surface ahead (it goes back into its own channel), one that advances or stays does.
    class Geometry:
        def __init__(self, previous_tip, free_tip):
            self.needle_previous = type(
                "N", (), {"tip": np.array(previous_tip), "tip_tangent": np.array([0, 0, -1.0])}
            )
            self.needle_free = type("N", (), {"tip": np.array(free_tip)})

    assert Detector._advancing(Geometry([0, 0, 0.09], [0, 0, 0.0899]))
    assert Detector._advancing(Geometry([0, 0, 0.09], [0, 0, 0.09]))
    assert not Detector._advancing(Geometry([0, 0, 0.09], [0, 0, 0.0901]))


LOWER_DEPTH = 0.006  # how far the cutting needle goes into the lower layer, along the vertical [m]
STROKE = 0.008  # the cut's stroke, the needle's base moved normal to the needle (along y) [m]


def _cut_through_layers(tmp_path, gap, direction, *overrides):
    """cube_cut's life through the two layers ``gap`` [m] apart: the needle in through the upper layer and
    LOWER_DEPTH into the lower one, then its base moved STROKE along y (it cuts both), pulled back until its
    tip is in the gap, out of the tissue, and in again along its cut; 10 mm/s. The scene, its records, its
    final state and the step at the end of the stroke."""
    d = np.asarray(DIRECTIONS[direction], dtype=float)
    cos = -d[2]
    through = (UPPER_THICKNESS + gap + LOWER_DEPTH) / cos
    entry, side = np.array([ENTRY[0], ENTRY[1], TOP]), np.array([0.0, 1.0, 0.0])

    def base(depth, moved=0.0):
        return entry + (depth - NEEDLE_LENGTH) * d + moved * side

    bases = [
        base(-0.002),
        base(through),
        base(through, STROKE),
        base((UPPER_THICKNESS + 0.5 * gap) / cos, STROKE),
        base(-0.003, STROKE),
        base(through, STROKE),
    ]
    times = times_at_speed(bases, 0.01)
    waypoints = trajectory_overrides(times, bases, d, duration=times[-1] + 0.2)
    scene = _scene_on_layers(tmp_path, "cube_cut", gap, *waypoints, *overrides)
    records, states = [], []
    Simulation(scene).run(on_step=lambda state, record: (records.append(record), states.append(state)))
    return scene, records, states[-1], round(times[2] / scene.time.dt) - 1


CUT_CASES = [
    *((gap, direction, "fast") for gap in (0.001, 0.003, 0.01) for direction in DIRECTIONS),
    (0.003, "30deg", "flexible"),
    (0.003, "0deg", "exact"),
]
CUT_VARIANTS = {
    "fast": ('compliance.strategy="fast"',),
    "flexible": ('compliance.strategy="fast"', "needle.rigid=false"),
    "exact": (),
}


@pytest.mark.parametrize(
    ("gap", "direction", "variant"), CUT_CASES, ids=[f"gap{g * 1e3:g}mm-{d}-{v}" for g, d, v in CUT_CASES]
)
def test_a_needle_through_two_layers_cuts_each_at_g_c_per_unit_length(tmp_path, gap, direction, variant):
    # Reference: the energy law (docs/cutting.md). The front gives way at G_c per unit length of needle in the
    # tissue, so on a straight stroke the needle is held with G_c L_in, L_in its length in both layers,
    # (8 mm + 6 mm) / cos(tilt), the gap not counted. The stretches' ends are located to d_c/16 each (two
    # parts, four ends: L_in to d_c/4); the surfaces' indentation under the needle is a hundredth of that.
    # The cut in each layer is its own (no triangle joins the layers across the gap), and every step of the
    # life keeps the invariants of the random lives (refsim.verification.invariants).
    from refsim.verification.invariants import life_violations

    scene, records, final, stroke_end = _cut_through_layers(tmp_path, gap, direction, *CUT_VARIANTS[variant])
    names = [e.name for r in records for e in r.events]
    assert names.count("cut_start") == 1 and "withdrawal" in names
    fracture, spacing = scene.cutting.fracture_energy, scene.cutting.point_spacing
    inserted = (UPPER_THICKNESS + LOWER_DEPTH) / -DIRECTIONS[direction][2]
    force = float(np.linalg.norm(records[stroke_end].needle_force))
    assert force == pytest.approx(fracture * inserted, abs=fracture * spacing / 4)
    lower_top = TOP - UPPER_THICKNESS - gap
    heights = final.cut.rest_points[final.cut.triangles][..., 2]  # rest z of each triangle's corners
    upper = heights >= TOP - UPPER_THICKNESS - 1e-9
    assert np.all(upper.all(axis=1) | (heights <= lower_top + 1e-9).all(axis=1))
    assert upper.all(axis=1).any() and (~upper).all(axis=1).any()  # both layers are cut
    assert life_violations(records, scene) == []


# What a user varies for a needle pushed into another layer while it cuts: the gap (within the tip's contact
# distance of 2 mm as it leaves the upper layer, and beyond), the needle's direction, the puncture rule, the
# compliance and the needle.
def _push_case(gap, direction, variant, *marks):
    return pytest.param(gap, direction, variant, id=f"gap{gap * 1e3:g}mm-{direction}-{variant}", marks=marks)


PUSH_CASES = [
    _push_case(0.003, "0deg", "fast"),
    _push_case(0.001, "30deg", "fast"),
    _push_case(0.01, "0deg", "plain"),
    *(
        _push_case(gap, direction, variant, pytest.mark.slow)
        for gap, direction, variant in (
            (0.001, "0deg", "fast"),
            (0.01, "0deg", "fast"),
            (0.003, "30deg", "fast"),
            (0.01, "30deg", "fast"),
            (0.003, "0deg", "plain"),
            (0.003, "30deg", "plain"),
            (0.003, "0deg", "exact"),
            (0.003, "30deg", "flexible"),
        )
    ),
]
PUSH_VARIANTS = {
    **CUT_VARIANTS,
    "plain": ('compliance.strategy="fast"', "insertion.puncture_within_step=false"),
}


@pytest.mark.parametrize(("gap", "direction", "variant"), PUSH_CASES)
def test_a_needle_pushed_through_the_gap_while_it_cuts_punctures_and_cuts_the_lower_layer(
    tmp_path, gap, direction, variant
):
    # cube_cut's needle 6 mm into the upper layer, its base moved 3 mm along y (the cut starts there), pushed
    # on along the needle through the layer and the gap to 5 mm into the lower layer, then moved 5 mm more
    # along y. Reference: the tip's rules do not depend on what holds the shaft: out of the upper layer's far
    # face it meets the lower layer's surface as a contact it punctures at f_p (capped within the step: at
    # f_p; the plain rule: at f_p or above), as an inserting needle does (before, a cutting needle's tip went
    # into the lower layer with no contact and no puncture). Then the energy law, as above: the front holds
    # the needle with G_c L_in, L_in = (8 + 5 mm) / cos(tilt), each stretch's ends located to d_c/16. The
    # strip extends down the shaft into the lower layer as a part of its own (no triangle across the gap).
    from refsim.verification.invariants import life_violations

    d = np.asarray(DIRECTIONS[direction], dtype=float)
    cos = -d[2]
    entry, side = np.array([ENTRY[0], ENTRY[1], TOP]), np.array([0, 1.0, 0])
    lower = (UPPER_THICKNESS + gap + 0.005) / cos

    def base(depth, moved):
        return entry + (depth - NEEDLE_LENGTH) * d + moved * side

    bases = [base(-0.002, 0.0), base(0.006, 0.0), base(0.006, 0.003), base(lower, 0.003), base(lower, 0.008)]
    times = times_at_speed(bases, 0.01)
    scene = _scene_on_layers(
        tmp_path,
        "cube_cut",
        gap,
        *PUSH_VARIANTS[variant],
        *trajectory_overrides(times, bases, d, duration=times[-1] + 0.2),
    )
    records, states = [], []
    Simulation(scene).run(on_step=lambda state, record: (records.append(record), states.append(state)))
    named = [(r, e) for r in records for e in r.events if e.name != "tear"]
    assert [e.name for _, e in named] == ["puncture", "cut_start", "exit", "puncture"]
    f_p = scene.insertion.puncture_force
    exit_record, (punctured, puncture) = named[2][0], named[3]
    assert punctured.phase == "cutting" and records[-1].phase == "cutting"
    if variant == "plain":
        assert puncture.force >= f_p * (1.0 - 1e-6)
    else:
        assert puncture.force == pytest.approx(f_p, rel=1e-6)
    # In the gap the tip is out of the tissue: the lower layer is neither entered nor cut before its puncture.
    crossing = [
        state
        for record, state in zip(records, states, strict=True)
        if exit_record.step <= record.step < punctured.step
    ]
    assert crossing and all(state.instruments[0].tip_tet < 0 for state in crossing)
    assert all(len(state.instruments[0].cut_strip.part_ranges()) == 1 for state in crossing)
    fracture, spacing = scene.cutting.fracture_energy, scene.cutting.point_spacing
    # (At the stroke's end: a beam needle at rest after it unloads the front as it straightens.)
    force = float(np.linalg.norm(records[round(times[-1] / scene.time.dt) - 1].needle_force))
    inserted = (UPPER_THICKNESS + 0.005) / cos
    assert force == pytest.approx(fracture * inserted, abs=fracture * spacing / 4)
    final = states[-1]
    strip = final.instruments[0].cut_strip
    assert len(strip.part_ranges()) == 2
    heights = final.cut.rest_points[final.cut.triangles][..., 2]
    upper = heights >= TOP - UPPER_THICKNESS - 1e-9
    assert np.all(upper.all(axis=1) | (heights <= TOP - UPPER_THICKNESS - gap + 1e-9).all(axis=1))
    assert life_violations(records, scene) == []


def _vertical_cut_life(tmp_path, gap, waypoints, *overrides):
    """cube_cut on the two layers ``gap`` [m] apart, its vertical needle (r = 0.5 mm) driven at 10 mm/s
    through ``waypoints``, (point on the top face, depth of the tip below it [m]) each: the scene, its step
    records and the waypoints' times."""
    down = np.array([0.0, 0.0, -1.0])
    bases = [at + (depth - NEEDLE_LENGTH) * down for at, depth in waypoints]
    times = times_at_speed(bases, 0.01)
    scene = _scene_on_layers(
        tmp_path,
        "cube_cut",
        gap,
        "needle.radius=0.0005",
        *overrides,
        *trajectory_overrides(times, bases, down, duration=times[-1] + 0.1),
    )
    records = []
    Simulation(scene).run(on_step=lambda state, record: records.append(record))
    return scene, records, times


def test_a_cutting_needle_pushed_into_a_hole_of_the_lower_layer_re_enters_it(tmp_path):
    # A first needle's life through both layers at Q (puncture, exit, puncture, withdrawal: each layer keeps
    # its channel), then in at P, 3 mm from Q along y, 6 mm into the upper layer (a needle of r = 0.5 mm: P is
    # outside Q's holes), its base moved to above Q (it cuts the upper layer), pushed on through the gap to
    # 5 mm into the lower layer and moved 2 mm more along y. Reference: the tip's rules do not depend on what
    # holds the shaft: the tip meets the lower layer's hole at Q as a hole, and enters it with no puncture
    # (the event reentry), as an inserting needle does; then each layer holds the cutting needle at G_c per
    # unit length of needle in it, L_in = 8 + 5 mm.
    from refsim.verification.invariants import life_violations

    gap, side = 0.003, np.array([0.0, 1.0, 0.0])
    p = np.array([ENTRY[0], ENTRY[1], TOP])
    q = p + 0.003 * side
    lower = UPPER_THICKNESS + gap + 0.005
    waypoints = [(q, -0.002), (q, lower), (q, -0.002), (p, -0.002), (p, 0.006), (q, 0.006), (q, lower)]
    waypoints.append((q + 0.002 * side, lower))
    scene, records, times = _vertical_cut_life(tmp_path, gap, waypoints, 'compliance.strategy="fast"')
    names = [e.name for r in records for e in r.events if e.name not in ("tear", "retraction")]
    assert names == ["puncture", "exit", "puncture", "withdrawal", "puncture", "cut_start", "exit", "reentry"]
    fracture, spacing = scene.cutting.fracture_energy, scene.cutting.point_spacing
    force = float(np.linalg.norm(records[round(times[-1] / scene.time.dt) - 1].needle_force))
    assert force == pytest.approx(fracture * (UPPER_THICKNESS + 0.005), abs=fracture * spacing / 4)
    assert life_violations(records, scene) == []


def _moved_in_the_gap(tmp_path, gap, direction, side, scene_name, *overrides):
    """Through the upper layer and 5 mm into the lower one, pulled back until the tip is in the gap, the base
    moved ``side`` [m] along y, and pushed back to 5 mm into the lower layer (a needle of r = 0.5 mm); the
    scene, its records and the waypoints' times."""
    direction = np.asarray(DIRECTIONS[direction], dtype=float)
    cos = -direction[2]
    through = (UPPER_THICKNESS + gap + 0.005) / cos
    in_gap = (UPPER_THICKNESS + 0.5 * gap) / cos
    entry, lateral = np.array([ENTRY[0], ENTRY[1], TOP]), np.array([0.0, side, 0.0])
    waypoints = [(-0.002, 0.0), (through, 0.0), (in_gap, 0.0), (in_gap, 1.0), (through, 1.0)]
    bases = [entry + (d - NEEDLE_LENGTH) * direction + s * lateral for d, s in waypoints]
    times = times_at_speed(bases, SPEED)
    scene = _scene_on_layers(
        tmp_path,
        scene_name,
        gap,
        "needle.radius=0.0005",
        "time.dt=0.01",
        *trajectory_overrides(times, bases, direction, duration=times[-1] + 0.1),
        *overrides,
    )
    records = []
    Simulation(scene).run(on_step=lambda state, record: records.append(record))
    return scene, records, times


MOVED_CASES = [
    pytest.param(0.003, "0deg", 0.001, "cube", id="gap3mm-0deg-side1mm-inserting"),
    pytest.param(0.001, "30deg", 0.0015, "cube", id="gap1mm-30deg-side1.5mm-inserting"),
    pytest.param(0.003, "0deg", 0.003, "cube_cut", id="gap3mm-0deg-side3mm-cutting"),
    pytest.param(0.003, "30deg", 0.003, "cube", id="gap3mm-30deg-side3mm-inserting", marks=pytest.mark.slow),
    pytest.param(0.001, "0deg", 0.003, "cube_cut", id="gap1mm-0deg-side3mm-cutting", marks=pytest.mark.slow),
    pytest.param(
        0.003, "30deg", 0.003, "cube_cut", id="gap3mm-30deg-side3mm-cutting", marks=pytest.mark.slow
    ),
]


@pytest.mark.parametrize(("gap", "direction", "side", "scene_name"), MOVED_CASES)
def test_a_tip_moved_sideways_in_the_gap_punctures_the_lower_layer_at_its_new_place(
    tmp_path, gap, direction, side, scene_name
):
    # The tip backed out of the lower layer into the gap (the shaft in the upper layer: inserting, or cutting
    # it once the sideways move starts a cut), its base moved sideways by more than the needle's radius, and
    # pushed in again. Reference: the tip's rules for a tip outside the tissue do not depend on how it left:
    # backed out of a face it entered by, it is in its channel's mouth only while it meets that hole; moved
    # away from it, the surface ahead is intact tissue, which it punctures at f_p (the capped rule) as in
    # approach. (Before, it went into the lower layer with no contact and no puncture wherever it was.)
    from refsim.verification.invariants import life_violations

    scene, records, times = _moved_in_the_gap(tmp_path, gap, direction, side, scene_name)
    punctures = [(r.step, e) for r in records for e in r.events if e.name == "puncture"]
    pushed = round(times[3] / scene.time.dt)
    assert [step <= pushed for step, _ in punctures] == [True, True, False]
    assert punctures[-1][1].force == pytest.approx(scene.insertion.puncture_force, rel=1e-6)
    # punctured at its new place, more than the needle's radius (the hole's) from where it first punctured
    # the lower layer, and in that layer at the end
    at = {r.step: np.asarray(r.instruments[0].needle_positions[-1]) for r in records}
    first, again = at[punctures[1][0]], at[punctures[-1][0]]
    assert np.linalg.norm((again - first)[:2]) > scene.needle.radius
    assert at[records[-1].step][2] < TOP - UPPER_THICKNESS - gap
    assert not any(e.name in ("reentry", "withdrawal") for r in records for e in r.events)
    assert life_violations(records, scene) == []


@pytest.mark.parametrize("side", [0.0, 0.003], ids=["same-place", "side3mm"])
def test_a_cutting_needle_backed_out_of_the_lower_layer_meets_its_channel_or_intact_tissue(tmp_path, side):
    # In 6 mm, a 3 mm stroke along y (the cut starts), pushed on through the gap 5 mm into the lower layer
    # (it punctures it while cutting), pulled back until the tip is in the gap, moved ``side`` along y, pushed
    # back to 5 mm. Reference: the tip's rules do not depend on what holds the shaft. Backed out of the lower
    # layer, that layer keeps its channel (as in insertion): pushed in at the same place, the tip is in its
    # channel's mouth (no event); moved 3 mm first, it meets intact tissue and punctures it at f_p. (Before,
    # the cutting phase recorded no channel there: the tip punctured its own hole again.)
    from refsim.verification.invariants import life_violations

    gap, along = 0.003, np.array([0.0, 1.0, 0.0])
    p = np.array([ENTRY[0], ENTRY[1], TOP])
    q = p + 0.003 * along
    lower, in_gap = UPPER_THICKNESS + gap + 0.005, UPPER_THICKNESS + 0.5 * gap
    moved = q + side * along
    waypoints = [(p, -0.002), (p, 0.006), (q, 0.006), (q, lower), (q, in_gap)]
    waypoints += [(moved, in_gap), (moved, lower)]
    scene, records, times = _vertical_cut_life(tmp_path, gap, waypoints)
    named = [(r.step, e) for r in records for e in r.events if e.name not in ("tear", "retraction")]
    expected = ["puncture", "cut_start", "exit", "puncture"] + (["puncture"] if side else [])
    assert [e.name for _, e in named] == expected
    # the lower layer's first puncture comes before the back-out
    assert named[3][0] < round(times[4] / scene.time.dt)
    if side:
        assert named[-1][0] > round(times[5] / scene.time.dt)
        assert named[-1][1].force == pytest.approx(scene.insertion.puncture_force, rel=1e-6)
    assert life_violations(records, scene) == []


@pytest.mark.parametrize("out_by", [0.0001, 0.0002])
def test_a_tip_pulled_just_out_of_its_entry_face_and_pushed_in_again_is_in_its_channel(out_by):
    # The cube (4³ cells), 6 mm in, held, pulled back until its tip is out of the top face by less than the
    # ring's release margin (d_i / 2: the entry point is kept), and pushed back to 6 mm. Reference: the tip
    # is in the mouth of its own channel, not out of a far face: no surface to meet, no event, no new point,
    # and the force back to the held one (its channel's end is where it cut to: it cuts again at f_cut there).
    # (A tip out of any face once met the top face again as another layer: a re-entry and one more point.)
    direction, entry = np.array([0.0, 0.0, -1.0]), np.array([ENTRY[0], ENTRY[1], TOP])
    depths, times = [-0.002, 0.006, 0.006, -out_by, -out_by, 0.006], [0.0, 0.4, 0.5, 0.8, 0.9, 1.2]
    vector = lambda v: "[" + ", ".join(repr(float(c)) for c in v) + "]"  # noqa: E731
    bases = [entry + (d - NEEDLE_LENGTH) * direction for d in depths]
    scene = load_scene(
        "cube",
        [
            "mesh.cells=[4, 4, 4]",
            "time.dt=0.01",
            "time.duration=1.2",
            f"trajectory.times={vector(times)}",
            "trajectory.base_positions=[" + ", ".join(vector(b) for b in bases) + "]",
            "trajectory.directions=[" + ", ".join(vector(direction) for _ in bases) + "]",
        ],
    )
    records = []
    Simulation(scene).run(on_step=lambda state, record: records.append(record))
    named = [e.name for r in records for e in r.events if e.name != "retraction"]
    assert named == ["puncture"]
    held = next(r for r in records if abs(r.time - 0.5) < 1e-9)
    assert records[-1].insertion_point_count == held.insertion_point_count
    assert records[-1].needle_force[2] == pytest.approx(held.needle_force[2], rel=0.02)
