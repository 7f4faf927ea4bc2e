"""The cutting laws (refsim/cutting/laws.py) on hand-made loads: each law's cut-start criterion at and
either side of its threshold, where its crack front gives way, what it keeps at the cut start; the scene's
choice of a law and its keys; and that no code outside the law classes compares a law's name."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from refsim.cutting.laws import (
    CUTTING_LAWS,
    LIMIT_TOLERANCE,
    EnergyLaw,
    FrontPush,
    PaperLaw,
    law_of_key,
)
from refsim.scene import load_scene
from refsim.scene.fields import FieldError
from refsim.scene.spec import CuttingSpec

# A load just off the threshold, relative: far above round-off (1e-16) and far below any physical change.
OFF = 1e-9
DIRECTION = np.array([0.0, -1.0, 0.0])  # unit, exactly: ‖t‖ is the magnitude put along it


# ----------------------------------------------------------------------------------------- cut start


@pytest.mark.parametrize("g_c", [45.0, 200.0])
def test_energy_law_starts_at_gc_per_inserted_length(g_c):
    # Energy law: the cut starts when ‖t‖ ≥ G_c L_in (Griffith: the shaft's lateral load per unit inserted
    # length reaches the fracture energy per unit area).
    law, inserted = EnergyLaw(fracture_energy=g_c), 0.037
    threshold = g_c * inserted
    below = law.cut_start(DIRECTION * threshold * (1 - OFF), inserted_length=inserted, point_count=9)
    at = law.cut_start(DIRECTION * threshold, inserted_length=inserted, point_count=9)
    above = law.cut_start(DIRECTION * threshold * (1 + OFF), inserted_length=inserted, point_count=9)
    assert below is None
    assert at is not None and above is not None
    assert at.unit == "N/m" and at.extent == 0.0
    assert at.trigger == pytest.approx(g_c, rel=1e-14)  # ‖t‖ / L_in
    # The number of insertion points plays no part in it.
    assert law.cut_start(DIRECTION * threshold, inserted_length=inserted, point_count=1) is not None


def test_energy_law_needs_an_inserted_length():
    law = EnergyLaw()
    assert law.cut_start(DIRECTION * 1e3, inserted_length=0.0, point_count=5) is None
    assert law.cut_start(DIRECTION * 1e3, inserted_length=-1e-3, point_count=5) is None


@pytest.mark.parametrize(("f_c", "points"), [(1.0, 12), (0.25, 3)])
def test_paper_law_starts_above_equation_3(f_c, points):
    # Paper's equation 3: the cut starts when ‖t‖ > n_i f_c (strictly) over the n_i insertion points.
    law = PaperLaw(cutting_force=f_c, extent=2e-3)
    threshold = points * f_c
    assert law.cut_start(DIRECTION * threshold * (1 - OFF), inserted_length=0.01, point_count=points) is None
    assert law.cut_start(DIRECTION * threshold, inserted_length=0.01, point_count=points) is None
    above = law.cut_start(DIRECTION * threshold * (1 + OFF), inserted_length=0.01, point_count=points)
    assert above is not None and above.unit == "N" and above.extent == 2e-3
    assert above.trigger == pytest.approx(f_c * (1 + OFF), rel=1e-14)  # ‖t‖ / n_i
    # No insertion point: no criterion (whatever the load).
    assert law.cut_start(DIRECTION * 1e3, inserted_length=0.01, point_count=0) is None


def test_what_each_law_keeps_at_the_cut_start():
    assert EnergyLaw().kept_at_cut_start(7).tolist() == [0, 6]  # entry and deepest point, both without rows
    assert EnergyLaw().kept_at_cut_start(1).tolist() == [0]
    assert PaperLaw().kept_at_cut_start(7).tolist() == [0]  # the entry point
    assert not EnergyLaw.rows_while_cutting and PaperLaw.rows_while_cutting
    assert EnergyLaw.excludes_entry_point and not PaperLaw.excludes_entry_point
    assert EnergyLaw(fracture_energy=80.0).front_strength == 80.0 and np.isinf(PaperLaw().front_strength)


# ------------------------------------------------------------------------------------ the crack front


# The hand-made front: the cut runs along +x (ĉ); each front row's direction is −ĉ (back into the cut); every
# needle point is at the origin at the end of the step (see _push for where it and the crack tip started).
C_HAT = np.array([1.0, 0.0, 0.0])


@dataclass
class _Front:
    """Front rows on hand-made gaps (duck-typed `FrontRows`): front rows, their segments, sliding rows at the
    front and theirs, with the gaps at the start and at the end of the step."""

    rows: np.ndarray
    segment: np.ndarray
    gap_values: np.ndarray
    previous_gaps: np.ndarray
    band_rows: np.ndarray
    band_segment: np.ndarray
    band_gap_values: np.ndarray
    band_previous_gaps: np.ndarray

    @property
    def directions(self):
        return np.tile(-C_HAT, (self.rows.size, 1))

    @property
    def arc_lengths(self):
        return np.zeros(self.rows.size)

    @property
    def band_directions(self):
        return np.tile([0.0, 1.0, 0.0], (self.band_rows.size, 1))

    @property
    def band_arc_lengths(self):
        return np.zeros(self.band_rows.size)

    def gaps(self, crack_tips, needle):
        return self.gap_values

    def band_gaps(self, positions, needle):
        return self.band_gap_values


class _Needle:
    """A needle whose every point is at the origin at the end of the step."""

    @staticmethod
    def points(arcs):
        return np.zeros((np.size(arcs), 3))


class _Strip:
    class front:  # noqa: N801 - the strip's crack front, as CutStrip names it
        @staticmethod
        def positions(positions, tets):
            return np.zeros((3, 3))


@dataclass
class _Growth:
    tets: np.ndarray
    point_spacing: float = 1e-3


def _push(
    forces,
    limits,
    gaps,
    band_forces=(),
    band_limits=(),
    *,
    pushed=1.0,
    carried=0.0,
    compliance=None,
    band_gaps=None,
    band_pushed=0.0,
):
    """A front after a step: front rows with ``forces``, ``limits`` and end gaps ``gaps`` [m], whose needle
    point moved ``pushed`` [m] into the front (along ĉ) over the step while the tissue carried the crack tip
    ``carried`` [m] along ĉ (so δ fell by pushed − carried); sliding rows at the front along +y with
    ``band_forces``, ``band_limits``, end gaps ``band_gaps``, the needle moved ``band_pushed`` along +y
    relative to the tissue. ``compliance``: the rows' C [m/N] (None: none)."""
    forces, band_forces = np.asarray(forces, float), np.asarray(band_forces, float)
    f, b = forces.size, band_forces.size
    gaps = np.asarray(gaps, float)
    band_gaps = np.zeros(b) if band_gaps is None else np.asarray(band_gaps, float)
    front = _Front(
        np.arange(f),
        np.arange(f),
        gaps,
        gaps + (pushed - carried),
        np.arange(f, f + b),
        np.arange(b),
        band_gaps,
        band_gaps - band_pushed,
    )
    return FrontPush(
        growth=_Growth(np.zeros((1, 4), dtype=np.int64)),
        cut=None,
        strip=_Strip(),
        direction=C_HAT,
        positions=np.zeros((4, 3)),
        step=0,
        needle=_Needle(),
        front=front,
        multipliers=np.concatenate([forces, band_forces]),
        force_limit=np.concatenate([np.asarray(limits, float), np.asarray(band_limits, float)]),
        compliance=np.zeros(0) if compliance is None else np.full(f + b, float(compliance)),
    )


