"""The `refsim` command line: run, verify, bench, render, plot, study, export, interactive.

Exit codes: 0 success; 1 a verification case failed; 2 bad input (scene, file, option; nothing is written);
3 the simulation stopped on a detected numerical problem or a failed write (the results file keeps every
completed step, complete = false, the reason in stop_reason; a full disk before the first step, a figure or an
export leaves no file); 130 interrupted by SIGINT, 129 by SIGHUP, 143 by SIGTERM (same). No command prints a
traceback: unexpected errors are reported in one line (-v logs the traceback). A closed standard output
(`refsim run ... | head`) does not change the exit code: what would have been printed is dropped.
"""

from __future__ import annotations

import argparse
import errno
import importlib.util
import io
import logging
import os
import signal
import sys
import threading
from pathlib import Path

__all__ = ["main"]

logger = logging.getLogger("refsim")

EXIT_FAILED, EXIT_INPUT, EXIT_SIMULATION, EXIT_INTERRUPTED, EXIT_TERMINATED = 1, 2, 3, 130, 143

#: The optional packages of each extra of pyproject.toml (import names) that a command needs.
EXTRA_MODULES = {
    "viz": ("pyvista", "matplotlib", "imageio"),
    "study": ("distributed", "tqdm"),
    "mesh": ("gmsh",),
    "osqp": ("osqp",),
}


class MissingExtraError(ModuleNotFoundError):
    """A command needs a package of an optional extra that is not installed (exit code 2)."""

    def __init__(self, what: str, module: str, extra: str) -> None:
        super().__init__(
            f"{what} needs {module}, which is not installed: pip install 'refsim[{extra}]'", name=module
        )


def _extra_of(module: str) -> str | None:
    """The extra that installs the top-level package ``module``, None for a package refsim always installs."""
    top = module.split(".")[0]
    aliases = {"vtk": "pyvista", "vtkmodules": "pyvista", "imageio_ffmpeg": "imageio", "dask": "distributed"}
    top = aliases.get(top, top)
    return next((extra for extra, modules in EXTRA_MODULES.items() if top in modules), None)


def require_extra(extra: str, what: str, modules: tuple[str, ...] | None = None) -> None:
    """Raise :class:`MissingExtraError` before any work when a module of ``extra`` (all its modules, or
    ``modules``) cannot be imported."""
    for module in modules or EXTRA_MODULES[extra]:
        if importlib.util.find_spec(module) is None:
            raise MissingExtraError(what, module, extra)


def _progress_bar(total: int, enabled: bool):
    """A tqdm progress bar of the run's steps on stderr, the phase as its postfix; on a log file (stderr not a
    terminal) one line every 10 s."""
    from tqdm import tqdm

    tty = sys.stderr.isatty()
    return tqdm(
        total=total,
        unit="step",
        disable=not enabled,
        file=sys.stderr,
        dynamic_ncols=tty,
        mininterval=0.2 if tty else 10.0,
        delay=1e-3 if tty else 0.0,  # on a terminal, no empty bar above the load report of the scene
        leave=True,
    )


_FIGURE_SUFFIXES = (".png", ".jpg", ".jpeg")
# errno values of a failed write (exit code 3), as opposed to a path that cannot be written (bad input, 2).
_WRITE_FAILURES = (errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EFBIG)


class _PipeSafe(io.TextIOBase):
    """Standard output that survives a closed pipe (`refsim run ... | head`): after a BrokenPipeError the
    stream's descriptor is pointed at /dev/null and later output is dropped, so the command finishes its work
    (the XDMF sidecar, the exit code of the run) instead of failing on a print."""

    def __init__(self, stream) -> None:
        self._stream = stream
        self.broken = False

    def _break(self) -> None:
        self.broken = True
        try:  # the interpreter flushes sys.__stdout__ at exit: it must not meet the closed pipe again
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, self._stream.fileno())
            os.close(devnull)
        except (OSError, ValueError, io.UnsupportedOperation):
            pass

    def write(self, text: str) -> int:
        if not self.broken:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._break()
        return len(text)

    def flush(self) -> None:
        if not self.broken:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._break()

    def isatty(self) -> bool:
        try:
            return not self.broken and self._stream.isatty()
        except ValueError:  # the wrapped stream was closed (a library kept this object past main)
            return False

    def fileno(self) -> int:
        return self._stream.fileno()

    @property
    def encoding(self):
        return getattr(self._stream, "encoding", "utf-8")

    def __getattr__(self, name: str):  # buffer, errors, ...: those of the wrapped stream
        return getattr(self._stream, name)


