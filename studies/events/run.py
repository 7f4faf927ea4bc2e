"""Event steps against the solver tolerance, with the margins the runs report (issue 24, item 7).

A reference gives one answer as the tolerance goes to zero, or says with the run that an event sits on a knife
edge and how far it can move (refsim.simulation.margins). Each scenario runs with Gauss–Seidel and the exact
solver at tolerances 1e-4 … 1e-12; for every run the events' steps and the margin each event reports (its
criterion against its threshold at the event step and the step before, the solver's accuracy, the steps it
could move, the knife-edge flag).

Scenarios (each small enough to run the whole sweep on one core):

- ``cube_cut``: cube_cut on 4³ cells, the stroke of tests/simulation/test_life_cycle.py (inserted 19 mm, cut
  8 mm along +x): puncture, cut start, tears.
- ``cube_tilted``: the cube on 4³ cells, the needle tilted 33.5° from the top face's normal (tan θ = 0.66)
  with μ_p = 0.7, the tip pressed in at 0.47 mm/s, dt = 1 ms (the liver entries' numbers on the cube).
- ``cube_stick_limit``: the same entry with μ_p half an accuracy below the friction ratio a stuck tip carries
  there (measured by a first run with μ_p = 2, as tests/simulation/test_margins.py does): the tip at the
  edge of stick.
- ``liver_tilted_±x``, ``liver_tilted_±z``: liver_rigid on the coarse phantom (its breathing kept), the needle
  tilted 33.5° from the anterior face's normal at the robot's entry point towards ±x or ±z, μ_p = 0.7,
  inserted at 20 mm/s for 0.8 s; ``liver_slow_tilted_…``: the same entries pressed in at 4 mm/s from 0.1 mm
  before the face for 1 s, so that the tip's contact loads over tens of steps before the puncture.

    python studies/events/run.py [--output studies/events/output] [--quick]

Writes output/summary.json, docs/figures/event_tolerance.png and docs/event_sensitivity.md (generated: do not
edit by hand).
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
TOLERANCES = (1e-4, 1e-6, 1e-8, 1e-10, 1e-12)
METHODS = ("gauss_seidel", "exact")
THETA = 33.5  # degrees from the surface normal: tan θ = 0.662
MU = 0.7
#: Directions the liver entries tilt towards (projected on the anterior face), by name.
LIVER_TILTS = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0)}
CUBE_ENTRY, CUBE_TOP, CUBE_NEEDLE = (0.00123, 0.00231), 0.1, 0.32


def _vector(values) -> str:
    return "[" + ", ".join(repr(float(x)) for x in values) + "]"


def _tilted(normal: np.ndarray, theta_degrees: float, towards=(1.0, 0.0, 0.0)) -> np.ndarray:
    """The unit direction θ from −normal, turned towards ``towards`` projected on the face."""
    normal = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    towards = np.asarray(towards, dtype=float)
    tangent = towards - (towards @ normal) * normal
    tangent /= np.linalg.norm(tangent)
    theta = np.radians(theta_degrees)
    return -np.cos(theta) * normal + np.sin(theta) * tangent


def cube_cut_overrides() -> list[str]:
    knots = [(0.00123, 0.422), (0.00123, 0.403), (0.00123, 0.403), (0.00923, 0.403), (0.00923, 0.403)]
    times = [0.0, 1.9, 2.0, 2.8, 3.0]
    bases = "[" + ", ".join(f"[{x!r}, 0.00231, {z!r}]" for x, z in knots) + "]"
    return [
        "mesh.cells=[4, 4, 4]",
        f"trajectory.times={times!r}",
        f"trajectory.base_positions={bases}",
        "trajectory.directions=[" + ", ".join(["[0, 0, -1]"] * len(times)) + "]",
        f"time.duration={times[-1]}",
    ]


def cube_tilted_overrides(mu: float) -> list[str]:
    direction = _tilted(np.array([0.0, 0.0, 1.0]), THETA)
    top = np.array([*CUBE_ENTRY, CUBE_TOP])
    bases = [top + d * direction - CUBE_NEEDLE * direction for d in (-1e-9, 7e-5)]
    return [
        "mesh.cells=[4, 4, 4]",
        "time.dt=0.001",
        "time.duration=0.15",
        "trajectory.times=[0.0, 0.15]",
        f"trajectory.base_positions=[{_vector(bases[0])}, {_vector(bases[1])}]",
        f"trajectory.directions=[{_vector(direction)}, {_vector(direction)}]",
        f"insertion.surface_friction_coefficient={mu!r}",
    ]


def liver_trajectory(path: Path, towards, *, speed: float = 0.02, gap: float = 0.002, duration=0.8) -> None:
    """A straight tilted insertion into the coarse phantom at the robot's entry point, the tip ``gap`` [m]
    before the face at t = 0 and moving at ``speed`` [m/s] for ``duration`` [s], as a CSV file."""
    from refsim.geometry.closest import closest_points_on_triangles, triangle_normals
    from refsim.scene import load_scene
    from refsim.scene.build import build_models

    scene = load_scene("liver_rigid")
    mesh = build_models(scene).mesh
    robot = ROOT / "refsim" / "scenes" / "liver_robot.csv"
    samples = np.loadtxt(robot, delimiter=",", comments="#", skiprows=3)
    base, along = samples[0, 1:4], samples[0, 4:7]
    entry = base + (scene.needle.length + 0.002) * along  # the robot starts 2 mm before the face
    triangles = np.asarray(mesh.rest_positions)[np.asarray(mesh.boundary_faces)]
    closest, _ = closest_points_on_triangles(np.repeat(entry[None], len(triangles), axis=0), triangles)
    face = int(np.argmin(np.linalg.norm(closest - entry, axis=1)))
    entry = closest[face]
    normal = triangle_normals(triangles[face : face + 1])[0]
    direction = _tilted(normal, THETA, towards)
    times = np.linspace(0.0, duration, 17)
    tips = entry[None] + (-gap + speed * times)[:, None] * direction
    bases = tips - scene.needle.length * direction
    rows = np.column_stack([times, bases, np.repeat(direction[None], len(times), axis=0)])
    header = "tilted entry of studies/events/run.py\n\nt,x,y,z,dx,dy,dz"
    np.savetxt(path, rows, delimiter=",", header=header, comments="# ", fmt="%.12g")
    # the reader skips '#' lines; the column line must not be commented
    text = path.read_text().replace("# t,x,y,z,dx,dy,dz", "t,x,y,z,dx,dy,dz")
    path.write_text(text)


def liver_overrides(trajectory: Path, duration: float = 0.8) -> list[str]:
    return [
        f"trajectory.file={json.dumps(str(trajectory))}",
        f"time.duration={duration!r}",
        f"insertion.surface_friction_coefficient={MU!r}",
    ]


def one_run(scene_name: str, overrides: list[str], method: str, tolerance: float) -> dict:
    from refsim.scene import load_scene
    from refsim.simulation import Simulation
    from refsim.simulation.margins import CriterionSeries, assess

    settings = [
        f'solver.method="{method}"',
        f"solver.tolerance={tolerance!r}",
        "solver.max_iterations=200000",
    ]
    scene = load_scene(scene_name, [*overrides, *settings])
    records = []
    started = time.perf_counter()
    Simulation(scene).run(on_step=lambda state, record: records.append(record))
    seconds = time.perf_counter() - started
    events = [(r.step, e.name) for r in records for e in r.events]
    series = CriterionSeries.of(
        [r.step for r in records for _ in r.criteria], [c for r in records for c in r.criteria]
    )
    margins = assess(events, series)
    solved = [r.solver for r in records if r.solver is not None]
    return {
        "method": method,
        "tolerance": tolerance,
        "events": events,
        "margins": [
            {
                "step": m.step,
                "name": m.name,
                "value": None if m.at_event is None else float(m.at_event.value),
                "before": None if m.before is None else float(m.before.value),
                "threshold": None if m.at_event is None else float(m.at_event.threshold),
                "accuracy": None if m.at_event is None else float(m.at_event.accuracy),
                "unit": None if m.at_event is None else m.at_event.unit,
                "earlier": m.earlier,
                "later": m.later,
                "knife_edge": m.knife_edge,
                "feeding": list(m.feeding),
                "text": m.text(),
            }
            for m in margins
        ],
        "unconverged": sum(not s.converged for s in solved),
        "max_residual": max((float(s.residual) for s in solved), default=0.0),
        "seconds": seconds,
        "steps": len(records),
        "series": {n: series_of(series, n) for n in ("puncture", "tip_slip")},
    }


def series_of(series, name: str) -> list:
    chosen = series.name == name
    return np.column_stack(
        [series.step[chosen], series.value[chosen], series.threshold[chosen], series.accuracy[chosen]]
    ).tolist()


def stick_limit_mu() -> float:
    """μ_p half an accuracy below the friction ratio of the stuck tip the step before its puncture (a
    first run with μ_p = 2)."""
    run = one_run("cube", cube_tilted_overrides(2.0), "gauss_seidel", 1e-8)
    (puncture,) = [m for m in run["margins"] if m["name"] == "puncture"]
    ratio = {int(s): (v, a) for s, v, _, a in run["series"]["tip_slip"]}
    value, accuracy = ratio[puncture["step"] - 1]
    return float(value - 0.5 * accuracy)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=ROOT / "studies" / "events" / "output")
    parser.add_argument("--quick", action="store_true", help="tolerances 1e-4 and 1e-8 only")
    parser.add_argument("--only", nargs="*", help="scenarios to run (default: all)")
    args = parser.parse_args()
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    args.output.mkdir(parents=True, exist_ok=True)
    tolerances = (1e-4, 1e-8) if args.quick else TOLERANCES
    summary_path = args.output / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    trajectories = {}
    for name, towards in LIVER_TILTS.items():
        trajectories[name] = args.output / f"liver_tilted_{name}.csv"
        liver_trajectory(trajectories[name], towards)
        trajectories[f"slow_{name}"] = args.output / f"liver_slow_tilted_{name}.csv"
        liver_trajectory(trajectories[f"slow_{name}"], towards, speed=0.004, gap=1e-4, duration=1.0)
    scenarios = {
        "cube_cut": ("cube_cut", cube_cut_overrides),
        "cube_tilted": ("cube", lambda: cube_tilted_overrides(MU)),
        "cube_stick_limit": ("cube", lambda: cube_tilted_overrides(stick_limit_mu())),
        **{
            f"liver_tilted_{name}": ("liver_rigid", lambda name=name: liver_overrides(trajectories[name]))
            for name in LIVER_TILTS
        },
        **{
            f"liver_slow_tilted_{name}": (
                "liver_rigid",
                lambda name=name: liver_overrides(trajectories[f"slow_{name}"], 1.0),
            )
            for name in LIVER_TILTS
        },
    }
    for label, (scene_name, make) in scenarios.items():
        if args.only and label not in args.only:
            continue
        overrides = make()
        runs = []
        for tolerance in tolerances:
            for method in METHODS:
                run = one_run(scene_name, overrides, method, tolerance)
                head = f"{label} {method} {tolerance:g}: {run['events'][:4]} ({run['seconds']:.1f} s)"
                print(head, flush=True)
                for margin in run["margins"][:3]:
                    print("   ", margin["text"], flush=True)
                runs.append(run)
        summary[label] = {"scene": scene_name, "overrides": overrides, "runs": runs}
        summary_path.write_text(json.dumps(summary, indent=1))
    sys.path.insert(0, str(Path(__file__).parent))
    from plot import main as plot

    plot(summary_path)


if __name__ == "__main__":
    main()
