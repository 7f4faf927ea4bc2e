"""Timings of the tissue's step stages per compliance strategy, for ``refsim bench`` (figures, never
asserted).

Everything here runs on the paper's 0.1 m cube (E = 500 kPa, ν = 0.4, 1000 kg/m³, dt = 0.01 s, Rayleigh 1 /
0.01, bottom face fixed, gravity) meshed with ``cells`` hexahedra per axis (6 tets each; 8 is the paper's
3,072 tets). The loaded step sequence is a **boundary motion**: the fixed bottom face is sheared along x by
``shear`` metres over the run (prescribed displacements, a Dirichlet condition), so that the tissue rotates
and the matrix changes from step to step. Each step does what the simulation does for the tissue: co-rotation
and assembly, the strategy's factorisation and free motion, W for rows on the DoFs of the 7 top nodes nearest
the centre (21 DoFs, as the cube's insertion touches) and the correction.

The reference of every ratio is **one SuperLU factorisation of the cube's matrix** as refsim did it before
(COLAMD ordering, symmetric mode), timed in the same process right before the strategies.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

from refsim.fem.compliance import STRATEGY_VARIANTS, Exact, Refreshed, make_strategy
from refsim.fem.linear import SuperLUSolver, linear_solver_info
from refsim.fem.threads import hot_path_threads, thread_settings
from refsim.fem.tissue import TissueModel, TissueState
from refsim.materials import HookeMaterial

__all__ = [
    "bench_strategies",
    "bench_scaling",
    "superlu_reference_ms",
    "growth_exponent",
    "compare_runs",
    "header_lines",
    "format_rows",
]

logger = logging.getLogger(__name__)

_CUBE_SIZE = 0.1
_MATERIAL = HookeMaterial(youngs_modulus=5.0e5, poisson_ratio=0.4, density=1000.0)
_DT = 0.01
STAGES = ("assembly", "factorisation", "free_solve", "compliance", "correction")


def _best_ms(function: Callable[[], object], repeats: int) -> tuple[float, object]:
    """Smallest wall time over ``repeats`` calls [ms], and the last result."""
    best, result = np.inf, None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        best = min(best, time.perf_counter() - start)
    return 1e3 * best, result


def bench_model(mesh, fixed_nodes: np.ndarray) -> TissueModel:
    """The benches' tissue on ``mesh`` (rest_positions, tets): the cube's material, Rayleigh damping and
    gravity, ``fixed_nodes`` held."""
    return TissueModel(
        np.asarray(mesh.rest_positions, dtype=float),
        np.asarray(mesh.tets),
        _MATERIAL,
        rayleigh_mass=1.0,
        rayleigh_stiffness=0.01,
        fixed_nodes=np.asarray(fixed_nodes),
        gravity=(0.0, 0.0, -9.81),
    )


def cube_model(cells: int) -> TissueModel:
    """The paper's cube with ``cells`` hexahedra per axis, bottom face fixed."""
    from refsim.mesh.generators import box_mesh

    mesh = box_mesh(size=(_CUBE_SIZE,) * 3, cells=(cells,) * 3, origin=(0.0, 0.0, 0.0))
    rest = np.asarray(mesh.rest_positions, dtype=float)
    return bench_model(mesh, np.flatnonzero(rest[:, 2] < 1e-9 * _CUBE_SIZE))


def _rows(model: TissueModel, nodes: int = 7) -> sp.csr_matrix:
    """Unit rows on the DoFs of the ``nodes`` top nodes nearest the top centre (3 rows per node)."""
    rest = model.rest_positions
    centre = np.array([0.5, 0.5, 1.0]) * _CUBE_SIZE
    chosen = np.argsort(np.linalg.norm(rest - centre, axis=1))[:nodes]
    dofs = (3 * chosen[:, None] + np.arange(3)).ravel()
    return sp.csr_matrix(
        (np.ones(dofs.size), (np.arange(dofs.size), dofs)), shape=(dofs.size, model.dof_count)
    )