def _write_failed(path: Path, what: str, error: OSError, *partial: Path):
    """The error for a failed write of ``path``: partial files removed; a full disk (ENOSPC, EDQUOT, EIO,
    EFBIG) is a failed write (RunWriteError, exit 3), anything else bad input (exit 2); both name the path."""
    from refsim.io.driver import RunWriteError

    for item in (path, *partial):
        try:
            Path(item).unlink(missing_ok=True)
        except OSError:
            pass
    message = f"{path}: writing the {what} failed ({error.strerror or error}); no {what} was left"
    if error.errno in _WRITE_FAILURES:
        return RunWriteError(error.errno, message)
    return OSError(error.errno, message)


def _results_input(path, command: str) -> Path:
    """The results file a command reads, checked before anything is written (a missing, truncated or
    non-refsim file is bad input, named); a run that did not complete is said so on stderr, with its reason
    and the steps it kept."""
    from refsim.io.reader import results_status

    path = Path(path)
    complete, steps, reason = results_status(path)
    if not complete:
        why = reason or "no stop reason recorded: the run may still be writing it, or was killed"
        print(
            f"refsim {command}: note: {path} holds a run that did not complete ({why}); its {steps} "
            "completed steps are used",
            file=sys.stderr,
        )
    return path


def _output_path(path, result: Path, what: str, suffixes: tuple[str, ...] | None = None) -> Path:
    """An output of a command beside the results file ``result`` (one that reads it, or ``run``'s figure),
    checked before anything is written: its suffix (one of ``suffixes``), not the results file itself
    (writing it would destroy the run), and a path that can be created
    (:func:`refsim.io.driver.check_output_path`)."""
    from refsim.io.driver import check_output_path

    path = Path(path)
    if suffixes is not None and path.suffix.lower() not in suffixes:
        raise ValueError(f"{path}: the {what} must be a file ending in {', '.join(suffixes)}")
    if path.resolve() == result.resolve():
        raise ValueError(f"{path}: is the results file; give another path for the {what}")
    return check_output_path(path, overwrite=True, what=what)


def _cmd_run(args: argparse.Namespace) -> int:
    from refsim.io.driver import check_results_path, run_scene
    from refsim.kernel_warmup import start_background_compilation
    from refsim.scene import load_scene

    # After a fresh install, the kernels on the second core too (refsim.kernel_warmup), from before the
    # scene's loading (1.7 s of imports and mesh); stopped at exit, bad input included.
    start_background_compilation()
    if not args.quiet:  # the load report: the fixed set, an aimed insertion (refsim.scene.build)
        logging.getLogger("refsim.scene.load").setLevel(logging.INFO)
    scene = load_scene(args.scene, args.set or ())
    output = check_results_path(args.output, overwrite=args.overwrite, scene=scene)
    figure = None
    if args.figure:  # checked before the run, not after it
        require_extra("viz", "--figure", ("pyvista", "matplotlib"))
        figure = _output_path(args.figure, output, "--figure picture", _FIGURE_SUFFIXES)
    bar = _progress_bar(scene.time.step_count, enabled=not args.quiet)

    def progress(done: int, total: int, phase: str) -> None:
        bar.set_postfix_str(phase, refresh=False)
        bar.update(done - bar.n)

    try:
        summary = run_scene(scene, output, overwrite=args.overwrite, progress=progress)
    finally:
        bar.close()
    if summary.stopped_by_signal:
        print(
            f"\nrefsim run: {summary.stop_reason}; {summary.steps_written} completed steps kept in {output}",
            file=sys.stderr,
        )
    elif summary.status != "complete":
        print(
            f"refsim run: error: {summary.stop_reason}; {summary.steps_written} completed steps kept in "
            f"{output} (complete = false)",
            file=sys.stderr,
        )
    print(f"scene {scene.name} ({scene.source}) -> {output}")
    if summary.status != "write_failed":  # the sidecar writes into the results file: not on a full disk
        _write_sidecar(output)
    print(summary.format())
    print(summary.format_table())
    if figure is not None and summary.complete:
        from refsim.viz import plot_result, render_result

        figure.parent.mkdir(parents=True, exist_ok=True)
        plot_path = figure.with_name(figure.stem + "_forces" + figure.suffix)
        try:
            render_result(output, figure)
            plot_result(output, plot_path)
        except OSError as error:
            raise _write_failed(figure, "figure", error, plot_path) from None
        print(f"figures: {figure}, {plot_path}")
    return summary.exit_code


