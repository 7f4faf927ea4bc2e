"""The exact solver's floor on small problems: µs per call of its layers on fresh copies of a problem.

Usage::

    python studies/solvers/entry_floor.py [--below 30] [--calls 2000] [--repeats 5]

For every contact-only problem of the shared set with fewer than ``--below`` rows, on ``dataclasses.replace``
copies (nothing cached on the problem, as for a new simulation step), best of ``--repeats`` batches of
``--calls`` calls, µs per call of: the layered set-up (``block_arrays`` and ``data_scales``: what problems of
120 rows or more run before the kernel), the compiled call alone (``_dense_newton_fresh``:
set-up with group friction merged, ‖δ_free‖, W's asymmetry, the kernel's buffers and the dense Newton kernel
with the pre-sweeps), ``solve_newton`` with the pre-sweeps and stall rule of ``method="auto"`` (the compiled
call and its Python layer), ``solve_exact(method="auto")`` (its checks and the report on top). The differences
are the layers' costs. Prints one line per problem and the medians, with the machine's load average.
"""

from __future__ import annotations

import os

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from run import external_problems, shared_problems  # noqa: E402

from refsim.solvers import solve_exact  # noqa: E402
from refsim.solvers.exact import _AUTO_STALL, _presweep_budget  # noqa: E402
from refsim.solvers.laws import block_arrays, law_arrays  # noqa: E402
from refsim.solvers.newton import _dense_newton_fresh, solve_newton  # noqa: E402
from refsim.solvers.residual import data_scales  # noqa: E402

TOLERANCE = 1e-8


def per_call(function, problem, calls: int, repeats: int) -> float:
    """Best over ``repeats`` batches of the mean µs of ``function(copy)`` over ``calls`` fresh copies."""
    best = np.inf
    for _ in range(repeats):
        copies = [dataclasses.replace(problem) for _ in range(calls)]
        start = time.perf_counter()
        for copy in copies:
            function(copy)
        best = min(best, (time.perf_counter() - start) / calls * 1e6)
    return best


def compiled_call(problem) -> None:
    """The one compiled call of solve_newton on a small fresh problem, with solve_newton's arguments."""
    p = problem
    _dense_newton_fresh(
        p.compliance,
        p.free_gap,
        law_arrays(p),
        np.zeros(p.row_count),
        TOLERANCE,
        100,
        1e-2,
        3,
        _AUTO_STALL,
        _presweep_budget(p.row_count),
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--below", type=int, default=30)
    parser.add_argument("--calls", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)
    problems = [
        p
        for _, p in external_problems(shared_problems())
        if len(p.contacts) and 3 * len(p.contacts) == p.row_count and p.row_count < args.below
    ]
    print(f"load average at start {os.getloadavg()[0]:.2f}; {len(problems)} problems below {args.below} rows")
    measures = {
        "set-up": lambda p: (block_arrays(p), data_scales(p)),
        "compiled call": compiled_call,
        "solve_newton": lambda p: solve_newton(
            p, tolerance=TOLERANCE, presweeps=_presweep_budget(p.row_count), stall_iterations=_AUTO_STALL
        ),
        "solve_exact": lambda p: solve_exact(p, tolerance=TOLERANCE, method="auto"),
    }
    for function in measures.values():  # compiled kernels loaded
        function(dataclasses.replace(problems[0]))
    table = []
    for problem in problems:
        row = [per_call(function, problem, args.calls, args.repeats) for function in measures.values()]
        table.append(row)
        print(
            f"{problem.name[:36]:36s} {problem.row_count:3d} rows: "
            + ", ".join(f"{name} {value:.1f} µs" for name, value in zip(measures, row, strict=True))
        )
    medians = np.median(np.array(table), axis=0)
    print(
        "median: "
        + ", ".join(f"{name} {value:.1f} µs" for name, value in zip(measures, medians, strict=True))
    )
    print(f"load average at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
