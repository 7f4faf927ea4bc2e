"""The critical needle stiffness against the breathing amplitude (issue 13, "beyond the paper").

For each breathing amplitude the robot's compensating motion is recomputed (studies/liver/make_trajectory.py's
target and insertion), then the liver scene runs without cutting for each needle modulus E; the quantity of
interest is the cut criterion's load, the largest shaft lateral force per inserted length q = ‖t‖/L_in [N/m]
(the energy law cuts when q reaches G_c). The critical modulus E_c(a) is where q(E) = G_c, interpolated in
log E; a clinician reads it as "needles stiffer than E_c tear the liver at this breathing amplitude".

    python studies/liver_stiffness/run.py [--output DIR] [--quick] [--workers N] [--amplitudes MM ...]
        [--moduli GPA ...]

Writes summary.json (a row per run: amplitude, E, q_max, the step of q_max, ms per step) and the run's HDF5
files; plot.py draws docs/figures/liver_stiffness.png. Runs on 2 processes, one BLAS thread each.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "studies" / "liver"))


def shaft_load(records, states, tets, needle_geometry, puncture_force: float) -> tuple[float, int]:
    """Largest ‖t‖ / L_in over the run [N/m] and its step: t the insertion rows' lateral force without the
    entry point's rows (the energy law's cut-start load), L_in the needle's length below the entry point as
    the cut-start event measures it (EventRules._cut_starts), over L_in > 1 cm (below it the load per length
    is the surface's); ``puncture_force``: the scene's f_p, the entry point's allowance."""
    from refsim.simulation.events import shaft_lateral_force

    best, at = 0.0, -1
    for record, state in zip(records, states, strict=False):
        if state.path.point_count == 0 or state.phase != "insertion":
            continue
        force = shaft_lateral_force(
            record.row_source,
            record.row_kind,
            record.row_directions,
            record.row_forces,
            without_entry=True,
            surface_allowance=puncture_force,
            points=record.row_point,
        )
        entry = state.path.positions(state.tissue.positions, tets)[:1]
        needle = needle_geometry(state.needle)
        length = needle.length - float(needle.project(entry)[0][0])
        if length > 0.01 and np.linalg.norm(force) / length > best:
            best, at = float(np.linalg.norm(force) / length), record.step
    return best, at


def one_run(amplitude: float, modulus: float, trajectory: str, output: str) -> dict:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from refsim.scene import load_scene
    from refsim.simulation import Simulation

    scene = load_scene(
        "liver_rigid",
        [
            f"needle.youngs_modulus={modulus}",
            f"boundary.amplitude=[0, 0, {-amplitude}]",
            f"trajectory.file={json.dumps(trajectory)}",
            "cutting.enabled=false",
        ],
    )
    simulation = Simulation(scene)
    records, states = [], []
    started = time.perf_counter()
    simulation.run(on_step=lambda s, r: (records.append(r), states.append(s)))
    seconds = time.perf_counter() - started
    load, step = shaft_load(
        records,
        states,
        simulation.tets,
        simulation.event_rules.needle_geometry,
        scene.insertion.puncture_force,
    )
    return {
        "amplitude": amplitude,
        "youngs_modulus": modulus,
        "q_max": load,
        "step": step,
        "ms_per_step": 1e3 * seconds / len(records),
        "fracture_energy": load_scene("liver_rigid").cutting.fracture_energy,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=ROOT / "studies" / "liver_stiffness" / "output")
    parser.add_argument("--quick", action="store_true", help="2 amplitudes x 3 moduli")
    parser.add_argument("--workers", type=int, default=2, help="processes (one BLAS thread each)")
    parser.add_argument("--amplitudes", type=float, nargs="+", help="breathing amplitudes [mm]")
    parser.add_argument("--moduli", type=float, nargs="+", help="needle moduli [GPa]")
    args = parser.parse_args(argv)
    args.output.mkdir(parents=True, exist_ok=True)
    amplitudes = [0.010, 0.020] if args.quick else [0.010, 0.015, 0.020]
    moduli = [25e9, 100e9, 400e9] if args.quick else [25e9, 50e9, 100e9, 200e9, 400e9]
    amplitudes = [a * 1e-3 for a in args.amplitudes] if args.amplitudes else amplitudes
    moduli = [e * 1e9 for e in args.moduli] if args.moduli else moduli
    import make_trajectory

    from refsim.simulation.robot import compensating_trajectory, write_trajectory_csv

    jobs = []
    for amplitude in amplitudes:
        scene = make_trajectory._scene_without_trajectory("liver_rigid")
        from dataclasses import replace

        scene = replace(scene, boundary=replace(scene.boundary, amplitude=(0.0, 0.0, -amplitude)))
        trajectory = compensating_trajectory(
            scene,
            target=make_trajectory.TARGET,
            direction=make_trajectory.DIRECTION,
            start_gap=make_trajectory.START_GAP,
            depth=make_trajectory.DEPTH,
            speed=make_trajectory.SPEED,
            sample_count=401,
        )
        path = write_trajectory_csv(trajectory, args.output / f"robot_{amplitude * 1e3:g}mm.csv")
        jobs += [(amplitude, modulus, str(path), str(args.output)) for modulus in moduli]
    started = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        rows = list(pool.map(one_run, *zip(*jobs, strict=False)))
    summary = {
        "rows": rows,
        "wall_seconds": time.perf_counter() - started,
        "workers": args.workers,
        "blas_threads": 1,
    }
    (args.output / "summary.json").write_text(json.dumps(summary, indent=1))
    for row in rows:
        print(
            f"a = {row['amplitude'] * 1e3:4.0f} mm  E = {row['youngs_modulus'] / 1e9:5.0f} GPa  "
            f"q_max = {row['q_max']:6.1f} N/m (step {row['step']})  {row['ms_per_step']:.0f} ms/step"
        )
    print(f"{len(rows)} runs in {summary['wall_seconds']:.0f} s on {args.workers} workers")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
