"""The bodies of the time step behind one protocol: free motion, compliance of rows, correction.

Every body of a :class:`~refsim.simulation.simulation.Simulation` (the tissue, the needle) implements
:class:`Body` with the same signatures, so the step sums W = Σ_b H_b A_b⁻¹ H_bᵀ and corrects x_b = x_b,free +
A_b⁻¹ H_bᵀ λ over a list of bodies without naming them:

- ``free_motion(state, control, dt) -> (free_state, system)``: the body's state at the end of the step without
  constraint forces, and its step system (what the compliance and the correction need; None for a kinematic
  body);
- ``compliance(system, jacobian) -> (W_b, responses)``: W_b = H_b A_b⁻¹ H_bᵀ [m/N] of the rows' Jacobian on
  the body, and what the correction needs of it (opaque to the caller);
- ``correct(system, previous, free, responses, multipliers, dt) -> state``: x = x_free + A⁻¹Hᵀλ and the
  velocities over the whole step.

A deformable body's A⁻¹ is applied by its own bound compliance strategy (:mod:`refsim.fem.compliance`): the
tissue's is the scene's ``compliance`` section, a flexible needle's the exact strategy with a direct
factorisation (:mod:`refsim.simulation.needle_body`). A kinematic body (a rigid needle) has no DoFs
(``dof_count`` None), no Jacobian in any row, adds nothing to W, and its correction returns its free state.

A body's ``name`` is the key of its Jacobian in :attr:`refsim.constraints.RowBlock.jacobians` and the field of
:class:`~refsim.simulation.state.SimulationState` that holds its state.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

from refsim.constraints import TISSUE
from refsim.fem.tissue import TissueModel, TissueState
from refsim.scene.controls import ControlValues

__all__ = ["Body", "TissueBody"]


@runtime_checkable
class Body(Protocol):
    """A body of the time step (see the module docstring for the contract of each operation).

    Attributes
    ----------
    name : Its name: the key of its Jacobian in a row block and its state's field in the simulation state.
    dof_count : DoFs in the constraint problem (columns of its Jacobian); None or 0 for a kinematic body.
    """

    name: str
    dof_count: int | None

    def free_motion(self, state: Any, control: ControlValues, dt: float) -> tuple[Any, Any]:
        """The free state at the end of the step and the step's system (None for a kinematic body)."""
        ...

    def compliance(self, system: Any, jacobian: Any) -> tuple[np.ndarray, Any]:
        """W_b = H_b A_b⁻¹ H_bᵀ [m/N], dense (rows, rows), and the responses the correction reads."""
        ...

    def correct(
        self, system: Any, previous: Any, free: Any, responses: Any, multipliers: np.ndarray, dt: float
    ) -> Any:
        """The state after the constraint forces: x = x_free + A⁻¹Hᵀλ (``responses`` None: no rows on it)."""
        ...


class TissueBody:
    """The tissue model driven by the boundary controls.

    Parameters
    ----------
    model : The co-rotational tetrahedral model; its fixed nodes must include every node a boundary motion
        moves.
    compliance : The bound compliance strategy (`refsim.fem.compliance.make_strategy(...).bind()`): how A⁻¹ is
        applied (refactorised every step, refreshed, precomputed); one per run. The exact strategy by default.
    """

    name = TISSUE

    def __init__(self, model: TissueModel, compliance=None) -> None:
        from refsim.fem.compliance import make_strategy

        self.model = model
        self.dof_count = model.dof_count
        self.strategy = compliance if compliance is not None else make_strategy("exact").bind()
        self._fixed = np.asarray(model.fixed_nodes)

    def prepare(self, dt: float) -> None:
        """Set up the compliance strategy from the tissue at rest for steps of ``dt`` [s] before the first
        step (the fast and precomputed strategies' rest factor,
        :meth:`refsim.fem.compliance.BodyCompliance.prepare`)."""
        self.strategy.prepare(self.model.rest_system(dt))

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

    def free_motion(self, state: TissueState, control: ControlValues, dt: float):
        """The free state (positions x_free [m] and velocities (x_free − x₀)/dt, each (n, 3)) and the step's
        compliance (:class:`refsim.fem.compliance.StepCompliance`)."""
        positions, velocities, system = self.model.free_motion(
            state,
            dt,
            fixed_displacements=self.prescribed_increments(state, control),
            compliance=self.strategy,
        )
        return TissueState(positions=positions, velocities=velocities), system

    @staticmethod
    def compliance(system, jacobian):
        """W = H A⁻¹ Hᵀ [m/N], and what the correction needs: the rows H themselves (the step's compliance
        keeps the columns A⁻¹Hᵀ it computed for W, keyed on H)."""
        return system.delassus(jacobian), jacobian

    @staticmethod
    def correct(
        system, previous: TissueState, free: TissueState, responses, multipliers: np.ndarray, dt: float
    ) -> TissueState:
        """x = x_free + A⁻¹ Hᵀ λ, v = (x − x₀)/dt."""
        positions = free.positions
        if responses is not None and multipliers.size:
            positions = positions + system.correction(responses, multipliers).reshape(-1, 3)
        return TissueState(positions=positions, velocities=(positions - previous.positions) / dt)
