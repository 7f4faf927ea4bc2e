"""Random needle lives on the paper's cube and the invariants every step of any life keeps (layer 6).

A *life* is one needle's trajectory drawn from a seed (:func:`draw_life`): cube_cut on 4³ cells (the energy
law, G_c = 200 J/m², f_p = 0.8 N), a time step of 5, 10 or 20 ms, a rigid or a flexible needle, the exact or
the fast tissue compliance, Gauss–Seidel or the exact constraint solver, a tilt of 0–35° at any azimuth, an
entry inside a surface triangle, on a grid edge or at a grid vertex, and 3–5 segments between waypoints that
insert, pull back (above the surface too), move the needle's line sideways, turn it by up to 20° and hold.
Every waypoint time is a whole number of steps, the tip moves at most 20 mm/s, and each segment keeps the
scene's own check on the tip's travel per step, so a life is never refused. A life of the "model" family
(:data:`FAMILIES`) also draws the mesh (3³ to 8³ cells, stretched tets), d_i, d_c, f_p, G_c, the friction
coefficients, the needle's radius and the tissue's thickness (a 20 mm layer, which a needle leaves through
its far face; :data:`MODEL_CHOICES`); one of the "two" family runs a second needle beside the first in
the same tissue, which holds and does not cut (its own trajectory drawn alike, kept apart from the first's
by the scene's own check), and each needle is checked on its own rows and events.

:func:`life_violations` checks what must hold at every step of any life, whatever the needle does:

- ``finite``: the tissue positions (when recorded), the needle's positions, its force and the rows' forces;
- ``rows``: the step ends with the rows of its end state (:func:`end_state_violations`);
- ``phase`` (records holding the tissue's positions at every step, which :func:`draw_life`'s scenes ask for):
  a needle in insertion or cutting has some of its centreline in the tissue as deformed at the step, or lies
  within the insertion points' release margin of it (the ring's hysteresis, a share of d_i, by which a
  pulled-back tip outlives its last point; the model's needle is its centreline): refsim.simulation.events'
  table, a needle is withdrawn when no part of it is left in the tissue (:func:`phase_violation`). The faults
  this was written for: a needle tilted in its stroke's plane and pulled out after a stroke towards its tilt,
  never withdrawn (the entry point's projection on its axis above its tip), and one pulled out while moving
  sideways towards its tilt, kept in insertion with its tip 1.7 mm above the surface and 0.77 N on it. (The
  withdrawal's step is not checked here: its record is its second solve, in which a released bent needle may
  spring into the surface, and a tip pressed into a surface it has not punctured is no part of the needle in
  the tissue, while the approach's contact, one row linearised at the step's start, lets a needle buckled at a
  layer's edge, or an organ breathing onto a shaft, into the tissue by 0.2 to 9.5 mm in 17 of the 596 slow
  lives: docs/coupling.md, "The face the tip meets". tests/simulation/test_cracks.py and test_life_cycle.py
  check the withdrawals of those faults' lives.)
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

Used by ``tests/simulation/test_random_life_cycles.py`` (a few seeds by default, many in the slow set) and by
``studies/lifecycle/run.py`` (any range of seeds, with a report per seed).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "Life",
    "Violation",
    "draw_life",
    "end_state_violations",
    "inserted_length",
    "inserted_lengths",
    "layers_mesh_file",
    "life_violations",
    "phase_violation",
    "shaft_contact_loads",
]

SCENE = "cube_cut"
CELLS = (4, 4, 4)
#: The families of lives :func:`draw_life` draws from: "cube" on the 4³ cube with the scene's model values;
#: "model" also draws the mesh and the model's values a user sets (:data:`MODEL_CHOICES`); "two" draws a
#: second needle's life beside the first in the same tissue, one that holds and does not cut, entering
#: about 30 mm from it (:data:`TWO_SHIFT`); "liver" the same kind of
#: life on the liver scene (an unstructured organ that breathes under the needle), entering at a random point
#: of its surface, its segments in the tangent plane's frame there.
#: "layers" the cube's kind of life in two layers with a gap between them (a wall over an organ,
#: :data:`LAYERS_CHOICES`), which the needle crosses, cuts and leaves part by part.
FAMILIES = ("cube", "model", "two", "liver", "layers")
#: The "two" family: each needle's entry is this far off the middle along x [m] (the cutter's to −x, the
#: holder's to +x), both needles' radius [m] (thin, so that they pass each other), the holder's draws tried.
TWO_SHIFT = 0.015
TWO_RADIUS = 0.002
TWO_ATTEMPTS = 50
#: The "liver" family: the scene (the paper's liver with breathing), how far a sideways move takes the line's
#: crossing of the tangent plane at the entry [m], and the entry points tried (one whose start lies outside).
LIVER_SCENE = "liver_rigid"
LIVER_CLIP = 0.01
LIVER_ATTEMPTS = 50
#: What a life of the "model" family draws from, each value with the same chance: the cells per axis (cubic
#: and stretched tets), d_i and d_c [m], f_p [N], G_c [J/m²], the friction coefficients (surface, shaft), the
#: needle's radius [m] and the tissue's thickness [m] (a third of the lives on a 20 mm layer).
MODEL_CHOICES = {
    "cells": ((3, 3, 3), (4, 4, 4), (5, 5, 5), (6, 6, 6), (8, 8, 8), (4, 4, 8), (6, 6, 3)),
    "spacing": (0.25e-3, 0.5e-3, 1e-3, 2e-3),
    "point_spacing": (0.25e-3, 0.5e-3, 1e-3, 2e-3),
    "puncture_force": (0.4, 0.8, 1.6),
    "fracture_energy": (100.0, 200.0, 400.0),
    "friction": (0.0, 0.1, 0.2),
    "radius": (0.5e-3, 2e-3, 8e-3),
    "thickness": (0.1, 0.1, 0.02),
}
#: A tissue thinner than the cube (``thickness`` < 0.1 m) is a layer with the cube's top face, held on its
#: sides (a needle can leave it through its far face and come back), with this many cells across it at least.
LAYER_CELLS = 2
#: What a life of the "layers" family draws from (``default_rng([seed, 4])``), each value with the same
#: chance: the upper layer's thickness, the gap under it and the lower layer's thickness [m]. Both span the
#: cube's 10 × 10 cm on 4 × 4 cells (the upper one a cell per 4 mm of thickness, at least 2; the lower one
#: 4), the upper layer's top face the cube's; held on their sides, the lower one on its bottom too.
LAYERS_CHOICES = {
    "upper": (0.004, 0.008, 0.012),
    "gap": (0.0005, 0.001, 0.003, 0.01),
    "lower": (0.015, 0.025),
}
#: The "layers" family's needle radius [m] (the thin-layer tests' needle: cube_cut's 8 mm spans the gaps).
LAYERS_RADIUS = 0.0005
#: The time steps a life draws from [s].
TIME_STEPS = (0.005, 0.01, 0.02)
#: The tip's largest speed [m/s].
MAX_TIP_SPEED = 20e-3
#: The share of insertion.contact_distance the scene's check on the tip's travel per step is kept within.
TRAVEL_SHARE = 0.8
#: The force bound's factor over f_p + G_c L_in (module docstring).
BOUND_FACTOR = 2.0
#: A force [N] below which a step without rows counts as carrying none.
NO_ROW_FORCE = 1e-9
#: The ``phase`` invariant's sampling of the needle's centreline [m] (:func:`_length_inside`'s): a length in
#: the tissue at most this is none, a distance from it at most this is touching it.
PHASE_SAMPLING = 1e-4


@dataclass(frozen=True)
class Life:
    """One drawn needle life: what it varies and the scene overrides that run it.

    Attributes
    ----------
    seed : The seed it was drawn from.
    family : Its family (:data:`FAMILIES`).
    model : What the "model" family drew (cells, spacing, point_spacing, puncture_force, fracture_energy,
        friction; :data:`MODEL_CHOICES`), or the "layers" family (upper, gap, lower: :data:`LAYERS_CHOICES`);
        empty for the other families (4³ cells, the scene's values).
    second : The "two" family's second needle (it holds, it does not cut): its waypoints as ``waypoints``;
        empty for the other families.
    scene_name : The built-in scene it runs (:data:`LIVER_SCENE` for the "liver" family, whose waypoints
        are in the world's frame and set the trajectory, else :data:`SCENE`).
    dt : The time step [s].
    rigid, fast, exact_solver : A rigid needle (else a beam), the fast compliance (else exact), the exact
        constraint solver (else Gauss–Seidel).
    tilt_deg, azimuth_deg : The needle's first direction from the vertical and its azimuth [°].
    entry : Where the needle's line first crosses the top face, (x, y) [m].
    waypoints : Per waypoint: its time [s], what the segment to it does ("start", "move", "turn", "hold"),
        the tip's depth along the needle below the top face [m] (negative above it), where the needle's line
        crosses the top face (x, y) [m] and the needle's direction.
    overrides : The ``SECTION.KEY=VALUE`` overrides of :data:`SCENE` that run it.
    """

    seed: int
    dt: float
    rigid: bool
    fast: bool
    exact_solver: bool
    tilt_deg: float
    azimuth_deg: float
    entry: tuple[float, float]
    waypoints: tuple[dict, ...]
    overrides: tuple[str, ...] = field(repr=False)
    family: str = "cube"
    model: tuple[tuple[str, object], ...] = ()
    second: tuple[dict, ...] = ()
    scene_name: str = SCENE

    def scene(self):
        """The scene of this life: :data:`SCENE` with its overrides, and for the "two" family its needle as
        the first of two instruments ("cutter", which cuts, and "holder", which does not)."""
        from refsim.scene import load_scene
        from refsim.scene.loader import scene_from_dict

        if self.family == "layers":  # (its mesh file, written again if the temporary folder was emptied)
            values = dict(self.model)
            layers_mesh_file(values["upper"], values["gap"], values["lower"])
        scene = load_scene(self.scene_name, list(self.overrides))
        if self.scene_name != SCENE:
            data = scene.to_dict()
            data["trajectory"] = _trajectory(self.waypoints, float(scene.needle.length))
            return scene_from_dict(
                data, source=f"{self.family} life {self.seed}", base_directory=str(_scenes_directory())
            )
        if not self.second:
            return scene
        data = scene.to_dict()
        first = data.pop("trajectory")
        second = dict(first, **_trajectory(self.second, float(scene.needle.length)))
        data["instruments"] = [
            {"name": "cutter", "cuts": True, "trajectory": first},
            {"name": "holder", "cuts": False, "trajectory": second},
        ]
        return scene_from_dict(data, source=f"{self.family} life {self.seed}")

    def describe(self) -> str:
        """One line: the life's parameters and its waypoints (for a failing test's message)."""
        kinds = " ".join(f"{w['kind']}@{w['time']:g}s:{1e3 * w['depth']:.1f}mm" for w in self.waypoints[1:])
        if self.second:
            kinds += "; holder " + " ".join(
                f"{w['kind']}@{w['time']:g}s:{1e3 * w['depth']:.1f}mm" for w in self.second[1:]
            )
        model = "".join(f"{key} {value}, " for key, value in self.model)
        return (
            f"{self.family} seed {self.seed}: {model}dt {self.dt:g} s, "
            f"{'rigid' if self.rigid else 'flexible'}, "
            f"{'fast' if self.fast else 'exact'} compliance, "
            f"{'exact' if self.exact_solver else 'gauss_seidel'} solver, "
            f"tilt {self.tilt_deg:.1f} deg; {kinds}"
        )


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


def _rotate(vector: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """``vector`` rotated by ``angle`` [rad] about the unit ``axis`` (Rodrigues' formula)."""
    return (
        vector * np.cos(angle)
        + np.cross(axis, vector) * np.sin(angle)
        + axis * (axis @ vector) * (1.0 - np.cos(angle))
    )


def _fmt(values) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def _scenes_directory():
    """The folder of the built-in scenes (a scene's relative paths are read from it)."""
    from pathlib import Path

    import refsim

    return Path(refsim.__file__).resolve().parent / "scenes"


def _trajectory(waypoints, length: float) -> dict:
    """A [trajectory] table's waypoints (times, base_positions, directions) for a needle of ``length`` [m]
    whose tip is at each waypoint's depth along its direction below where its line crosses the top face."""
    return {
        "times": tuple(float(w["time"]) for w in waypoints),
        "base_positions": tuple(
            tuple(float(v) for v in w["anchor"] + (w["depth"] - length) * w["direction"]) for w in waypoints
        ),
        "directions": tuple(tuple(float(v) for v in w["direction"]) for w in waypoints),
    }


def _draw_run(rng) -> tuple[float, bool, bool, bool]:
    """The run's settings, the first draws of every family from ``rng``: (dt [s], rigid needle, fast
    compliance, exact solver)."""
    dt = float(rng.choice(TIME_STEPS))
    return dt, bool(rng.random() < 0.6), bool(rng.random() < 0.3), bool(rng.random() < 0.25)


def _run_overrides(dt: float, steps: int, rigid: bool, fast: bool, exact_solver: bool) -> list[str]:
    """The overrides of the run's settings: dt, a duration of ``steps`` steps and at least 2 s (a final
    hold), the needle, the compliance and the solver; the tissue's positions recorded at every step (what
    the ``phase`` invariant and an organ's inserted length read)."""
    steps = max(steps, int(np.ceil(2.0 / dt - 1e-9)))
    overrides = [
        f"time.dt={dt!r}",
        f"time.duration={round(steps * dt, 10)!r}",
        f"needle.rigid={'true' if rigid else 'false'}",
        "output.tissue_every=1",
    ]
    if fast:
        overrides.append("compliance.strategy=fast")
    if exact_solver:
        overrides.append('solver.method="exact"')
    return overrides


def _draw_needle(rng, geometry: dict, dt: float, shift: float) -> tuple[float, float, np.ndarray, list, int]:
    """One needle's life from ``rng`` (:func:`draw_life`): (tilt [°], azimuth [°], entry (x, y) [m],
    waypoints, its steps). ``geometry``: the needle's length, the contact distance, the top face's height
    and the top face's grid lines per axis [m], and optionally ``spread`` (the entry's spread about the
    middle, a share of ±15 mm, 1 by default) and ``clip`` (how far sideways moves take the line's crossing of
    the top face from the middle, 35 mm by default); ``shift``: added to the entry's x [m] (off the grid
    lines)."""
    length, contact, top, grids = (geometry[key] for key in ("length", "contact", "top", "grids"))
    spread, clip = geometry.get("spread", 1.0), geometry.get("clip", 0.035)
    tilt = float(rng.uniform(0.0, 35.0))
    azimuth = float(rng.uniform(0.0, 360.0))
    t, a = np.radians(tilt), np.radians(azimuth)
    direction = np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), -np.cos(t)])
    entry = rng.uniform(-0.015, 0.015, size=2) * spread + [shift, 0.0]
    where = rng.random()
    if where < 0.1:  # on a grid edge
        entry[0] = float(rng.choice(grids[0]))
    elif where < 0.15:  # at a grid vertex
        entry = np.array([rng.choice(grids[0]), rng.choice(grids[1])], dtype=float)
    count = int(rng.integers(4, 7))
    total = float(rng.uniform(2.5, 5.0))
    shares = np.maximum(rng.dirichlet(np.full(count - 1, 2.0)) * total, 0.3)
    reach = TRAVEL_SHARE * contact / dt  # the scene's estimate of the tip's speed may reach this [m/s]
    anchor = np.array([entry[0], entry[1], top])
    depth = -float(rng.uniform(1e-3, 6e-3))
    waypoints = [{"time": 0.0, "kind": "start", "depth": depth, "anchor": anchor, "direction": direction}]
    steps = 0
    for index in range(1, count):
        previous = waypoints[-1]
        share = float(shares[index - 1])
        anchor, direction = previous["anchor"].copy(), previous["direction"].copy()
        depth, kind = previous["depth"], "move"
        budget = float(rng.uniform(0.4, 1.0)) * MAX_TIP_SPEED * share  # the tip's path [m]
        if index >= 2 and rng.random() < 0.2:
            kind = "hold"
        else:
            if index >= 2 and rng.random() < 0.35:
                # A turn about the line's crossing of the top face moves the base by about L times the angle,
                # which the scene's check counts twice (base speed and turning rate).
                limit = (reach * share - budget) / (2.0 * length)
                angle = min(np.radians(float(rng.uniform(3.0, 20.0))), limit)
                angle = min(angle, 0.5 * budget / max(previous["depth"], 1e-3))  # the tip's sweep
                if angle > np.radians(1.0):
                    for _ in range(20):
                        axis = np.cross(direction, rng.normal(size=3))
                        axis /= np.linalg.norm(axis)
                        turned = _rotate(direction, axis, angle)
                        if -turned[2] >= np.cos(np.radians(45.0)):  # at most 45° from the vertical
                            direction, kind = turned / np.linalg.norm(turned), "turn"
                            break
            sweep = abs(previous["depth"]) * float(
                np.arccos(np.clip(direction @ previous["direction"], -1, 1))
            )
            left = max(budget - sweep, 0.0)
            if index >= 2 or rng.random() < 0.3:
                offset = rng.normal(0.0, 4e-3, size=2)
                offset *= min(1.0, 0.5 * left / max(float(np.linalg.norm(offset)), 1e-12))
                anchor[:2] = np.clip(anchor[:2] + offset, -clip, clip)
                left -= float(np.linalg.norm(anchor[:2] - previous["anchor"][:2]))
            target = float(rng.uniform(3e-3, 50e-3)) if index == 1 else float(rng.uniform(-6e-3, 50e-3))
            depth = float(np.clip(target, previous["depth"] - left, previous["depth"] + left))
        tips = [previous["anchor"] + previous["depth"] * previous["direction"], anchor + depth * direction]
        pair = (previous["direction"], direction)
        bases = [tip - length * d for tip, d in zip(tips, pair, strict=True)]
        turn = float(np.arccos(np.clip(pair[0] @ pair[1], -1.0, 1.0)))
        duration = max(share, float(np.linalg.norm(tips[1] - tips[0])) / MAX_TIP_SPEED)
        duration = max(duration, (float(np.linalg.norm(bases[1] - bases[0])) + length * turn) / reach)
        steps += int(np.ceil(duration / dt - 1e-9))
        waypoints.append(
            {
                "time": round(steps * dt, 10),
                "kind": kind,
                "depth": depth,
                "anchor": anchor,
                "direction": direction,
            }
        )
    return tilt, azimuth, entry, waypoints, steps


