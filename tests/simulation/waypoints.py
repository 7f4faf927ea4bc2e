"""Scene overrides for a needle driven through waypoints of its base, shared by the simulation tests."""

from __future__ import annotations

import numpy as np


def times_at_speed(bases, speed: float, *, shortest: float = 0.1) -> list[float]:
    """Waypoint times [s] for ``bases`` (positions of the needle's base [m]) reached one after the other at
    ``speed`` [m/s], each segment at least ``shortest`` long, rounded to whole steps of 10 ms."""
    times = [0.0]
    for before, after in zip(bases[:-1], bases[1:], strict=True):
        distance = float(np.linalg.norm(np.asarray(after, dtype=float) - np.asarray(before, dtype=float)))
        times.append(round(times[-1] + max(distance / speed, shortest), 2))
    return times


def vector(values) -> str:
    """A TOML array of floats."""
    return "[" + ", ".join(repr(float(c)) for c in values) + "]"


def trajectory_overrides(times, bases, directions, *, duration: float) -> list[str]:
    """The ``--set`` overrides of a [trajectory] through ``bases`` at ``times`` along ``directions`` (one
    direction for all when a single vector is given), and a run of ``duration`` [s]."""
    directions = np.asarray(directions, dtype=float)
    if directions.ndim == 1:
        directions = np.repeat(directions[None], len(bases), axis=0)
    return [
        f"time.duration={float(duration)!r}",
        f"trajectory.times={vector(times)}",
        "trajectory.base_positions=[" + ", ".join(vector(b) for b in bases) + "]",
        "trajectory.directions=[" + ", ".join(vector(d) for d in directions) + "]",
    ]