def test_energy_front_gives_way_at_its_strength_with_the_needle_past_the_crack_tip():
    # A front row of segment length ℓ_k carries at most G_c ℓ_k; it gave way where λ ≥ (1 − tol) G_c ℓ_k
    # (tol = LIMIT_TOLERANCE: the solve's accuracy) and the needle is past the crack tip (gap < 0); its
    # overshoot is −gap (the needle moved farther than that into the front over the step).
    limit = 200.0 * 0.5e-3
    forces = [limit, limit * (1 - LIMIT_TOLERANCE), limit * (1 - 10 * LIMIT_TOLERANCE), limit]
    gaps = [-2e-4, -3e-4, -4e-4, 1e-5]
    over, slip = EnergyLaw().given_way(_push(forces, [limit] * 4, gaps))
    assert over.tolist() == [2e-4, 3e-4, 0.0, 0.0]
    assert slip.size == 0


def test_a_front_left_at_its_strength_is_not_cut_without_motion():
    # The front at its strength with the needle a hair through the crack tip (the load a stroke left: the
    # row at G_c ℓ_k, δ below its compression by round-off or by the crack-tip polyline's kinks a needle
    # moving along its own axis slides along), but the needle did not move into the front relative to the
    # tissue: nothing is cut, however many steps.
    limit = 0.1
    push = _push([limit, limit], [limit, limit], [-2e-6, -3e-9], pushed=0.0)
    over, _ = EnergyLaw().given_way(push)
    assert over.tolist() == [0.0, 0.0]
    assert EnergyLaw().grow(push) is None


