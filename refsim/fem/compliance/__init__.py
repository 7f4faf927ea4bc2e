"""Compliance strategies as values: how a body's step system gives its free motion, W and its correction
(layer 2).

Every deformable body (the tissue, a flexible needle) assembles, at each step, its effective stiffness
A = M/dt² + C/dt + K on its free DoFs (always the same sparsity pattern) and the right-hand side of the free
motion (see :mod:`refsim.fem.integration`): a :class:`StepSystem`. A **strategy** is a plain value (like the
solver factories scikit-fem passes to ``solve``), chosen for the tissue by the scene key
``compliance.strategy``; a flexible needle binds its own (exact, :mod:`refsim.simulation.needle_body`):

``Exact()``
    Factorises A every step (refsim's reference): free motion, W = H A⁻¹ Hᵀ and the correction A⁻¹ Hᵀ λ are
    those of a fresh factorisation, to round-off. A step whose A is the last one, bit for bit (a tissue at
    rest), keeps its factor: the same factor, so the same bits.
``Refreshed(refresh_every=10, tolerance=1e-10)``
    Factorises A every ``refresh_every`` steps only. The free motion solves the *current* A by conjugate
    gradients preconditioned by the stale factor, to a relative residual ``tolerance``. W and the correction:
    with ``compliance_update="pcg"`` (default) the columns A⁻¹ e_j of the DoFs the rows touch are also solved
    by preconditioned CG on the current A to ``tolerance``, so W is *corrected* (its error is that of the CG
    solves, ‖ΔW‖ ≤ ‖H‖² ‖A⁻¹‖ · tolerance · ‖e_j‖ per column); with ``"stale"`` W comes from the stale factor
    alone and its error is only measured (``against_exact``).
``Precomputed()``
    SOFA's precomputed constraint correction: the rest compliance C₀ = A₀⁻¹ (A at the rest shape) is computed
    once (dense when the body has at most ``dense_limit`` free DoFs, otherwise kept as the rest factor) and
    rotated per node, W = H R C₀ Rᵀ Hᵀ with R block-diagonal (one rotation per 3-DoF group). The free motion
    is CG on the current A preconditioned by the rest factor. For comparison and large interactive runs: its W
    is not the current one (on cube_cut it moves forces markedly).
``Fast()``
    The same W and correction as ``Precomputed`` without assembling or factorising any matrix during the run
    (the rest factor once, in single precision where the solver has it: ``Fast.rest_precision``): the body
    builds its step system with an operator v ↦ A v applied per tet (:mod:`refsim.fem.corotated_matvec`)
    instead of A, the free motion is CG on that operator preconditioned by the rotated rest compliance
    R C₀ Rᵀ, started from the last free displacement x' plus R C₀ Rᵀ (b − A' x') (a :class:`FreeMotionStart`
    the run's state carries), and C₀'s columns are solved per node the first time a row touches the node,
    then kept (a memo of the model: one (f, 3) solve per node, applied by the compiled kernels of
    :mod:`refsim.fem.compliance.kernels` in node order, so its bits depend on no history). Its error against
    exact is W's: exact for rigid motions of the rest shape, bounded by ‖H‖² ‖A⁻¹‖ ‖Ã⁻¹‖ ‖A − Ã‖
    (Ã = R A₀ Rᵀ) when the tissue deforms.

Binding a strategy to a body (:meth:`bind`) gives a :class:`BodyCompliance` that keeps what lives across steps
(the analysis, the stale or rest factor). What changes with the run is state: the refreshed strategy's stale
factor is a :class:`StaleFactor` (the matrix it factorised and its age in steps), the fast strategy's start a
:class:`FreeMotionStart`, that the run's state carries
(:meth:`BodyCompliance.carried`, :meth:`BodyCompliance.resume`: a body resumed from a carried factor
factorises its matrix again, which gives the same factor, so a restarted run has the uninterrupted run's
bits). The rest is a memo of the body's model (the rest factor, the symbolic analysis) or of one step (W's
columns for rows H, kept by value); its :meth:`BodyCompliance.step` takes a step system and returns a
:class:`StepCompliance` with ``free_displacement``, :meth:`~StepCompliance.delassus` (W for rows H given as a
scipy CSR matrix of shape (rows, dof_count)) and :meth:`~StepCompliance.correction` (A⁻¹ Hᵀ λ). Every fast
strategy can also compute the exact answer in the same step (``against_exact=True``) and report its errors in
:attr:`StepCompliance.report`.
"""

from __future__ import annotations

from refsim.fem.compliance.bodies import (
    STRATEGIES,
    STRATEGY_CLASSES,
    STRATEGY_VARIANTS,
    W_UPDATES,
    BodyCompliance,
    Exact,
    Fast,
    Precomputed,
    Refreshed,
)
from refsim.fem.compliance.system import (
    FreeMotionStart,
    PartialSolveMarks,
    StaleFactor,
    StepCompliance,
    StepSystem,
    pcg,
)

__all__ = [
    "STRATEGIES",
    "STRATEGY_VARIANTS",
    "W_UPDATES",
    "StaleFactor",
    "FreeMotionStart",
    "PartialSolveMarks",
    "StepSystem",
    "StepCompliance",
    "BodyCompliance",
    "Exact",
    "Refreshed",
    "Precomputed",
    "Fast",
    "make_strategy",
    "pcg",
    "strategy_variant",
]


def strategy_variant(variant: str) -> tuple[str, str]:
    """The strategy and W update of a name of :data:`STRATEGY_VARIANTS` ("refreshed_stale" ->
    ("refreshed", "stale"); a strategy alone has the default update)."""
    if variant not in STRATEGY_VARIANTS:
        raise ValueError(f"compliance strategy {variant!r}: expected one of {', '.join(STRATEGY_VARIANTS)}")
    name, _, update = variant.partition("_")
    return name, update or W_UPDATES[0]


def make_strategy(
    name: str = "exact",
    *,
    refresh_every: int = 10,
    linear_solver: str = "auto",
    against_exact: bool = False,
    tolerance: float | None = None,
    w_update: str | None = None,
):
    """The one factory of compliance strategies: a scene's ``compliance`` section, or a benchmark's variant.

    Parameters
    ----------
    name : A strategy of :data:`STRATEGIES`, or a variant of :data:`STRATEGY_VARIANTS` ("refreshed_stale"),
        which also sets the W update.
    refresh_every : Of :class:`Refreshed`.
    linear_solver : "auto", "pardiso", "cholmod" or "superlu".
    against_exact : Report errors against exact each step (fast strategies only; ignored by exact).
    tolerance : Relative residual at which the PCG of the iterating strategies (refreshed, precomputed, fast)
        stops; None: each strategy's own default (its class's ``tolerance``). The exact strategy ignores it.
    w_update : Of :class:`Refreshed` (its ``compliance_update``), one of :data:`W_UPDATES`; None: the
        variant's, else "pcg". A variant's update and another ``w_update`` together are an error.
    """
    name, update = strategy_variant(name)
    if w_update is not None and update != W_UPDATES[0] and w_update != update:
        raise ValueError(f"compliance strategy {name}_{update}: its W update is {update!r}, not {w_update!r}")
    w_update = w_update or update
    return STRATEGY_CLASSES[name].configured(
        refresh_every=refresh_every,
        linear_solver=linear_solver,
        against_exact=against_exact,
        tolerance=tolerance,
        w_update=w_update,
    )
