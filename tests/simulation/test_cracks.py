"""A needle back inside a cut it left cuts on from its crack tip (the tissue keeps the strip: ``Crack``).

cube_cut on 4³ cells (d_c = 0.5 mm, G_c = 200 J/m²): the needle is inserted 17 mm at x = 1.23 mm and cuts
8 mm along +x. Then it comes back into that cut, two ways:

- ``reinserted``: withdrawn, moved 4 mm back in the air and inserted 17 mm again along the cut;
- ``reinserted_deeper``: the same, inserted 25 mm: 8 mm below the cut;
- ``moved_back``: moved back 9 mm through its cut and 1 mm beyond the line it entered along (event leave_cut,
  then a second cut the other way, into intact tissue), then forward again;
- ``behind``: withdrawn and inserted 17 mm again 3 mm behind the line the cut entered along, in its plane: it
  cuts the 3 mm of intact tissue up to the old cut (a new strip), then runs into the old cut;

and in each it is pushed along +x to 4 mm beyond where its first stroke ended.

Reference: between the line the first stroke entered along and its crack tip the tissue is cut down to the
first stroke's depth L_0 = 17 mm, so a needle moving along the cut there cuts only what lies below L_0, at
G_c per unit length (Griffith: G_c (L − L_0), 1.6 N for L = 25 mm), and no more than the faces' friction,
μ_c times their normal load (Coulomb), when L ≤ L_0 (the faces' rows act along the deformed surface's
normals, whose tilt, a few degrees, adds at most a tenth of that load). Past the crack tip (where the first
stroke ended, less the front rows' compression: within 2 d_c) it cuts intact tissue at G_c L (3.4 N for
L = 17 mm), the rows standing for L − 3 d_c to L + d_c of needle as in ``test_life_cycle.py``. Before the
tissue kept the strip, the needle was gripped by insertion points in the cut tissue: its force grew 0.65 N
per mm along the cut until a new cut started there, which then cut the already cut tissue again at G_c L.
"""

from __future__ import annotations

import numpy as np
import pytest

from refsim.constraints import SLIDING
from refsim.geometry import TetLocator
from refsim.scene import load_scene
from refsim.simulation import Simulation
from tests.simulation.test_life_cycle import (
    ENTRIES,
    NEEDLE_LENGTH,
    _path_overrides,
    _vertical_run_on_cube_cut,
    assert_each_step_ends_with_the_rows_of_its_end_state,
)

X0, Y = 0.00123, 0.00231
STROKE_END = X0 + 0.008  # where the first stroke ends [m]
FINAL = X0 + 0.012  # where the needle is pushed to at last [m]
DOWN, UP = 0.403, 0.422  # base heights [m]: the tip 17 mm deep, and 2 mm above the top face
FIRST_DEPTH = 0.017  # L_0 [m]

# (time [s], base x [m], base z [m]) knots after the first stroke (insert 17 mm, cut 8 mm, hold 0.2 s)
FIRST = [(0.0, X0, UP), (1.9, X0, DOWN), (2.0, X0, DOWN), (2.8, STROKE_END, DOWN), (3.0, STROKE_END, DOWN)]
LIVES = {
    # withdrawn, re-inserted 4 mm behind where the stroke ended, pushed on along the cut
    "reinserted": [
        (4.0, STROKE_END, UP),
        (4.4, X0 + 0.004, UP),
        (5.4, X0 + 0.004, DOWN),
        (5.5, X0 + 0.004, DOWN),
        (6.3, FINAL, DOWN),
    ],
    # the same, 8 mm deeper than the cut
    "reinserted_deeper": [
        (4.0, STROKE_END, UP),
        (4.4, X0 + 0.004, UP),
        (5.4, X0 + 0.004, DOWN - 0.008),
        (5.5, X0 + 0.004, DOWN - 0.008),
        (6.3, FINAL, DOWN - 0.008),
    ],
    # withdrawn, re-inserted 3 mm behind the cut's entry line, then pushed along it into the cut
    "behind": [
        (4.0, STROKE_END, UP),
        (4.4, X0 - 0.003, UP),
        (5.4, X0 - 0.003, DOWN),
        (5.5, X0 - 0.003, DOWN),
        (6.3, FINAL, DOWN),
    ],
    # moved back through its cut and 1 mm beyond its entry line, then forward along it
    "moved_back": [(3.9, X0 - 0.001, DOWN), (4.1, X0 - 0.001, DOWN), (5.4, FINAL, DOWN)],
}
NEEDLES = {"rigid": (), "flexible": ("needle.rigid=false",)}
SOLVERS = {"gauss_seidel": (), "exact": ('solver.method="exact"',)}