def draw_life(seed: int, family: str = "cube") -> Life:
    """One random needle life on cube_cut, from ``numpy.random.default_rng(seed)``.

    ``family`` "cube": on 4³ cells with the scene's model values; "model": the mesh's cells, d_i, d_c, f_p,
    G_c and the friction coefficients drawn too (:data:`MODEL_CHOICES`, from ``default_rng([seed, 1])``, so
    that the trajectory's draws are those of the same seed in the "cube" family).

    The run (2.5–5 s, at least 2 s) is split at random among the segments; each moving segment draws what it
    does within its share of time: the tip's path at most 20 mm/s, a turn and the line's sideways motion
    within the scene's check on the tip's travel per step (the base's speed plus the needle's length times
    its turning rate, within 80 % of the contact distance per step). An entry on a grid edge or at a grid
    vertex is on the mesh's grid lines of the top face (at −25, 0 and 25 mm on 4 cells)."""
    from refsim.scene import load_scene

    if family not in FAMILIES:
        raise ValueError(f"family {family!r} is not one of {', '.join(FAMILIES)}")
    cells, model, model_overrides = CELLS, {}, []
    if family == "model":
        drawn = np.random.default_rng([seed, 1])
        model = {key: choices[int(drawn.integers(len(choices)))] for key, choices in MODEL_CHOICES.items()}
        cells = model["cells"]
        thickness = model["thickness"]
        if thickness < 0.1:
            cells = (*cells[:2], max(LAYER_CELLS, round(cells[2] * thickness / 0.1)))
            model["cells"] = cells
        model_overrides = [
            f"needle.radius={model['radius']!r}",
            f"insertion.spacing={model['spacing']!r}",
            f"cutting.point_spacing={model['point_spacing']!r}",
            f"insertion.puncture_force={model['puncture_force']!r}",
            f"cutting.fracture_energy={model['fracture_energy']!r}",
            f"insertion.surface_friction_coefficient={model['friction']!r}",
            f"insertion.shaft_friction_coefficient={model['friction']!r}",
        ]
        if thickness < 0.1:
            model_overrides += [
                f"mesh.size=[0.1, 0.1, {thickness!r}]",
                f"mesh.origin=[-0.05, -0.05, {0.1 - thickness!r}]",
                'mesh.fixed_faces=["xmin", "xmax", "ymin", "ymax"]',
            ]
    if family == "liver":
        return _liver_life(seed)
    cells_override = f"mesh.cells=[{', '.join(str(c) for c in cells)}]"
    if family == "layers":
        drawn = np.random.default_rng([seed, 4])
        model = {key: choices[int(drawn.integers(len(choices)))] for key, choices in LAYERS_CHOICES.items()}
        cells_override = f'mesh.file="{layers_mesh_file(model["upper"], model["gap"], model["lower"])}"'
        model_overrides = ['mesh.fixed_faces=["xmin", "xmax", "ymin", "ymax", "zmin"]']
    base_scene = load_scene(SCENE, [cells_override, *model_overrides])
    length = float(base_scene.needle.length)
    contact = float(base_scene.insertion.contact_distance)
    # the cube's box (the layers': the same 10 x 10 cm top face on 4 x 4 cells)
    box = base_scene if family != "layers" else load_scene(SCENE, ["mesh.cells=[4, 4, 4]"])
    top = float(box.mesh.origin[2] + box.mesh.size[2])
    size = np.asarray(box.mesh.size, dtype=float)
    origin = np.asarray(box.mesh.origin, dtype=float)
    grids = [origin[k] + size[k] * np.arange(1, cells[k]) / cells[k] for k in range(2)]

    rng = np.random.default_rng(seed)
    dt, rigid, fast, exact_solver = _draw_run(rng)
    geometry = {"length": length, "contact": contact, "top": top, "grids": grids}
    shift = -TWO_SHIFT if family == "two" else 0.0
    tilt, azimuth, entry, waypoints, steps = _draw_needle(rng, geometry, dt, shift)
    bases = [w["anchor"] + (w["depth"] - length) * w["direction"] for w in waypoints]
    overrides = [
        cells_override,
        *model_overrides,
        *_run_overrides(dt, steps, rigid, fast, exact_solver),
        f"trajectory.times={_fmt([w['time'] for w in waypoints])}",
        "trajectory.base_positions=[" + ", ".join(_fmt(b) for b in bases) + "]",
        "trajectory.directions=[" + ", ".join(_fmt(w["direction"]) for w in waypoints) + "]",
    ]
    if family == "two":
        overrides.append(f"needle.radius={TWO_RADIUS!r}")
    if family == "layers":
        overrides.append(f"needle.radius={LAYERS_RADIUS!r}")  # a thin needle
    life = Life(
        seed=seed,
        dt=dt,
        rigid=rigid,
        fast=fast,
        exact_solver=exact_solver,
        tilt_deg=tilt,
        azimuth_deg=azimuth,
        entry=(float(entry[0]), float(entry[1])),
        waypoints=tuple(waypoints),
        overrides=tuple(overrides),
        family=family,
        model=tuple(model.items()),
    )
    return life if family != "two" else _with_holder(life, seed, geometry, steps)