def superlu_reference_ms(model: TissueModel, repeats: int = 3) -> float:
    """One SuperLU factorisation (COLAMD, symmetric mode: refsim before issue 12) of the model's step matrix
    [ms]."""
    state = TissueState(positions=model.rest_positions, velocities=np.zeros_like(model.rest_positions))
    with hot_path_threads():
        matrix = model.assemble_step(state, _DT).matrix
        # a new solver each time: one that factorised these values keeps its factor (refsim.fem.linear)
        return _best_ms(lambda: SuperLUSolver("COLAMD").factorise(matrix), repeats)[0]


def _run_strategy(
    model: TissueModel, strategy, steps: int, shear: float, rows: sp.csr_matrix
) -> dict[str, float | int]:
    """Time ``steps`` loaded steps of one strategy; ms per step by stage (means) and the error report."""
    body = strategy.bind()
    state = model.rest_state()
    per_step = np.zeros((steps, len(STAGES)))
    iterations, column_iterations, errors = (
        [],
        [],
        {"free_motion_error": 0.0, "compliance_error": 0.0, "correction_error": 0.0},
    )
    drive = np.zeros((model.fixed_nodes.size, 3))
    drive[:, 0] = shear / steps
    lam = 1e-2 * np.sin(np.arange(rows.shape[0]))  # forces [N] of the rows, for the correction
    with hot_path_threads():
        # One untimed set-up step: the analysis, the rest factor and dense C₀ of the precomputed strategy.
        state = _advance(model, body, state, drive, rows, lam)
        for index in range(steps):
            t0 = time.perf_counter()
            system = model.assemble_step(state, _DT, fixed_displacements=drive)
            t1 = time.perf_counter()
            step = body.step(system)
            t2 = time.perf_counter()
            step.delassus(rows)
            t3 = time.perf_counter()
            correction = step.correction(rows, lam)
            t4 = time.perf_counter()
            # body.step does the factorisation (when there is one) and the free solve: split by timing a solve
            # alone
            factorised = bool(step.report.get("refactorised", False))
            per_step[index] = [t1 - t0, t2 - t1, 0.0, t3 - t2, t4 - t3]
            if not factorised:
                per_step[index, 2], per_step[index, 1] = per_step[index, 1], 0.0
            iterations.append(step.report.get("pcg_iterations", 0))
            column_iterations.append(step.report.get("column_pcg_iterations", 0))
            for key in errors:
                errors[key] = max(errors[key], float(step.report.get(key, 0.0)))
            displacement = step.free_displacement + correction
            positions = state.positions + displacement.reshape(-1, 3)
            state = TissueState(positions=positions, velocities=displacement.reshape(-1, 3) / _DT)
    # The exact strategy's factorisation and its solve come together from body.step; time one solve apart.
    if isinstance(strategy, Exact):
        solver = body._solver
        solve_ms, _ = _best_ms(lambda: solver.solve(system.rhs), 3)
        per_step[:, 2] = 1e-3 * solve_ms
        per_step[:, 1] = np.maximum(per_step[:, 1] - 1e-3 * solve_ms, 0.0)
    # Medians over the steps (this machine is shared: a mean takes in the other users' bursts), except the
    # factorisation, whose mean is the cost per step amortised over the refresh period.
    means = 1e3 * np.median(per_step, axis=0)
    means[1] = 1e3 * per_step[:, 1].mean()
    name = strategy.name
    if isinstance(strategy, Refreshed) and strategy.compliance_update != "pcg":
        name = f"refreshed_{strategy.compliance_update}"
    out: dict[str, float | int] = {"strategy": name}
    out.update({f"{stage}_ms": float(value) for stage, value in zip(STAGES, means, strict=True)})
    out["total_ms"] = float(means.sum())
    out["pcg_iterations"] = float(np.mean(iterations))
    out["column_pcg_iterations"] = float(np.mean(column_iterations))
    out["final_max_displacement"] = float(np.abs(state.positions - model.rest_positions).max())
    if getattr(strategy, "against_exact", False):
        out.update(errors)
    return out


def _advance(model, body, state, drive, rows, lam) -> TissueState:
    step = body.step(model.assemble_step(state, _DT, fixed_displacements=drive))
    step.delassus(rows)
    displacement = step.free_displacement + step.correction(rows, lam)
    return TissueState(
        positions=state.positions + displacement.reshape(-1, 3), velocities=displacement.reshape(-1, 3) / _DT
    )


