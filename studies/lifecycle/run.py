"""Random needle lives on cube_cut (4³ cells; ``--family model`` draws the mesh and the model's values too,
``--family two`` a second needle that holds beside the one that cuts): run a range of seeds, check every step
of each against the invariants of `refsim.verification.invariants`, write one JSON line per seed and print a
table.

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 \\
        python studies/lifecycle/run.py --seeds 0 200 [--workers 2] [--out studies/lifecycle/results.jsonl]
    python studies/lifecycle/run.py --trace 1124 [--steps 220 240]   # one seed, step by step
    python studies/lifecycle/run.py --family model --seeds 0 200   # the mesh and the model's values drawn too

``--seeds A B`` runs seeds A, A+1, ..., B−1; ``--resume`` keeps the seeds the output file already holds;
``--budget-minutes M`` starts no seed after M minutes (one worker). Each line holds the life's parameters and
overrides (paste them into ``load_scene("cube_cut", [...])`` to run it again), its status (``ok``,
``violation``, ``error``: the run raised), the first violation of each invariant, the peak needle force, the
peak of ‖F‖ / (f_p + G_c L_in) over its steps (the force invariant allows 2), the events and the
wall time. The default test suite runs seeds 0–5 and the slow set 6–199
(``tests/simulation/test_random_life_cycles.py``); this study runs any range, for a campaign.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
import traceback
from collections import Counter
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_name, "1")


def _run(life, on_record=None):
    """Run a life: (scene, records, error), error a dict when the run raised."""
    from refsim.simulation import Simulation

    scene = life.scene()
    records = []

    def on_step(state, record):
        records.append(record)
        if on_record is not None:
            on_record(record)

    error = None
    try:
        Simulation(scene).run(on_step=on_step)
    except Exception as caught:  # noqa: BLE001 - any exception of a run is a finding
        frames = [f for f in traceback.extract_tb(caught.__traceback__) if "/refsim/" in f.filename]
        error = {
            "type": type(caught).__name__,
            "message": str(caught)[:2000],
            "where": f"{frames[-1].filename.split('/refsim/', 1)[1]}:{frames[-1].lineno}" if frames else None,
            "after_step": int(records[-1].step) if records else 0,
        }
    return scene, records, error


def run_seed(seed: int, family: str = "cube") -> dict:
    """Draw, run and check one seed of ``family``: its JSON line as a dict."""
    import numpy as np

    from refsim.verification.invariants import (
        NO_ROW_FORCE,
        inserted_lengths,
        life_violations,
        shaft_contact_loads,
    )
    from refsim.verification.life_cycles import draw_life

    logging.getLogger("refsim").setLevel(logging.ERROR)  # the scene's notes on fast needles, every life
    life = draw_life(seed, family)
    started = time.perf_counter()
    scene, records, error = _run(life)
    seconds = time.perf_counter() - started
    reference = scene.insertion.puncture_force, scene.cutting.fracture_energy
    forces = np.array([float(np.linalg.norm(record.needle_force)) for record in records])
    ratios = forces / (reference[0] + reference[1] * inserted_lengths(records, scene))
    shaft = shaft_contact_loads(records)
    ratios[shaft > NO_ROW_FORCE] = np.nan  # the shaft contact has no law's limit (invariants, force_bound)
    peak_force = float(forces.max()) if forces.size else 0.0
    valid = np.isfinite(ratios)
    at = int(np.argmax(np.where(valid, ratios, -1.0))) if valid.any() else None
    peak_ratio = float(ratios[at]) if at is not None else 0.0
    ratio_step = int(records[at].step) if at is not None else None
    violations = {
        v.invariant: {"step": v.step, "time": v.time, "phase": v.phase, "detail": v.detail}
        for v in life_violations(records, scene)
    }
    status = "error" if error else ("violation" if violations else "ok")
    return {
        "seed": seed,
        "family": family,
        "status": status,
        "life": life.describe(),
        "overrides": list(life.overrides),
        "steps": len(records),
        "peak_force": round(peak_force, 4),
        "peak_ratio": round(peak_ratio, 4),
        "peak_ratio_step": ratio_step,
        "shaft_contact_peak": round(float(shaft.max()) if shaft.size else 0.0, 4),
        # every instrument's largest element strain (0 for rigid needles; InstrumentRecord.needle_strain)
        "needle_strain_peak": max(
            (float(part.needle_strain) for record in records for part in record.instruments), default=0.0
        ),
        "events": dict(Counter(e.name for r in records for e in r.events)),
        "violations": violations,
        "error": error,
        "wall_seconds": round(seconds, 2),
    }


def summary(lines: list[dict]) -> str:
    """One row per seed, then the totals."""
    from refsim.simulation.needle_body import STRAIN_WARNING

    header = (
        f"{'seed':>5} {'status':<9} {'steps':>5} {'peak N':>7} {'ratio':>6} {'s':>6}  events / violations"
    )
    rows = [header, "-" * len(header)]
    for line in sorted(lines, key=lambda item: item["seed"]):
        text = " ".join(f"{k}:{v}" for k, v in sorted(line["events"].items()))
        if line["violations"]:
            text += " | " + "; ".join(f"{name}@{info['step']}" for name, info in line["violations"].items())
        if line["error"]:
            text += f" | {line['error']['type']} at {line['error']['where']}"
        rows.append(
            f"{line['seed']:>5} {line['status']:<9} {line['steps']:>5} {line['peak_force']:>7.3f} "
            f"{line['peak_ratio']:>6.2f} {line['wall_seconds']:>6.1f}  {text}"
        )
    rows.append("-" * len(header))
    status = Counter(line["status"] for line in lines)
    rows.append(f"seeds: {len(lines)}  " + "  ".join(f"{k}: {v}" for k, v in sorted(status.items())))
    invariants = Counter(name for line in lines for name in line["violations"])
    if invariants:
        rows.append(
            "violations by invariant: " + ", ".join(f"{k}: {v}" for k, v in sorted(invariants.items()))
        )
    if lines:
        ratios = sorted(line["peak_ratio"] for line in lines)
        rows.append(
            f"peak ||F|| / (f_p + G_c L_in): median {ratios[len(ratios) // 2]:.2f}, "
            f"largest {ratios[-1]:.2f} (the invariant allows 2)"
        )
        shaft = [line.get("shaft_contact_peak", 0.0) for line in lines]
        pressed = sum(value > 0.0 for value in shaft)
        rows.append(
            f"shaft contact before a puncture (no law's limit): {pressed} lives, "
            f"largest load {max(shaft):.3g} N"
        )
        strains = [line.get("needle_strain_peak", 0.0) for line in lines]
        beyond = sum(value > STRAIN_WARNING for value in strains)
        rows.append(
            f"flexible needles' largest element strain: {max(strains):.2g} ({beyond} lives above "
            f"{STRAIN_WARNING:g}, the run's warning)"
        )
    return "\n".join(rows)


def trace(seed: int, steps: tuple[int, int] | None, family: str = "cube") -> None:
    """Run one seed and print each step (within ``steps``): phase, events, force and the load of each row
    role."""
    import numpy as np

    from refsim.verification.invariants import life_violations
    from refsim.verification.life_cycles import draw_life

    life = draw_life(seed, family)
    print(life.describe())
    print("overrides:", json.dumps(list(life.overrides)))

    def on_record(record):
        if steps is not None and not steps[0] <= record.step <= steps[1]:
            return
        roles = {}
        for role in np.unique(record.row_role):
            chosen = record.row_role == role
            load = record.row_forces[chosen] @ record.row_directions[chosen]
            roles[int(role)] = round(float(np.linalg.norm(load)), 4)
        print(
            f"step {record.step:4d} t={record.time:.3f} {record.phase!s:<9} "
            f"{','.join(e.name for e in record.events):<20} |F|={np.linalg.norm(record.needle_force):.4f} "
            f"tip={np.round(1e3 * np.asarray(record.needle_positions[-1]), 3).tolist()} mm, "
            f"load by role {roles}"
        )

    scene, records, error = _run(life, on_record)
    for violation in life_violations(records, scene):
        print(violation)
    if error:
        print("error:", error)


def main(argv=None) -> int:
    from refsim.verification.life_cycles import FAMILIES

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs=2, metavar=("FIRST", "STOP"), default=(0, 40))
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--out", type=Path, default=Path(__file__).with_name("results.jsonl"))
    parser.add_argument("--resume", action="store_true", help="keep the seeds already in --out")
    parser.add_argument("--budget-minutes", type=float, default=float("inf"), help="start no seed after this")
    parser.add_argument(
        "--family",
        choices=FAMILIES,
        default="cube",
        help="the lives' family (refsim.verification.life_cycles)",
    )
    parser.add_argument("--trace", type=int, metavar="SEED", help="run one seed step by step")
    parser.add_argument("--steps", type=int, nargs=2, metavar=("FROM", "TO"), help="with --trace")
    args = parser.parse_args(argv)
    if args.trace is not None:
        trace(args.trace, tuple(args.steps) if args.steps else None, args.family)
        return 0
    begun = time.perf_counter()
    seeds = list(range(*args.seeds))
    kept = []
    if args.resume and args.out.exists():
        kept = [json.loads(text) for text in args.out.read_text().splitlines() if text.strip()]
        kept = [line for line in kept if line.get("family", "cube") == args.family]
    done = {line["seed"] for line in kept}
    todo = [seed for seed in seeds if seed not in done]
    lines = [line for line in kept if line["seed"] in seeds]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with args.out.open("a" if args.resume else "w") as out:

        def write(line: dict) -> None:
            out.write(json.dumps(line) + "\n")
            out.flush()
            lines.append(line)
            print(f"seed {line['seed']}: {line['status']} ({line['wall_seconds']} s)", flush=True)

        if args.workers > 1:
            with ProcessPoolExecutor(max_workers=args.workers) as pool:
                for future in as_completed([pool.submit(run_seed, seed, args.family) for seed in todo]):
                    write(future.result())
        else:
            for seed in todo:
                if time.perf_counter() - begun > 60.0 * args.budget_minutes:
                    print(f"budget of {args.budget_minutes} min spent: stopped before seed {seed}")
                    break
                write(run_seed(seed, args.family))
    print(summary(lines))
    return 1 if any(line["status"] != "ok" for line in lines) else 0


if __name__ == "__main__":
    sys.exit(main())
