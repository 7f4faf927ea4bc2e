"""Cost of W and the correction for one step's rows: unit loads on every DoF touched (the former exact path)
against min(rows, DoFs) loads and the factor's forward half (the current one), interleaved in one process.

    OPENBLAS_NUM_THREADS=1 python studies/coupling_cost/bench_compliance.py cube [section.key=value ...]

Runs the scene, keeps the tissue's step system and rows of the last step, then times ``delassus`` +
``correction`` 10 times each way (the former path is the strategy's generic one, taken by hiding the exact
factor's solves) and prints the medians, their ratio and the relative difference of W and of the correction.
"""

from __future__ import annotations

import sys
import time

import numpy as np
import scipy.sparse as sp

from refsim.scene import load_scene
from refsim.simulation import Simulation, bodies


def main(argv: list[str]) -> None:
    captured = {}
    original = bodies.TissueBody.compliance

    def spy(system, jacobian):
        captured["args"] = (system, jacobian)
        return original(system, jacobian)

    bodies.TissueBody.compliance = staticmethod(spy)
    Simulation(load_scene(argv[0], argv[1:])).run()
    bodies.TissueBody.compliance = original
    system, jacobian = captured["args"]
    rows = sp.csr_matrix(jacobian)
    touched = np.unique(rows.indices).size
    print(f"rows {rows.shape[0]}, DoFs touched {touched}, free DoFs {system.free_dofs.size}")
    multipliers = np.random.default_rng(0).standard_normal(rows.shape[0])

    def timed(former: bool):
        system._cache_key = None
        saved = (system._solve, system._half)
        if former:
            system._solve, system._half = None, None
        start = time.perf_counter()
        w = system.delassus(rows)
        correction = system.correction(rows, multipliers)
        seconds = time.perf_counter() - start
        system._solve, system._half = saved
        return seconds, w, correction

    seconds = {True: [], False: []}
    for _ in range(10):
        for former in (True, False):
            seconds[former].append(timed(former)[0])
    _, w0, c0 = timed(True)
    _, w1, c1 = timed(False)
    before, after = np.median(seconds[True]), np.median(seconds[False])
    print(f"former {1e3 * before:.2f} ms, current {1e3 * after:.2f} ms, ratio {before / after:.2f}")
    print(
        f"relative difference: W {np.abs(w0 - w1).max() / np.abs(w0).max():.1e}, "
        f"correction {np.abs(c0 - c1).max() / np.abs(c0).max():.1e}"
    )


if __name__ == "__main__":
    main(sys.argv[1:])
