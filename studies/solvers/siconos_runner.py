"""Solve frictional-contact problems with Siconos (run by the system Python: Debian's python3-siconos).

Usage (called by studies/solvers/run.py in a subprocess)::

    /usr/bin/python3 studies/solvers/siconos_runner.py problems.npz results.npz

``problems.npz`` holds, for i = 0, 1, ...: W_i (3k, 3k), q_i (3k,), mu_i (k,) and ``tolerance``; the results
hold for every solver name S and problem i: ``S_r_i`` (the reactions), ``S_seconds_i`` (best of three) and
``S_info_i`` (Siconos' return code). The errors are recomputed by the caller with refsim's residual.
"""

import sys
import time

import numpy as np
import siconos.numerics as sn

SOLVERS = {
    "NSN_AC": sn.SICONOS_FRICTION_3D_NSN_AC,
    "NSGS": sn.SICONOS_FRICTION_3D_NSGS,
    "PROX": sn.SICONOS_FRICTION_3D_PROX,
    "VI_FPP": sn.SICONOS_FRICTION_3D_VI_FPP,
}


def main(source, target):
    data = np.load(source)
    tolerance = float(data["tolerance"])
    count = int(data["count"])
    results = {}
    for i in range(count):
        compliance, free, mu = data[f"W_{i}"], data[f"q_{i}"], data[f"mu_{i}"]
        problem = sn.FrictionContactProblem(
            3, np.ascontiguousarray(compliance), np.ascontiguousarray(free), np.ascontiguousarray(mu)
        )
        for name, code in SOLVERS.items():
            best, reaction, info = np.inf, None, -1
            for _ in range(3):
                options = sn.SolverOptions(code)
                options.dparam[sn.SICONOS_DPARAM_TOL] = tolerance
                options.iparam[sn.SICONOS_IPARAM_MAX_ITER] = 10000
                r = np.zeros(free.size)
                u = np.zeros(free.size)
                start = time.perf_counter()
                info = sn.fc3d_driver(problem, r, u, options)
                best = min(best, time.perf_counter() - start)
                reaction = r
            results[f"{name}_r_{i}"] = reaction
            results[f"{name}_seconds_{i}"] = best
            results[f"{name}_info_{i}"] = info
    np.savez(target, **results)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
