"""The exact mode's price per step: solve-stage milliseconds of a scene run with Gauss–Seidel and with the
exact solver, measured in one process, the two modes alternated.

Usage::

    python studies/solvers/exact_mode.py [--scenes cube cube_cut] [--repeats 3] [--slowest 10]

Each scene runs once per mode to load the compiled kernels, then ``repeats`` times per mode, alternating.
Printed per scene and mode: the solve stage's mean ms per step of each run, their median, and the mean over
steps of each step's fastest run (the least sensitive to other jobs on a shared machine: every step is solved
the same way in every run); the paths that answered, the unconverged steps, the mean iterations (sweeps, or
Newton iterations plus pre-sweeps); then the ratio exact / Gauss–Seidel of both measures. The machine's load
average is printed with it.
"""

from __future__ import annotations

import os

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import argparse  # noqa: E402
import re  # noqa: E402

import numpy as np  # noqa: E402

from refsim.scene import load_scene  # noqa: E402
from refsim.simulation import Simulation  # noqa: E402

MODES = {
    "gauss_seidel": ["solver.method=gauss_seidel"],
    "exact": ["solver.method=exact", "solver.exact_method=auto"],
}


def run_once(scene_name: str, mode: str, steps: int | None = None):
    """(solve seconds per step, paths count, unconverged steps, mean iterations) of one run; the iterations
    are Gauss–Seidel sweeps for Gauss–Seidel, and Newton iterations + Gauss–Seidel pre-sweeps (counted from
    the report's message, "N Gauss-Seidel pre-sweep(s)") for the exact solver."""
    records = []
    Simulation(load_scene(scene_name, MODES[mode])).run(steps=steps, on_step=lambda s, r: records.append(r))
    seconds = np.array([r.stage_seconds.get("solve", 0.0) for r in records])
    reports = [r.solver for r in records if r.solver is not None]
    paths: dict[str, int] = {}
    for report in reports:
        paths[report.path] = paths.get(report.path, 0) + 1
    unconverged = sum(not report.converged for report in reports)
    iterations = (
        float(np.mean([report.iterations + _presweeps(report.message) for report in reports]))
        if reports
        else 0.0
    )
    steps = [
        (
            r.step,
            r.row_forces.size,
            "-" if r.solver is None else r.solver.path,
            0 if r.solver is None else r.solver.iterations,
            0 if r.solver is None else _presweeps(r.solver.message),
        )
        for r in records
    ]
    return seconds, paths, unconverged, iterations, steps


def _presweeps(message: str) -> int:
    found = re.search(r"(\d+) Gauss-Seidel pre-sweep", message)
    return int(found.group(1)) if found else 0


def measure(scene_name: str, repeats: int) -> dict:
    for mode in MODES:
        run_once(scene_name, mode, steps=40)  # compiled kernels loaded
    runs = {mode: [] for mode in MODES}
    info = {}
    for _ in range(repeats):
        for mode in MODES:
            seconds, paths, unconverged, iterations, steps = run_once(scene_name, mode)
            runs[mode].append(seconds)
            info[mode] = (paths, unconverged, iterations, steps)
    result = {}
    for mode in MODES:
        table = np.array(runs[mode])
        result[mode] = {
            "run_means_ms": (table.mean(axis=1) * 1e3).tolist(),
            "median_ms": float(np.median(table.mean(axis=1)) * 1e3),
            "fastest_per_step_ms": float(table.min(axis=0).mean() * 1e3),
            "paths": info[mode][0],
            "unconverged": info[mode][1],
            "iterations": info[mode][2],
            "per_step_ms": table.min(axis=0) * 1e3,
            "steps": info[mode][3],
        }
    return result


def print_slowest(scene_name: str, result: dict, count: int) -> None:
    """The ``count`` steps of the largest exact time (fastest of the runs), with Gauss–Seidel's time of the
    same step, the rows, the exact path, Newton iterations and pre-sweeps, and their share of the exact run's
    time."""
    exact, gs = result["exact"], result["gauss_seidel"]
    order = np.argsort(exact["per_step_ms"])[::-1][:count]
    share = exact["per_step_ms"][order].sum() / exact["per_step_ms"].sum()
    print(f"{scene_name}: {count} slowest exact steps ({100 * share:.0f} % of the exact solve time)")
    for index in order:
        step, rows, path, newton, swept = exact["steps"][index]
        print(
            f"  step {step}: exact {exact['per_step_ms'][index]:.3f} ms, Gauss-Seidel "
            f"{gs['per_step_ms'][index]:.3f} ms, {rows} rows, {path}, {newton} Newton iteration(s), "
            f"{swept} pre-sweep(s)"
        )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["cube", "cube_cut"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--slowest", type=int, default=0, help="also list the N slowest exact steps")
    args = parser.parse_args(argv)
    print(f"load average at start {os.getloadavg()[0]:.2f}")
    for scene_name in args.scenes:
        result = measure(scene_name, args.repeats)
        for mode, row in result.items():
            print(
                f"{scene_name} {mode}: solve ms/step per run {[round(v, 3) for v in row['run_means_ms']]}, "
                f"median {row['median_ms']:.3f}, fastest per step {row['fastest_per_step_ms']:.3f}; "
                f"paths {row['paths']}, unconverged {row['unconverged']}, mean iterations "
                f"{row['iterations']:.2f}"
            )
        gs, exact = result["gauss_seidel"], result["exact"]
        print(
            f"{scene_name} exact / Gauss-Seidel: median {exact['median_ms'] / gs['median_ms']:.2f}, "
            f"fastest per step {exact['fastest_per_step_ms'] / gs['fastest_per_step_ms']:.2f}"
        )
        if args.slowest:
            print_slowest(scene_name, result, args.slowest)
    print(f"load average at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
