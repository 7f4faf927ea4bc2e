"""The window of G_c over which the liver scenes give the paper's outcome, by bisection on G_c.

    PYTHONPATH=. python studies/liver/window.py [--set section.key=value ...] [--tolerance 0.002]
    PYTHONPATH=. python studies/liver/window.py --matrix      (the outcome over d_c, dt, d_i and the phantom)

The paper's outcome (section 5, Figure 2): the flexible needle (liver_flexible) does not cut, the rigid one
(liver_rigid) cuts. Each run is one liver scene with cutting on, stopped at its cut start; the outcome is
monotone in G_c for each needle (the runs are identical up to the first step where ‖t‖ ≥ G_c L_in), so each
needle has one threshold G*: it cuts for G_c < G*, not above. The window is G*_flexible < G_c < G*_rigid,
each end bisected to ``--tolerance`` (relative) from a bracket that the script checks first. Overrides apply
to both scenes; ones that change the tissue or the breathing recompute the robot's motion
(studies/liver/make_trajectory.py) into the output folder.

Writes output/window.json and the page docs/liver_window.md (the window, the chosen G_c's margin and, with
--matrix, the outcome matrix). One process, one BLAS thread.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
OUTPUT = ROOT / "studies" / "liver" / "output"
PAGE = ROOT / "docs" / "liver_window.md"
SCENES = ("liver_flexible", "liver_rigid")
# Sections whose keys change the tissue's motion under breathing, hence the robot's compensating motion.
MOTION_SECTIONS = ("tissue.", "boundary.", "mesh.")
MEDIUM = 'mesh.file="../mesh/data/liver_phantom_medium.vtu"'
MATRIX = {
    "scene as is": [],
    "d_c = 0.5 mm": ["cutting.point_spacing=0.5e-3"],
    "d_c = 2 mm": ["cutting.point_spacing=2e-3"],
    "dt = 5 ms": ["time.dt=0.005"],
    "dt = 20 ms": ["time.dt=0.02"],
    "d_i = 0.5 mm": ["insertion.spacing=0.5e-3"],
    "d_i = 2 mm": ["insertion.spacing=2e-3"],
    "medium phantom": [MEDIUM],
    # the medium phantom is about 9 times slower: its first 2 s (the coarse runs decide in the first inhale)
    "medium phantom, first 2 s": [MEDIUM, "time.duration=2.0"],
}


def robot_override(overrides: list[str], directory: Path) -> list[str]:
    """``trajectory.file=...`` of the robot's motion for these overrides (none when they keep the scene's
    tissue and breathing, whose motion is refsim/scenes/liver_robot.csv)."""
    motion = sorted(text for text in overrides if text.startswith(MOTION_SECTIONS))
    if not motion:
        return []
    import hashlib

    import make_trajectory

    name = hashlib.sha1("\n".join(motion).encode()).hexdigest()[:12]
    path = directory / f"robot_{name}.csv"
    if not path.is_file():
        directory.mkdir(parents=True, exist_ok=True)
        make_trajectory.write_robot(path, "liver_rigid", motion)
    return [f"trajectory.file={json.dumps(str(path))}"]


def run_outcome(name: str, overrides: list[str], fracture_energy: float, directory: Path) -> dict:
    """One run with cutting on, stopped at the cut start: whether it cut, when, its trigger (‖t‖/L_in [N/m]),
    the largest ‖t‖/L_in over the insertion steps before it, the run's steps and wall time."""
    from refsim.scene import load_scene
    from refsim.simulation import Simulation
    from refsim.simulation.events import shaft_lateral_force

    scene = load_scene(
        name,
        [*overrides, *robot_override(overrides, directory), f"cutting.fracture_energy={fracture_energy!r}"],
    )
    simulation = Simulation(scene)
    state = simulation.initial_state()
    started = time.perf_counter()
    result = {"scene": name, "fracture_energy": fracture_energy, "cut": False, "step": None, "trigger": None}
    largest, largest_at = 0.0, (None, None, None)
    steps = scene.time.step_count
    for index in range(steps):  # noqa: B007 (index is the run's length below)
        state, record = simulation.step(state, record_tissue=False)
        if record.row_forces is not None and state.phase == "insertion" and state.path.point_count:
            force = shaft_lateral_force(
                record.row_source,
                record.row_kind,
                record.row_directions,
                record.row_forces,
                without_entry=True,
                surface_allowance=scene.insertion.puncture_force,
                points=record.row_point,
            )
            rules = simulation.event_rules
            entry = state.path.positions(state.tissue.positions, simulation.tets)[:1]
            needle = rules.needle_geometry(state.needle)
            inserted = needle.length - float(needle.project(entry)[0][0])  # as EventRules._cut_starts
            if inserted > 0.0 and float((force @ force) ** 0.5) / inserted > largest:
                largest = float((force @ force) ** 0.5) / inserted
                largest_at = (record.step, state.time, inserted)
        starts = [event for event in record.events if event.name == "cut_start"]
        if starts:
            result.update(cut=True, step=record.step, trigger=float(starts[0].force), time=state.time)
            break
    result.update(
        largest_load=largest,
        largest_step=largest_at[0],
        largest_time=largest_at[1],
        largest_inserted=largest_at[2],
        steps=index + 1,
        seconds=time.perf_counter() - started,
        step_count=steps,
    )
    return result


