"""Speed against error: every fast option of options.toml on each scene, against the scene's exact mode.

Each scene gets one study (refsim.sweep): one run per option (the option's overrides on the scene) and a
reference run in the exact mode (options.toml's [reference]). The study file stores, per run, the mean ms per
step and the relative errors against the reference: of the needle force history (‖F − F_ref‖/‖F_ref‖ over all
steps) and of each quantity of interest.

    python studies/pareto/run.py [--output studies/pareto/output] [--scenes cube cube_cut] [--workers N |
                                 --scheduler ADDR] [--quick]

``--quick`` (for tests): cube only, 3 cells per axis, 0.4 s, three options.
"""

from __future__ import annotations

import argparse
import tomllib
from pathlib import Path

HERE = Path(__file__).resolve().parent
QUANTITIES = {
    "cube": ("needle_force@t=1.9", "axial_force@t=1.9", "needle_force@end", "puncture_force"),
    "cube_cut": ("needle_force@cut_start", "lateral_stroke@cut_start", "cut_area", "lateral_force@end"),
}


def options(path: Path = HERE / "options.toml") -> dict:
    """The option table: {"reference": (label, overrides), "options": [dict(family, label, set, scenes)]}."""
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    table = []
    for index, option in enumerate(data.get("option", [])):
        missing = {"family", "label", "set"} - set(option)
        if missing:
            raise ValueError(f"{path}: [[option]] {index + 1} misses {sorted(missing)}")
        table.append(
            {
                "family": option["family"],
                "label": option["label"],
                "set": tuple(option["set"]),
                "scenes": tuple(option.get("scenes", ())),
            }
        )
    reference = data["reference"]
    return {"reference": (reference.get("label", "exact"), tuple(reference["set"])), "options": table}


def study(scene: str, table: dict, *, base=(), name=None):
    """The study of one scene: a case per option that applies to it."""
    from refsim.sweep import StudySpec

    cases = tuple(
        (option["label"], option["set"])
        for option in table["options"]
        if not option["scenes"] or scene in option["scenes"]
    )
    families = {option["label"]: option["family"] for option in table["options"]}
    return StudySpec(
        name=name or f"pareto_{scene}",
        scene=scene,
        cases=cases,
        overrides=tuple(base),
        quantities=QUANTITIES.get(scene, ("needle_force@end",)),
        reference=table["reference"],
        source=str(HERE / "options.toml"),
        extra={"families": families},
    )


def main(argv: list[str] | None = None) -> None:
    from refsim.sweep import run_study
    from refsim.sweep.study import start_client

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", default=str(HERE / "output"))
    parser.add_argument("--scenes", nargs="+", default=["cube", "cube_cut"])
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--scheduler", default=None)
    parser.add_argument("--quick", action="store_true", help="small and short (for tests)")
    parser.add_argument("-q", "--quiet", action="store_true")
    args = parser.parse_args(argv)
    table = options()
    output = Path(args.output)
    output.mkdir(parents=True, exist_ok=True)
    scenes, base = args.scenes, ()
    if args.quick:
        scenes, base = ["cube"], ("mesh.cells=[3, 3, 3]", "time.duration=0.4", "output.tissue_every=10")
        keep = {"paper", "tol 1e-4", "cap 5"}
        table = {**table, "options": [o for o in table["options"] if o["label"] in keep]}
    client, cluster = start_client(args.scheduler, args.workers)
    try:
        for scene in scenes:
            spec = study(scene, table, base=base, name=f"pareto_{scene}" + ("_quick" if args.quick else ""))
            result = run_study(
                spec,
                output / f"{spec.name}.h5",
                client=client,
                warm_up=not args.quick,
                progress=not args.quiet,
            )
            runs = result["runs"]
            print(f"{spec.name}: reference {result['reference']['ms_per_step']:.1f} ms/step")
            for label, ms, error in zip(
                runs["label"], runs["ms_per_step"], runs["errors"]["force_history"], strict=True
            ):
                print(f"  {label:<12} {ms:8.2f} ms/step  force history error {error:.3e}")

    finally:
        client.close()
        if cluster is not None:
            cluster.close()


if __name__ == "__main__":
    main()