def test_the_cut_is_the_needles_motion_relative_to_the_tissue():
    # Galilean: the tissue carrying the crack tip onto a needle that stood still (carried < 0) is the needle
    # moving into the front, as much as the needle moving by that much into a tissue that stood still; a
    # needle and a crack tip moving together (a breathing organ carrying both) cut nothing.
    limit = 0.1
    law = EnergyLaw()
    onto = law.given_way(_push([limit], [limit], [-8e-6], pushed=0.0, carried=-5e-6))[0]
    into = law.given_way(_push([limit], [limit], [-8e-6], pushed=5e-6, carried=0.0))[0]
    together = law.given_way(_push([limit], [limit], [-8e-6], pushed=5e-6, carried=5e-6))[0]
    assert onto.tolist() == into.tolist() == [5e-6]
    assert together.tolist() == [0.0]


@pytest.mark.parametrize(
    ("pushed", "carried", "cut"), [(1e-4, 0.0, 1e-4), (1e-4, 3e-5, 7e-5), (1e-3, 0.0, 4e-4)]
)
def test_the_front_is_cut_by_the_needles_motion_into_it_less_what_the_tissue_carried(pushed, carried, cut):
    # The needle moved ``pushed`` along ĉ; the tissue carried the crack tip ``carried`` ahead of it: the cut
    # is pushed − carried, at most how far the needle is through the crack tip (−gap = 4e-4 m).
    limit = 0.1
    over, _ = EnergyLaw().given_way(_push([limit], [limit], [-4e-4], pushed=pushed, carried=carried))
    assert over[0] == pytest.approx(cut, rel=1e-12)


def test_a_compliant_front_row_cuts_only_beyond_its_compression():
    # A compliant row (C) at its limit holds the needle at δ = −C λ (the annulus the mesh does not resolve,
    # compressed): that is no cut; the needle through the crack tip beyond it cuts the difference.
    limit, compliance = 0.1, 2e-5
    held = -compliance * limit
    assert EnergyLaw().given_way(_push([limit], [limit], [held], compliance=compliance))[0].tolist() == [0.0]
    over, _ = EnergyLaw().given_way(_push([limit], [limit], [held - 3e-6], compliance=compliance))
    assert over[0] == pytest.approx(3e-6, rel=1e-9)


def test_energy_front_gives_way_sideways_where_a_sliding_row_at_the_front_reaches_its_limit():
    # A sliding row at the front at its limit, the needle gone on out of the plane the way the row pushes
    # against (λ < 0 pushes the needle along −y; it went +y): its slip is how far it went, at most |r|.
    limit = 0.1
    push = _push(
        [0.0],
        [limit],
        [1e-4],
        band_forces=[-limit, 0.5 * limit, -limit],
        band_limits=[limit] * 3,
        band_gaps=[2e-5, 3e-5, 2e-5],
        band_pushed=5e-5,
    )
    over, slip = EnergyLaw().given_way(push)
    assert over.tolist() == [0.0] and slip.tolist() == [2e-5, 0.0, 2e-5]
    # The same with the needle still: no slip.
    still = _push([0.0], [limit], [1e-4], band_forces=[-limit], band_limits=[limit], band_gaps=[2e-5])
    assert EnergyLaw().given_way(still)[1].tolist() == [0.0]


def test_energy_front_that_holds_does_not_grow():
    limit = 0.1
    assert EnergyLaw().grow(_push([0.5 * limit], [limit], [-1e-4])) is None  # below its strength
    assert EnergyLaw().grow(_push([limit], [limit], [1e-4])) is None  # at it, the needle behind the crack tip
    assert EnergyLaw().grow(_push([], [], [])) is None  # no front row


def test_paper_front_tears_at_ft():
    # Paper law: a tear when the strongest front row's force reaches f_t; below it the front holds.
    law = PaperLaw(tearing_force=1.0)
    assert law.grow(_push([0.2, 1.0 * (1 - OFF)], [np.inf] * 2, [0.0, 0.0])) is None
    assert law.grow(_push([], [], [])) is None


# ------------------------------------------------------------------------------ the scene's choice


def test_the_scene_builds_the_chosen_law_with_its_keys_and_defaults():
    energy = CuttingSpec(enabled=True, point_spacing=1e-3, fracture_energy=80.0)
    assert energy.cutting_law == EnergyLaw(fracture_energy=80.0)
    assert energy.cutting_force is None and energy.tearing_force is None and energy.extent is None
    paper = CuttingSpec(enabled=True, law="paper", point_spacing=1e-3, tearing_force=2.0)
    assert paper.cutting_law == PaperLaw(cutting_force=1.0, tearing_force=2.0, extent=1e-3)
    assert paper.fracture_energy is None and paper.cutting_force == PaperLaw().cutting_force
    assert CuttingSpec(enabled=True, point_spacing=1e-3).fracture_energy == EnergyLaw().fracture_energy


