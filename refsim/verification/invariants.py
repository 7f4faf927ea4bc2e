"""The invariants every step of any needle life keeps, whatever the needle does (layer 6): what the random
lives of :mod:`refsim.verification.life_cycles` are checked against.

:func:`life_violations` checks what must hold at every step of any life, whatever the needle does:

- ``finite``: the tissue positions (when recorded), the needle's positions, its force and the rows' forces;
- ``rows``: the step ends with the rows of its end state (:func:`end_state_violations`);
- ``phase`` (records holding the tissue's positions at every step, which the scenes of
  :func:`refsim.verification.life_cycles.draw_life` ask for): a needle in insertion or cutting has some of its
  centreline in the tissue as deformed at the step, or lies within the insertion points' release margin of it
  (the ring's hysteresis, a share of d_i, by which a pulled-back tip outlives its last point; the model's
  needle is its centreline): refsim.simulation.events' table, a needle is withdrawn when no part of it is left
  in the tissue (:func:`phase_violation`). The faults this was written for: a needle tilted in its stroke's
  plane and pulled out after a stroke towards its tilt, never withdrawn (the entry point's projection on its
  axis above its tip), and one pulled out while moving sideways towards its tilt, kept in insertion with its
  tip 1.7 mm above the surface and 0.77 N on it. (The withdrawal's step is not checked here: its record is its
  second solve, in which a released bent needle may spring into the surface, and a tip pressed into a surface
  it has not punctured is no part of the needle in the tissue, while the approach's contact, one row
  linearised at the step's start, lets a needle buckled at a layer's edge, or an organ breathing onto a shaft,
  into the tissue by 0.2 to 9.5 mm in 17 of the 596 slow lives: docs/coupling.md, "The face the tip meets".
  tests/simulation/test_cracks.py and test_life_cycle.py check the withdrawals of those faults' lives.)
- ``force_without_rows``: no force on the needle in a step without rows;
- ``force_bound`` (a needle that cuts; one that does not is held by its shaft without a law's limit, by
  design): ‖F‖ ≤ 2 (f_p + G_c L_in) at every step, L_in the needle's length inside the tissue (the
  undeformed cube; an organ's mesh as deformed at the step). Not at a step whose load is on the approach's
  shaft contact (rows keeping the needle's side out of the surface before a puncture): no law limits those
  (docs/coupling.md, "Shaft contact before puncture"), a known limit the study reports on its own
  (:func:`shaft_contact_loads`). Reference: the laws bound what the tissue can hold the needle with — its
  tip's contact gives way at f_p, the front's and the cut faces' rows (and the cut start that replaces faces
  which hold) at G_c per unit inserted length, and the friction (μ = 0.1) adds a tenth of its normal load —
  so f_p + G_c L_in bounds the force the tissue holds the needle with, less the elastic transients of a turn
  and the tissue's damping (Rayleigh β = 0.01 s: a fifth of the lateral force at a stroke's start, scene
  notes). The factor 2 is room for those; the faults this invariant was written for held the needle at 3–15
  times the bound (the faces of a cut without a limit; a needle re-entering its hole off its axis, pulled
  back to the hole's old entry point), and 4–25 times (a needle less deep than d_i, held by its entry
  point's rows alone, which the cut start left out).

Used by ``tests/simulation/test_random_life_cycles.py``, the life-cycle tests and
``studies/lifecycle/run.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "Violation",
    "end_state_violations",
    "inserted_length",
    "inserted_lengths",
    "life_violations",
    "phase_violation",
    "shaft_contact_loads",
]

#: The force bound's factor over f_p + G_c L_in (module docstring).
BOUND_FACTOR = 2.0
#: A force [N] below which a step without rows counts as carrying none.
NO_ROW_FORCE = 1e-9
#: The ``phase`` invariant's sampling of the needle's centreline [m] (:func:`_length_inside`'s): a length in
#: the tissue at most this is none, a distance from it at most this is touching it.
PHASE_SAMPLING = 1e-4


@dataclass(frozen=True)
class Violation:
    """An invariant a step broke: its name, the step, its time [s], the phase, what was measured and the
    instrument (its name in a scene of several, else empty)."""

    invariant: str
    step: int
    time: float
    phase: str
    detail: str
    instrument: str = ""

    def __str__(self) -> str:
        where = f"{self.instrument}: " if self.instrument else ""
        return (
            f"{where}{self.invariant} at step {self.step} (t = {self.time:g} s, {self.phase}): {self.detail}"
        )


def _rows_of(record, instrument: int) -> np.ndarray | slice:
    """The rows of ``instrument`` (its index in the scene's order) in ``record``: a mask, or every row."""
    if record.row_instrument is None or len(record.instruments) == 1:
        return slice(None)
    return np.asarray(record.row_instrument) == instrument


def end_state_violations(records, instrument: int = 0) -> list[tuple[str, int]]:
    """The steps of a run that do not end with the rows of their end state for ``instrument`` (its index in
    the scene's order; the needle of a one-needle scene is 0): (check, step) pairs.

    An event crossed inside a step that changes what holds the needle (``STEP_SOLVED_AGAIN``) solves the step
    again with the rows after it, so no record holds rows its own end state has ended (docs/cutting.md, "When
    an event takes effect"). The checks: ``approach_rows`` (in the approach phase only the tip's contact
    rows), ``front_outside_cutting`` (no crack-front row outside the cutting phase, after leave_cut),
    ``removed_point_rows`` (no row of an insertion point the step removed: the rows' point indices below the
    points kept), ``tip_after_exit`` (no tip row from the step of an exit through a far face until the
    needle enters the tissue again) and ``reentry_without_rows`` (rows holding the needle from the step of a
    re-entry into a hole: insertion points' rows, or the cut's while the needle cuts). Each reads the
    instrument's own rows, phase and events."""
    from refsim.constraints import FRONT, NORMAL, SLIDING, TANGENT, TIP
    from refsim.simulation import Phase

    found = []
    exited = False
    for record in records:
        own = record.instruments[instrument]
        names = {event.name for event in own.events}
        exited = (exited and not names & {"puncture", "reentry", "withdrawal"}) or "exit" in names
        rows = _rows_of(record, instrument)
        roles, points = np.asarray(record.row_role)[rows], np.asarray(record.row_point)[rows]
        # (a needle that cuts is held by its cut's rows, in every part of the tissue it is through)
        held_by_cut = own.phase == Phase.CUTTING and bool(np.any(np.isin(roles, (SLIDING, FRONT))))
        checks = (
            ("approach_rows", own.phase == Phase.APPROACH and not np.isin(roles, (NORMAL, TANGENT)).all()),
            ("front_outside_cutting", own.phase != Phase.CUTTING and bool(np.any(roles == FRONT))),
            ("removed_point_rows", bool(np.any(points >= own.insertion_point_count))),
            ("tip_after_exit", exited and bool(np.any(roles == TIP))),
            ("reentry_without_rows", "reentry" in names and not np.any(points >= 0) and not held_by_cut),
        )
        found.extend((name, int(record.step)) for name, failed in checks if failed)
    return found


def inserted_length(needle_positions: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> float:
    """The needle's length inside the box [lower, upper] [m] (the undeformed tissue), its polyline
    ``needle_positions`` (k, 3) sampled every 0.1 mm or finer."""
    return _length_inside(
        needle_positions, lambda points: np.all((points > lower) & (points < upper), axis=1)
    )


def _length_inside(needle_positions: np.ndarray, inside) -> float:
    """The length of the polyline ``needle_positions`` (k, 3) [m] whose samples (every 0.1 mm or finer)
    ``inside`` (points (q, 3) → bool (q,)) says are in the tissue."""
    start, end = needle_positions[:-1], needle_positions[1:]
    lengths = np.linalg.norm(end - start, axis=1)
    count = max(int(np.ceil(lengths.max() / 1e-4)), 2) if lengths.size else 0
    if count == 0:
        return 0.0
    s = (np.arange(count) + 0.5) / count
    points = start[:, None, :] + s[None, :, None] * (end - start)[:, None, :]
    mask = np.asarray(inside(points.reshape(-1, 3))).reshape(len(start), count)
    return float((lengths * mask.mean(axis=1)).sum())


def phase_violation(
    phase: str,
    needle_positions: np.ndarray,
    locator,
    release_margin: float,
    *,
    withdrawn: bool = False,
) -> str | None:
    """What is wrong with a needle in ``phase`` whose centreline is the polyline ``needle_positions`` (k, 3)
    [m] in the tissue ``locator`` locates in (a `refsim.geometry.TetLocator` on the step's positions), or
    None (the ``phase`` invariant of :func:`life_violations`): in insertion or cutting, none of its centreline
    in the tissue and that centreline farther from it than ``release_margin`` [m] (the insertion points'
    release margin) plus :data:`PHASE_SAMPLING` (the model's needle is its centreline: its rows, stretches and
    withdrawal are the centreline's); at the step of its withdrawal (``withdrawn``), more than that sampling
    of its centreline in the tissue."""
    needle_positions = np.asarray(needle_positions, dtype=float)
    inside = _length_inside(needle_positions, lambda points: locator.locate(points)[0] >= 0)
    if phase == "approach":
        if withdrawn and inside > PHASE_SAMPLING:
            return f"withdrawn with {1e3 * inside:.2f} mm of the needle in the tissue"
        return None
    if inside > 0.0:
        return None
    distance = _distance_to(needle_positions, locator)
    if distance > release_margin + PHASE_SAMPLING:
        return f"in {phase} with no part of the needle in the tissue, {1e3 * distance:.2f} mm from it"
    return None


def _distance_to(needle_positions: np.ndarray, locator) -> float:
    """The distance [m] from the polyline ``needle_positions`` (k, 3), sampled every 0.1 mm or finer, to the
    tissue ``locator`` locates in."""
    start, end = needle_positions[:-1], needle_positions[1:]
    lengths = np.linalg.norm(end - start, axis=1)
    count = max(int(np.ceil(lengths.max() / PHASE_SAMPLING)), 2) if lengths.size else 0
    if count == 0:
        return float(locator.locate_nearest(needle_positions)[2].min())
    s = np.arange(count + 1) / count
    points = start[:, None, :] + s[None, :, None] * (end - start)[:, None, :]
    return float(locator.locate_nearest(points.reshape(-1, 3))[2].min())


def inserted_lengths(records, scene, instrument: int = 0) -> np.ndarray:
    """L_in of ``instrument`` at each record [m]: its needle's length inside the tissue, the undeformed box of
    a box mesh (the cube's), the deformed mesh of the step otherwise, the needle's radius around it (an organ
    that moves, whose thin parts the centreline may pass beside while the rows hold the needle: the records
    must hold the tissue's positions, ``output.tissue_every = 1``; NaN where they do not)."""
    if scene.mesh.generator == "box":
        lower = np.asarray(scene.mesh.origin, dtype=float)
        upper = lower + np.asarray(scene.mesh.size, dtype=float)
        return np.array(
            [
                inserted_length(np.asarray(r.instruments[instrument].needle_positions), lower, upper)
                for r in records
            ]
        )
    from refsim.geometry.search import TetLocator
    from refsim.scene.build import build_models

    tets = np.asarray(build_models(scene).mesh.tets)
    radius = float(scene.instrument_specs[instrument].needle.radius)
    lengths, locator = [], None
    for record in records:
        if record.tissue_positions is None:
            lengths.append(np.nan)
            continue
        locator = TetLocator(np.asarray(record.tissue_positions), tets, previous=locator)
        needle = np.asarray(record.instruments[instrument].needle_positions)
        lengths.append(
            _length_inside(needle, lambda points, found=locator: found.locate_nearest(points)[2] <= radius)
        )
    return np.asarray(lengths, dtype=float)


def shaft_contact_loads(records, instrument: int = 0) -> np.ndarray:
    """The load of ``instrument``'s shaft-contact rows at each record [N] (‖Σ n λ‖ over the rows of source
    ``shaft_contact``: the approach's rows that keep the needle's side out of the surface)."""
    from refsim.constraints import SHAFT_CONTACT

    loads = []
    for record in records:
        rows = _rows_of(record, instrument)
        source = np.asarray(record.row_source)[rows]
        chosen = source == SHAFT_CONTACT
        forces = np.asarray(record.row_forces)[rows][chosen]
        directions = np.asarray(record.row_directions)[rows][chosen]
        loads.append(float(np.linalg.norm(forces @ directions)) if chosen.any() else 0.0)
    return np.asarray(loads)


def life_violations(records, scene) -> list[Violation]:
    """The first violation of each invariant (module docstring) for each instrument over the ``records`` of
    a run of ``scene``, in the order found; empty when every step keeps them all. The force bound is checked
    for the instruments that cut (one that does not is held by its shaft with no law's limit, by design)."""
    fracture_energy = float(scene.cutting.fracture_energy)
    puncture = float(scene.insertion.puncture_force)
    specs = scene.instrument_specs
    first: dict[tuple[str, int], Violation] = {}
    inside = {index: inserted_lengths(records, scene, index) for index, spec in enumerate(specs) if spec.cuts}

    def note(name, index, record, detail):
        if (name, index) not in first:
            own = record.instruments[index]
            label = specs[index].name if len(specs) > 1 else ""
            first[(name, index)] = Violation(
                name, int(record.step), float(record.time), str(own.phase), detail, label
            )

    shaft = {index: shaft_contact_loads(records, index) for index in inside}
    for position, record in enumerate(records):
        row_forces = np.asarray(record.row_forces)
        tissue_bad = record.tissue_positions is not None and not np.all(np.isfinite(record.tissue_positions))
        for index, spec in enumerate(specs):
            own = record.instruments[index]
            arrays = [("needle_positions", own.needle_positions), ("needle_force", own.needle_force)]
            arrays.append(("row_forces", row_forces[_rows_of(record, index)]))
            bad = [name for name, values in arrays if not np.all(np.isfinite(np.asarray(values)))]
            bad += ["tissue_positions"] if tissue_bad else []
            if bad:
                note("finite", index, record, "not finite: " + ", ".join(bad))
                continue
            force = float(np.linalg.norm(own.needle_force))
            if row_forces[_rows_of(record, index)].size == 0 and force > NO_ROW_FORCE:
                note("force_without_rows", index, record, f"{force:.3g} N on the needle, no rows")
            if not spec.cuts:
                continue
            length = inside[index][position]
            if not np.isfinite(length) or shaft[index][position] > NO_ROW_FORCE:
                continue
            bound = BOUND_FACTOR * (puncture + fracture_energy * length)
            if force > bound:
                note(
                    "force_bound",
                    index,
                    record,
                    f"{force:.3f} N > {bound:.3f} N = {BOUND_FACTOR:g} (f_p + G_c L_in), "
                    f"L_in = {1e3 * length:.2f} mm",
                )
    by_step = {int(record.step): record for record in records}
    for index in range(len(specs)):
        for check, step in end_state_violations(records, index):
            note("rows", index, by_step[step], check)
    for record, index, detail in _phase_violations(records, scene):
        note("phase", index, record, detail)
    return list(first.values())


def _phase_violations(records, scene):
    """The ``phase`` invariant's violations (:func:`phase_violation`) of every instrument at every record
    holding the tissue's positions: (record, instrument, detail), in step order."""
    from refsim.geometry.search import TetLocator
    from refsim.scene.build import build_models

    if not any(record.tissue_positions is not None for record in records):
        return
    tets = np.asarray(build_models(scene).mesh.tets)
    margin = scene.insertion.coupling_model.retraction_margin(float(scene.insertion.spacing))
    locator = None
    for record in records:
        if record.tissue_positions is None:
            continue
        locator = TetLocator(np.asarray(record.tissue_positions), tets, previous=locator)
        for index, own in enumerate(record.instruments):
            detail = phase_violation(str(own.phase), own.needle_positions, locator, margin)
            if detail is not None:
                yield record, index, detail