def _write_sidecar(output: Path) -> None:
    """The ParaView sidecar (RESULT.xdmf) of a results file; a failure is reported, never fatal to the run."""
    from refsim.io.xdmf import write_xdmf

    try:
        print(f"ParaView: {write_xdmf(output)}")
    except (OSError, ValueError, RuntimeError) as error:  # h5py reports a failed flush as RuntimeError
        print(f"refsim: no XDMF sidecar for {output}: {error}", file=sys.stderr)


def _cmd_study(args: argparse.Namespace) -> int:
    """`refsim study`: a study file, or a scene with --sweep options, run on Dask."""
    require_extra("study", "this command")
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
        spec = study_from_options(
            args.target,
            args.sweep,
            combine="zip" if args.zip else "product",
            overrides=args.set or (),
            quantities=args.quantity,
            reference=args.reference,
            name=args.name,
        )
    output = Path(args.output) if args.output else Path(f"{spec.name}_study.h5")
    study = run_study(
        spec,
        output,
        scheduler=args.scheduler,
        workers=args.workers,
        progress=not args.quiet,
        warm_up=not args.no_warm_up,
        overwrite=args.overwrite,
    )
    runs = study["runs"]
    print(
        f"study {spec.name}: {len(runs['id'])} runs, {study['attributes']['runs_complete']} complete, "
        f"{study['attributes']['runs_failed']} failed -> {output}"
    )
    for index, status in enumerate(runs.get("status", [])):
        if status != "complete":  # name every run that did not finish, with its file and its reason
            print(
                f"  run {runs['id'][index]} ({runs['label'][index]}): {status}: {runs['error'][index]} "
                f"[{output.parent / runs['file'][index]}]",
                file=sys.stderr,
            )
    for row in study["convergence"]:
        print(
            f"  {row['key']:<22} {row['quantity']:<26} {row['kind']:<11} order {row['order']:7.3f}  "
            f"extrapolated {row['extrapolated']:.6g}  GCI {100 * row['gci']:.3g}%"
        )
    return 0 if study["attributes"]["runs_failed"] == 0 else EXIT_SIMULATION


def _cmd_export(args: argparse.Namespace) -> int:
    """`refsim export`: ParaView sidecar, reference problems (problem set, FCLib) and the force CSV."""
    from refsim.io.export import export_force_csv, export_problems, export_vtu
    from refsim.io.xdmf import write_xdmf

    for option, value, needs, given in (
        ("--fclib", args.fclib, "--problems", args.problems),
        ("--vtu-folder", args.vtu_folder, "--vtu", args.vtu),
    ):
        if value is not None and not given:
            raise ValueError(f"refsim export: {option} {value} goes with {needs}; it does nothing alone")
    if not (args.xdmf or args.problems or args.csv or args.vtu):
        raise ValueError(
            "refsim export: choose at least one of --xdmf, --vtu STEP, --problems OUT.h5, --csv OUT.csv"
        )
    result = _results_input(args.result, "export")
    if args.problems:
        _output_path(args.problems, result, "problem set")
    if args.csv:
        _output_path(args.csv, result, "force CSV")
    for folder, option in ((args.vtu_folder, "--vtu-folder"), (args.fclib, "--fclib")):
        if folder is not None and Path(folder).exists() and not Path(folder).is_dir():
            raise ValueError(f"{option} {folder}: is a file, not a folder")
    if args.vtu:
        files = export_vtu(result, args.vtu, args.vtu_folder)
        print(
            f"wrote {len(files)} files: "
            + ", ".join(str(f) for f in files[:4])
            + (", ..." if len(files) > 4 else "")
        )
    if args.xdmf:
        try:
            print(f"wrote {write_xdmf(result)}")
        except OSError as error:
            raise _write_failed(result.with_suffix(".xdmf"), "XDMF sidecar", error) from None
    if args.problems:
        try:
            summary = export_problems(result, args.problems, fclib_folder=args.fclib)
        except OSError as error:
            if Path(args.problems).exists() and not isinstance(error, FileNotFoundError):
                raise _write_failed(Path(args.problems), "problem set", error) from None
            raise
        print(
            f"wrote {summary['problems']} problems with their exact solutions to {args.problems}"
            + (f"; {len(summary['fclib'])} FCLib files in {args.fclib}" if args.fclib else "")
        )
        if summary["unconverged"]:
            print(f"  exact solve above tolerance at steps {summary['unconverged']}", file=sys.stderr)
    if args.csv:
        try:
            print(f"wrote {export_force_csv(result, args.csv)}")
        except OSError as error:
            if Path(args.csv).exists():
                raise _write_failed(Path(args.csv), "force CSV", error) from None
            raise
    return 0


