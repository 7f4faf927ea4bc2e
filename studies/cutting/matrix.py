"""The cutting variant matrix of issue 11, as a table: for each case the tears, the cut's extent along ĉ, the
largest needle-to-cut distance (normal to the cut, of a needle sample in it) and its bound at that step, the
topology, the peak force, ms per cutting step, and how well posed the cut block is: the solver's sweeps while
cutting (mean, max; Gauss–Seidel's cap is 1,000), the steps not converged, and the smallest λ_min/λ_max of the
cut rows' W + diag(C) over the cutting steps.

    PYTHONPATH=. python studies/cutting/matrix.py [--solver exact]

The cases are those of tests/simulation/test_cutting.py (tests/simulation/cutting_cases.py builds them).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))


def main(argv=None) -> int:
    from tests.simulation.cutting_cases import CuttingCase, run_case
    from tests.simulation.test_cutting import CASES

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--solver", default="gauss_seidel", choices=("gauss_seidel", "exact"))
    args = parser.parse_args(argv)
    print(
        "| case | cut start | tears | extent [mm] | stroke [mm] | needle-to-cut [mm] | its bound [mm] | disc "
        "| peak [N] "
        "| ms/cutting step | sweeps mean (max) | not converged | min λ_min/λ_max |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, case in sorted(CASES.items()):
        case = CuttingCase(
            **{**case.__dict__, "overrides": case.overrides + (f'solver.method="{args.solver}"',)}
        )
        run = run_case(case)
        # The simulation's own time per cutting step (its stages; not this script's measurements).
        cutting = [sum(r.stage_seconds.values()) for r in run.records if r.phase == "cutting"]
        peak = max(np.linalg.norm(r.needle_force) for r in run.records)
        sweeps = [r.solver.iterations for r in run.records if r.phase == "cutting" and r.solver is not None]
        failed = sum(1 for r in run.records if r.solver is not None and not r.solver.converged)
        ratio = min(b.smallest / b.largest for b in run.blocks) if run.blocks else float("nan")
        # The bound of the step where the needle is farthest from the cut (C λ plus the linearisation's
        # share).
        worst = max(run.offsets, key=lambda o: o[1]) if run.offsets else (0, 0.0, 0.0)
        print(
            f"| {name} | {run.first('cut_start')} | {run.count('tear')} | {run.extent() * 1e3:.2f} | "
            f"{np.linalg.norm(case.stroke) * 1e3:.1f} | {run.needle_to_cut * 1e3:.3f} | {worst[2] * 1e3:.3f} "
            f"| "
            f"{run.topology.is_disc} | "
            f"{peak:.2f} | {1e3 * np.mean(cutting):.0f} | {np.mean(sweeps):.1f} ({max(sweeps)}) | {failed} | "
            f"{ratio:.2f} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