def layers_mesh_file(upper: float, gap: float, lower: float) -> str:
    """The mesh file of two layers (:data:`LAYERS_CHOICES`): an ``upper`` [m] thick layer whose top face is
    the cube's (z = 0.1 m), a ``gap`` [m] under it, a ``lower`` [m] thick layer, both 10 × 10 cm; written once
    in the system's temporary folder (its name holds the three values) and reused."""
    import os
    import tempfile
    from pathlib import Path

    import meshio

    from refsim.mesh.generators import box_mesh

    folder = Path(tempfile.gettempdir()) / "refsim-lives"
    path = folder / f"layers-{upper * 1e3:g}-{gap * 1e3:g}-{lower * 1e3:g}mm.vtu"
    if path.exists():
        return str(path)
    folder.mkdir(parents=True, exist_ok=True)
    top = 0.1
    boxes = [
        box_mesh(
            size=(0.1, 0.1, upper),
            cells=(4, 4, max(LAYER_CELLS, round(upper / 0.004))),
            origin=(-0.05, -0.05, top - upper),
        ),
        box_mesh(size=(0.1, 0.1, lower), cells=(4, 4, 4), origin=(-0.05, -0.05, top - upper - gap - lower)),
    ]
    points = np.vstack([box.rest_positions for box in boxes])
    tets = np.vstack([boxes[0].tets, boxes[1].tets + boxes[0].rest_positions.shape[0]])
    # written under another name and renamed: a process reading the file never sees it half written
    partial = folder / f"{path.stem}.{os.getpid()}.vtu"
    meshio.write(partial, meshio.Mesh(points, [("tetra", tets)]))
    os.replace(partial, path)
    return str(path)


