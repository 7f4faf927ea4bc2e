"""Speed against error under refinement: mesh resolution and insertion spacing d_i.

The scene is the paper's cube with the insertion followed by a 3 mm lateral motion of the base (no cut), so
the quantity of interest, the lateral force on the needle at the end, depends on the whole coupling. Each run
writes its HDF5 results; the summary (`summary.json`) holds, per run, the lateral force, the insertion points
and the mean milliseconds per step. The error of each run is taken against the finest run of its sweep (the
reference), so it measures convergence, not accuracy against an exact solution.

    python studies/resolution/run.py [--output studies/resolution/output] [--quick]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

LATERAL = [
    "trajectory.times=[0.0, 1.9, 2.0, 2.3]",
    "trajectory.base_positions=[[0.00123, 0.00231, 0.422], [0.00123, 0.00231, 0.403], "
    "[0.00123, 0.00231, 0.403], [0.00423, 0.00231, 0.403]]",
    "trajectory.directions=[[0, 0, -1], [0, 0, -1], [0, 0, -1], [0, 0, -1]]",
    "time.duration=2.3",
    "output.tissue_every=1000",
]


def sweeps(quick: bool) -> dict[str, list[tuple[str, list[str]]]]:
    cells = (3, 4) if quick else (4, 6, 8, 12)
    spacings = (2e-3, 1e-3) if quick else (2e-3, 1e-3, 0.5e-3, 0.25e-3)
    base = ["mesh.cells=[4, 4, 4]"] if quick else []  # the spacing sweep runs on the paper's mesh
    return {
        "mesh": [(f"cells={c}", [f"mesh.cells=[{c}, {c}, {c}]"]) for c in cells],
        "spacing": [(f"d_i={s * 1e3:g} mm", [*base, f"insertion.spacing={s}"]) for s in spacings],
    }


def run_one(overrides: list[str], output: Path) -> dict:
    """One run through the run driver (the same path as `refsim run`: checks, results file with the cut
    surface, summary); a run that stops early is an error of the study."""
    from refsim.io.driver import run_scene
    from refsim.scene import load_scene

    scene = load_scene("cube", LATERAL + overrides)
    last = {}

    def keep_last(state, record):
        last["record"] = record

    summary = run_scene(scene, output, overwrite=True, on_step=keep_last, handle_signals=False)
    if not summary.complete:
        raise RuntimeError(f"{output}: the run stopped early ({summary.status}): {summary.stop_reason}")
    record = last["record"]
    import h5py

    from refsim.io import schema

    with h5py.File(output, "r") as handle:
        tet_count = int(handle[schema.STATIC["tissue/tets"].path].shape[0])
    return {
        "lateral_force": float(-record.needle_force[0]),
        "insertion_points": int(record.insertion_point_count),
        "ms_per_step": 1e3 * summary.seconds / summary.steps,
        "tet_count": tet_count,
        "file": str(output),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", default=str(Path(__file__).parent / "output"))
    parser.add_argument("--quick", action="store_true", help="fewer, coarser runs (for tests)")
    args = parser.parse_args(argv)
    output = Path(args.output)
    output.mkdir(parents=True, exist_ok=True)
    summary: dict = {}
    for sweep, runs in sweeps(args.quick).items():
        rows = []
        for label, overrides in runs:
            name = f"{sweep}_{label.replace(' ', '').replace('=', '')}.h5"
            row = run_one(overrides, output / name)
            row["label"] = label
            rows.append(row)
            print(
                f"{sweep:8s} {label:14s} force {row['lateral_force']:.4f} N  {row['ms_per_step']:.1f} ms/step"
            )
        reference = rows[-1]["lateral_force"]
        for row in rows:
            row["error"] = (
                abs(row["lateral_force"] - reference) / abs(reference) if reference else float("nan")
            )
        summary[sweep] = rows
    (output / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"summary: {output / 'summary.json'}")


if __name__ == "__main__":
    main()