# ---------------------------------------------------------------------- reference set (issue 27)


def _cmd_reference(args: argparse.Namespace) -> int:
    """`refsim reference`: list the cases, build the package at a level, or write its page."""
    from refsim.reference import case_names, load_case

    if args.action == "list":
        for name in case_names():
            case = load_case(name)
            print(f"{name:<22} {case.title}  (levels: {', '.join(case.levels)})")
        return 0
    if args.action == "page":
        from refsim.io.driver import check_output_path
        from refsim.reference.page import write_page

        if args.package is None or args.output is None:
            raise ValueError(
                "refsim reference page: give the package folder (--package DIR) and the page (-o PAGE.md)"
            )
        check_output_path(args.output, overwrite=True, what="page")
        print(f"wrote {write_page(args.package, args.output)}")
        return 0
    from refsim.reference import build_reference

    if args.output is None:
        raise ValueError("refsim reference build: give the package folder with -o DIR")
    if Path(args.output).exists() and not Path(args.output).is_dir():
        raise ValueError(f"-o {args.output}: is a file; expected the package folder")
    manifest = build_reference(
        args.output,
        level=args.level,
        cases=args.cases,
        scheduler=args.scheduler,
        workers=args.workers,
        command="refsim " + " ".join(sys.argv[1:]),
    )
    print(
        f"reference set ({args.level}) in {args.output}: {len(manifest['cases'])} cases, "
        f"{manifest['seconds']:.1f} s"
    )
    for name, case in manifest["cases"].items():
        for quantity, row in case["quantities"].items():
            print(
                f"  {name:<22} {quantity:<24} {'/'.join(row['methods']):<22} "
                f"largest U/scale {row['largest_relative_uncertainty']:.3g}"
            )
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    """`refsim compare CASE THEIR.csv`: their results against the reference; exit 1 when a quantity fails."""
    from refsim.io.driver import check_output_path
    from refsim.reference import compare, format_comparison
    from refsim.reference.compare import comparison_figure

    figure = None
    if args.output:  # checked before the comparison, not after it
        figure = Path(args.output)
        if figure.suffix.lower() not in _FIGURE_SUFFIXES:
            raise ValueError(f"-o {figure}: expected a picture file ending in {', '.join(_FIGURE_SUFFIXES)}")
        check_output_path(figure, overwrite=True, what="figure")
    if Path(args.theirs).suffix.lower() in (".h5", ".hdf5"):  # a refsim run: checked, incomplete said so
        _results_input(args.theirs, "compare")
    comparisons = compare(args.case, args.theirs, args.reference)
    print(format_comparison(args.case, comparisons))
    if figure is not None:
        figure.parent.mkdir(parents=True, exist_ok=True)
        try:
            print(f"wrote {comparison_figure(figure, args.case, comparisons)}")
        except OSError as error:
            raise _write_failed(figure, "figure", error) from None
    return 0 if all(item.all_passed for item in comparisons) else EXIT_FAILED


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
    from refsim.fem import bench
    from refsim.fem.compliance import STRATEGY_VARIANTS, strategy_variant
    from refsim.scene import load_scene

    for variant in args.strategies or ():  # before any timing
        strategy_variant(variant)
    if not 1 <= args.repeats <= 50:
        raise ValueError(f"--repeats {args.repeats}: expected timed runs per strategy, in [1, 50]")
    if args.scene:
        from refsim.scene.loader import check_overrides

        for section, key in check_overrides(args.set or ()):
            if section == "compliance" and key in ("strategy", "w_update"):
                raise ValueError(
                    f"--set compliance.{key}: refsim bench sets it for each of --strategies; name the "
                    f"strategies there (e.g. --strategies exact fast refreshed_stale)"
                )
    if args.tissue or not args.scene:  # the scaling table's cubes, before any timing (mesh.cells' range)
        from refsim.scene.build import check_memory

        for cells in args.cells:
            if not 1 <= cells <= 256:
                raise ValueError(f"--cells {cells}: expected cells per axis of the cube, in [1, 256]")
            check_memory(6 * cells**3, "--cells", cells)
    print("\n".join(bench.header_lines()))
    reference_ms = None
    if args.scene:
        strategies = args.strategies or ["exact"]
        if args.against_exact and "exact" not in strategies:
            strategies = ["exact", *strategies]
        reference_ms = bench.superlu_reference_ms(bench.cube_model(8))
        print(
            f"reference: one SuperLU (COLAMD) factorisation of the cube's matrix, this run: "
            f"{reference_ms:.2f} ms"
        )
        from refsim.simulation.bench import time_strategies

        scenes = {}
        for strategy in strategies:
            key, update = strategy_variant(strategy)
            overrides = [*(args.set or ()), f'compliance.strategy="{key}"', f'compliance.w_update="{update}"']
            scenes[strategy] = load_scene(args.scene, overrides)
        timed = time_strategies(scenes, args.repeats)
        for strategy, run in timed.items():
            scene, per_step = run.scene, run.median_ms
            spread = (
                f" (median of {run.step_ms.size} runs, {run.step_ms.min():.2f} to {run.step_ms.max():.2f})"
                if run.step_ms.size > 1
                else ""
            )
            print(
                f"\nscene {scene.name}, compliance {strategy} (w_update {scene.compliance.w_update}, "
                f"refresh_every {scene.compliance.refresh_every}): "
                f"solver {scene.solver.method}, tolerance {scene.solver.tolerance:g}; {per_step:.2f} ms per "
                f"step{spread}, {per_step / run.reference_ms:.2f} of the SuperLU factorisation "
                f"({run.reference_ms:.2f} ms around these runs), timed on runs after a first one (which "
                f"compiles the kernels); set-up {run.setup_ms:.1f} ms (the simulation built from the scene's "
                f"models: the fast mode's rest factorisation)"
            )
            print(run.summary.format_table(beside_paper=True))
            print(
                "paper: Perrusi, Baksic and Courtecuisse 2021, Table 1 (their C++ in SOFA, their machine, "
                "Gauss-Seidel; penetration = our approach phase)"
            )
            if run.summary.cut_points:
                print(run.summary.format_cut())
        if args.against_exact:
            print(
                "\nagainst exact (same scene): time per step (wall, each run above), positions [m], needle "
                "force [N], events"
            )
            exact = timed["exact"]
            for strategy, run in timed.items():
                if strategy == "exact":
                    continue
                errors = bench.compare_runs(exact.kept, run.kept)
                ratios = run.step_ms / exact.step_ms
                rounds = f" (each round: {ratios.min():.2f} to {ratios.max():.2f})" if ratios.size > 1 else ""
                print(
                    f"  {strategy:<12} time {run.median_ms / exact.median_ms:.2f} of the exact "
                    f"step{rounds}, position {errors['position_error']:.3e} m, force "
                    f"{errors['force_error']:.3e} N "
                    f"(peak {errors['peak_force']:.4g} N), events "
                    f"{'same' if errors['same_events'] else 'DIFFER: '}"
                    f"{errors.get('event_shift', '')}"
                )
    if args.tissue or not args.scene:
        strategies = tuple(args.strategies or STRATEGY_VARIANTS)
        reference_ms, rows = bench.bench_strategies(8, strategies=strategies, against_exact=True)
        print(
            f"\ntissue step on the paper's cube (8 cells per axis, bottom sheared 1 cm over the run), ms per "
            f"step; "
            f"SuperLU (COLAMD) factorisation of its matrix, this run: {reference_ms:.2f} ms"
        )
        for row in rows:
            row["ratio_to_superlu"] = row["total_ms"] / reference_ms
        print(
            bench.format_rows(
                rows,
                [
                    "strategy",
                    "assembly_ms",
                    "factorisation_ms",
                    "free_solve_ms",
                    "compliance_ms",
                    "correction_ms",
                    "total_ms",
                    "ratio_to_superlu",
                    "pcg_iterations",
                    "free_motion_error",
                    "compliance_error",
                    "correction_error",
                ],
            )
        )
        scaling = bench.bench_scaling(tuple(args.cells))
        print("\nscaling (refreshed: every 10 steps), ms per step; *_compliance_ms: W and the correction")
        print(bench.format_rows(scaling))
        dofs = [row["free_dofs"] for row in scaling]
        for key in [k for k in scaling[0] if k.endswith("_ms")]:
            exponent = bench.growth_exponent(dofs, [row[key] for row in scaling])
            print(f"growth exponent of {key} against free DoFs: {exponent:.2f}")
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    require_extra("viz", "this command", ("pyvista", "imageio") if args.animate else ("pyvista",))
    from refsim.viz import animate_result, render_result

    if not (args.output or args.animate):
        raise ValueError("refsim render needs -o FIG.png, --animate OUT.gif|.mp4, or both")
    result = _results_input(args.result, "render")
    if args.output:
        _output_path(args.output, result, "picture", _FIGURE_SUFFIXES)
    if args.animate:
        _output_path(args.animate, result, "animation", (".gif", ".mp4"))
    framing = {"camera": args.camera, "view_up": args.view_up, "zoom": args.zoom, "focus": args.focus}
    if args.animate:
        animate_result(Path(args.result), Path(args.animate), every=args.every, fps=args.fps, **framing)
        print(f"wrote {args.animate}")
    if args.output:
        render_result(Path(args.result), Path(args.output), step=args.step, **framing)
        print(f"wrote {args.output}")
    return 0


