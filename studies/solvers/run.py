"""Solver study: error against iterations and time for Gauss–Seidel and the exact solver (writes HDF5).

Usage::

    python studies/solvers/run.py [-o studies/solvers/output/solvers.h5] [--data PATH]
    python studies/solvers/run.py --benchmark [--benchmark-output studies/solvers/output/exact_benchmark.h5]

The benchmark (issue 15) times, in one run, the exact solver (semismooth Newton first), today's
solve_exact before it (the cone route of commit 132aab8, loaded from git), Gauss–Seidel and, when Debian's
python3-siconos is installed, Siconos' NSN_AC, NSGS, PROX and VI_FPP (in a subprocess of /usr/bin/python3),
all at 1e-8, and prints the table of docs/solver_study.md (solved, shifted geometric mean time with a 10 ms
shift).

For every problem: one long Gauss–Seidel run recording the natural residual after every sweep, Gauss–Seidel
runs at several tolerances (timed, best of three), and the exact solver with every backend. The error of a
Gauss–Seidel answer is its natural residual and its gap error ‖δ − δ_exact‖ / max(‖δ_exact‖, ‖δ_free‖) against
the exact solution (λ is not unique when W is singular; δ is). Problems from elsewhere (for instance recorded
from the cube scene's steps) are studied by passing them to :func:`run_study`.
"""

from __future__ import annotations

import os

# The problems are small and dense (at most a few hundred rows): multi-threaded BLAS only adds overhead and,
# on a shared machine, oversubscription (measured: 180x180 least squares 26 ms threaded, 1.8 ms on one
# thread). Set before numpy is imported; an explicit setting in the environment wins.
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import argparse  # noqa: E402
import logging  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import h5py  # noqa: E402
import numpy as np  # noqa: E402

from refsim.solvers import ConstraintProblem, available_backends, solve_exact, solve_gauss_seidel  # noqa: E402
from refsim.solvers.readers import read_problem  # noqa: E402

logger = logging.getLogger("studies.solvers")

GS_TOLERANCES = (1e-2, 1e-3, 1e-4, 1e-6, 1e-8)
GS_HISTORY_SWEEPS = 5000
GS_CAP = 5000
EXACT_TOLERANCE = 1e-9
#: friction problems of the shared set are slightly non-symmetric (README: 1e-7 to 1e-3)
SYMMETRY_TOLERANCE = 1e-3
SCHEMA = "refsim-solver-study/1"


def shared_problems() -> Path:
    """The external problem folder (REFSIM_SHARED_DATA overrides ``../shared/data``)."""
    base = os.environ.get("REFSIM_SHARED_DATA")
    if base:
        return Path(base) / "solver-problems"
    repository = Path(__file__).resolve().parents[2]
    candidates = [repository / ".." / "shared" / "data", repository / ".." / ".." / "shared" / "data"]
    for root in candidates:  # beside a checkout (/work/main) or two levels up for a worktree (/work/wt/NAME)
        if (root / "solver-problems" / "MANIFEST.tsv").is_file():
            return root / "solver-problems"
    return candidates[0] / "solver-problems"


def external_problems(root: Path) -> list[tuple[str, ConstraintProblem]]:
    """Every readable problem of the shared set, with its family (folder) name."""
    problems = []
    for line in (root / "MANIFEST.tsv").read_text().splitlines()[1:]:
        name = line.split("\t")[0]
        try:
            problems.append((name.split("/")[0], read_problem(root / name)))
        except ValueError as error:
            logger.warning("skipped %s: %s", name, error)
    return problems


def cube_problems(every: int = 5) -> list[tuple[str, ConstraintProblem]]:
    """Constraint problems recorded from the built-in scenes: every ``every``-th step of the cube's insertion
    (family "cube insertion") and of cube_cut from its "cut_start" event on (family "cube cutting")."""
    import dataclasses

    from refsim.scene import load_scene
    from refsim.simulation import Simulation

    problems = []
    for scene_name, family in (("cube", "cube insertion"), ("cube_cut", "cube cutting")):
        scene = load_scene(scene_name, ["output.record_problems=true"])
        records = []
        Simulation(scene).run(on_step=lambda state, record, records=records: records.append(record))
        start = 0
        if family == "cube cutting":
            start = next(r.step for r in records if any(e.name == "cut_start" for e in r.events))
        kept = [r for r in records if r.problem is not None and r.step >= start and r.step % every == 0]
        problems.extend(
            (family, dataclasses.replace(r.problem, name=f"{scene_name}_step_{r.step:04d}")) for r in kept
        )
        logger.info("%s: %d problems recorded", family, len(kept))
    return problems


