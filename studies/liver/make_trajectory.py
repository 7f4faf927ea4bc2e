"""Precompute the robot's motion of the liver scenes: insertion towards the target, following its breathing.

    python studies/liver/make_trajectory.py [--output refsim/scenes/liver_robot.csv]

The tissue alone is simulated under the scenes' boundary motion (refsim.simulation.robot.target_motion); the
needle pose follows the target's displacement. Both liver scenes share the tissue, the motion and this file.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

TARGET = np.array([-0.05, -0.0115, 0.01])  # [m] 8 cm below the anterior face, in the right lobe
DIRECTION = np.array([0.0, -1.0, 0.0])  # inserted from the anterior face, posteriorly
START_GAP, DEPTH, SPEED = 0.002, 0.08, 0.02  # [m], [m], [m/s]


def main(argv=None) -> int:
    from refsim.simulation.robot import compensating_trajectory, write_trajectory_csv

    root = Path(__file__).resolve().parents[2]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=root / "refsim" / "scenes" / "liver_robot.csv")
    parser.add_argument(
        "--scene", default="liver_rigid", help="a liver scene (its tissue and boundary motion)"
    )
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], help="section.key=value, as refsim run --set"
    )
    args = parser.parse_args(argv)
    # The scene reads the file we are writing: load it with a placeholder straight trajectory.
    scene = _scene_without_trajectory(args.scene, args.overrides)
    trajectory = compensating_trajectory(
        scene,
        target=TARGET,
        direction=DIRECTION,
        start_gap=START_GAP,
        depth=DEPTH,
        speed=SPEED,
        sample_count=401,
    )
    write_trajectory_csv(
        trajectory,
        args.output,
        comment=(
            "The robot's base motion of the liver scenes (refsim studies/liver/make_trajectory.py):\n"
            f"target {TARGET.tolist()} m, direction {DIRECTION.tolist()}, start gap {START_GAP} m, depth "
            f"{DEPTH} m, "
            f"speed {SPEED} m/s, following the target's motion under the [boundary] section of {args.scene}"
        ),
    )
    nominal = trajectory.base_positions[:, 1] - trajectory.base_positions[0, 1]
    follow = trajectory.base_positions - trajectory.base_positions[0]
    follow[:, 1] -= nominal  # (the insertion is along y; what is left across it is the target's motion)
    print(
        f"wrote {args.output}: {trajectory.times.size} samples over {trajectory.times[-1]:g} s; the target "
        f"moves up to {np.abs(follow[:, [0, 2]]).max() * 1e3:.2f} mm across the needle"
    )
    return 0


def write_robot(path: Path, scene: str = "liver_rigid", overrides=()) -> Path:
    """Write the robot's motion for ``scene`` with ``overrides`` (its tissue and breathing) to ``path``."""
    from refsim.simulation.robot import compensating_trajectory, write_trajectory_csv

    trajectory = compensating_trajectory(
        _scene_without_trajectory(scene, overrides),
        target=TARGET,
        direction=DIRECTION,
        start_gap=START_GAP,
        depth=DEPTH,
        speed=SPEED,
        sample_count=401,
    )
    return write_trajectory_csv(trajectory, path)


def _scene_without_trajectory(name: str, overrides=()):
    """The scene (with ``section.key=value`` overrides) with a straight placeholder trajectory instead of the
    file being written (the tissue simulation does not use the needle)."""
    import tomllib
    from importlib import resources

    from refsim.scene.loader import parse_override, scene_from_dict

    path = (
        Path(name)
        if name.endswith(".toml")
        else Path(str(resources.files("refsim") / "scenes" / f"{name}.toml"))
    )
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    for text in overrides:
        section, key, value = parse_override(text)
        data.setdefault(section, {})[key] = value
    base = (TARGET - (DEPTH + START_GAP) * DIRECTION - 0.12 * DIRECTION).tolist()
    data["trajectory"] = {
        "times": [0.0, 1.0],
        "base_positions": [base, base],
        "directions": [DIRECTION.tolist(), DIRECTION.tolist()],
    }
    return scene_from_dict(data, source=str(path), base_directory=str(path.parent))


if __name__ == "__main__":
    raise SystemExit(main())