def _cmd_plot(args: argparse.Namespace) -> int:
    require_extra("viz", "this command", ("matplotlib",))
    from matplotlib.figure import Figure

    from refsim.viz import plot_result

    result = _results_input(args.result, "plot")
    formats = tuple(f".{name}" for name in Figure().canvas.get_supported_filetypes())
    plot_result(result, _output_path(args.output, result, "plot", formats))
    print(f"wrote {args.output}")
    return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="refsim", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="log at debug level")
    commands = parser.add_subparsers(dest="command", required=True)
    _add_run_command(commands)
    _add_interactive_command(commands)
    _add_verify_command(commands)
    _add_bench_command(commands)
    _add_render_command(commands)
    _add_plot_command(commands)
    _add_study_command(commands)
    _add_export_command(commands)
    _add_reference_command(commands)
    _add_compare_command(commands)
    return parser


def _add_run_command(commands) -> None:
    """`refsim run` and its arguments."""
    run = commands.add_parser("run", help="run a scene and write its HDF5 results")
    run.add_argument("scene", help="scene file (.toml) or built-in scene name (cube, cube_cut, ...)")
    run.add_argument("-o", "--output", required=True, help="results file (.h5)")
    run.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override a scene value")
    run.add_argument("--figure", help="also write a picture (PNG) and a force plot beside it")
    run.add_argument("--overwrite", action="store_true", help="replace an existing results file")
    run.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    run.set_defaults(handler=_cmd_run)


