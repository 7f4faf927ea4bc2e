"""Gauss–Seidel against the exact mode on the cutting cases of the agreement test, as a table: tears, whether
the events (names and steps) are the same, the largest difference of the needle forces, Gauss–Seidel's sweeps
while cutting (mean, max; its cap is 1,000) and the smallest λ_min/λ_max of the cut block over the cutting
steps.

    PYTHONPATH=. python studies/cutting/agreement.py

The cases are those of tests/simulation/test_cutting.py::test_gauss_seidel_and_exact_agree_on_the_events.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

NAMES = ("x", "diagonal", "tilt-30", "entry-vertex", "entry-edge", "d_c-0.25", "d_c-2", "turn-L")


def main() -> int:
    from tests.simulation.cutting_cases import CuttingCase, run_case
    from tests.simulation.test_cutting import CASES, TURNING

    print(
        "| case (GS and exact) | tears | same events | max \\|F_GS − F_exact\\| [N] | sweeps mean (max) "
        "| min λ_min/λ_max |"
    )
    print("|---|---|---|---|---|---|")
    for name in NAMES:
        case = {**CASES, **TURNING}[name]
        iterative = run_case(case)
        exact = run_case(
            CuttingCase(**{**case.__dict__, "overrides": case.overrides + ('solver.method="exact"',)})
        )
        forces = [np.stack([r.needle_force for r in run.records]) for run in (iterative, exact)]
        sweeps = [
            r.solver.iterations for r in iterative.records if r.phase == "cutting" and r.solver is not None
        ]
        ratio = min(b.smallest / b.largest for b in iterative.blocks + exact.blocks)
        same = "yes" if iterative.events == exact.events else "no"
        print(
            f"| {name} | {iterative.count('tear')} | {same} | {np.abs(forces[0] - forces[1]).max():.1e} | "
            f"{np.mean(sweeps):.1f} ({max(sweeps)}) | {ratio:.2f} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
