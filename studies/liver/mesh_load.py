"""Why the liver outcome depends on the phantom: the decisive load, measured on each mesh (issue 24, item 8).

    PYTHONPATH=. python studies/liver/mesh_load.py [--fine 0.006] [--free] [--ring 0.018] [--duration 1.45]
        [--set section.key=value ...] [--output output/mesh_load.json]

The outcome is decided by the cut-start criterion alone, ‖t‖ ≥ G_c L_in with t the shaft's lateral load
through the insertion points (the entry point left out): no cut row exists before it, so the cut rows'
coupling cannot move the window. Each run here is liver_flexible with cutting on at a G_c it never reaches,
every mesh driven by the same robot motion (refsim/scenes/liver_robot.csv), over the first inhale; per mesh
it writes the largest ‖t‖/L_in, when, L_in, and the load of every insertion point along the needle at that
step. Also measured: the tissue's own motion (no needle) at material points along the needle's line, relative
to the target the robot follows (the displacement that loads the needle), and, with ``--ring``, the same runs
with the coupling ring's radius held at that value on every mesh (ρ_c = max(r, h, ring), the sub-grid
annulus with it), which separates what the mesh resolves from what the sub-grid term models.

``--set`` changes the scene (e.g. the breathing's ``boundary.facing_angle``). Meshes: the shipped coarse
(20 mm) and medium (9 mm) phantoms, and with ``--fine SIZE`` one generated at that size (needs gmsh). Writes
output/mesh_load.json. One process, one BLAS thread.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
OUTPUT = ROOT / "studies" / "liver" / "output"
TARGET = np.array([-0.05, -0.0115, 0.01])  # studies/liver/make_trajectory.py
DEPTH = 0.08
DEPTHS = np.array([2, 5, 10, 15, 20, 25, 30]) * 1e-3  # below the nominal entry, along the needle


def run_load(mesh_file: str, duration: float, overrides=()) -> dict:
    """The largest ‖t‖/L_in of liver_flexible on ``mesh_file`` (cutting never starts) and the load profile
    along the needle at that step."""
    from refsim.constraints import BILATERAL, INSERTION
    from refsim.scene import load_scene
    from refsim.simulation import Simulation
    from refsim.simulation.events import shaft_lateral_force

    scene = load_scene(
        "liver_flexible",
        [
            f"mesh.file={json.dumps(mesh_file)}",
            f"time.duration={duration!r}",
            'trajectory.file="liver_robot.csv"',
            "cutting.fracture_energy=1e9",
            *overrides,
        ],
    )
    simulation = Simulation(scene)
    state = simulation.initial_state()
    best = {"load": 0.0}
    started = time.perf_counter()
    for _ in range(scene.time.step_count):
        state, record = simulation.step(state, record_tissue=False)
        if record.row_forces is None or state.phase != "insertion" or not state.path.point_count:
            continue
        source, kind = np.asarray(record.row_source), np.asarray(record.row_kind)
        force = shaft_lateral_force(
            source,
            kind,
            record.row_directions,
            record.row_forces,
            without_entry=True,
            surface_allowance=scene.insertion.puncture_force,
            points=record.row_point,
        )
        entry = state.path.positions(state.tissue.positions, simulation.tets)[:1]
        needle = simulation.event_rules.needle_geometry(state.needle)
        inserted = needle.length - float(needle.project(entry)[0][0])  # as EventRules._cut_starts
        if inserted <= 0.0 or float(np.linalg.norm(force)) / inserted <= best["load"]:
            continue
        lateral = np.flatnonzero((source == INSERTION) & (kind == BILATERAL))
        per_point = (np.asarray(record.row_directions)[lateral] * record.row_forces[lateral, None]).reshape(
            -1, 2, 3
        )
        along = force / np.linalg.norm(force)
        rings = state.path.rings.layout
        best = {
            "load": float(np.linalg.norm(force)) / inserted,
            "time": float(state.time),
            "inserted_length": inserted,
            "point_loads": (per_point.sum(axis=1) @ along).tolist(),  # [N], entry first, every d_i
            "mesh_sizes": rings.mesh_size.tolist(),
            "ring_radii": rings.radius.tolist(),
        }
    best["seconds"] = time.perf_counter() - started
    return best


def free_motion(mesh_file: str, duration: float, overrides=()) -> list[float]:
    """The tissue's motion (no needle) across the needle at ``DEPTHS`` below the entry, relative to the
    target, at the end of ``duration`` [m] (|x, z|), by the scene's own time stepping (as
    `refsim.simulation.robot.target_motion`, for several points at once)."""
    from refsim.geometry import TetLocator
    from refsim.scene import load_scene
    from refsim.scene.build import build_controls, build_models
    from refsim.simulation.bodies import TissueBody

    scene = load_scene(
        "liver_rigid",
        [
            f"mesh.file={json.dumps(mesh_file)}",
            f"time.duration={duration!r}",
            'trajectory.file="liver_robot.csv"',
            *overrides,
        ],
    )
    models = build_models(scene)
    controls, mesh = build_controls(scene, models), models.mesh
    points = np.vstack([TARGET[None], TARGET + np.outer(DEPTH - DEPTHS, [0.0, 1.0, 0.0])])
    tets, barycentric = TetLocator(mesh.rest_positions, mesh.tets).locate(points)
    body, state, dt = TissueBody(models.tissue), models.tissue.rest_state(), scene.time.dt
    for index in range(1, scene.time.step_count + 1):
        free, system = body.free_motion(state, controls.at(index * dt), dt)
        state = body.correct(system, state, free, None, np.zeros(0), dt)
    nodes = mesh.tets[np.maximum(tets, 0)]
    moved = np.einsum("pk,pkd->pd", barycentric, state.positions[nodes] - mesh.rest_positions[nodes])
    relative = np.linalg.norm((moved[1:] - moved[0])[:, [0, 2]], axis=1)
    return np.where(tets[1:] >= 0, relative, np.nan).tolist()


def main(argv=None) -> int:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fine", type=float, help="also a phantom generated at this size [m] (needs gmsh)")
    parser.add_argument("--ring", type=float, help="also every mesh with the ring radius held at this [m]")
    parser.add_argument(
        "--duration", type=float, default=1.45, help="[s]; the first inhale's peak is at 1.4 s"
    )
    parser.add_argument("--free", action="store_true", help="also the tissue's own motion along the needle")
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], help="section.key=value (both needles' scene)"
    )
    parser.add_argument("--output", type=Path, default=OUTPUT / "mesh_load.json")
    args = parser.parse_args(argv)
    meshes = {
        "coarse (20 mm)": "../mesh/data/liver_phantom_coarse.vtu",
        "medium (9 mm)": "../mesh/data/liver_phantom_medium.vtu",
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    if args.fine:
        from refsim.mesh import generate_liver_phantom, write_mesh

        path = args.output.parent / f"liver_phantom_{1e3 * args.fine:g}mm.vtu"
        if not path.is_file():
            write_mesh(path, generate_liver_phantom(args.fine))
        meshes[f"generated ({1e3 * args.fine:g} mm)"] = str(path)
    data = json.loads(args.output.read_text()) if args.output.is_file() else {}
    for label, mesh_file in meshes.items():
        run = run_load(mesh_file, args.duration, args.overrides)
        data.setdefault("default", {})[label] = run
        print(
            f"{label}: largest ‖t‖/L_in {run['load']:.2f} N/m at t = {run['time']:.2f} s, "
            f"L_in = {1e3 * run['inserted_length']:.1f} mm ({run['seconds']:.0f} s)",
            flush=True,
        )
        if args.free:
            data.setdefault("free_motion", {})[label] = free_motion(mesh_file, args.duration, args.overrides)
            print(
                f"  tissue across the needle, relative to the target [mm]: "
                f"{np.round(1e3 * np.array(data['free_motion'][label]), 3).tolist()}",
                flush=True,
            )
        args.output.write_text(json.dumps(data, indent=1))
    if args.ring:
        from refsim.constraints import coupling

        default = coupling.coupling_radius

        def held(needle_radius, mesh_size):
            return np.maximum(default(needle_radius, mesh_size), args.ring)

        coupling.coupling_radius = held  # the ring and its sub-grid annulus read it
        try:
            for label, mesh_file in meshes.items():
                run = run_load(mesh_file, args.duration, args.overrides)
                data.setdefault(f"ring {1e3 * args.ring:g} mm", {})[label] = run
                print(f"{label}, ring held at {1e3 * args.ring:g} mm: {run['load']:.2f} N/m", flush=True)
                args.output.write_text(json.dumps(data, indent=1))
        finally:
            coupling.coupling_radius = default
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
