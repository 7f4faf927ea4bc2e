"""The tissue as a body of the step: free motion under the controls, compliance of rows, correction.

The needle bodies (:mod:`refsim.simulation.needle_body`) have the same three operations. How A⁻¹ is applied
(refactorised every step, refreshed, precomputed) is the compliance strategy of the tissue model
(:mod:`refsim.fem`); this wrapper only reads the controls and keeps the step's system.
"""

from __future__ import annotations

import numpy as np

from refsim.fem.tissue import TissueModel, TissueState
from refsim.scene.controls import ControlValues

__all__ = ["TissueBody"]


class TissueBody:
    """The tissue model driven by the boundary controls.

    Parameters
    ----------
    model : The co-rotational tetrahedral model; its fixed nodes must include every node a boundary motion
        moves.
    compliance : The bound compliance strategy (`refsim.fem.compliance.make_strategy(...).bind()`): how A⁻¹ is
        applied (refactorised every step, refreshed, precomputed); one per run. The exact strategy by default.
    """

    def __init__(self, model: TissueModel, compliance=None) -> None:
        from refsim.fem.compliance import make_strategy

        self.model = model
        self.strategy = compliance if compliance is not None else make_strategy("exact").bind()
        self._fixed = np.asarray(model.fixed_nodes)

    def prescribed_increments(self, state: TissueState, control: ControlValues) -> np.ndarray | None:
        """Displacement of every fixed node over the step [m], shape (fixed_count, 3), or None (all held)."""
        if control.boundary_nodes.size == 0:
            return None
        where = np.searchsorted(self._fixed, control.boundary_nodes)
        inside = where < self._fixed.size
        if not (np.all(inside) and np.all(self._fixed[where[inside]] == control.boundary_nodes)):
            missing = np.setdiff1d(control.boundary_nodes, self._fixed)
            raise ValueError(
                f"boundary motion moves nodes that are not fixed in the tissue model: {missing[:10]}"
            )
        increments = np.zeros((self._fixed.size, 3))
        target = self.model.rest_positions[control.boundary_nodes] + control.boundary_displacements
        increments[where] = target - state.positions[control.boundary_nodes]
        return increments

    def free_motion(self, state: TissueState, dt: float, control: ControlValues):
        """Free positions [m] (n, 3) and the step's system (for the compliance and the correction)."""
        free, _, system = self.model.free_motion(
            state,
            dt,
            fixed_displacements=self.prescribed_increments(state, control),
            compliance=self.strategy,
        )
        return free, system

    @staticmethod
    def compliance(system, jacobian):
        """W = H A⁻¹ Hᵀ [m/N], and what the correction needs (the rows H: the step's compliance keeps the
        columns A⁻¹Hᵀ it computed for W)."""
        return system.delassus(jacobian), jacobian

    @staticmethod
    def correct(
        system, previous: TissueState, free: np.ndarray, jacobian, multipliers: np.ndarray, dt: float
    ):
        """x = x_free + A⁻¹ Hᵀ λ, v = (x − x₀)/dt."""
        positions = free
        if jacobian is not None and multipliers.size:
            positions = free + system.correction(jacobian, multipliers).reshape(-1, 3)
        return TissueState(positions=positions, velocities=(positions - previous.positions) / dt)