def threshold(name: str, overrides: list[str], low: float, high: float, tolerance: float, log) -> dict:
    """G* of one scene: it cuts at ``low`` and not at ``high`` (checked), bisected until (high − low) /
    low < ``tolerance``."""
    directory = OUTPUT / "robots"
    runs = []

    def cuts(value: float) -> bool:
        run = run_outcome(name, overrides, value, directory)
        runs.append(run)
        log(
            f"  {name} G_c = {value:7.3f}: {'cuts at step ' + str(run['step']) if run['cut'] else 'no cut'}"
            f" ({run['steps']} steps, {run['seconds']:.0f} s)"
        )
        return run["cut"]

    while not cuts(low):
        low, high = 0.8 * low, low
    while cuts(high):
        low, high = high, 1.25 * high
    while (high - low) / low >= tolerance:
        middle = 0.5 * (low + high)
        if cuts(middle):
            low = middle
        else:
            high = middle
    return {"scene": name, "cuts_at": low, "no_cut_at": high, "runs": runs}


def main(argv=None) -> int:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="section.key=value")
    parser.add_argument("--tolerance", type=float, default=0.002, help="relative width of each end's bracket")
    parser.add_argument("--bracket", type=float, default=0.15, help="initial bracket: G ± this fraction")
    parser.add_argument(
        "--guess", type=float, nargs=2, metavar=("FLEXIBLE", "RIGID"), help="initial guesses of the two ends"
    )
    parser.add_argument("--matrix", action="store_true", help="the outcome at the scenes' G_c per variant")
    parser.add_argument(
        "--variants",
        nargs="+",
        choices=list(MATRIX),
        help="with --matrix: only these (the others kept)",
    )
    parser.add_argument("--output", type=Path, default=OUTPUT / "window.json")
    parser.add_argument("--page", type=Path, default=PAGE)
    args = parser.parse_args(argv)
    from refsim.scene import load_scene

    chosen = load_scene("liver_rigid", args.overrides).cutting.fracture_energy
    data = json.loads(args.output.read_text()) if args.output.is_file() else {}
    log = lambda text: print(text, flush=True)  # noqa: E731
    if args.matrix:
        rows = (
            data.get("matrix", {}).get("rows", {})
            if data.get("matrix", {}).get("fracture_energy") == chosen
            else {}
        )
        for label in args.variants or MATRIX:
            overrides = [*args.overrides, *MATRIX[label]]
            rows[label] = {name: run_outcome(name, overrides, chosen, OUTPUT / "robots") for name in SCENES}
            flexible, rigid = rows[label]["liver_flexible"], rows[label]["liver_rigid"]
            rigid_cut = f"cuts at step {rigid['step']}" if rigid["cut"] else "no cut"
            log(
                f"{label}: flexible {'cuts' if flexible['cut'] else 'no cut'} (largest load "
                f"{flexible['largest_load']:.1f} N/m), rigid {rigid_cut}"
                f" ({rigid['trigger'] or rigid['largest_load']:.1f} N/m)"
            )
            data["matrix"] = {"fracture_energy": chosen, "overrides": args.overrides, "rows": rows}
            _write(data, args)
    else:
        guesses = args.guess or (chosen, chosen)
        ends = {}
        for name, guess in zip(SCENES, guesses, strict=True):
            low, high = guess * (1 - args.bracket), guess * (1 + args.bracket)
            ends[name] = threshold(name, args.overrides, low, high, args.tolerance, log)
        low = ends["liver_flexible"]["no_cut_at"]
        high = ends["liver_rigid"]["cuts_at"]
        data["window"] = {
            "overrides": args.overrides,
            "fracture_energy": chosen,
            "tolerance": args.tolerance,
            "low": low,
            "high": high,
            "ends": ends,
        }
        log(f"window: {low:.2f} < G_c < {high:.2f} J/m²: {_placement(low, high, chosen)}")
    _write(data, args)
    return 0


