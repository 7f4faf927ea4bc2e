"""Time the results writer per step: blocks of 1, 8, 32 and 128 steps, on the records of a cube run.

    OPENBLAS_NUM_THREADS=1 python studies/faults/bench_writer.py [--cells 8] [--steps 220]

The records are computed once, kept in memory, then written again and again, so only the writer is timed
(the file is flushed and closed each time, as `refsim run` does).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path


def main(argv=None) -> None:
    from refsim.io import ResultWriter
    from refsim.scene import load_scene
    from refsim.simulation import Simulation

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=8)
    parser.add_argument("--steps", type=int, default=220)
    args = parser.parse_args(argv)
    scene = load_scene("cube", [f"mesh.cells=[{args.cells}, {args.cells}, {args.cells}]"])
    simulation = Simulation(scene)
    records = []
    simulation.run(steps=args.steps, on_step=lambda state, record: records.append(record))
    print(
        f"cube {args.cells}^3 cells, {len(records)} steps, tissue recorded every {scene.output.tissue_every}"
    )
    with tempfile.TemporaryDirectory() as folder:
        for block in (1, 8, 32, 128):
            best = float("inf")
            for repeat in range(3):
                path = Path(folder) / f"w{block}_{repeat}.h5"
                start = time.perf_counter()
                with ResultWriter(path, scene, simulation.models, buffer_steps=block) as writer:
                    for record in records:
                        writer.append(record)
                best = min(best, time.perf_counter() - start)
            print(f"block of {block:4d} steps: {1e3 * best / len(records):6.3f} ms per step")


if __name__ == "__main__":
    main()
