"""The needle's centreline as the constraint builders see it: points, tangents, projections and Jacobians.

A rigid needle is a straight segment moved kinematically by its base: it has no DoFs in the constraint problem
(its Jacobian is None, its compliance zero). A flexible needle wraps the beam model's centreline, whose
Jacobian maps the 6 DoFs of each node to centreline points.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

import numpy as np
import scipy.sparse as sp

__all__ = ["NeedleGeometry", "RigidNeedleGeometry", "BeamNeedleGeometry", "needle_rows"]


class NeedleGeometry(Protocol):
    """What the constraint builders need from a needle in one configuration."""

    length: float

    @property
    def tip(self) -> np.ndarray:
        """The tip, the centreline point at arc length ``length`` [m], shape (3,)."""

    @property
    def tip_tangent(self) -> np.ndarray:
        """The unit tangent at the tip, shape (3,)."""

    def points(self, arc_lengths: np.ndarray) -> np.ndarray:
        """Centreline points [m] at arc lengths [m] from the base, shape (q, 3)."""

    def tangents(self, arc_lengths: np.ndarray) -> np.ndarray:
        """Unit tangents (base to tip), shape (q, 3)."""

    def jacobian(self, arc_lengths: np.ndarray) -> sp.csr_matrix | None:
        """d(points)/d(DoFs), shape (3q, dof_count), or None for a kinematic needle."""

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest centreline points: (arc_lengths (q,) [m] clamped to [0, length], closest (q, 3) [m])."""


@dataclass(frozen=True)
class RigidNeedleGeometry:
    """A straight rigid needle: base (3,) [m], unit direction (3,) base to tip, length [m]."""

    base: np.ndarray
    direction: np.ndarray
    length: float

    @property
    def tip(self) -> np.ndarray:
        """Tip position [m], shape (3,)."""
        return self.base + self.length * self.direction

    @property
    def tip_tangent(self) -> np.ndarray:
        """Unit tangent at the tip, shape (3,)."""
        return self.tangents(np.array([self.length]))[0]

    def points(self, arc_lengths: np.ndarray) -> np.ndarray:
        return self.base + np.asarray(arc_lengths, dtype=float)[:, None] * self.direction

    def tangents(self, arc_lengths: np.ndarray) -> np.ndarray:
        # the direction copied into each row (np.broadcast_to(...).copy()'s array, with less overhead)
        return np.repeat(np.reshape(self.direction, (1, 3)), np.size(arc_lengths), axis=0)

    def jacobian(self, arc_lengths: np.ndarray) -> None:
        return None

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = np.clip((np.asarray(points, dtype=float) - self.base) @ self.direction, 0.0, self.length)
        return s, self.points(s)


@dataclass(frozen=True)
class BeamNeedleGeometry:
    """A flexible needle: the beam model and one configuration of it.

    Attributes
    ----------
    model : A `refsim.fem.needle.NeedleModel`.
    positions : Node positions [m], shape (node_count, 3).
    frames : Node frames, shape (node_count, 3, 3).
    """

    model: object
    positions: np.ndarray
    frames: np.ndarray

    @property
    def length(self) -> float:
        return float(self.model.length)

    @cached_property
    def tip(self) -> np.ndarray:
        """Tip position [m], shape (3,) (kept: the events read it several times per step; read-only)."""
        tip = self.points(np.array([self.length]))[0]
        tip.setflags(write=False)
        return tip

    @cached_property
    def tip_tangent(self) -> np.ndarray:
        """Unit tangent at the tip, shape (3,) (kept, read-only)."""
        tangent = self.tangents(np.array([self.length]))[0]
        tangent.setflags(write=False)
        return tangent

    def points(self, arc_lengths: np.ndarray) -> np.ndarray:
        return self.model.centreline_points(self.positions, self.frames, np.asarray(arc_lengths, dtype=float))

    def tangents(self, arc_lengths: np.ndarray) -> np.ndarray:
        return self.model.centreline_tangents(
            self.positions, self.frames, np.asarray(arc_lengths, dtype=float)
        )

    def jacobian(self, arc_lengths: np.ndarray) -> sp.csr_matrix:
        return self.model.centreline_jacobian(
            self.positions, self.frames, np.asarray(arc_lengths, dtype=float)
        )

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        arc_lengths, closest, _ = self.model.project_on_centreline(self.positions, self.frames, points)
        return arc_lengths, closest


def needle_rows(
    geometry: NeedleGeometry, arc_lengths: np.ndarray, directions: np.ndarray
) -> sp.csr_matrix | None:
    """Rows nᵀ J(s) of H_needle for centreline points at ``arc_lengths`` along ``directions`` (r, 3)."""
    jacobian = geometry.jacobian(arc_lengths)
    if jacobian is None:
        return None
    row_count = len(arc_lengths)
    selector = sp.csr_matrix(
        (
            np.asarray(directions, dtype=float).ravel(),
            (np.repeat(np.arange(row_count), 3), np.arange(3 * row_count)),
        ),
        shape=(row_count, 3 * row_count),
    )
    return (selector @ jacobian).tocsr()