def _gap_error(
    problem: ConstraintProblem, multipliers: np.ndarray, reference_gap: np.ndarray | None
) -> float:
    if reference_gap is None:
        return float("nan")
    scale = max(np.linalg.norm(reference_gap), np.linalg.norm(problem.free_gap), np.finfo(float).tiny)
    return float(np.linalg.norm(problem.gap(multipliers) - reference_gap) / scale)


def _timed_gauss_seidel(problem, tolerance, repeats=3):
    best = None
    for _ in range(repeats):
        multipliers, report = solve_gauss_seidel(problem, tolerance=tolerance, max_iterations=GS_CAP)
        if best is None or report.seconds < best[1].seconds:
            best = (multipliers, report)
    return best


def study_problem(group: h5py.Group, family: str, problem: ConstraintProblem, backends: list[str]) -> None:
    """Run every solver on one problem and write the results into ``group``."""
    group.attrs.update(
        family=family,
        rows=problem.row_count,
        contacts=len(problem.contacts),
        asymmetry=problem.asymmetry(),
        rank=int(np.linalg.matrix_rank(problem.compliance)) if problem.row_count else 0,
        has_friction=bool(len(problem.contacts) or len(problem.shaft_friction)),
    )
    reference_gap = None
    for backend in backends:
        sub = group.create_group(f"exact/{backend}")
        try:
            multipliers, report = solve_exact(
                problem, tolerance=EXACT_TOLERANCE, backend=backend, symmetry_tolerance=SYMMETRY_TOLERANCE
            )
        except ValueError as error:
            sub.attrs.update(
                status="rejected",
                message=str(error),
                residual=np.nan,
                seconds=np.nan,
                iterations=0,
                converged=False,
            )
            continue
        sub.attrs.update(
            status="solved" if report.converged else "failed",
            message=report.message,
            residual=report.residual,
            seconds=report.seconds,
            iterations=report.iterations,
            converged=report.converged,
        )
        sub.create_dataset("history", data=report.history)
        if report.converged and reference_gap is None:
            reference_gap = problem.gap(multipliers)
    _, history = solve_gauss_seidel(problem, tolerance=0.0, max_iterations=GS_HISTORY_SWEEPS)
    gs = group.create_group("gauss_seidel")
    gs.create_dataset("history", data=history.history)
    gs.attrs.update(sweep_seconds=history.seconds / max(history.iterations, 1))
    records = []
    for tolerance in GS_TOLERANCES:
        multipliers, report = _timed_gauss_seidel(problem, tolerance)
        records.append(
            (
                tolerance,
                report.iterations,
                report.residual,
                report.seconds,
                report.converged,
                _gap_error(problem, multipliers, reference_gap),
                report.increment,
            )
        )
    gs.create_dataset("tolerance_runs", data=np.array(records, dtype=float))
    gs.attrs["tolerance_runs_columns"] = (
        "tolerance, iterations, residual, seconds, converged, gap_error, increment"
    )


def benchmark_sweeps(row_count: int = 100, sweeps: int = 1000, repeats: int = 7) -> dict[str, float]:
    """Seconds for ``sweeps`` Gauss–Seidel sweeps over ``row_count`` rows (best of ``repeats``).

    Two problems: all unilateral rows, and a needle-like mix (contacts, bilateral pairs with shaft friction).
    Every multiplier changes at every sweep (the worst case: each change costs one column update).
    """
    rng = np.random.default_rng(0)
    factor = rng.standard_normal((row_count, row_count))
    compliance = factor @ factor.T / row_count + np.eye(row_count)
    results = {}
    unilateral = ConstraintProblem(
        compliance=compliance,
        free_gap=-compliance @ rng.uniform(0.5, 1, row_count),
        unilateral=np.arange(row_count),
    )
    contacts = row_count // 6
    shafts = (row_count - 3 * contacts) // 3
    used = 3 * contacts + 3 * shafts
    mixed = ConstraintProblem(
        compliance=compliance,
        free_gap=rng.standard_normal(row_count),
        contacts=np.arange(3 * contacts).reshape(-1, 3),
        contact_friction=np.full(contacts, 0.5),
        bilateral=np.concatenate(
            [np.arange(3 * contacts, 3 * contacts + 2 * shafts), np.arange(used, row_count)]
        ),
        shaft_friction=np.arange(3 * contacts + 2 * shafts, used),
        shaft_pairs=np.arange(3 * contacts, 3 * contacts + 2 * shafts).reshape(-1, 2),
        shaft_friction_coefficient=np.full(shafts, 0.3),
    )
    for label, problem in (("unilateral", unilateral), ("mixed", mixed)):
        solve_gauss_seidel(problem, tolerance=0.0, max_iterations=2)  # compile / load the cache
        best = np.inf
        for _ in range(repeats):
            start = time.perf_counter()
            solve_gauss_seidel(problem, tolerance=0.0, max_iterations=sweeps)
            best = min(best, time.perf_counter() - start)
        results[label] = best
    return results


