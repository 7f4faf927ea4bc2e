"""Wall time of one 16-run study on 1 and on 2 Dask workers (LocalCluster), measured in one session.

The study: the cube on 4³ cells (2.2 s, 220 steps), insertion.spacing × solver.tolerance, 4 × 4 runs, without
the warm-up run. Each timing is the wall time of ``run_study`` from a fresh output folder, the cluster's start
included (``refsim study`` as a user runs it). The worker counts alternate (1, 2, 1, 2, ...) so that a change
of the machine's load during the session falls on both.

    python studies/scaling/run.py [--workers 1 2] [--repeat 2] [--output /tmp/refsim_scaling]

Prints one line per timing and the load average before and after; writes nothing else.
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
from pathlib import Path

SWEEPS = ("insertion.spacing=1e-3,7e-4,5e-4,3e-4", "solver.tolerance=1e-4,1e-6,1e-8,1e-10")
SET = ("mesh.cells=[4, 4, 4]", "output.tissue_every=1000")


def study():
    from refsim.sweep import StudySpec, parse_sweep

    return StudySpec(
        name="scaling",
        scene="cube",
        sweeps=tuple(parse_sweep(text) for text in SWEEPS),
        overrides=SET,
        quantities=("needle_force@end", "puncture_force"),
    )


def main(argv: list[str] | None = None) -> None:
    from refsim.sweep import run_study

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--output", default="/tmp/refsim_scaling")
    args = parser.parse_args(argv)
    spec = study()
    print(f"{len(spec.runs())} runs; load average before: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    for repeat in range(args.repeat):
        for workers in args.workers:
            folder = Path(args.output) / f"w{workers}_{repeat}"
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir(parents=True)
            start = time.perf_counter()
            result = run_study(spec, folder / "scaling.h5", workers=workers, progress=False, warm_up=False)
            seconds = time.perf_counter() - start
            complete = result["attributes"]["runs_complete"]
            print(
                f"workers {workers}  repeat {repeat}: {seconds:6.1f} s wall, {complete}/{len(spec.runs())} "
                f"complete, load {os.getloadavg()[0]:.2f}"
            )
    print(f"load average after: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