def _add_interactive_command(commands) -> None:
    """`refsim interactive` (its parser lives with the command; argparse only, so --help stays light)."""
    from refsim.interactive.command import add_parser

    add_parser(commands)


def _add_verify_command(commands) -> None:
    """`refsim verify` and its arguments."""
    verify = commands.add_parser("verify", help="run the verification cases and print their table")
    verify.set_defaults(handler=_cmd_verify)


def _add_bench_command(commands) -> None:
    """`refsim bench` and its arguments."""
    bench = commands.add_parser("bench", help="time a scene (the paper's Table 1) and the tissue model")
    bench.add_argument("scene", nargs="?", help="scene to time; without it, only the tissue model bench")
    bench.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override a scene value")
    bench.add_argument(
        "--tissue", action="store_true", help="also time the tissue step per strategy and its scaling"
    )
    bench.add_argument(
        "--cells",
        type=int,
        nargs="+",
        default=[8, 12, 16, 24],
        help="cells per axis of the scaling table (default 8 12 16 24)",
    )
    bench.add_argument(
        "--strategies",
        nargs="+",
        metavar="STRATEGY",
        help="compliance strategies to time: a compliance.strategy, or refreshed_<w_update> (default: all; "
        "with a scene: exact)",
    )
    bench.add_argument(
        "--against-exact",
        action="store_true",
        help="also run the scene exactly and report each strategy's errors (positions, forces, events)",
    )
    bench.add_argument(
        "--repeats",
        type=int,
        default=3,
        help="timed runs of the scene per strategy, interleaved; each strategy's time is their median "
        "(default 3, in [1, 50])",
    )
    bench.set_defaults(handler=_cmd_bench)


