"""Peak memory of the cube scene (build and 5 steps) against its tet count: the source of
refsim.scene.build.BYTES_PER_TET.

    OPENBLAS_NUM_THREADS=1 python studies/faults/memory_per_tet.py

Each size runs in its own process (the peak resident set size, ru_maxrss, only grows); prints one JSON line
per size and the marginal bytes per tetrahedron between consecutive sizes.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys


def measure(cells: int) -> dict:
    from refsim.scene import load_scene
    from refsim.simulation import Simulation

    scene = load_scene("cube", [f"mesh.cells=[{cells}, {cells}, {cells}]", "time.duration=0.05"])
    Simulation(scene).run(steps=5)
    return {
        "cells": cells,
        "tets": 6 * cells**3,
        "peak_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
    }


def main() -> None:
    if len(sys.argv) > 1:
        print(json.dumps(measure(int(sys.argv[1]))))
        return
    rows = []
    for cells in (4, 8, 12, 16, 20):
        done = subprocess.run(
            [sys.executable, __file__, str(cells)], capture_output=True, text=True, check=True
        )
        rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), flush=True)
    for a, b in zip(rows[:-1], rows[1:], strict=True):
        per_tet = 1024 * (b["peak_kb"] - a["peak_kb"]) / (b["tets"] - a["tets"])
        print(f"{a['cells']}^3 -> {b['cells']}^3 cells: {per_tet:.0f} bytes per tetrahedron")


if __name__ == "__main__":
    main()
