"""The energy law's cut-start load of a liver run: the largest shaft lateral force per inserted length.

    python studies/liver/criterion.py RESULT.h5 [RESULT.h5 ...]

For each results file (a run with cutting disabled shows the whole load history), prints the largest
q = ‖t‖ / L_in [N/m] over the insertion steps, t the insertion rows' lateral force without the entry point's
(refsim.simulation.events.shaft_lateral_force), L_in the tip's travel along the needle since the puncture,
counted from 1 cm (below it the load per length is the surface's). Compare q with the scene's G_c.
"""

from __future__ import annotations

import sys

import numpy as np


def largest_load(path: str) -> tuple[float, int]:
    from refsim.io import read_results
    from refsim.simulation.events import shaft_lateral_force

    results = read_results(path)
    punctures = [event.step for event in results.events if event.name == "puncture"]
    if not punctures:
        return 0.0, -1
    first = punctures[0]
    tips = results.needle_positions[:, -1]
    axes = results.needle_positions[:, -1] - results.needle_positions[:, 0]
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    offsets = results.constraint_offsets
    insertion = results.phase_names.index("insertion")
    best, at = 0.0, -1
    for index in range(first, results.step_count):
        if results.phase[index] != insertion:
            continue
        rows = slice(offsets[index], offsets[index + 1])
        force = shaft_lateral_force(
            results.constraint_source[rows],
            results.constraint_kind[rows],
            results.constraint_directions[rows],
            results.constraint_forces[rows],
            without_entry=True,
            surface_allowance=float(results.scene["insertion"]["puncture_force"]),
        )
        length = float((tips[index] - tips[first - 1]) @ axes[index])
        if length > 0.01 and np.linalg.norm(force) / length > best:
            best, at = float(np.linalg.norm(force) / length), index + 1
    return best, at


def main(argv=None) -> int:
    for path in sys.argv[1:] if argv is None else argv:
        load, step = largest_load(path)
        print(f"{path}: largest shaft lateral force per inserted length {load:.1f} N/m at step {step}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