def run_study(
    problems: list[tuple[str, ConstraintProblem]], output: Path, backends: list[str] | None = None
) -> Path:
    """Study ``problems`` (family, problem) and write the HDF5 file ``output``; returns its path.

    This is the hook for problems from elsewhere: pass any list of :class:`ConstraintProblem` (for instance
    recorded from the cube scene's steps, with family ``"cube"``).
    """
    backends = backends or [name for name in ("clarabel", "osqp") if name in available_backends()]
    output.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with h5py.File(output, "w") as handle:
        handle.attrs.update(
            schema=SCHEMA,
            created=time.strftime("%Y-%m-%dT%H:%M:%S"),
            backends=backends,
            gs_tolerances=GS_TOLERANCES,
            gs_cap=GS_CAP,
            exact_tolerance=EXACT_TOLERANCE,
            symmetry_tolerance=SYMMETRY_TOLERANCE,
        )
        bench = handle.create_group("benchmark")
        for label, seconds in benchmark_sweeps().items():
            bench.attrs[f"{label}_1000_sweeps_100_rows_seconds"] = seconds
        group = handle.create_group("problems")
        for family, problem in problems:
            key = f"{family}__{problem.name or 'problem'}"
            if key in group:  # same family and name twice: number the later ones
                key = f"{key}_{len(group)}"
            logger.info("%s (%d rows)", key, problem.row_count)
            study_problem(group.create_group(key), family, problem, backends)
        handle.attrs["seconds"] = time.perf_counter() - start
    return output


LEGACY_COMMIT = "132aab8"
BENCHMARK_TOLERANCE = 1e-8
SHIFT_SECONDS = 0.010
SICONOS_PYTHON = Path("/usr/bin/python3")