CASES = [
    pytest.param(life, needle, solver, friction, marks=[pytest.mark.slow] if slow else [])
    for life in LIVES
    for needle in NEEDLES
    for solver in SOLVERS
    for friction in (0.0, 0.3)
    for slow in [(needle, solver, friction) != ("rigid", "gauss_seidel", 0.0) or life == "reinserted_deeper"]
]


def _run(knots, *overrides):
    """cube_cut on 4³ cells with the vertical needle's base through ``knots`` ((time [s], x [m], z [m]), at
    y = Y): the scene and each step's record."""
    tips = [(t, np.array([x, Y, z - NEEDLE_LENGTH])) for t, x, z in knots]
    records, _, scene = _vertical_run_on_cube_cut(tips, *overrides)
    return scene, records


@pytest.mark.parametrize(("life", "needle", "solver", "friction"), CASES)
def test_a_needle_back_in_its_cut_slides_to_the_crack_tip_and_cuts_on_from_there(
    life, needle, solver, friction
):
    scene, records = _run(
        FIRST + LIVES[life], *NEEDLES[needle], *SOLVERS[solver], f"cutting.friction_coefficient={friction}"
    )
    assert_each_step_ends_with_the_rows_of_its_end_state(records)
    named = lambda name: [r for r in records if any(e.name == name for e in r.events)]  # noqa: E731
    resumed = named("cut_resume")
    assert len(resumed) == 1, [(r.step, [e.name for e in r.events]) for r in records if r.events]
    # Back in its cut: no new cut starts there (the first stroke's, and moved back, the one beyond its entry
    # line are before it).
    assert all(r.step < resumed[0].step for r in named("cut_start"))
    assert records[-1].phase == "cutting"
    d_c, g_c = scene.cutting.point_spacing, scene.cutting.fracture_energy
    length = DOWN + FIRST_DEPTH - LIVES[life][-1][2]  # L [m]
    deeper = length - FIRST_DEPTH
    after = [r for r in records if r.time >= LIVES[life][-2][0]]  # the last push
    x = np.array([r.needle_positions[-1, 0] for r in after])
    along = np.array([r.needle_force[0] for r in after])
    # Behind the old cut (2 d_c from where the push starts, to d_c short of its entry line), intact tissue.
    before = (x > x[0] + 2 * d_c) & (x < X0 - d_c)
    assert np.all(-along[before] >= g_c * (length - 3 * d_c)), along[before].max()
    assert np.all(-along[before] <= g_c * (length + d_c)), along[before].min()
    # In the cut, from 2 d_c past its entry line (and from where the push starts: the rows below the cut take
    # up their load over that; the tissue ahead of a needle cutting into the cut moves with it until its crack
    # tip reaches the cut) to 2 d_c short of the crack tip: what lies below the cut, else the faces' friction
    # at most.
    inside = (x > max(X0, x[0]) + 2 * d_c) & (x < STROKE_END - 2 * d_c)
    assert np.count_nonzero(inside) >= 12
    for record, force in zip(np.array(after, dtype=object)[inside], along[inside], strict=True):
        faces = float(np.abs(record.row_forces[record.row_role == SLIDING]).sum())
        if deeper > 0.0:
            assert g_c * (deeper - 3 * d_c) <= -force <= g_c * (deeper + d_c) + friction * faces, record.step
        else:
            assert abs(force) <= (friction + 0.1) * faces + 1e-9, (record.step, force, faces)
    # The crack tip resists from where the first stroke left it.
    onset = x[np.flatnonzero((x > X0 + 2 * d_c) & (-along > g_c * (max(deeper, 0.0) + 0.5 * FIRST_DEPTH)))[0]]
    assert STROKE_END - 2 * d_c <= onset <= STROKE_END + d_c, onset
    # Beyond it, intact tissue cut at G_c per unit length.
    beyond = x > STROKE_END + 2 * d_c
    assert np.count_nonzero(beyond) >= 12
    assert np.all(-along[beyond] >= g_c * (length - 3 * d_c)), along[beyond].max()
    assert np.all(-along[beyond] <= g_c * (length + d_c)), along[beyond].min()


