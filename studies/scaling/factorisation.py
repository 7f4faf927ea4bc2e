"""The exact mode's numeric factorisation: refsim's supernodal Cholesky against PARDISO's phase 22, one
thread.

For each matrix (the cube's step matrix at 8, 12 and 16 cells per axis, the medium liver phantom's), both
solvers are analysed once, then their numeric factorisations are timed alternately (``--rounds`` rounds of
one factorisation each), so that a loaded machine slows both alike: read the ratios of one run. Also: the
supernodal solver with fundamental supernodes only (no relaxed amalgamation) and with SuperLU's
minimum-degree ordering, the SuperLU reference of ``refsim bench``, the analysis (symbolic) times, and the
solves of a step (a full solve, the partial inverse block on 21 marked DoFs, the solve of a load on them)
against PARDISO's, marked alike.

Run: ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 python studies/scaling/factorisation.py``
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import scipy.sparse as sp

from refsim.fem.bench import _DT, bench_model, cube_model
from refsim.fem.linear import PardisoSolver, SuperLUSolver, SupernodalSolver
from refsim.fem.supernodal import SymbolicFactor
from refsim.fem.threads import hot_path_threads, thread_settings
from refsim.fem.tissue import TissueModel, TissueState


def step_matrix(model: TissueModel) -> sp.csr_matrix:
    state = TissueState(positions=model.rest_positions, velocities=np.zeros_like(model.rest_positions))
    matrix = sp.csr_matrix(model.assemble_step(state, _DT).matrix)
    matrix.sort_indices()
    return matrix


def liver_model() -> TissueModel:
    """The medium liver phantom (10,523 tets), its lowest 10 % of nodes (by z) fixed."""
    from refsim.mesh.phantom import liver_phantom

    mesh = liver_phantom("medium")
    rest = np.asarray(mesh.rest_positions, dtype=float)
    low = rest[:, 2].min() + 0.1 * np.ptp(rest[:, 2])
    return bench_model(mesh, np.flatnonzero(rest[:, 2] < low))


def _reference(key: str) -> str:
    """What a timing is compared with: PARDISO's phase 22 for a factorisation, PARDISO's own for a solve."""
    return key.split()[0] + " pardiso" if " " in key else "pardiso22"


def measure(name: str, matrix: sp.csr_matrix, rounds: int) -> dict:
    upper = sp.triu(matrix, format="csr")
    upper.sort_indices()
    pardiso = PardisoSolver()
    start = time.perf_counter()
    pardiso.factorise(upper)
    pardiso_analysis = time.perf_counter() - start
    order = pardiso.fill_reducing_order(upper)
    minimum_degree = SupernodalSolver("minimum-degree")._order(upper)
    start = time.perf_counter()
    relaxed = SymbolicFactor(upper, order)
    analysis = time.perf_counter() - start
    fundamental = SymbolicFactor(upper, order, relaxation=())
    degree = SymbolicFactor(upper, minimum_degree)
    # the solves a step makes: the free motion's, W's partial inverse block on 21 DoFs (7 nodes) and the
    # correction's solve of a load on them
    supernodal = SupernodalSolver()
    supernodal.factorise(upper)
    marks = np.arange(matrix.shape[0] // 2, matrix.shape[0] // 2 + 21)
    rhs = np.linspace(-1.0, 1.0, matrix.shape[0])
    load = np.zeros(matrix.shape[0])
    load[marks] = 1.0
    marked_pardiso = PardisoSolver()
    for solver in (supernodal, marked_pardiso):
        solver.mark(marks)
        solver.factorise(upper)
    candidates = {
        "pardiso22": lambda: pardiso._call(22),
        "supernodal": lambda: relaxed.factorise(upper.data),
        "fundamental": lambda: fundamental.factorise(upper.data),
        "supernodal_mmd": lambda: degree.factorise(upper.data),
        # a new SuperLU solver each time: one that factorised these values keeps its factor
        "superlu_colamd": lambda: SuperLUSolver("COLAMD").factorise(matrix),
        "solve pardiso": lambda: marked_pardiso.solve(rhs),
        "solve supernodal": lambda: supernodal.solve(rhs),
        "block21 pardiso": lambda: marked_pardiso.inverse_block(marks),
        "block21 supernodal": lambda: supernodal.inverse_block(marks),
        "marked pardiso": lambda: marked_pardiso.solve_marked(load),
        "marked supernodal": lambda: supernodal.solve_marked(load),
    }
    times = {key: [] for key in candidates}
    for _ in range(rounds):
        for key, run in candidates.items():
            start = time.perf_counter()
            run()
            times[key].append(time.perf_counter() - start)
    best = {key: 1e3 * min(values) for key, values in times.items()}
    # the median over rounds of each round's ratio to its reference (paired: one round's calls share the
    # machine's load of that moment)
    paired = {
        key: float(np.median(np.divide(values, times[_reference(key)]))) for key, values in times.items()
    }
    median = {key: 1e3 * float(np.median(values)) for key, values in times.items()}
    return {
        "matrix": name,
        "n": matrix.shape[0],
        "nnz_A": matrix.nnz,
        "nnz_L_pardiso": int(pardiso._iparm[17]),
        "nnz_L_supernodal": relaxed.nnz,
        "supernodes": relaxed.first.size - 1,
        "supernodes_fundamental": fundamental.first.size - 1,
        "nnz_L_mmd": degree.nnz,
        "analysis_ms": 1e3 * analysis,
        "pardiso_analysis_ms": 1e3 * pardiso_analysis,
        "best": best,
        "median": median,
        "paired": paired,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--cells", type=int, nargs="+", default=[8, 12, 16])
    parser.add_argument("--no-liver", action="store_true")
    arguments = parser.parse_args()
    matrices = [(f"cube {cells}", step_matrix(cube_model(cells))) for cells in arguments.cells]
    if not arguments.no_liver:
        matrices.append(("liver medium", step_matrix(liver_model())))
    # compile (or load) the kernels before timing
    SymbolicFactor(matrices[0][1], np.arange(matrices[0][1].shape[0])).factorise(matrices[0][1].data)
    with hot_path_threads():
        print(
            "threads:", "; ".join(f"{s['library']} {s['version']} {s['threads']}" for s in thread_settings())
        )
        for name, matrix in matrices:
            row = measure(name, matrix, arguments.rounds)
            best, median = row["best"], row["median"]
            print(
                f"{name}: n {row['n']}, nnz(A) {row['nnz_A']}, nnz(L) pardiso {row['nnz_L_pardiso']} "
                f"supernodal {row['nnz_L_supernodal']} (mmd {row['nnz_L_mmd']}), supernodes "
                f"{row['supernodes']} (fundamental {row['supernodes_fundamental']}), analysis "
                f"{row['analysis_ms']:.1f} ms (pardiso phase 11 {row['pardiso_analysis_ms']:.1f} ms)"
            )
            for key in best:
                reference = _reference(key)
                print(
                    f"    {key:18s} best {best[key]:8.3f} ms  median {median[key]:8.3f} ms  "
                    f"best/{reference} {best[key] / best[reference]:.2f}  "
                    f"median of the rounds' ratios {row['paired'][key]:.2f}"
                )


if __name__ == "__main__":
    main()