def _liver_life(seed: int) -> Life:
    """A life of the "liver" family (:func:`draw_life`): the needle's draws of the "cube" family from
    ``default_rng(seed)`` in a local frame whose top face is the tangent plane at the entry (a side of the
    local frame's top face is the organ's outward normal), the entry an area-weighted random point of the
    organ's surface from ``default_rng([seed, 3, attempt])``, the first whose start (the tip 1-6 mm out
    along the needle) lies outside the organ."""
    from refsim.geometry.search import TetLocator
    from refsim.scene import load_scene
    from refsim.scene.build import build_models

    base_scene = load_scene(LIVER_SCENE)
    mesh = build_models(base_scene).mesh
    rest, faces = np.asarray(mesh.rest_positions, dtype=float), np.asarray(mesh.boundary_faces)
    corners = rest[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    areas = np.linalg.norm(normals, axis=1)
    normals /= areas[:, None]
    outward = np.sign(np.einsum("ij,ij->i", normals, corners.mean(axis=1) - rest.mean(axis=0)))
    locator = TetLocator(rest, np.asarray(mesh.tets))

    rng = np.random.default_rng(seed)
    dt, rigid, fast, exact_solver = _draw_run(rng)
    geometry = {
        "length": float(base_scene.needle.length),
        "contact": float(base_scene.insertion.contact_distance),
        "top": 0.0,
        "grids": [np.zeros(1), np.zeros(1)],
        "spread": 0.0,
        "clip": LIVER_CLIP,
    }
    tilt, azimuth, _, local, steps = _draw_needle(rng, geometry, dt, 0.0)
    for attempt in range(LIVER_ATTEMPTS):
        pick = np.random.default_rng([seed, 3, attempt])
        face = int(pick.choice(len(faces), p=areas / areas.sum()))
        u, v = pick.random(2)
        u, v = (1.0 - u, 1.0 - v) if u + v > 1.0 else (u, v)
        origin = (
            corners[face, 0]
            + u * (corners[face, 1] - corners[face, 0])
            + v * (corners[face, 2] - corners[face, 0])
        )
        normal = outward[face] * normals[face]
        first = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
        first /= np.linalg.norm(first)
        frame = np.column_stack([first, np.cross(normal, first), normal])  # local x, y, z in the world
        waypoints = [
            dict(w, anchor=origin + frame @ w["anchor"], direction=frame @ w["direction"]) for w in local
        ]
        start = waypoints[0]["anchor"] + waypoints[0]["depth"] * waypoints[0]["direction"]
        if locator.locate(start[None])[0][0] < 0:
            break
    else:
        raise ValueError(
            f"seed {seed}: no entry of the liver in {LIVER_ATTEMPTS} attempts whose start is outside"
        )
    overrides = list(_run_overrides(dt, steps, rigid, fast, exact_solver))
    return Life(
        seed=seed,
        dt=dt,
        rigid=rigid,
        fast=fast,
        exact_solver=exact_solver,
        tilt_deg=tilt,
        azimuth_deg=azimuth,
        entry=(float(origin[0]), float(origin[1])),
        waypoints=tuple(waypoints),
        overrides=tuple(overrides),
        family="liver",
        scene_name=LIVER_SCENE,
    )


def _with_holder(life: Life, seed: int, geometry: dict, steps: int) -> Life:
    """``life`` with a second needle that holds (the "two" family), drawn from ``default_rng([seed, 2,
    attempt])`` until the scene's own check keeps the two shafts apart (refsim models no contact between
    instruments) over the whole run, at most :data:`TWO_ATTEMPTS` attempts."""
    import dataclasses

    from refsim.scene.build import build_models
    from refsim.scene.loader import InstrumentsOverlap

    for attempt in range(TWO_ATTEMPTS):
        second, second_steps = _draw_needle(
            np.random.default_rng([seed, 2, attempt]), geometry, life.dt, TWO_SHIFT
        )[3:]
        end = max(steps, second_steps, int(np.ceil(2.0 / life.dt - 1e-9)))  # as _run_overrides
        overrides = [o for o in life.overrides if not o.startswith("time.duration=")]
        overrides.append(f"time.duration={round(end * life.dt, 10)!r}")
        candidate = dataclasses.replace(life, overrides=tuple(overrides), second=tuple(second))
        try:
            build_models(candidate.scene())
        except InstrumentsOverlap:
            continue
        return candidate
    raise ValueError(f"seed {seed}: no holder's life kept apart from the cutter's in {TWO_ATTEMPTS} attempts")


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