def bench_strategies(
    cells: int = 8,
    *,
    strategies: tuple[str, ...] = STRATEGY_VARIANTS,
    steps: int = 30,
    shear: float = 0.01,
    refresh_every: int = 10,
    against_exact: bool = True,
    linear_solver: str = "auto",
) -> tuple[float, list[dict[str, float | int]]]:
    """ms per step by stage of each strategy on the loaded cube, and the SuperLU reference of the same run.

    Returns
    -------
    The SuperLU (COLAMD) factorisation time of the cube's matrix [ms], and one dict per strategy:
    ``strategy``, ``assembly_ms`` (co-rotation, forces and A in the fixed pattern), ``factorisation_ms`` (mean
    per step: every step for exact, every ``refresh_every`` for refreshed, none for precomputed after its
    set-up), ``free_solve_ms`` (the solve or the PCG), ``compliance_ms`` (W for 21 rows), ``correction_ms``,
    ``total_ms``, ``pcg_iterations`` (mean), and with ``against_exact`` the largest per-step errors against an
    exact factorisation of the same matrices (``free_motion_error`` [m], ``compliance_error`` relative
    Frobenius, ``correction_error`` [m]).
    """
    model = cube_model(cells)
    rows = _rows(model)
    reference = superlu_reference_ms(model, repeats=5)
    results = []
    for name in strategies:
        strategy = make_strategy(
            name,
            refresh_every=refresh_every,
            against_exact=against_exact and name != "exact",
            linear_solver=linear_solver,
        )
        _run_strategy(model, strategy, 1, shear, rows)  # warm-up: numba compilation
        results.append(_run_strategy(model, strategy, steps, shear, rows))
        if against_exact and name != "exact":
            # Timings without the error bookkeeping (it runs an exact factorisation each step)
            timed = _run_strategy(
                model,
                make_strategy(name, refresh_every=refresh_every, linear_solver=linear_solver),
                steps,
                shear,
                rows,
            )
            errors = {
                k: results[-1][k] for k in ("free_motion_error", "compliance_error", "correction_error")
            }
            results[-1] = {**timed, **errors}
        logger.info("strategy bench: %s", results[-1])
    return reference, results


def growth_exponent(sizes: np.ndarray, costs: np.ndarray) -> float:
    """Least-squares slope of log(cost) against log(size): cost ∝ size^p."""
    sizes, costs = np.asarray(sizes, dtype=float), np.asarray(costs, dtype=float)
    keep = (sizes > 0) & (costs > 0)
    if keep.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(sizes[keep]), np.log(costs[keep]), 1)[0])


def bench_scaling(
    cells_per_axis: tuple[int, ...] = (8, 12, 16, 24),
    *,
    steps: int = 10,
    refresh_every: int = 10,
    strategies: tuple[str, ...] = tuple(name for name in STRATEGY_VARIANTS if name != "precomputed"),
    linear_solver: str = "auto",
    max_step_seconds: float = 30.0,
) -> list[dict[str, float | int]]:
    """Cost per step of each strategy on refined cubes (the loaded step sequence of :func:`bench_strategies`).

    Sizes after one whose exact step took longer than ``max_step_seconds`` are skipped (logged).

    Returns
    -------
    One dict per size: ``cells_per_axis``, ``free_dofs``, ``exact_factorisation_ms``, then per strategy
    ``<name>_ms`` (mean per step over ``steps`` steps; the refreshed factorisation amortised over
    ``refresh_every``) and ``<name>_compliance_ms`` (W and correction), and ``pcg_iterations`` (free motion,
    refreshed).
    """
    out = []
    for cells in cells_per_axis:
        model = cube_model(int(cells))
        rows = _rows(model)
        _run_strategy(model, Exact(linear_solver=linear_solver), 1, 0.01, rows)  # numba, analysis
        row: dict[str, float | int] = {
            "cells_per_axis": int(cells),
            "free_dofs": int(model.dof_count - model.fixed_dofs.size),
        }
        for name in strategies:
            result = _run_strategy(
                model,
                make_strategy(name, refresh_every=refresh_every, linear_solver=linear_solver),
                steps,
                0.01,
                rows,
            )
            if name == "exact":
                row["exact_factorisation_ms"] = result["factorisation_ms"]
            row[f"{name}_ms"] = result["total_ms"]
            row[f"{name}_compliance_ms"] = result["compliance_ms"] + result["correction_ms"]
            if name == "refreshed":
                row["pcg_iterations"] = result["pcg_iterations"]
        logger.info("scaling bench: %s", row)
        out.append(row)
        if row.get("exact_ms", 0.0) > 1e3 * max_step_seconds:
            logger.warning(
                "exact step took %.1f s on %d cells per axis: larger sizes skipped",
                row["exact_ms"] / 1e3,
                cells,
            )
            break
    return out


