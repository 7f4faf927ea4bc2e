"""The `refsim` command line: run, verify, bench, render, plot, study, export.

Exit codes: 0 success; 1 a verification case failed; 2 bad input (scene, file, option); 3 the simulation
stopped on a detected error (the results file keeps every completed step); 130 interrupted (same).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

__all__ = ["main"]

logger = logging.getLogger("refsim")

EXIT_FAILED, EXIT_INPUT, EXIT_SIMULATION, EXIT_INTERRUPTED = 1, 2, 3, 130


class _Progress:
    """A one-line progress bar on stderr (only when stderr is a terminal, or every 10% otherwise)."""

    def __init__(self, total: int, enabled: bool = True) -> None:
        self.total, self.enabled, self.start = total, enabled, time.perf_counter()
        self.tty = sys.stderr.isatty()
        self._last_decile = -1

    def update(self, done: int, phase: str) -> None:
        if not self.enabled:
            return
        elapsed = time.perf_counter() - self.start
        rate = done / elapsed if elapsed > 0 else 0.0
        fraction = done / self.total
        if self.tty:
            bar = "#" * int(30 * fraction)
            sys.stderr.write(f"\r[{bar:<30}] {done}/{self.total} steps  {rate:5.1f} steps/s  {phase:<9}")
            if done == self.total:
                sys.stderr.write("\n")
            sys.stderr.flush()
        elif int(10 * fraction) > self._last_decile:
            self._last_decile = int(10 * fraction)
            sys.stderr.write(f"{done}/{self.total} steps ({100 * fraction:.0f}%), {rate:.1f} steps/s, {phase}\n")


def _cmd_run(args: argparse.Namespace) -> int:
    from refsim.io import ResultWriter
    from refsim.scene import load_scene
    from refsim.simulation import Simulation, SimulationError
    from refsim.simulation.summary import RunSummary

    scene = load_scene(args.scene, args.set or ())
    output = Path(args.output)
    if output.exists() and not args.overwrite:
        raise ValueError(f"{output}: the results file exists; pass --overwrite to replace it")
    simulation = Simulation(scene)  # every input error surfaces here, before any file is written
    steps = scene.time.step_count
    progress = _Progress(steps, enabled=not args.quiet)
    summary = RunSummary()
    output.parent.mkdir(parents=True, exist_ok=True)
    status = 0
    with ResultWriter(output, scene, simulation.models, overwrite=args.overwrite) as writer:

        written_cut = [None]

        def on_step(state, record) -> None:
            writer.append(record)
            if state.cut is not None and state.cut is not written_cut[0]:
                # The cut changed in this step: rewrite its history now, so an interrupted run keeps it too.
                writer.write_cut_surface(*_cut_history(state.cut), tet_indices=state.cut.tet_indices,
                                         barycentric=state.cut.barycentric)
                written_cut[0] = state.cut
            summary.add(record)
            progress.update(record.step, record.phase)

        try:
            simulation.run(on_step=on_step)
        except SimulationError as error:
            print(f"refsim run: {error}", file=sys.stderr)
            status = EXIT_SIMULATION
        except KeyboardInterrupt:
            print(f"\nrefsim run: interrupted; {summary.steps} completed steps kept in {output}", file=sys.stderr)
            status = EXIT_INTERRUPTED
    print(f"scene {scene.name} ({scene.source}) -> {output}")
    _write_sidecar(output)
    print(summary.format())
    print(summary.format_table())
    if args.figure and status == 0:
        from refsim.viz import plot_result, render_result

        figure = Path(args.figure)
        figure.parent.mkdir(parents=True, exist_ok=True)
        render_result(output, figure)
        plot_path = figure.with_name(figure.stem + "_forces" + figure.suffix)
        plot_result(output, plot_path)
        print(f"figures: {figure}, {plot_path}")
    return status


def _write_sidecar(output: Path) -> None:
    """The ParaView sidecar (RESULT.xdmf) of a results file; a failure is reported, never fatal to the run."""
    from refsim.io.xdmf import write_xdmf

    try:
        print(f"ParaView: {write_xdmf(output)}")
    except (OSError, ValueError) as error:
        print(f"refsim: no XDMF sidecar for {output}: {error}", file=sys.stderr)


def _cmd_study(args: argparse.Namespace) -> int:
    """`refsim study`: a study file, or a scene with --sweep options, run on Dask."""
    from refsim.sweep import load_study, run_study, study_from_options

    target = Path(args.target)
    is_study_file = target.suffix == ".toml" and target.is_file() and args.sweep is None
    if is_study_file:
        spec = load_study(target)
        if args.set:
            import dataclasses

            spec = dataclasses.replace(spec, overrides=tuple(spec.overrides) + tuple(args.set))
    else:
        if not args.sweep:
            raise ValueError(f"{args.target}: give --sweep section.key=v1,v2,... (or a study file .toml)")
        spec = study_from_options(args.target, args.sweep, combine="zip" if args.zip else "product",
                                  overrides=args.set or (), quantities=args.quantity,
                                  reference=args.reference, name=args.name)
    output = Path(args.output) if args.output else Path(f"{spec.name}_study.h5")
    study = run_study(spec, output, scheduler=args.scheduler, workers=args.workers, progress=not args.quiet)
    runs = study["runs"]
    print(f"study {spec.name}: {len(runs['id'])} runs, {study['attributes']['runs_complete']} complete, "
          f"{study['attributes']['runs_failed']} failed -> {output}")
    for row in study["convergence"]:
        print(f"  {row['key']:<22} {row['quantity']:<26} {row['kind']:<11} order {row['order']:7.3f}  "
              f"extrapolated {row['extrapolated']:.6g}  GCI {100 * row['gci']:.3g}%")
    return 0 if study["attributes"]["runs_failed"] == 0 else EXIT_SIMULATION


def _cmd_export(args: argparse.Namespace) -> int:
    """`refsim export`: ParaView sidecar, reference problems (problem set, FCLib) and the force CSV."""
    from refsim.io.export import export_force_csv, export_problems
    from refsim.io.xdmf import write_xdmf

    result = Path(args.result)
    if not (args.xdmf or args.problems or args.csv):
        raise ValueError("refsim export: choose at least one of --xdmf, --problems OUT.h5, --csv OUT.csv")
    if args.xdmf:
        print(f"wrote {write_xdmf(result)}")
    if args.problems:
        summary = export_problems(result, args.problems, fclib_folder=args.fclib)
        print(f"wrote {summary['problems']} problems with their exact solutions to {args.problems}"
              + (f"; {len(summary['fclib'])} FCLib files in {args.fclib}" if args.fclib else ""))
        if summary["unconverged"]:
            print(f"  exact solve above tolerance at steps {summary['unconverged']}", file=sys.stderr)
    if args.csv:
        print(f"wrote {export_force_csv(result, args.csv)}")
    return 0


def _cut_history(cut):
    return cut.rest_points, cut.created_step, cut.triangles, cut.triangle_created_step


def _cmd_verify(args: argparse.Namespace) -> int:
    from refsim.verification import format_table, run_cases

    results = run_cases()
    print(format_table(results))
    failed = [r for r in results if not r.passed]
    print(f"{len(results) - len(failed)} passed, {len(failed)} failed")
    return EXIT_FAILED if failed else 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from refsim.scene import load_scene
    from refsim.simulation import Simulation
    from refsim.simulation.summary import RunSummary

    if args.scene:
        scene = load_scene(args.scene, args.set or ())
        simulation = Simulation(scene)
        summary = RunSummary()
        simulation.run(on_step=lambda state, record: summary.add(record))
        print(f"scene {scene.name}: solver {scene.solver.method}, tolerance {scene.solver.tolerance:g}")
        print(summary.format_table())
        if summary.cut_points:
            print(summary.format_cut())
    if args.tissue or not args.scene:
        from refsim.fem.bench import bench_tissue

        print("tissue model, 0.1 m cube (ms): co-rotational update, assembly, factorisation, one solve")
        rows = bench_tissue(cells_per_axis=tuple(args.cells))
        keys = list(rows[0].keys())
        print("  ".join(f"{k:>14}" for k in keys))
        for row in rows:
            print("  ".join(f"{row[k]:>14.4g}" if isinstance(row[k], float) else f"{row[k]:>14}" for k in keys))
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    from refsim.viz import render_result

    render_result(Path(args.result), Path(args.output), step=args.step)
    print(f"wrote {args.output}")
    return 0


def _cmd_plot(args: argparse.Namespace) -> int:
    from refsim.viz import plot_result

    plot_result(Path(args.result), Path(args.output))
    print(f"wrote {args.output}")
    return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="refsim", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="log at debug level")
    commands = parser.add_subparsers(dest="command", required=True)

    run = commands.add_parser("run", help="run a scene and write its HDF5 results")
    run.add_argument("scene", help="scene file (.toml) or built-in scene name (cube, cube_cut, ...)")
    run.add_argument("-o", "--output", required=True, help="results file (.h5)")
    run.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override a scene value")
    run.add_argument("--figure", help="also write a picture (PNG) and a force plot beside it")
    run.add_argument("--overwrite", action="store_true", help="replace an existing results file")
    run.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    run.set_defaults(handler=_cmd_run)

    verify = commands.add_parser("verify", help="run the verification cases and print their table")
    verify.set_defaults(handler=_cmd_verify)

    bench = commands.add_parser("bench", help="time a scene (the paper's Table 1) and the tissue model")
    bench.add_argument("scene", nargs="?", help="scene to time; without it, only the tissue model bench")
    bench.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override a scene value")
    bench.add_argument("--tissue", action="store_true", help="also time the tissue model on refined cubes")
    bench.add_argument("--cells", type=int, nargs="+", default=[8, 16, 32], help="cells per axis (default 8 16 32)")
    bench.set_defaults(handler=_cmd_bench)

    render = commands.add_parser("render", help="off-screen picture of a results file")
    render.add_argument("result")
    render.add_argument("-o", "--output", required=True)
    render.add_argument("--step", type=int, default=None, help="step to show (default: last)")
    render.set_defaults(handler=_cmd_render)

    plot = commands.add_parser("plot", help="force on the needle base against depth and time")
    plot.add_argument("result")
    plot.add_argument("-o", "--output", required=True)
    plot.set_defaults(handler=_cmd_plot)

    study = commands.add_parser("study", help="parameter sweep on Dask (a LocalCluster, or --scheduler)")
    study.add_argument("target", help="study file (.toml), or a scene (file or built-in name) with --sweep")
    study.add_argument("--sweep", action="append", metavar="SECTION.KEY=V1,V2,...", help="values of a scene key")
    study.add_argument("--zip", action="store_true", help="pair the i-th values of every sweep (default: product)")
    study.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override for every run")
    study.add_argument("--quantity", action="append", help="quantity of interest (refsim.sweep.quantities)")
    study.add_argument("--reference", action="append", metavar="SECTION.KEY=VALUE",
                       help="override of the reference run (errors are taken against it)")
    study.add_argument("--name", help="study name (default: the scene's)")
    study.add_argument("-o", "--output", help="study file (.h5); runs go to <stem>_runs/ beside it")
    study.add_argument("--scheduler", help="address of a running Dask scheduler, e.g. tcp://host:8786")
    study.add_argument("--workers", type=int, help="LocalCluster worker processes (default: the cores)")
    study.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    study.set_defaults(handler=_cmd_study)

    export = commands.add_parser("export", help="ParaView sidecar, reference problems, force CSV of a result")
    export.add_argument("result")
    export.add_argument("--xdmf", action="store_true", help="write RESULT.xdmf beside the file (ParaView)")
    export.add_argument("--problems", metavar="OUT.h5", help="recorded problems with exact solutions")
    export.add_argument("--fclib", metavar="FOLDER", help="with --problems: FCLib files of pure-contact steps")
    export.add_argument("--csv", metavar="OUT.csv", help="needle force history")
    export.set_defaults(handler=_cmd_export)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `refsim` console script; returns the exit code."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.handler(args)
    except (ValueError, FileNotFoundError, OSError) as error:
        print(f"refsim {args.command}: error: {error}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print(f"refsim {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
