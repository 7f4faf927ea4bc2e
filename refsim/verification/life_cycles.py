"""Random needle lives on the paper's cube, drawn from a seed (layer 6).

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

The invariants every step of a life keeps are checked by :mod:`refsim.verification.invariants`
(:func:`~refsim.verification.invariants.life_violations`).

Used by ``tests/simulation/test_random_life_cycles.py`` (a few seeds by default, many in the slow set) and by
``studies/lifecycle/run.py`` (any range of seeds, with a report per seed).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Life", "draw_life", "layers_mesh_file"]

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