def compare_runs(reference: dict, candidate: dict) -> dict[str, float | bool | str]:
    """Errors of a run against the exact run of the same scene.

    Parameters
    ----------
    reference, candidate : ``{"tissue_positions": (steps, n, 3), "needle_force": (steps, 3),
        "events": [(step, name), ...]}`` of the two runs.

    Returns
    -------
    ``position_error`` (largest |Δx| over steps and nodes [m]), ``force_error`` (largest |ΔF| of the needle
    force [N]), ``peak_force`` of the reference [N], ``same_events`` and, when they differ, ``event_shift``
    (the steps of the first differing events).
    """
    x_ref, x = np.asarray(reference["tissue_positions"]), np.asarray(candidate["tissue_positions"])
    f_ref, f = np.asarray(reference["needle_force"]), np.asarray(candidate["needle_force"])
    steps = min(len(x_ref), len(x))
    force_steps = min(len(f_ref), len(f))
    events_ref, events = list(reference["events"]), list(candidate["events"])
    out: dict[str, float | bool | str] = {
        "position_error": float(np.abs(x_ref[:steps] - x[:steps]).max()) if steps else float("nan"),
        "force_error": float(np.linalg.norm(f_ref[:force_steps] - f[:force_steps], axis=1).max())
        if force_steps
        else float("nan"),
        "peak_force": float(np.linalg.norm(f_ref, axis=1).max()) if len(f_ref) else float("nan"),
        "same_events": events_ref == events,
    }
    if events_ref != events:
        first = next(
            (i for i, (a, b) in enumerate(zip(events_ref, events, strict=False)) if a != b),
            min(len(events_ref), len(events)),
        )
        out["event_shift"] = (
            f"event {first}: exact {events_ref[first] if first < len(events_ref) else None}, "
            f"this {events[first] if first < len(events) else None}; counts {len(events_ref)} / {len(events)}"
        )
    return out


def header_lines() -> list[str]:
    """Thread settings (outside and inside refsim's hot path) and the linear solver with its versions."""
    lines = ["thread pools outside the hot path: " + _threads_text(thread_settings())]
    with hot_path_threads():
        lines.append("thread pools inside the hot path:  " + _threads_text(thread_settings()))
    info = linear_solver_info()
    lines.append(
        f"linear solver: {info['linear_solver']} (available {', '.join(info['available'])}; "
        f"${'REFSIM_LINEAR_SOLVER'}={info['environment'] or 'unset'}); scipy {info['scipy']}, pypardiso "
        f"{info['pypardiso']}, mkl {info['mkl']}"
    )
    return lines


def _threads_text(settings: list[dict]) -> str:
    return ", ".join(f"{s['library']} {s['version']} ({s['api']}) {s['threads']} thread(s)" for s in settings)


def format_rows(rows: list[dict], keys: list[str] | None = None) -> str:
    """A plain-text table of dicts (numbers to 4 significant digits)."""
    if not rows:
        return ""
    keys = keys or list(rows[0].keys())
    cells = [
        [f"{row.get(k, ''):.4g}" if isinstance(row.get(k), float) else str(row.get(k, "")) for k in keys]
        for row in rows
    ]
    # Each column as wide as its widest cell or heading, so that no value runs into the next column.
    widths = [max(len(k), *(len(line[i]) for line in cells)) for i, k in enumerate(keys)]
    lines = ["  ".join(f"{k:>{w}}" for k, w in zip(keys, widths, strict=True))]
    lines += ["  ".join(f"{c:>{w}}" for c, w in zip(line, widths, strict=True)) for line in cells]
    return "\n".join(lines)
