"""The cost of each further needle (issue 23, item 5): N parallel needles on a template grid (brachytherapy
places 10-20) inserted together into the paper's cube, the ms per step of each stage against N, and the cost
per extra needle per step (the least-squares slope over N).

    PYTHONPATH=. python studies/instruments/many_needles.py [--counts 1 2 5 10 20] [--cells 8] [--write N OUT]

Each needle is the paper's needle section with an 18 G radius (0.6 mm; the paper's 8 mm needles 5 mm apart
would overlap), entered 5 mm apart on a grid off the mesh's lines, its tip 2 mm above the top
face, pushed 12 mm deep at 10 mm/s (1.4 s), every needle at once. `--write N OUT.toml` writes the scene of N
needles (for `refsim bench OUT.toml`). Timings are wall clock of one process: compare the counts of ONE run.
"""

from __future__ import annotations

import argparse
import sys
import time
import tomllib
from importlib import resources
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

PITCH = 0.005  # 5 mm between neighbouring entries (a brachytherapy template's grid)
DEPTH = 0.012
SPEED = 0.01


def scene_dict(count: int, cells: int = 8, duration: float | None = None) -> dict:
    """two_needles.toml with ``count`` needles on a grid 5 mm apart (none cuts), ``cells`` per axis."""
    data = tomllib.loads((resources.files("refsim") / "scenes" / "two_needles.toml").read_text("utf-8"))
    data["name"] = f"needles_{count}"
    data["mesh"]["cells"] = [cells, cells, cells]
    data["needle"]["radius"] = 0.0006
    data["cutting"]["enabled"] = False
    travel = (DEPTH + 0.002) / SPEED
    data["time"]["duration"] = float(duration if duration is not None else round(travel, 2))
    side = int(np.ceil(np.sqrt(count)))
    length = data["needle"]["length"]
    top = data["mesh"]["origin"][2] + data["mesh"]["size"][2]
    instruments = []
    for k in range(count):
        row, column = divmod(k, side)
        x = (column - 0.5 * (side - 1)) * PITCH + 0.00077
        y = (row - 0.5 * (side - 1)) * PITCH + 0.00131
        start, end = top + 0.002 + length, top - DEPTH + length
        instruments.append(
            {
                "name": f"n{k}",
                "cuts": False,
                "trajectory": {
                    "times": [0.0, travel],
                    "base_positions": [[x, y, start], [x, y, end]],
                    "directions": [[0.0, 0.0, -1.0]] * 2,
                },
            }
        )
    data["instruments"] = instruments
    data["output"]["tissue_every"] = 1000
    return data


def _toml(data: dict) -> str:
    """A minimal TOML writer for the scene dict (tables, arrays of tables, numbers, strings, lists)."""

    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, list | tuple):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)

    lines = [f"{k} = {value(v)}" for k, v in data.items() if not isinstance(v, dict | list)]
    for key, table in data.items():
        if isinstance(table, dict):
            lines.append(f"\n[{key}]")
            lines += [f"{k} = {value(v)}" for k, v in table.items()]
    for item in data.get("instruments", []):
        lines.append("\n[[instruments]]")
        lines += [f"{k} = {value(v)}" for k, v in item.items() if not isinstance(v, dict)]
        lines.append("[instruments.trajectory]")
        lines += [f"{k} = {value(v)}" for k, v in item["trajectory"].items()]
    return "\n".join(lines) + "\n"


def measure(count: int, cells: int) -> dict:
    """Run the scene of ``count`` needles; ms per step of each stage (every step) and the rows per step."""
    from refsim.scene import scene_from_dict
    from refsim.simulation import Simulation

    simulation = Simulation(scene_from_dict(scene_dict(count, cells), source=f"needles_{count}.toml"))
    records = []
    start = time.perf_counter()
    simulation.run(on_step=lambda state, record: records.append(record))
    wall = time.perf_counter() - start
    stages = {
        name: 1e3 * np.mean([r.stage_seconds.get(name, 0.0) for r in records])
        for name in records[0].stage_seconds
    }
    punctured = sum(
        any(e.name == "puncture" for r in records for e in r.instruments[k].events) for k in range(count)
    )
    return dict(
        count=count,
        steps=len(records),
        ms=1e3 * wall / len(records),
        stages=stages,
        rows=float(np.mean([r.row_forces.size for r in records])),
        punctured=punctured,
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[1, 2, 5, 10, 20])
    parser.add_argument("--cells", type=int, default=8)
    parser.add_argument("--write", nargs=2, metavar=("N", "OUT"))
    args = parser.parse_args(argv)
    if args.write:
        Path(args.write[1]).write_text(_toml(scene_dict(int(args.write[0]), args.cells)), encoding="utf-8")
        return 0
    measure(1, args.cells)  # compile or load the kernels first
    results = [measure(count, args.cells) for count in args.counts]
    names = list(results[0]["stages"])
    print(f"{'N':>3} {'punct':>5} {'rows':>7} {'ms/step':>8} " + " ".join(f"{n[:11]:>11}" for n in names))
    for r in results:
        print(
            f"{r['count']:>3} {r['punctured']:>5} {r['rows']:>7.1f} {r['ms']:>8.2f} "
            + " ".join(f"{r['stages'][n]:>11.2f}" for n in names)
        )
    counts = np.array([r["count"] for r in results], dtype=float)
    for label, values in [("total", [r["ms"] for r in results])] + [
        (n, [r["stages"][n] for r in results]) for n in names
    ]:
        slope = np.polyfit(counts, np.asarray(values), 1)[0]
        print(f"per extra needle per step, {label}: {slope:.3f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
