"""A robot-held needle that compensates a tissue motion (the paper's liver experiment, after Baksic et al.
2020): the base follows a nominal insertion plus the motion of the target, precomputed by simulating the
tissue alone under its boundary motion.

The robot knows where the target is at every time, not how the rest of the organ moves: the needle tracks the
target, and the relative motion between the target and the entry point is what loads the needle.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from refsim.geometry import TetLocator
from refsim.scene import Scene
from refsim.scene.build import build_controls, build_models
from refsim.scene.trajectory import Trajectory
from refsim.simulation.bodies import TissueBody

__all__ = ["target_motion", "compensating_trajectory", "write_trajectory_csv"]


def target_motion(scene: Scene, target: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Displacement of the tissue's material point at ``target`` (rest) under the scene's boundary motion
    alone, without the needle [m], shape (len(times), 3), by the scene's own time stepping.

    Parameters
    ----------
    scene : A scene with a [boundary] motion.
    target : Rest position of the target [m], shape (3,), inside the tissue.
    times : Sample times [s], increasing, within the scene's duration, shape (w,).
    """
    models = build_models(scene)
    controls = build_controls(scene, models)
    mesh = models.mesh
    tets, barycentric = TetLocator(mesh.rest_positions, mesh.tets).locate(
        np.asarray(target, dtype=float)[None]
    )
    if tets[0] < 0:
        raise ValueError(f"target {np.asarray(target).tolist()} m is outside the tissue")
    nodes = mesh.tets[tets[0]]
    body = TissueBody(models.tissue)
    state = models.tissue.rest_state()
    dt = scene.time.dt
    step_times = np.arange(scene.time.step_count + 1) * dt
    history = np.zeros((step_times.size, 3))
    for index in range(1, step_times.size):  # the tissue's own steps (one solve each)
        control = controls.at(step_times[index])
        free, system = body.free_motion(state, control, dt)
        state = body.correct(system, state, free, None, np.zeros(0), dt)
        history[index] = barycentric[0] @ state.positions[nodes] - barycentric[0] @ mesh.rest_positions[nodes]
    return np.stack([np.interp(times, step_times, history[:, k]) for k in range(3)], axis=1)


def compensating_trajectory(
    scene: Scene,
    *,
    target: np.ndarray,
    direction: np.ndarray,
    start_gap: float,
    depth: float,
    speed: float,
    sample_count: int = 200,
) -> Trajectory:
    """The base motion of a robot inserting a needle towards ``target`` while following the target's motion.

    The needle points along ``direction`` at the target; its tip starts ``start_gap`` before the entry
    (``depth`` before the target along the needle, so the tip reaches the target at full depth) and advances
    at ``speed``, then holds; at every time the whole pose is shifted by the target's displacement.

    Parameters
    ----------
    scene : The scene (its needle length, boundary motion, duration).
    target : Rest position of the target [m], shape (3,).
    direction : Needle direction (base to tip), shape (3,), normalised here.
    start_gap : Distance of the tip from the entry at t = 0 [m], > 0.
    depth : Depth of the target below the entry along the needle [m], > 0.
    speed : Insertion speed [m/s], > 0.
    sample_count : Trajectory samples over the scene's duration.
    """
    direction = np.asarray(direction, dtype=float)
    direction = direction / np.linalg.norm(direction)
    target = np.asarray(target, dtype=float)
    times = np.linspace(0.0, scene.time.duration, sample_count)
    travel = np.minimum(times * speed, start_gap + depth)
    tip = target - (depth + start_gap) * direction + travel[:, None] * direction
    base = tip - scene.needle.length * direction + target_motion(scene, target, times)
    return Trajectory(times, base, np.broadcast_to(direction, base.shape).copy())


def write_trajectory_csv(trajectory: Trajectory, path: str | Path, *, comment: str = "") -> Path:
    """Write a trajectory as the CSV a scene reads (t, x, y, z, dx, dy, dz [s, m, -]); returns the path."""
    path = Path(path)
    data = np.column_stack([trajectory.times, trajectory.base_positions, trajectory.directions])
    header = "t,x,y,z,dx,dy,dz"
    if comment:
        header = "\n".join(f"# {line}" for line in comment.splitlines()) + "\n" + header
    np.savetxt(path, data, delimiter=",", header=header, comments="", fmt="%.9g")
    return path