def _write(data: dict, args) -> None:
    data["machine"] = {"load": os.getloadavg()[0], "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(data, indent=1))
    args.page.write_text(page(data))


def _at(run: dict, prefix: str = ", ") -> str:
    """Where a run's largest ‖t‖/L_in was reached (time, inserted length), when recorded."""
    if run.get("largest_time") is None:
        return ""
    text = f"{prefix}t = {run['largest_time']:.2f} s, L_in = {1e3 * run['largest_inserted']:.0f} mm"
    return text + (")" if prefix == " (" else "")


#: The published fracture toughness of liver [J/m²] the scenes cite: 76-185 (Azar and Hayward 2008, needle
#: insertion, porcine in vivo), 164 ± 6 (Gokgol et al. 2012, bovine), 187-225 (blade cutting).
PUBLISHED = (76.0, 225.0)


def _placement(low: float, high: float, chosen: float) -> str:
    """Where the scenes' G_c and the published values sit against the window low < G_c < high."""
    if low < chosen < high:
        where = (
            f"Around the scenes' G_c = {chosen:g} J/m² the window reaches {100 * (1 - low / chosen):.1f} % "
            f"below and {100 * (high / chosen - 1):.1f} % above it."
        )
    else:
        side = "above" if chosen >= high else "below"
        where = (
            f"The scenes' G_c = {chosen:g} J/m² lies {side} the window: there neither needle cuts"
            if side == "above"
            else f"The scenes' G_c = {chosen:g} J/m² lies below the window: there both needles cut"
        ) + "."
    overlap = min(high, PUBLISHED[1]) > max(low, PUBLISHED[0])
    published = (
        f" The window {'meets' if overlap else 'does not meet'} the published {PUBLISHED[0]:g}–"
        f"{PUBLISHED[1]:g} J/m² (the scenes cite them); ±20 % around its geometric centre needs a ratio "
        f"high/low ≥ 1.5, measured {high / low:.2f}."
    )
    return where + published


def page(data: dict) -> str:
    """The generated page: the window and the outcome matrix."""
    lines = [
        "# The liver outcome's window in G_c (generated)",
        "",
        "Generated by `PYTHONPATH=. python studies/liver/window.py` (the window, by bisection) and "
        "`PYTHONPATH=. python studies/liver/window.py --matrix` (the outcome per variant) from "
        "`studies/liver/output/window.json`; do not edit. The scenes and their sources: "
        "[liver.md](liver.md).",
        "",
    ]
    window = data.get("window")
    if window:
        low, high, chosen = window["low"], window["high"], window["fracture_energy"]
        centre = (low * high) ** 0.5
        lines += [
            "## The window",
            "",
            f"The flexible needle does not cut and the rigid one cuts for "
            f"**{low:.1f} < G_c < {high:.1f} J/m²** (each end bisected to {100 * window['tolerance']:g} %; "
            f"overrides: {', '.join(window['overrides']) or 'none'}): {centre:.1f} J/m² "
            f"± {100 * (high - low) / (high + low):.1f} % (geometric centre, ± half the width over the "
            f"mean). {_placement(low, high, chosen)}",
            "",
            "| scene | cuts at G_c = | does not cut at G_c = | runs |",
            "|---|---|---|---|",
        ]
        for name, end in window["ends"].items():
            lines.append(f"| {name} | {end['cuts_at']:.2f} | {end['no_cut_at']:.2f} | {len(end['runs'])} |")
        lines.append("")
    matrix = data.get("matrix")
    if matrix:
        lines += [
            f"## The outcome at G_c = {matrix['fracture_energy']:g} J/m² over d_c, dt, d_i and the phantom",
            "",
            "Each variant changes one key of both scenes; the flexible needle's largest ‖t‖/L_in over the "
            "run (it must stay below G_c) and the rigid needle's cut start (its trigger ‖t‖/L_in ≥ G_c), or, "
            "when it does not cut, its largest ‖t‖/L_in. A run that does not cut is the run without "
            "cutting: its largest load is that needle's end of the window for the variant.",
            "",
            "| variant | flexible: cuts? | flexible: largest ‖t‖/L_in [N/m] | rigid: cuts? "
            "| rigid: cut start (step, t) | rigid: trigger [N/m] | outcome |",
            "|---|---|---|---|---|---|---|",
        ]
        for label, row in matrix["rows"].items():
            f, r = row["liver_flexible"], row["liver_rigid"]
            outcome = {
                (False, True): "paper",
                (False, False): "**neither cuts**",
                (True, True): "**both cut**",
                (True, False): "**only the flexible cuts**",
            }[(bool(f["cut"]), bool(r["cut"]))]
            start = f"{r['step']}, {r['time']:.2f} s" if r["cut"] else "—"
            trigger = f"{r['trigger']:.1f}" if r["cut"] else f"{r['largest_load']:.1f} (largest{_at(r)})"
            lines.append(
                f"| {label} | {'yes' if f['cut'] else 'no'} | {f['largest_load']:.1f}{_at(f, ' (')} | "
                f"{'yes' if r['cut'] else 'no'} | {start} | {trigger} | {outcome} |"
            )
        lines.append("")
    machine = data.get("machine", {})
    lines.append(f"Last written {machine.get('date', '?')}, load {machine.get('load', 0):.1f}.")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
