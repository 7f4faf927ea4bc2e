"""Which refined parameter carries a reference case's error: runs that refine one of dt, d_i = d_c and the
mesh at a time, read with the case's own quantities.

    python studies/reference/separate.py CASE RESULT.h5 [RESULT.h5 ...]

prints, per results file, its dt, d_i, d_c and mesh cells, the case's quantities (refsim.reference: the
sampled curves, the event abscissae located by their criterion's crossing) and its events (how many tears,
when the needle left its cut). Runs for liver_rigid (the case's overrides, then one parameter at a time from
d_i = d_c = 0.5 mm, dt = 0.005 s, 24 beam elements)::

    B='--set solver.method="exact" --set solver.tolerance=1e-10 --set cutting.fracture_energy=30.5'
    refsim run liver_rigid $B --set time.dt=0.01 --set insertion.spacing=0.0005 \\
        --set cutting.point_spacing=0.0005 --set needle.element_count=24 -o dt01_d05.h5     # dt doubled
    refsim run liver_rigid $B --set time.dt=0.005 --set insertion.spacing=0.001 \\
        --set cutting.point_spacing=0.001 --set needle.element_count=24 -o dt005_d1.h5      # d doubled

and for laceration (refsim/reference/cases/laceration.scene.toml, from its standard level's 7 cells):
``--set mesh.cells=[N,N,N]`` with dt and d_i = d_c held (N = 5, 7, 9), or dt halved at 7 cells. Compare the
output with the case's levels (the runs of a built package, ``DIR/cases/CASE/study_runs/``).
"""

from __future__ import annotations

import sys

import numpy as np


def describe(case_name: str, path: str) -> list[str]:
    from refsim.io import read_results
    from refsim.reference import load_case
    from refsim.reference.cases import results_values

    results = read_results(path)
    scene = results.scene
    events: dict[str, list[float]] = {}
    for event in results.events:
        events.setdefault(event.name, []).append(float(results.time[results.index_of(event.step)]))
    lines = [
        f"{path}: dt = {scene['time']['dt']:.6g} s, d_i = {scene['insertion']['spacing']:.6g} m, "
        f"d_c = {scene['cutting']['point_spacing']:.6g} m, cells = {scene['mesh'].get('cells', '-')}; "
        f"tears {len(events.get('tear', []))}, cut starts at "
        f"{', '.join(f'{t:.4f}' for t in events.get('cut_start', [])) or '-'} s, leaves its cut at "
        f"{', '.join(f'{t:.4f}' for t in events.get('leave_cut', [])) or '-'} s"
    ]
    for name, value in results_values(load_case(case_name), results).items():
        lines.append(f"    {name}: {np.array2string(np.atleast_1d(value), precision=6)}")
    return lines


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) < 2:
        print(__doc__)
        return 2
    for path in argv[1:]:
        print("\n".join(describe(argv[0], path)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