def legacy_solve_exact():
    """``solve_exact`` as it was before the Newton path (commit 132aab8), loaded from git; None when git or
    the commit is unavailable."""
    import subprocess
    import types

    repository = Path(__file__).resolve().parents[2]
    try:
        source = subprocess.run(
            ["git", "-C", str(repository), "show", f"{LEGACY_COMMIT}:refsim/solvers/exact.py"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError) as error:
        logger.warning("legacy solve_exact unavailable: %s", error)
        return None
    module = types.ModuleType("refsim_legacy_exact")
    exec(compile(source, f"{LEGACY_COMMIT}:refsim/solvers/exact.py", "exec"), module.__dict__)  # noqa: S102
    return module.solve_exact


def _best_time(function, problem, repeats=3):
    """Best of ``repeats`` times of function(copy of problem): each run gets a fresh copy, so nothing cached
    on the problem (compiled-kernel block arrays, data scales) is reused, as in a simulation step.

    The copies are made before the first timed call, so that only the loop runs between timed calls, as in the
    Siconos runner (``siconos_runner.py``: its solver options are built between calls). Building a copy
    between the calls (validation, about 120 µs of Python and NumPy) evicts the solver's code and data from
    the caches: measured 2026-12-02 on FC3D_Example1 (9 rows) and Rover1040 (15 rows), best of 30, 32 and 76
    µs with the copies made first, 45 and 97 µs with a copy made before each call (and 94 and 149 µs after a
    16 MB read)."""
    import dataclasses

    best, result = np.inf, None
    copies = [dataclasses.replace(problem) for _ in range(repeats)]
    for fresh in copies:
        start = time.perf_counter()
        result = function(fresh)
        best = min(best, time.perf_counter() - start)
    return best, result


def _siconos(problems, tolerance):
    """Siconos results {solver: [(seconds, reactions, info) per problem or None]} for contact-only
    problems."""
    import subprocess
    import tempfile

    if not SICONOS_PYTHON.is_file():
        return {}
    check = subprocess.run([str(SICONOS_PYTHON), "-c", "import siconos.numerics"], capture_output=True)
    if check.returncode != 0:
        logger.warning("python3-siconos not installed: no Siconos comparison")
        return {}
    chosen = [
        i
        for i, (_, p) in enumerate(problems)
        if len(p.contacts)
        and 3 * len(p.contacts) == p.row_count
        and np.array_equal(p.contacts.reshape(-1), np.arange(p.row_count))
    ]
    with tempfile.TemporaryDirectory() as folder:
        source, target = Path(folder) / "problems.npz", Path(folder) / "results.npz"
        arrays = {"tolerance": tolerance, "count": len(chosen)}
        for k, i in enumerate(chosen):
            problem = problems[i][1]
            arrays.update(
                {
                    f"W_{k}": problem.compliance,
                    f"q_{k}": problem.free_gap,
                    f"mu_{k}": problem.contact_friction,
                }
            )
        np.savez(source, **arrays)
        runner = Path(__file__).resolve().parent / "siconos_runner.py"
        environment = dict(os.environ, PYTHONPATH="")
        done = subprocess.run(
            [str(SICONOS_PYTHON), str(runner), str(source), str(target)],
            capture_output=True,
            text=True,
            env=environment,
        )
        if done.returncode != 0:
            logger.warning("Siconos runner failed: %s", done.stderr[-2000:])
            return {}
        data = np.load(target)
        results = {}
        for name in ("NSN_AC", "NSGS", "PROX", "VI_FPP"):
            entries = [None] * len(problems)
            for k, i in enumerate(chosen):
                entries[i] = (
                    float(data[f"{name}_seconds_{k}"]),
                    data[f"{name}_r_{k}"],
                    int(data[f"{name}_info_{k}"]),
                )
            results[name] = entries
    return results


def shifted_geometric_mean(seconds, shift=SHIFT_SECONDS) -> float:
    """exp(mean(log(t + shift))) − shift [s] (the benchmark mean of Mittelmann's tables)."""
    seconds = np.asarray(seconds, dtype=float)
    if seconds.size == 0:
        return float("nan")
    return float(np.exp(np.mean(np.log(seconds + shift))) - shift)


def _table(table, subset, sizes, tolerance, title) -> str:
    """Markdown table over the problems of ``subset`` for every solver that attempted all of them."""
    names = [
        name for name, rows in table.items() if not np.isnan(np.array(rows, dtype=float)[subset, 1]).any()
    ]
    errors = {name: np.array(table[name], dtype=float)[:, 1] for name in names}
    seconds = {name: np.array(table[name], dtype=float)[:, 0] for name in names}
    everyone = subset & np.logical_and.reduce([errors[name] <= tolerance for name in names])
    lines = [
        f"**{title}**: {int(subset.sum())} problems, {int(everyone.sum())} solved by all; shifted geometric "
        f"mean (shift {SHIFT_SECONDS * 1e3:.0f} ms) of the time over the problems each solves.",
        "",
        "| solver | solved to 1e-8 | SGM ms | SGM ms, < 100 rows | SGM ms, ≥ 100 rows | SGM ms, solved by "
        "all |",
        "|---|---|---|---|---|---|",
    ]
    for name in names:
        solved = subset & (errors[name] <= tolerance)
        cells = [
            shifted_geometric_mean(seconds[name][solved & part]) * 1e3
            for part in (np.ones_like(solved), sizes < 100, sizes >= 100)
        ]
        cells.append(shifted_geometric_mean(seconds[name][everyone]) * 1e3)
        lines.append(
            f"| {name} | {int(solved.sum())} / {int(subset.sum())} | "
            + " | ".join(f"{c:.3f}" for c in cells)
            + " |"
        )
    return "\n".join(lines)


def _ratio_table(table, sizes, tolerance, reference="refsim exact (Newton first)") -> str:
    """Per-size ratios of ``reference``'s time to the fastest Siconos solver that solved the same problem (and
    to refsim's Gauss-Seidel), over the problems both solved: median and shifted geometric mean ratio."""
    errors = {name: np.array(rows, dtype=float)[:, 1] for name, rows in table.items()}
    seconds = {name: np.array(rows, dtype=float)[:, 0] for name, rows in table.items()}
    mine = errors[reference] <= tolerance
    siconos = [name for name in table if name.startswith("Siconos")]
    best = np.full(sizes.size, np.inf)
    for name in siconos:
        solved = errors[name] <= tolerance
        best[solved] = np.minimum(best[solved], seconds[name][solved])
    lines = [
        f"**Per-size time ratios of {reference}** (median of per-problem ratios over the problems both "
        "solve; SGM ratio: ratio of the shifted geometric means over those problems)",
        "",
        "| against | rows | problems | median ratio | SGM ratio |",
        "|---|---|---|---|---|",
    ]
    others = {"fastest Siconos solver on each problem": best}
    for name in siconos:  # each Siconos solver on the problems it solves
        others[name] = np.where(errors[name] <= tolerance, seconds[name], np.inf)
    others["refsim Gauss-Seidel"] = np.where(
        errors["refsim Gauss-Seidel"] <= tolerance, seconds["refsim Gauss-Seidel"], np.inf
    )
    for label, other in others.items():
        spans = (
            ((0, 30), (30, 100), (100, 10**9), (0, 10**9))
            if not label.startswith("Siconos")
            else ((0, 10**9),)
        )
        for low, high in spans:
            part = mine & np.isfinite(other) & (sizes >= low) & (sizes < high)
            if not part.any():
                continue
            ratio = seconds[reference][part] / other[part]
            sgm = shifted_geometric_mean(seconds[reference][part]) / shifted_geometric_mean(other[part])
            span = f"{low}–{high - 1}" if high < 10**9 else (f"≥ {low}" if low else "all")
            lines.append(f"| {label} | {span} | {int(part.sum())} | {np.median(ratio):.2f} | {sgm:.2f} |")
    return "\n".join(lines)


def _figure(table, sizes, tolerance, path: Path) -> None:
    """Time against rows for every solver (filled: solved to the tolerance, open: not)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(7.5, 4.5))
    markers = "osD^v<>ph*"
    for index, (name, rows) in enumerate(table.items()):
        rows = np.array(rows, dtype=float)
        seconds, errors = rows[:, 0], rows[:, 1]
        shown = np.isfinite(seconds)
        solved = shown & (errors <= tolerance)
        color = f"C{index}"
        axis.scatter(
            sizes[solved], seconds[solved] * 1e3, marker=markers[index % 10], color=color, s=14, label=name
        )
        axis.scatter(
            sizes[shown & ~solved],
            seconds[shown & ~solved] * 1e3,
            marker=markers[index % 10],
            s=14,
            facecolors="none",
            edgecolors=color,
        )
    axis.set(
        xscale="log",
        yscale="log",
        xlabel="rows",
        ylabel="time [ms]",
        title=f"Time to {tolerance:.0e} (filled: solved; open: not solved)",
    )
    axis.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=130)
    plt.close(figure)


def benchmark_exact(problems, output: Path, rounds: int = 2) -> str:
    """Time every solver on ``problems`` at 1e-8 (see the module notes); write ``output``; return the markdown
    table. A problem counts as solved by a solver when both refsim residuals of its answer are ≤ 1e-8.

    refsim's solvers and the Siconos subprocess take turns ``rounds`` times (the legacy solver runs in the
    first round only); each solver's time on a problem is its best over the rounds, so that a drift of the
    machine's speed between the two phases (seen here: the same loop 12 to 17 ms from one second to the next)
    does not favour either."""
    from refsim.solvers import data_residual, natural_residual

    tolerance = BENCHMARK_TOLERANCE
    legacy = legacy_solve_exact()
    solvers = {
        "refsim exact (Newton first)": lambda p: solve_exact(p, tolerance=tolerance, method="auto")[0],
        "refsim Gauss-Seidel": lambda p: solve_gauss_seidel(p, tolerance=tolerance, max_iterations=20_000)[0],
    }
    if legacy is not None:
        solvers["refsim exact before (cone route, 132aab8)"] = lambda p: legacy(
            p, tolerance=tolerance, symmetry_tolerance=SYMMETRY_TOLERANCE
        )[0]
    if problems:
        solve_exact(problems[0][1], tolerance=tolerance, method="auto")  # load the compiled kernels
    table = {name: [(np.inf, np.nan)] * len(problems) for name in solvers}
    paths = []
    siconos: dict[str, list] = {}
    for turn in range(rounds):
        for index, (family, problem) in enumerate(problems):
            for name, solver in solvers.items():
                if "before" in name and turn > 0:
                    continue
                repeats = 1 if "before" in name else 3
                try:
                    seconds, multipliers = _best_time(solver, problem, repeats)
                    error = max(natural_residual(problem, multipliers), data_residual(problem, multipliers))
                except ValueError as failure:  # the legacy solver rejects non-symmetric W
                    seconds, error = np.nan, np.inf
                    logger.info("%s rejects %s: %s", name, problem.name, str(failure)[:80])
                if turn == 0 or seconds < table[name][index][0]:
                    table[name][index] = (seconds, error)
            if turn == 0:
                _, report = solve_exact(problem, tolerance=tolerance, method="auto")
                paths.append(report.path)
                logger.info(
                    "%s/%s (%d rows): %s",
                    family,
                    problem.name,
                    problem.row_count,
                    ", ".join(
                        f"{n.split()[1]} {t[index][0] * 1e3:.2f} ms {t[index][1]:.1e}"
                        for n, t in table.items()
                    ),
                )
        for name, entries in _siconos(problems, tolerance).items():
            kept = siconos.setdefault(name, list(entries))
            for index, entry in enumerate(entries):
                if entry is not None and kept[index] is not None and entry[0] < kept[index][0]:
                    kept[index] = entry
        logger.info("round %d of %d done", turn + 1, rounds)
    for name, entries in siconos.items():
        rows = []
        for (_, problem), entry in zip(problems, entries, strict=True):
            if entry is None:
                rows.append((np.nan, np.nan))
                continue
            seconds, reaction, _ = entry
            rows.append((seconds, max(natural_residual(problem, reaction), data_residual(problem, reaction))))
        table[f"Siconos {name}"] = rows
    sizes = np.array([p.row_count for _, p in problems])
    output.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(output, "w") as handle:
        handle.attrs.update(
            created=time.strftime("%Y-%m-%dT%H:%M:%S"),
            tolerance=tolerance,
            shift_seconds=SHIFT_SECONDS,
            names=[p.name for _, p in problems],
            families=[f for f, _ in problems],
            rows=sizes,
            exact_paths=paths,
        )
        for name, rows in table.items():
            handle.create_dataset(name, data=np.array(rows, dtype=float))
    contact_only = np.array(
        [bool(len(p.contacts)) and 3 * len(p.contacts) == p.row_count for _, p in problems]
    )
    lines = [
        _table(
            table,
            np.ones(len(problems), bool),
            sizes,
            tolerance,
            "All problems (shared set and the recorded cube steps), refsim's solvers",
        ),
        "",
        _table(
            table,
            contact_only,
            sizes,
            tolerance,
            "Contact-only problems (3-D Coulomb; the problems Siconos' fc3d solvers take)",
        ),
        "",
        _ratio_table(table, sizes, tolerance),
    ]
    _figure(table, sizes, tolerance, output.with_suffix(".png"))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "-o", "--output", type=Path, default=Path(__file__).resolve().parent / "output" / "solvers.h5"
    )
    parser.add_argument("--data", type=Path, default=None, help="solver-problems folder")
    parser.add_argument("--benchmark", action="store_true", help="only the exact-solver benchmark (issue 15)")
    parser.add_argument(
        "--benchmark-output",
        type=Path,
        default=Path(__file__).resolve().parent / "output" / "exact_benchmark.h5",
    )
    parser.add_argument("--cube-every", type=int, default=5, help="record every n-th cube step")
    parser.add_argument(
        "--rounds",
        type=int,
        default=2,
        help="benchmark: turns of refsim's solvers and Siconos, best time over them (>= 1)",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    root = args.data or shared_problems()
    if not (root / "MANIFEST.tsv").is_file():
        raise SystemExit(f"external problems absent: {root}")
    problems = external_problems(root) + cube_problems(args.cube_every)
    if args.rounds < 1:
        parser.error(f"--rounds {args.rounds}: valid range >= 1")
    if args.benchmark:
        print(benchmark_exact(problems, args.benchmark_output, rounds=args.rounds))
        return
    path = run_study(problems, args.output)
    logger.info("wrote %s", path)


if __name__ == "__main__":
    main()