def _add_render_command(commands) -> None:
    """`refsim render` and its arguments."""
    render = commands.add_parser("render", help="off-screen picture (or animation) of a results file")
    render.add_argument("result")
    render.add_argument("-o", "--output", help="picture to write (.png)")
    render.add_argument("--step", type=int, default=None, help="step to show (default: last)")
    render.add_argument(
        "--camera",
        default=None,
        help="view direction from the focus to the camera: auto (default: face the cut, else "
        "beside the needle), iso, xy, yx, xz, zx, yz, zy, or x,y,z",
    )
    render.add_argument(
        "--view-up", default=None, metavar="X,Y,Z", help="up direction (default: needle base up)"
    )
    render.add_argument("--zoom", type=float, default=1.0, help="magnification after the framing (default 1)")
    render.add_argument(
        "--focus",
        default="auto",
        help="what to frame: auto (the tissue, the needle entering it and the cut), insertion (the needle's "
        "inserted part, insertion points and cut, close up), needle, cut, tissue, or a point x,y,z [m]",
    )
    render.add_argument("--animate", metavar="OUT", help="also write an animation (.gif or .mp4)")
    render.add_argument(
        "--every", type=int, default=1, metavar="K", help="animation: one frame every K steps"
    )
    render.add_argument("--fps", type=float, default=10.0, help="animation: frames per second (default 10)")
    render.set_defaults(handler=_cmd_render)


def _add_plot_command(commands) -> None:
    """`refsim plot` and its arguments."""
    plot = commands.add_parser("plot", help="force on the needle base against depth and time")
    plot.add_argument("result")
    plot.add_argument("-o", "--output", required=True)
    plot.set_defaults(handler=_cmd_plot)


def _add_study_command(commands) -> None:
    """`refsim study` and its arguments."""
    study = commands.add_parser("study", help="parameter sweep on Dask (a LocalCluster, or --scheduler)")
    study.add_argument("target", help="study file (.toml), or a scene (file or built-in name) with --sweep")
    study.add_argument(
        "--sweep", action="append", metavar="SECTION.KEY=V1,V2,...", help="values of a scene key"
    )
    study.add_argument(
        "--zip", action="store_true", help="pair the i-th values of every sweep (default: product)"
    )
    study.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override for every run")
    study.add_argument("--quantity", action="append", help="quantity of interest (refsim.sweep.quantities)")
    study.add_argument(
        "--reference",
        action="append",
        metavar="SECTION.KEY=VALUE",
        help="override of the reference run (errors are taken against it)",
    )
    study.add_argument("--name", help="study name (default: the scene's)")
    study.add_argument("-o", "--output", help="study file (.h5); runs go to <stem>_runs/ beside it")
    study.add_argument(
        "--scheduler",
        help="address of a running Dask scheduler, e.g. tcp://host:8786; it and its workers run the study's "
        "code: give only one you started (default: a LocalCluster on 127.0.0.1)",
    )
    study.add_argument("--workers", type=int, help="LocalCluster worker processes (default: the cores)")
    study.add_argument(
        "--overwrite", action="store_true", help="replace an -o file that is not this study's study file"
    )
    study.add_argument(
        "--no-warm-up",
        action="store_true",
        help="no untimed warm-up run per worker (the first run then includes kernel compilation)",
    )
    study.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    study.set_defaults(handler=_cmd_study)