@pytest.mark.parametrize(
    ("law", "key", "value", "owner"),
    [
        ("energy", "cutting_force", 1.0, "paper"),
        ("energy", "tearing_force", 1.0, "paper"),
        ("energy", "extent", 1e-3, "paper"),
        ("paper", "fracture_energy", 200.0, "energy"),
    ],
)
def test_a_key_of_the_law_not_chosen_is_an_error_naming_it(law, key, value, owner):
    with pytest.raises(FieldError) as raised:
        CuttingSpec(enabled=True, point_spacing=1e-3, law=law, **{key: value})
    message = str(raised.value)
    assert raised.value.key == key and "law" in raised.value.related
    assert key in message and f"{owner!r} cutting law" in message and f"law = {law!r}" in message
    assert law_of_key(key) == owner


def test_every_law_key_is_a_scene_key_of_one_law_only():
    keys = [key for law in CUTTING_LAWS.values() for key in law.keys]
    assert len(keys) == len(set(keys))
    fields = set(CuttingSpec.__dataclass_fields__)
    assert set(keys) <= fields
    assert law_of_key("point_spacing") is None and law_of_key("friction_coefficient") is None


@pytest.mark.parametrize("name", ["cube", "cube_cut", "liver_rigid", "liver_flexible"])
def test_builtin_scenes_load_under_either_law_where_they_set_no_law_key(name):
    scene = load_scene(name)
    assert scene.cutting.cutting_law.name == scene.cutting.law
    if scene.cutting.fracture_energy == EnergyLaw().fracture_energy:  # G_c left at its default
        assert load_scene(name, ['cutting.law="paper"']).cutting.cutting_law == PaperLaw()


def test_no_code_outside_the_laws_compares_a_law_name():
    # The law is chosen once (CuttingSpec.cutting_law); detection and events ask the law object.
    root = Path(__file__).resolve().parents[2] / "refsim"
    comparison = re.compile(r"""law\s*(==|!=|\bin\b)\s*\(?["']|["'](energy|paper)["']\s*(==|!=)""")
    found = [
        f"{path.relative_to(root)}:{number}: {line.strip()}"
        for path in sorted(root.rglob("*.py"))
        if path.name != "laws.py"
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1)
        if comparison.search(line)
    ]
    assert not found, found


@pytest.mark.parametrize("law", [EnergyLaw(fracture_energy=200.0), PaperLaw(cutting_force=1.0)], ids=str)
def test_cut_start_load_is_what_cut_start_compares(law):
    # The event margin reads the law's cut-start load (refsim.simulation.margins): its value crosses its
    # threshold exactly where cut_start starts the cut (energy law: ‖t‖ ≥ G_c L_in at 200 N/m over 20 mm,
    # 4 N; paper law: ‖t‖ > n_i f_c over 5 points, 5 N), and the value is the load cut_start reports.
    length, points = 0.02, 5
    critical = 200.0 * length if isinstance(law, EnergyLaw) else 1.0 * points
    for scale in (0.5, 0.999, 1.001, 2.0):
        force = np.array([0.0, scale * critical, 0.0])
        load = law.cut_start_load(force, inserted_length=length, point_count=points)
        value, threshold, divisor, unit = load
        start = law.cut_start(force, inserted_length=length, point_count=points)
        assert (start is not None) == (value >= threshold) and unit == law.cut_start_unit
        assert value * divisor == pytest.approx(np.linalg.norm(force))
        if start is not None:
            assert start.trigger == pytest.approx(value)


def test_front_load_is_the_strongest_row_against_its_threshold():
    # Paper law: the strongest front row's force against f_t (grow tears when it reaches f_t); energy law:
    # the strongest force over its strength G_c ℓ_k against 1 (a row gives way at its strength).
    forces, limits = np.array([0.2, 0.9, 0.5]), np.array([1.0, 1.0, 0.4])
    assert PaperLaw(tearing_force=0.8).front_load(forces, limits) == (0.9, 0.8, 1.0, "N")
    value, threshold, divisor, unit = EnergyLaw().front_load(forces, limits)
    assert (value, threshold, divisor, unit) == (1.25, 1.0, 0.4, "1")
    assert PaperLaw().front_load(np.zeros(0), np.zeros(0)) is None
