"""Solver study: error against iterations and time for Gauss–Seidel and the exact solver (writes HDF5).

Usage::

    python studies/solvers/run.py [-o studies/solvers/output/solvers.h5] [--data PATH]

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
    root = Path(base) if base else Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
    return root / "solver-problems"


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
        Simulation(scene).run(on_step=lambda state, record: records.append(record))
        start = 0
        if family == "cube cutting":
            start = next(r.step for r in records if any(e.name == "cut_start" for e in r.events))
        kept = [r for r in records if r.problem is not None and r.step >= start and r.step % every == 0]
        problems.extend((family, dataclasses.replace(r.problem, name=f"{scene_name}_step_{r.step:04d}"))
                        for r in kept)
        logger.info("%s: %d problems recorded", family, len(kept))
    return problems


def _gap_error(problem: ConstraintProblem, multipliers: np.ndarray,
               reference_gap: np.ndarray | None) -> float:
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
    group.attrs.update(family=family, rows=problem.row_count, contacts=len(problem.contacts),
                       asymmetry=problem.asymmetry(),
                       rank=int(np.linalg.matrix_rank(problem.compliance)) if problem.row_count else 0,
                       has_friction=bool(len(problem.contacts) or len(problem.shaft_friction)))
    reference_gap = None
    for backend in backends:
        sub = group.create_group(f"exact/{backend}")
        try:
            multipliers, report = solve_exact(problem, tolerance=EXACT_TOLERANCE, backend=backend,
                                              symmetry_tolerance=SYMMETRY_TOLERANCE)
        except ValueError as error:
            sub.attrs.update(status="rejected", message=str(error), residual=np.nan, seconds=np.nan,
                             iterations=0, converged=False)
            continue
        sub.attrs.update(status="solved" if report.converged else "failed", message=report.message,
                         residual=report.residual, seconds=report.seconds, iterations=report.iterations,
                         converged=report.converged)
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
        records.append((tolerance, report.iterations, report.residual, report.seconds, report.converged,
                        _gap_error(problem, multipliers, reference_gap), report.increment))
    gs.create_dataset("tolerance_runs", data=np.array(records, dtype=float))
    gs.attrs["tolerance_runs_columns"] = ("tolerance, iterations, residual, seconds, converged, gap_error, "
                                          "increment")


def benchmark_sweeps(row_count: int = 100, sweeps: int = 1000, repeats: int = 7) -> dict[str, float]:
    """Seconds for ``sweeps`` Gauss–Seidel sweeps over ``row_count`` rows (best of ``repeats``).

    Two problems: all unilateral rows, and a needle-like mix (contacts, bilateral pairs with shaft friction).
    Every multiplier changes at every sweep (the worst case: each change costs one column update).
    """
    rng = np.random.default_rng(0)
    factor = rng.standard_normal((row_count, row_count))
    compliance = factor @ factor.T / row_count + np.eye(row_count)
    results = {}
    unilateral = ConstraintProblem(compliance=compliance,
                                   free_gap=-compliance @ rng.uniform(0.5, 1, row_count),
                                   unilateral=np.arange(row_count))
    contacts = row_count // 6
    shafts = (row_count - 3 * contacts) // 3
    used = 3 * contacts + 3 * shafts
    mixed = ConstraintProblem(
        compliance=compliance, free_gap=rng.standard_normal(row_count),
        contacts=np.arange(3 * contacts).reshape(-1, 3), contact_friction=np.full(contacts, 0.5),
        bilateral=np.concatenate([np.arange(3 * contacts, 3 * contacts + 2 * shafts),
                                  np.arange(used, row_count)]),
        shaft_friction=np.arange(3 * contacts + 2 * shafts, used),
        shaft_pairs=np.arange(3 * contacts, 3 * contacts + 2 * shafts).reshape(-1, 2),
        shaft_friction_coefficient=np.full(shafts, 0.3))
    for label, problem in (("unilateral", unilateral), ("mixed", mixed)):
        solve_gauss_seidel(problem, tolerance=0.0, max_iterations=2)  # compile / load the cache
        best = np.inf
        for _ in range(repeats):
            start = time.perf_counter()
            solve_gauss_seidel(problem, tolerance=0.0, max_iterations=sweeps)
            best = min(best, time.perf_counter() - start)
        results[label] = best
    return results


def run_study(problems: list[tuple[str, ConstraintProblem]], output: Path,
              backends: list[str] | None = None) -> Path:
    """Study ``problems`` (family, problem) and write the HDF5 file ``output``; returns its path.

    This is the hook for problems from elsewhere: pass any list of :class:`ConstraintProblem` (for instance
    recorded from the cube scene's steps, with family ``"cube"``).
    """
    backends = backends or [name for name in ("clarabel", "osqp") if name in available_backends()]
    output.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with h5py.File(output, "w") as handle:
        handle.attrs.update(schema=SCHEMA, created=time.strftime("%Y-%m-%dT%H:%M:%S"),
                            backends=backends, gs_tolerances=GS_TOLERANCES, gs_cap=GS_CAP,
                            exact_tolerance=EXACT_TOLERANCE, symmetry_tolerance=SYMMETRY_TOLERANCE)
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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", type=Path,
                        default=Path(__file__).resolve().parent / "output" / "solvers.h5")
    parser.add_argument("--data", type=Path, default=None, help="solver-problems folder")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    root = args.data or shared_problems()
    if not (root / "MANIFEST.tsv").is_file():
        raise SystemExit(f"external problems absent: {root}")
    path = run_study(external_problems(root) + cube_problems(), args.output)
    logger.info("wrote %s", path)


if __name__ == "__main__":
    main()