@pytest.mark.parametrize(
    ("needle", "solver"),
    [
        ("rigid", "gauss_seidel"),
        pytest.param("flexible", "gauss_seidel", marks=pytest.mark.slow),
        pytest.param("rigid", "exact", marks=pytest.mark.slow),
    ],
)
def test_a_needle_cutting_into_a_cut_from_beyond_its_crack_tip_slides_through_it(needle, solver):
    # Withdrawn after the first stroke, inserted 17 mm again 3 mm beyond where it ended (in intact tissue, in
    # the cut's plane) and pushed back along −x to 2 mm past the cut's entry line into intact tissue: it cuts
    # the 3 mm of intact tissue up to the old crack tip (a new strip, G_c L along +x), takes up the old cut
    # (cut_resume) and slides through it (the faces' friction at most, as above), leaves it behind its entry
    # line (leave_cut) and cuts the intact tissue there (a third strip, G_c L).
    knots = FIRST + [
        (4.0, STROKE_END, UP),
        (4.2, STROKE_END + 0.003, UP),
        (5.2, STROKE_END + 0.003, DOWN),
        (5.4, STROKE_END + 0.003, DOWN),
        (7.0, X0 - 0.002, DOWN),
    ]
    scene, records = _run(knots, *NEEDLES[needle], *SOLVERS[solver])
    assert_each_step_ends_with_the_rows_of_its_end_state(records)
    names = [e.name for r in records if r.time > 5.2 for e in r.events if e.name not in ("tear",)]
    assert names == ["cut_start", "cut_resume", "leave_cut", "cut_start"], names
    d_c, g_c, length = scene.cutting.point_spacing, scene.cutting.fracture_energy, FIRST_DEPTH
    push = [r for r in records if r.time >= 5.4]
    x = np.array([r.needle_positions[-1, 0] for r in push])
    along = np.array([r.needle_force[0] for r in push])
    intact = (x < x[0] - 2 * d_c) & (x > STROKE_END + d_c) | (x < X0 - 3 * d_c)
    assert np.count_nonzero(intact) >= 12
    assert np.all(along[intact] >= g_c * (length - 3 * d_c)), along[intact].min()
    assert np.all(along[intact] <= g_c * (length + d_c)), along[intact].max()
    inside = (x > X0 + 2 * d_c) & (x < STROKE_END - 2 * d_c)
    assert np.count_nonzero(inside) >= 12
    for record, force in zip(np.array(push, dtype=object)[inside], along[inside], strict=True):
        faces = float(np.abs(record.row_forces[record.row_role == SLIDING]).sum())
        assert abs(force) <= 0.1 * faces + 1e-9, (record.step, force, faces)


TILTED = {
    "0deg": (0.0, 0.0, -1.0),
    "30deg_yz": (0.0, 0.5, -0.8660254037844386),
    # tilted in the stroke's plane, the tip ahead of the base along the stroke, or behind it
    "30deg_xz_ahead": (0.5, 0.0, -0.8660254037844386),
    "30deg_xz_behind": (-0.5, 0.0, -0.8660254037844386),
}
ENTRY_VARIANTS = [
    pytest.param(
        entry,
        direction,
        marks=[]
        if (entry, direction) in {("vertex", "30deg_yz"), ("face", "30deg_xz_behind")}
        else pytest.mark.slow,
    )
    for entry in ENTRIES
    for direction in TILTED
]


def _in_the_tissue(simulation, record) -> bool:
    """Whether any point of the record's needle (its centreline every 0.1 mm) lies in the record's tissue."""
    nodes = record.needle_positions
    steps = np.linspace(0.0, 1.0, 200)[:, None]
    points = np.concatenate([a + steps * (b - a) for a, b in zip(nodes[:-1], nodes[1:], strict=True)])
    found, _ = TetLocator(record.tissue_positions, simulation.tets).locate(points)
    return bool(np.any(found >= 0))


