"""Quantities of interest read from a results file (refsim.io.read_results), by name.

A name is ``quantity`` or ``quantity@argument``:

- name: ``needle_force@EVENT``; meaning: ‖force of the tissue on the needle‖ at the first step of event EVENT
  (puncture, cut_start, tear, ...), at ``end`` (the last step) or at ``t=SECONDS`` (the nearest step), as the
  force profile reads it (``Results.profile_force``: at a puncture through the capped tip contact, the force
  at its give-way within the step, not the step's end); unit: N
- name: ``axial_force@EVENT``, ``lateral_force@EVENT``; meaning: its component along the base segment (minus
  sign: resisting insertion is positive) and the norm of the rest, of the same force; unit: N
- name: ``puncture_force``; meaning: the force that triggered the puncture event; unit: N
- name: ``time@EVENT``; meaning: time at the end of the step of the first EVENT (a multiple of the time step);
  unit: s
- name: ``cut_area``; meaning: area of the cut surface at the end, summed over its triangles in rest
  coordinates; unit: m²
- name: ``lateral_stroke@EVENT``; meaning: distance the needle base moved across the needle's initial axis, at
  EVENT (default ``cut_start``); unit: m
- name: ``displacement@X,Y,Z``; meaning: ‖tissue displacement‖ at the rest point (X, Y, Z) [m] at the last
  recorded tissue state (P1 interpolation in its tet); unit: m
- name: ``displacement_z@X,Y,Z``; meaning: its z component (likewise ``_x``, ``_y``); unit: m

A quantity that does not exist in a run (no cut, the event never happened) is NaN. Add a quantity by adding
one function to :data:`QUANTITIES`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

__all__ = ["QUANTITIES", "UNITS", "check_quantity", "force_history_error", "quantity", "quantities"]


def _event_index(results, event: str) -> int | None:
    if event in ("end", "last"):
        return results.step_count - 1 if results.step_count else None
    if event.startswith("t="):  # the step nearest a time [s]
        try:
            time = float(event[2:])
        except ValueError:
            raise ValueError(f"@{event}: expected t=SECONDS, e.g. needle_force@t=1.9") from None
        if results.step_count == 0 or time > results.time[-1] + 1e-9:
            return None
        return int(np.argmin(np.abs(results.time - time)))
    found = results.events_named(event)
    if not found:
        return None
    return results.index_of(found[0].step)


def _needle_force(results, event: str = "end") -> float:
    index = _event_index(results, event)
    return float("nan") if index is None else float(np.linalg.norm(results.profile_force[index]))


def _axial_force(results, event: str = "end") -> float:
    index = _event_index(results, event)
    if index is None:
        return float("nan")
    axial, _ = results.axial_lateral_force()
    return float(-axial[index])


def _lateral_force(results, event: str = "end") -> float:
    index = _event_index(results, event)
    if index is None:
        return float("nan")
    _, lateral = results.axial_lateral_force()
    return float(lateral[index])


def _event_time(results, event: str = "cut_start") -> float:
    found = results.events_named(event or "cut_start")
    return float(found[0].time) if found else float("nan")


def _puncture_force(results, argument: str = "") -> float:
    found = results.events_named("puncture")
    return float(found[0].force) if found else float("nan")


def triangle_areas(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Areas [m²] of triangles (t, 3) over points (p, 3) [m], shape (t,)."""
    corners = np.asarray(points, dtype=float)[np.asarray(triangles, dtype=np.int64)]
    return 0.5 * np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1
    )


def _cut_area(results, argument: str = "") -> float:
    if results.cut is None or results.cut.triangles.shape[0] == 0:
        return float("nan")
    return float(triangle_areas(results.cut.points, results.cut.triangles).sum())


def _lateral_stroke(results, event: str = "cut_start") -> float:
    index = _event_index(results, event or "cut_start")
    if index is None:
        return float("nan")
    rest = results.needle_rest_nodes
    axis = (rest[1] - rest[0]) / np.linalg.norm(rest[1] - rest[0])
    moved = results.base_position[index] - rest[0]
    return float(np.linalg.norm(moved - (moved @ axis) * axis))


def _displacement_vector(results, argument: str) -> np.ndarray:
    from refsim.geometry.search import TetLocator

    try:
        point = np.array([float(v) for v in argument.split(",")], dtype=float)
    except ValueError:
        point = np.zeros(0)
    if point.shape != (3,):
        raise ValueError(
            f"displacement@{argument}: expected a rest point X,Y,Z in metres, e.g. displacement@0,0,0.09"
        )
    if results.tissue_steps.size == 0:
        return np.full(3, np.nan)
    tet, barycentric = TetLocator(results.rest_positions, results.tets).locate(point[None], tolerance=1e-9)
    if tet[0] < 0:
        raise ValueError(f"displacement@{argument}: the point is outside the tissue at rest")
    displacement = results.tissue_positions[-1] - results.rest_positions
    return barycentric[0] @ displacement[results.tets[tet[0]]]


def _displacement(component: int | None) -> Callable:
    def compute(results, argument: str) -> float:
        vector = _displacement_vector(results, argument)
        return float(np.linalg.norm(vector) if component is None else vector[component])

    return compute


#: Quantity name → function(results, argument) → float.
QUANTITIES: dict[str, Callable] = {
    "needle_force": _needle_force,
    "axial_force": _axial_force,
    "lateral_force": _lateral_force,
    "puncture_force": _puncture_force,
    "time": _event_time,
    "cut_area": _cut_area,
    "lateral_stroke": _lateral_stroke,
    "displacement": _displacement(None),
    "displacement_x": _displacement(0),
    "displacement_y": _displacement(1),
    "displacement_z": _displacement(2),
}

#: Unit of each quantity.
UNITS = {
    "needle_force": "N",
    "axial_force": "N",
    "lateral_force": "N",
    "puncture_force": "N",
    "time": "s",
    "cut_area": "m^2",
    "lateral_stroke": "m",
    "displacement": "m",
    "displacement_x": "m",
    "displacement_y": "m",
    "displacement_z": "m",
}


def _split(name: str) -> tuple[str, str]:
    base, _, argument = str(name).partition("@")
    return base.strip(), argument.strip()


def check_quantity(name: str) -> str:
    """Return ``name`` if it names a known quantity, else raise a ValueError listing the known ones."""
    base, _ = _split(name)
    if base not in QUANTITIES:
        raise ValueError(
            f"quantity {name!r}: unknown; known quantities: {', '.join(QUANTITIES)} "
            "(with @EVENT or @X,Y,Z where they take one)"
        )
    return name


def quantity(results, name: str) -> float:
    """The quantity ``name`` of a run (NaN when the run does not have it)."""
    base, argument = _split(check_quantity(name))
    function = QUANTITIES[base]
    return function(results, argument) if argument else function(results)


def quantities(results, names) -> dict[str, float]:
    """Several quantities of one run, {name: value}."""
    return {name: quantity(results, name) for name in names}


def force_history_error(results, reference) -> float:
    """Relative L2 error of the needle force history against a reference run [-]:
    ‖F − F_ref‖ / ‖F_ref‖ over the reference's steps, F interpolated linearly in time (any time steps)."""
    if reference.step_count == 0 or results.step_count == 0:
        return float("nan")
    times = reference.time
    force = np.column_stack([np.interp(times, results.time, results.needle_force[:, i]) for i in range(3)])
    scale = np.linalg.norm(reference.needle_force)
    if scale == 0.0:
        return float("nan")
    return float(np.linalg.norm(force - reference.needle_force) / scale)