def _add_export_command(commands) -> None:
    """`refsim export` and its arguments."""
    export = commands.add_parser("export", help="ParaView sidecar, reference problems, force CSV of a result")
    export.add_argument("result")
    export.add_argument("--xdmf", action="store_true", help="write RESULT.xdmf beside the file (ParaView)")
    export.add_argument("--problems", metavar="OUT.h5", help="recorded problems with exact solutions")
    export.add_argument(
        "--fclib",
        metavar="FOLDER",
        help="with --problems: FCLib files of the steps FCLib can hold (the tip contact before puncture)",
    )
    export.add_argument("--csv", metavar="OUT.csv", help="needle force history")
    export.add_argument(
        "--vtu",
        metavar="STEP",
        help="deformed tissue, cut surface and every instrument's needle at a recorded tissue step (a step "
        "number, last, or all: every recorded step with a .pvd series) as .vtu files",
    )
    export.add_argument(
        "--vtu-folder", metavar="FOLDER", help="with --vtu: where to write (default: beside RESULT)"
    )
    export.set_defaults(handler=_cmd_export)


def _add_reference_command(commands) -> None:
    """`refsim reference` and its arguments."""
    reference = commands.add_parser("reference", help="the reference set: list its cases, build it, its page")
    reference.add_argument("action", choices=("list", "build", "page"), help="list the cases, build, or page")
    reference.add_argument("-o", "--output", help="build: the package folder; page: the page (.md)")
    reference.add_argument(
        "--level", default="coarse", help="refinement levels: coarse (default), standard, fine (a cluster's)"
    )
    reference.add_argument("--cases", nargs="+", help="cases to build (default: all)")
    reference.add_argument("--package", help="page: the package folder to write the page from")
    reference.add_argument("--scheduler", help="address of a running Dask scheduler, e.g. tcp://host:8786")
    reference.add_argument("--workers", type=int, help="LocalCluster worker processes (default: the cores)")
    reference.set_defaults(handler=_cmd_reference)


def _add_compare_command(commands) -> None:
    """`refsim compare` and its arguments."""
    compare = commands.add_parser(
        "compare", help="score another simulator's results against a reference case"
    )
    compare.add_argument("case", help="reference case (refsim reference list)")
    compare.add_argument("theirs", help="their results: CSV with columns quantity,x,value (or a refsim .h5)")
    compare.add_argument("--reference", default="reference", help="the package folder (default ./reference)")
    compare.add_argument("-o", "--output", help="figure: their values over the reference band (.png)")
    compare.set_defaults(handler=_cmd_compare)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `refsim` console script; returns the exit code."""
    args = _parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s"
    )
    # A closed pipe must raise BrokenPipeError (handled by _PipeSafe), not kill the process: Python ignores
    # SIGPIPE at start-up, but a library may have reset it at the C level (gmsh's initialize does).
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)
    stdout = sys.stdout
    sys.stdout = _PipeSafe(stdout)
    try:
        return _handle(args)
    finally:
        sys.stdout.flush()
        sys.stdout = stdout


def _handle(args: argparse.Namespace) -> int:
    from refsim.io.driver import RunWriteError

    try:
        if getattr(args, "set", None):  # every command's --set: each key once
            from refsim.scene.loader import check_overrides

            check_overrides(args.set)
        return args.handler(args)
    except RunWriteError as error:  # a full disk: nothing half-written is left
        print(f"refsim {args.command}: error: {error}", file=sys.stderr)
        return EXIT_SIMULATION
    except ModuleNotFoundError as error:  # an optional package, found missing where it is used
        extra = _extra_of(error.name or "")
        if extra is None:
            return _internal_error(args, error)
        if not isinstance(error, MissingExtraError):
            error = MissingExtraError("this command", error.name, extra)
        print(f"refsim {args.command}: error: {error}", file=sys.stderr)
        return EXIT_INPUT
    except (ValueError, OSError) as error:  # SceneError, MeshError, RunInputError, paths
        print(f"refsim {args.command}: error: {error}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print(f"refsim {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as error:  # noqa: BLE001 - never a traceback; -v logs it
        return _internal_error(args, error)


def _internal_error(args: argparse.Namespace, error: BaseException) -> int:
    """Report an unexpected error in one line (-v logs the traceback); exit code 2."""
    logger.debug("unexpected error", exc_info=error)
    print(
        f"refsim {args.command}: internal error: {type(error).__name__}: {error} (rerun with -v for the "
        "traceback, and report it)",
        file=sys.stderr,
    )
    return EXIT_INPUT


if __name__ == "__main__":
    sys.exit(main())