@pytest.mark.parametrize(("entry", "direction"), ENTRY_VARIANTS)
def test_a_needle_reinserted_along_its_cut_slides_in_it_whatever_its_entry_and_tilt(entry, direction):
    # The ``reinserted`` life with the needle entering inside a surface triangle, on a grid edge or at a grid
    # vertex of the 4³ mesh, vertical or tilted 30° (in the yz plane, normal to the stroke; in the xz plane,
    # the stroke's, the tip ahead of the base or behind it): inserted 17 mm along the needle, cut 8 mm along
    # +x, pulled out along the needle, re-inserted along the same direction 4 mm behind where the stroke
    # ended and pushed to 4 mm beyond it. References:
    # - the withdrawal is the step at which no point of the needle lies in the tissue any more (the tip out
    #   of the surface): tilted in the stroke's plane, the point where the needle entered is no longer on its
    #   axis, so a needle that tells its withdrawal by it was withdrawn with its tip 4 mm deep, or never;
    # - in the cut, the faces' friction at most (μ_c = 0: their normals' tilt);
    # - past the crack tip, intact tissue cut at G_c per unit area: the needle sweeps L |t × x̂| of crack
    #   front per unit stroke (L = 17 mm along the needle, t its direction): G_c L, or G_c L cos 30° in the
    #   xz plane.
    x, y = ENTRIES[entry]
    knots = [
        (0.0, (x, y), -0.002),
        (1.9, (x, y), FIRST_DEPTH),
        (2.0, (x, y), FIRST_DEPTH),
        (2.8, (x + 0.008, y), FIRST_DEPTH),
        (3.0, (x + 0.008, y), FIRST_DEPTH),
        (4.0, (x + 0.008, y), -0.002),
        (4.4, (x + 0.004, y), -0.002),
        (5.4, (x + 0.004, y), FIRST_DEPTH),
        (5.5, (x + 0.004, y), FIRST_DEPTH),
        (6.3, (x + 0.012, y), FIRST_DEPTH),
    ]
    scene = load_scene(
        "cube_cut",
        ["mesh.cells=[4, 4, 4]", "output.tissue_every=1", *_path_overrides(knots, TILTED[direction])],
    )
    simulation = Simulation(scene)
    records = []
    simulation.run(on_step=lambda state, record: records.append(record))
    assert_each_step_ends_with_the_rows_of_its_end_state(records)
    names = [e.name for r in records for e in r.events if e.name in ("cut_start", "withdrawal", "cut_resume")]
    assert names == ["cut_start", "withdrawal", "cut_resume"], names
    out = next(i for i, r in enumerate(records) if any(e.name == "withdrawal" for e in r.events))
    assert _in_the_tissue(simulation, records[out - 1]) and not _in_the_tissue(simulation, records[out]), (
        records[out].time
    )
    d_c, g_c = scene.cutting.point_spacing, scene.cutting.fracture_energy
    axis = np.asarray(TILTED[direction]) / np.linalg.norm(TILTED[direction])
    front = FIRST_DEPTH * float(np.linalg.norm(np.cross(axis, [1.0, 0.0, 0.0])))  # L |t × x̂|
    push = [r for r in records if r.time >= 5.5]
    # the needle's line from the entry along x: the tip's x less its offset from the entry at 17 mm
    crossing = np.array([r.needle_positions[-1, 0] for r in push]) - x - FIRST_DEPTH * axis[0]
    along = np.array([r.needle_force[0] for r in push])
    inside = (crossing > 0.004 + 2 * d_c) & (crossing < 0.008 - 2 * d_c)
    assert np.count_nonzero(inside) >= 12
    for record, force in zip(np.array(push, dtype=object)[inside], along[inside], strict=True):
        faces = float(np.abs(record.row_forces[record.row_role == SLIDING]).sum())
        assert abs(force) <= 0.1 * faces + 1e-9, (record.step, force, faces)
    beyond = crossing > 0.008 + 2 * d_c
    assert np.count_nonzero(beyond) >= 12
    assert np.all(-along[beyond] >= g_c * (front - 3 * d_c)), along[beyond].max()
    assert np.all(-along[beyond] <= g_c * (front + d_c)), along[beyond].min()
