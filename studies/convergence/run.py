"""Convergence of the quantities of interest under d_i, d_c and mesh refinement, on cube and cube_cut.

Each ``*.toml`` beside this script is a study file (refsim.sweep); this runs them on Dask (a LocalCluster with
one worker per core by default) into ``--output`` (one study file ``NAME.h5`` each, runs in ``NAME_runs/``).
Resumable: run it again after an interruption and only the missing runs are done.

    python studies/convergence/run.py [--output studies/convergence/output] [--workers N | --scheduler ADDR]
                                      [--only cube_mesh ...] [--quick]

``--quick`` (for tests): the cube's d_i and mesh sweeps only, three levels, 0.4 s, on 2 to 4 cells.
``--liver``: also the d_i and d_c sweeps of ``liver/`` (liver_rigid, liver_flexible on the coarse phantom, the
whole trajectory: 12 runs of about 1 min each on one core; the phantom has two mesh levels only, too few for
an order); with ``--only liver_rigid_spacing liver_rigid_point_spacing liver_flexible_spacing`` the liver
alone.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

HERE = Path(__file__).resolve().parent


def studies(quick: bool, only=None, liver: bool = False) -> list:
    from refsim.sweep import Sweep, load_study

    paths = sorted(HERE.glob("*.toml")) + (sorted((HERE / "liver").glob("*.toml")) if liver else [])
    specs = [load_study(path) for path in paths]
    if only:
        specs = [spec for spec in specs if spec.name in only]
    if not quick:
        return specs
    short = ("time.duration=0.4", "output.tissue_every=10")
    quick_specs = []
    for spec in specs:
        if spec.scene != "cube" or spec.sweeps[0].key not in ("insertion.spacing", "mesh.cells"):
            continue
        sweep = spec.sweeps[0]
        values = (2, 3, 4) if sweep.key == "mesh.cells" else sweep.values[:3]
        base = short if sweep.key == "mesh.cells" else short + ("mesh.cells=[3, 3, 3]",)
        quick_specs.append(
            dataclasses.replace(
                spec,
                name=spec.name + "_quick",
                overrides=base,
                sweeps=(Sweep(sweep.key, tuple(values), sweep.measure),),
            )
        )
    return quick_specs


def main(argv: list[str] | None = None) -> None:
    from refsim.sweep import run_study
    from refsim.sweep.study import start_client

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", default=str(HERE / "output"))
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--scheduler", default=None)
    parser.add_argument("--only", nargs="+", help="study names (the .toml stems)")
    parser.add_argument("--quick", action="store_true", help="small and short (for tests)")
    parser.add_argument(
        "--liver", action="store_true", help="also the liver sweeps of liver/ (12 runs, about 1 min each)"
    )
    parser.add_argument("-q", "--quiet", action="store_true")
    args = parser.parse_args(argv)
    output = Path(args.output)
    output.mkdir(parents=True, exist_ok=True)
    client, cluster = start_client(args.scheduler, args.workers)
    try:
        for spec in studies(args.quick, args.only, args.liver):
            study = run_study(
                spec,
                output / f"{spec.name}.h5",
                client=client,
                warm_up=not args.quick,
                progress=not args.quiet,
            )
            print(
                f"{spec.name}: {study['attributes']['runs_complete']}/{study['attributes']['runs_total']} "
                f"complete"
            )
            for row in study["convergence"]:
                print(
                    f"  {row['quantity']:<28} {row['kind']:<11} p = {row['order']:6.3f}  "
                    f"f_ext = {row['extrapolated']:.6g}  GCI = {100 * row['gci']:.3g} %"
                )

    finally:
        client.close()
        if cluster is not None:
            cluster.close()


if __name__ == "__main__":
    main()
