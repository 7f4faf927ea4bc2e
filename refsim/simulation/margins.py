"""Event margins: how far each event's criterion was from its threshold, against what the solver can resolve.

An event fires when a quantity computed from the step's multipliers λ crosses a threshold. The solver returns
λ only to its tolerance, so a criterion that sits within the solver's accuracy of its threshold could have
fired a step earlier or later with another solver, warm start or tolerance. Every step, the events record the
criteria they compare (:class:`Criterion`: value, threshold, accuracy; one line per event site in
:mod:`refsim.simulation.events` through :class:`MarginWatch`), the results file stores them (``criteria/``)
and :func:`assess` turns them into each event's margin (:class:`EventMargin`) and its knife-edge flag.

The criteria
------------
- ``puncture`` [N]: the tip's normal force against f_p. With the cap of ``insertion.puncture_within_step`` the
  force of the step that punctures is f_p by construction; the value is then the force the contact asks for,
  λ_n − δ_n / W_nn (λ_n where the gap is closed, more than f_p by the step's excess where the cap holds it).
- ``tip_slip`` [-] (fed to the puncture): the tip's friction ratio against μ_p, as the Coulomb law decides it:
  ‖λ_t − δ_t / W_tt‖ / λ_n (the ratio ‖λ_t‖/λ_n while the tip sticks, δ_t = 0; above μ_p by the slip's force
  while it slides; the largest of the two rows where the friction is a square, the norm where it is a disc).
  Evaluated where the normal force exceeds its accuracy (a contact the solve resolves as closed).
- ``cut_start`` [N/m or N]: the law's cut-start load against its threshold (energy law ‖t‖/L_in against G_c,
  paper law ‖t‖/n_i against f_c; `refsim.cutting.laws.CuttingLaw.cut_start_load`).
- ``tear`` [N or -]: the crack front's strongest row (paper law: its force against f_t; energy law: its force
  over its strength G_c ℓ_k against 1; `CuttingLaw.front_load`).
- ``advance`` [-] (energy law: whether the crack tip advances in a step; it feeds ``layer``): each front row
  gives way when it is at its strength G_c ℓ_k with the needle through the crack tip (`EnergyLaw.given_way`),
  which is its demand over its strength (:meth:`MarginWatch.demands`) exceeding 1; the criterion is the row
  whose decision is nearest its threshold relative to its accuracy ((ε_λ + τ D / W_ii) / (G_c ℓ_k)),
  recorded every cutting step with front rows.
- ``layer`` [m] (energy law: what lays a new layer, the event ``tear``; ``tear`` and ``advance`` feed it): how
  far the crack tip moved from the last layer (rest), against d_c (`refsim.cutting.strip.CutStrip.lay`),
  recorded in the steps where the crack tip moved. Its accuracy within the step is the gap's, τ D [m] (the
  crack tip follows the needle and the rows' compression, both resolved to the rows' gap accuracy, first
  order). The distance sums the crack tip's advances since the last layer, so :func:`assess` reads it with
  the advances of those steps whose ``advance`` decision was within its accuracy added to that accuracy (an
  advance another solver may not have made, or made larger: the crack tip's position, hence the tear's step,
  is then not decided by the tolerance).

The geometric events (new insertion points, exit, retraction, withdrawal, leave_cut) compare lengths of the
corrected positions; they carry no criterion here.

The accuracy
------------
The solvers stop on the natural residual, ‖e‖ ≤ τ D with D = max(‖δ_free‖, ‖λ‖, ‖δ‖) the problem's scale
(`refsim.solvers.residual`; τ is ``solver.tolerance``, or the residual the step reached when larger). Per row,
e is a force [N] where the law clamps λ (a row at a bound, a sliding friction row) and a gap [m] where the gap
must close. For the rows B a criterion reads, the error of their forces is then at most ‖e_B‖ where they are
clamped and ‖W_BB⁻¹‖ ‖e_B‖ = ‖e_B‖ / σ_min(W_BB) where their gaps close (the first-order solution of
W_BB Δλ = e_B, the other rows held); the bound takes the larger, ε_λ = τ D max(1, 1/σ_min(W_BB)) [N], with the
units of SI (the natural residual mixes N and m the same way). A criterion summing forces along unit
directions N_B (3 × |B|) is accurate to ‖N_B‖₂ ε_λ; one divided by a length or a count to ε_λ divided by it; a
ratio a/b to (ε_a + (a/b) ε_b)/b. The gap's own accuracy (in ``tip_slip``'s δ_t/W_tt) is τ D / W_tt.

Knife-edge
----------
A criterion is *within* its accuracy at a step when |value − threshold| ≤ accuracy. For an event at step k:
the steps it could move earlier are the consecutive steps k−1, k−2, … (of the same phase) at which any
criterion feeding it was within its accuracy (the event's own, or the tip's stick/slip decision for a
puncture); one step later when its own criterion was within its accuracy at k (a lower bound: after the event
its criterion is no longer evaluated, so how much later it could have fired is not known). An event that could
move :data:`KNIFE_EDGE_STEPS` steps or more is flagged knife-edge; the count is a window, not a prediction:
inside it, two solvers that both meet the tolerance may place the event at different steps.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from refsim.constraints import BILATERAL, FRICTION, INSERTION, PENETRATION, UNILATERAL
from refsim.constraints.rows import zero_compliance as zero_compliance_rows

__all__ = [
    "CRITERIA_OF_EVENT",
    "KNIFE_EDGE_STEPS",
    "Criterion",
    "CriterionSeries",
    "EventMargin",
    "MarginWatch",
    "assess",
    "force_accuracy",
    "held_rows",
    "problem_scale",
]

#: An event that could move this many steps or more is flagged knife-edge.
KNIFE_EDGE_STEPS = 2

#: The criteria that decide each event, in order: its own is the first evaluated at the event's step (a tear
#: of the energy law is decided by ``layer``, one of the paper law by ``tear``), the others feed it.
CRITERIA_OF_EVENT = {
    "puncture": ("puncture", "tip_slip"),
    "cut_start": ("cut_start",),
    "tear": ("layer", "tear", "advance"),
}


def shaft_lateral_rows(source, kind, points, without_entry: bool, mask=None) -> np.ndarray:
    """Indices of the insertion points' lateral (bilateral) rows, the cut-start load's rows, shape (k,):
    ``source``, ``kind``, ``points`` (each row's insertion point, the entry is 0) per row; ``without_entry``
    leaves the entry point's rows out (``CuttingLaw.excludes_entry_point``); ``mask`` (bool per row) keeps
    only those rows when given."""
    lateral = (np.asarray(source) == INSERTION) & (np.asarray(kind) == BILATERAL)
    if without_entry:
        lateral &= np.asarray(points) != 0
    if mask is not None:
        lateral &= mask
    return np.flatnonzero(lateral)


@dataclass(frozen=True)
class Criterion:
    """A criterion an event compares, as evaluated at the end of one step.

    Attributes
    ----------
    name : The criterion (``puncture``, ``tip_slip``, ``cut_start``, ``tear``).
    value : The quantity compared, in ``unit``.
    threshold : What it is compared with, in ``unit``.
    accuracy : How far the value can be from the exact solution's when the solve meets its tolerance, in
        ``unit``, ≥ 0 (module docstring).
    unit : "N", "N/m", "m" or "1".
    """

    name: str
    value: float
    threshold: float
    accuracy: float
    unit: str

    @property
    def margin(self) -> float:
        """value − threshold, in ``unit`` (≥ 0: the criterion holds)."""
        return self.value - self.threshold

    @property
    def within(self) -> bool:
        """Whether the threshold lies within the accuracy of the value."""
        return bool(abs(self.margin) <= self.accuracy)


def _over(numerator, diagonal) -> np.ndarray:
    """numerator / W_ii elementwise, for a compliance diagonal W_ii ≥ 0: a row with no compliance (W_ii = 0:
    every node it moves is held) answers ±inf to a non-zero numerator (a rigid row asks for any force) and
    0 to zero, without a division by zero."""
    numerator = np.asarray(numerator, dtype=float)
    diagonal = np.asarray(diagonal, dtype=float)
    numerator, diagonal = np.broadcast_arrays(numerator, diagonal)
    out = np.where(numerator == 0.0, 0.0, np.copysign(np.inf, numerator))
    np.divide(numerator, diagonal, out=out, where=diagonal > 0.0)
    return out


def problem_scale(problem, multipliers: np.ndarray) -> float:
    """D = max(‖δ_free‖, ‖λ‖, ‖δ‖), the natural residual's scale (`refsim.solvers.residual`)."""
    gap = problem.compliance @ multipliers + problem.free_gap
    scale = max(np.linalg.norm(problem.free_gap), np.linalg.norm(multipliers), np.linalg.norm(gap))
    return float(scale) if scale > 0.0 else 1.0


def held_rows(rows, problem) -> np.ndarray:
    """The rows of ``rows`` (a ``RowBlock``, or anything with its ``kind``) that no force can satisfy in
    ``problem`` (the step's constraint problem, its rows in that order), shape (row_count,) bool: a zero
    compliance W_ii (at most 1e-14 of the largest diagonal, as Gauss-Seidel's floor: the row moves a rigid
    needle and held tissue nodes only, so no multiplier changes its gap) with its free gap violated (below
    zero for a unilateral row, not zero for a bilateral one). Friction rows are left out (their gap is a
    slip, not a violation)."""
    gap = problem.free_gap
    violated = ((rows.kind == UNILATERAL) & (gap < 0.0)) | ((rows.kind == BILATERAL) & (gap != 0.0))
    return zero_compliance(problem) & violated


def zero_compliance(problem) -> np.ndarray:
    """The rows of ``problem`` whose compliance W_ii is zero (:func:`refsim.constraints.rows.zero_compliance`
    of its W), shape (row_count,) bool: their multipliers change no gap."""
    return zero_compliance_rows(problem.compliance)


def _spectral_norm(matrix: np.ndarray) -> float:
    """‖D‖₂ of a (k, 3) matrix D: the square root of the largest eigenvalue of its 3 × 3 Gram matrix DᵀD (a
    3 × 3 eigenvalue problem in place of the SVD of D that ``np.linalg.norm(D, ord=2)`` takes)."""
    gram = matrix.T @ matrix
    return float(np.sqrt(max(float(np.linalg.eigvalsh(gram)[-1]), 0.0)))


def force_accuracy(compliance: np.ndarray, rows: np.ndarray, residual_bound: float) -> float:
    """ε_λ = ‖e‖ max(1, 1/σ_min(W_BB)) [N]: the accuracy of the forces of ``rows`` (B) for a natural-map
    error ‖e‖ ≤ ``residual_bound`` (τ D), W the problem's compliance [m/N]."""
    rows = np.asarray(rows, dtype=np.int64)
    if rows.size == 0:
        return 0.0
    block = compliance.take(rows, axis=0).take(rows, axis=1)  # W[np.ix_(rows, rows)], without its index grid
    smallest = float(np.linalg.eigvalsh(0.5 * (block + block.T))[0])
    inverse = np.inf if smallest <= 0.0 else 1.0 / smallest
    return float(residual_bound * max(1.0, inverse))


@dataclass
class MarginWatch:
    """Collects the criteria the events compare in one step (:meth:`begin` each step, then one call per event
    site, then :meth:`taken`).

    Parameters
    ----------
    tolerance : The solver's tolerance τ (``solver.tolerance``).
    """

    tolerance: float
    _problem: object | None = None
    _rows: object | None = None
    _multipliers: np.ndarray | None = None
    _bound: float = 0.0
    _own: np.ndarray | None = None
    _own_rows: np.ndarray | None = None
    _criteria: list = field(default_factory=list)

    def begin(
        self,
        problem,
        rows,
        multipliers: np.ndarray,
        report,
        own: np.ndarray | None = None,
        scale: float | None = None,
    ) -> None:
        """Start a step: its constraint problem (None without rows), its rows (``RowBlock``), multipliers [N],
        solver report and which rows are this instrument's (``own``, a mask over the rows; all by default).
        The problem holds every instrument's rows; the rows an event names are indices into its instrument's
        own rows, mapped here to the problem's. ``scale``: the problem's :func:`problem_scale`, computed once
        per step for every instrument (a product by the whole W: per instrument, its cost grew as the cube of
        the instrument count); computed here when None."""
        self._criteria = []
        self._problem, self._rows, self._multipliers = problem, rows, multipliers
        count = 0 if problem is None else problem.row_count
        self._own = np.ones(count, dtype=bool) if own is None else np.asarray(own, dtype=bool)
        self._own_rows = np.flatnonzero(self._own)
        if problem is None:
            self._bound = 0.0
            return
        reached = float(getattr(report, "residual", 0.0))
        tolerance = max(self.tolerance, reached if np.isfinite(reached) else np.inf)
        self._bound = tolerance * (problem_scale(problem, multipliers) if scale is None else scale)

    def taken(self) -> tuple[Criterion, ...]:
        """The step's criteria, in the order the events compared them."""
        return tuple(self._criteria)

    def _accuracy(self, rows) -> float:
        return force_accuracy(self._problem.compliance, rows, self._bound)

    def puncture(self, normal_rows: np.ndarray, puncture_force: float) -> None:
        """The tip's normal force (its ``normal_rows``) against f_p and, with its friction rows, its
        stick/slip ratio against μ_p."""
        if self._problem is None or len(normal_rows) == 0:
            return
        problem, multipliers, rows = self._problem, self._multipliers, self._rows
        tangent_rows = np.flatnonzero((rows.source == PENETRATION) & (rows.kind == FRICTION) & self._own)
        gap = problem.compliance @ multipliers + problem.free_gap
        diagonal = np.diag(problem.compliance)
        held = bool(self.held(normal_rows).any())
        normal_rows = self._own_rows[np.asarray(normal_rows, dtype=np.int64)]
        normal = float(multipliers[normal_rows].sum())
        # The force the contact asks for: above f_p where the cap holds the row at f_p, the tip through.
        # A contact of zero compliance is decided whatever the solver's accuracy: held (held_rows: no force
        # closes its gap), it asks for more than any force; open (its gap above zero), for none.
        demand = np.inf if held else float(self.demands(normal_rows).sum())
        rigid = bool(zero_compliance(problem)[normal_rows].all())
        normal_accuracy = 0.0 if rigid else self._accuracy(normal_rows)
        self._criteria.append(Criterion("puncture", demand, float(puncture_force), normal_accuracy, "N"))
        if tangent_rows.size == 0 or normal <= normal_accuracy:
            return  # no friction, or a contact not resolved as closed: no stick/slip to decide
        coefficient = _tangent_coefficient(problem, tangent_rows)
        trial = multipliers[tangent_rows] - _over(gap[tangent_rows], diagonal[tangent_rows])
        disc = np.isin(tangent_rows, np.asarray(problem.contacts).ravel())
        tangential = float(np.linalg.norm(trial)) if np.all(disc) else float(np.abs(trial).max())
        ratio = tangential / normal
        # ε of the trial force: its λ_t and its δ_t / W_tt, each to the residual's bound.
        tangent_accuracy = self._accuracy(tangent_rows) + float(
            _over(self._bound, diagonal[tangent_rows].min())
        )
        accuracy = (tangent_accuracy + ratio * normal_accuracy) / normal
        self._criteria.append(Criterion("tip_slip", ratio, coefficient, accuracy, "1"))

    def cut_start(
        self,
        law,
        lateral_force: np.ndarray,
        inserted_length: float,
        point_count: int,
        rows: np.ndarray | None = None,
    ) -> None:
        """The ``law``'s cut-start load (``CuttingLaw.cut_start_load``) for the shaft's lateral force t [N],
        shape (3,), its accuracy over the insertion points' lateral rows, the entry point's included (a law
        that leaves them out counts their load beyond f_p, `refsim.simulation.events.shaft_lateral_force`: the
        bound holds either way), or over ``rows`` (indices into the instrument's own rows: the cut faces' rows
        of a needle pressed against them) when given."""
        if self._problem is None:
            return
        value, threshold, divisor, unit = law.cut_start_load(
            lateral_force, inserted_length=inserted_length, point_count=point_count
        )
        if rows is None:
            lateral = shaft_lateral_rows(
                self._rows.source, self._rows.kind, self._rows.points_of_rows, False, self._own
            )
        else:
            lateral = self._own_rows[np.asarray(rows, dtype=np.int64)]
        rows = self._rows
        spread = _spectral_norm(rows.directions[lateral]) if lateral.size else 0.0
        accuracy = spread * self._accuracy(lateral) / divisor if divisor > 0.0 else np.inf
        self._criteria.append(Criterion("cut_start", value, threshold, accuracy, unit))

    def tear(self, law, rows) -> None:
        """The crack front's load (``law.front_load``: value, threshold, divisor, unit) over its ``rows``,
        each row's force taken as the force it asks for (:meth:`demands`)."""
        rows = np.asarray(rows, dtype=np.int64)
        if self._problem is None or rows.size == 0:
            return
        rows = self._own_rows[rows]
        problem = self._problem
        limits = np.full(problem.row_count, np.inf)
        limits[problem.box_rows] = problem.box_upper
        demands = self.demands(rows)
        load = law.front_load(demands, limits[rows])
        if load is None:
            return
        value, threshold, divisor, unit = load
        accuracy = self._accuracy(rows)
        self._criteria.append(Criterion("tear", value, threshold, accuracy / divisor, unit))
        if unit == "1":  # a law whose rows give way at their strength (energy): each row's own decision
            self._criteria.append(self._advance(rows, limits[rows], accuracy, demands))

    def _advance(
        self, rows: np.ndarray, limits: np.ndarray, accuracy: float, demands: np.ndarray
    ) -> Criterion:
        """The ``advance`` criterion of the front ``rows`` (problem indices) with force limits ``limits``
        [N] and ``demands`` [N] (:meth:`demands` of the rows): the row whose give-way decision (demand over
        limit against 1) is nearest its threshold relative to its accuracy ((ε_λ + τ D / W_ii) / limit),
        ``accuracy`` being ε_λ of the rows [N]."""
        finite = np.isfinite(limits) & (limits > 0.0)
        if not np.any(finite):
            return Criterion("advance", 0.0, 1.0, 0.0, "1")
        rows, limits = rows[finite], limits[finite]
        ratios = demands[finite] / limits
        diagonal = self._problem.compliance[rows, rows]
        accuracies = (accuracy + _over(np.full(rows.size, self._bound), diagonal)) / limits
        nearest = int(np.argmin(np.abs(ratios - 1.0) / np.maximum(accuracies, np.finfo(float).tiny)))
        return Criterion("advance", float(ratios[nearest]), 1.0, float(accuracies[nearest]), "1")

    def layer(self, growth) -> None:
        """How far the crack tip was from the last layer against d_c (``FrontGrowth.layer_distance``, energy
        law: a layer, event ``tear``, is laid when it reaches d_c), to the gap's accuracy τ D [m]."""
        if self._problem is None or growth.layer_distance is None:
            return
        distance, spacing = float(growth.layer_distance), float(growth.layer_spacing)
        self._criteria.append(Criterion("layer", distance, spacing, self._bound, "m"))

    def held(self, rows: np.ndarray) -> np.ndarray:
        """Which of this instrument's ``rows`` (indices into its own rows) no force can satisfy this step
        (:func:`held_rows`: zero compliance, gap violated; a rigid needle pressed on held tissue), shape
        (|rows|,) bool."""
        rows = np.asarray(rows, dtype=np.int64)
        if self._problem is None or rows.size == 0:
            return np.zeros(rows.size, dtype=bool)
        return held_rows(self._rows, self._problem)[self._own_rows[rows]]

    def demands(self, rows: np.ndarray) -> np.ndarray:
        """The force each of ``rows`` asks for [N], shape (|rows|,): λ, plus −δ/W_ii where the row is held at
        its upper bound with its gap open below zero (the cap's excess)."""
        problem, multipliers = self._problem, self._multipliers
        rows = np.asarray(rows, dtype=np.int64)
        gap = problem.compliance[rows] @ multipliers + problem.free_gap[rows]
        diagonal = problem.compliance[rows, rows]
        capped = np.zeros(problem.row_count, dtype=bool)
        capped[np.asarray(problem.box_rows, dtype=np.int64)] = True
        capped = capped[rows]
        return multipliers[rows] + np.where(capped, _over(np.maximum(-gap, 0.0), diagonal), 0.0)


def _tangent_coefficient(problem, rows: np.ndarray) -> float:
    """μ of the tip's friction rows: the group coefficient (square) or the contact's (disc)."""
    groups = np.asarray(problem.group_friction)
    if groups.size and np.isin(rows, groups).any():
        return float(np.asarray(problem.group_friction_coefficient)[np.isin(groups, rows)].max())
    return float(np.asarray(problem.contact_friction).max())


@dataclass(frozen=True)
class CriterionSeries:
    """Criteria of a run, one entry per criterion and step, in step order (what ``criteria/`` stores).

    Attributes
    ----------
    step : Step of each entry, shape (c,). name : Criterion name, shape (c,).
    value, threshold, accuracy : In each entry's ``unit`` (Criterion), shape (c,). unit : shape (c,).
    """

    step: np.ndarray
    name: np.ndarray
    value: np.ndarray
    threshold: np.ndarray
    accuracy: np.ndarray
    unit: np.ndarray

    @classmethod
    def of(cls, steps: list[int], criteria: list[Criterion]) -> CriterionSeries:
        """The series of ``criteria``, each evaluated at the step of the same index in ``steps``."""
        return cls(
            step=np.asarray(steps, dtype=np.int64),
            name=np.array([c.name for c in criteria], dtype=object),
            value=np.array([c.value for c in criteria], dtype=float),
            threshold=np.array([c.threshold for c in criteria], dtype=float),
            accuracy=np.array([c.accuracy for c in criteria], dtype=float),
            unit=np.array([c.unit for c in criteria], dtype=object),
        )

    def at(self, name: str, step: int) -> Criterion | None:
        """The criterion ``name`` at ``step``, None when not evaluated there."""
        found = np.flatnonzero((self.name == name) & (self.step == step))
        if found.size == 0:
            return None
        i = int(found[-1])
        return Criterion(name, self.value[i], self.threshold[i], self.accuracy[i], str(self.unit[i]))

    def within_steps(self, name: str) -> np.ndarray:
        """The steps at which ``name`` was within its accuracy of its threshold, sorted."""
        chosen = self.name == name
        within = np.abs(self.value[chosen] - self.threshold[chosen]) <= self.accuracy[chosen]
        return np.unique(self.step[chosen][within])

    def evaluated_steps(self, name: str) -> np.ndarray:
        """The steps at which ``name`` was evaluated, sorted."""
        return np.unique(self.step[self.name == name])


@dataclass(frozen=True)
class EventMargin:
    """An event's margin: its criterion at the event step and at the step before, and how far it could move.

    Attributes
    ----------
    step : The event's step. name : The event.
    at_event, before : Its own criterion at the event step and at the step before (None: not evaluated).
    earlier : Consecutive steps before the event at which a criterion feeding it was within its accuracy.
    later : 1 when its own criterion was within its accuracy at the event step, else 0 (a lower bound: the
        criterion is not evaluated after the event).
    feeding : The criteria found within their accuracy in those steps (e.g. ``("tip_slip",)``).
    """

    step: int
    name: str
    at_event: Criterion | None
    before: Criterion | None
    earlier: int
    later: int
    feeding: tuple[str, ...] = ()

    @property
    def steps(self) -> int:
        """How many steps the event could move (earlier + later)."""
        return self.earlier + self.later

    @property
    def knife_edge(self) -> bool:
        """Whether the event could move :data:`KNIFE_EDGE_STEPS` steps or more."""
        return self.steps >= KNIFE_EDGE_STEPS

    def text(self) -> str:
        """One line: the criterion at the event and the step before, the accuracy, the flag."""

        def show(criterion: Criterion | None) -> str:
            if criterion is None:
                return "-"
            return f"{criterion.value:.6g} {criterion.unit}"

        criterion = self.at_event
        head = f"step {self.step:6d}  {self.name:<10}"
        if criterion is None:
            return f"{head} no criterion recorded"
        flag = f"KNIFE-EDGE: could move {self.steps} steps" if self.knife_edge else f"could move {self.steps}"
        fed = f" ({', '.join(self.feeding)} within accuracy)" if self.feeding else ""
        return (
            f"{head} {show(criterion)} against {criterion.threshold:.6g} (step before {show(self.before)}), "
            f"accuracy ±{criterion.accuracy:.3g}: {flag}{fed}"
        )


def assess(events, series: CriterionSeries) -> list[EventMargin]:
    """The margin of every event with a criterion (:data:`CRITERIA_OF_EVENT`), in order.

    Parameters
    ----------
    events : (step, name) of each event, in order.
    series : The run's criteria.
    """
    margins = []
    last_tear = None
    for step, name in events:
        step, name = int(step), str(name)
        criteria = CRITERIA_OF_EVENT.get(name)
        if criteria is None:
            continue
        own = next((c for c in criteria if series.at(c, step) is not None), criteria[0])
        at_event, before = series.at(own, step), series.at(own, step - 1)
        evaluated = series.evaluated_steps(own)
        within = {criterion: set(series.within_steps(criterion).tolist()) for criterion in criteria}
        if own == "layer":
            undecided = _undecided_advance(series, last_tear, step)
            within["layer"] = _layer_within(series, undecided)
            at_event, before = (
                None if c is None else _widened(c, undecided.get(s, 0.0))
                for c, s in ((at_event, step), (before, step - 1))
            )
        if name == "tear":
            last_tear = step
        earlier, fed = 0, set()
        candidate = step - 1
        while candidate in evaluated:
            hits = [c for c in criteria if candidate in within[c]]
            if not hits:
                break
            fed.update(hits)
            earlier += 1
            candidate -= 1
        later = int(at_event is not None and at_event.within)
        margins.append(EventMargin(step, name, at_event, before, earlier, later, tuple(sorted(fed))))
    return margins


def _undecided_advance(series: CriterionSeries, after: int | None, until: int) -> dict[int, float]:
    """The crack tip's advances the solve did not decide, summed: for every step s in (after, until] where
    ``layer`` was evaluated, the sum of the advances (growth of the layer distance over the step, [m]) of the
    steps up to s whose ``advance`` decision was within its accuracy."""
    chosen = (series.name == "layer") & (series.step <= until)
    if after is not None:
        chosen &= series.step > after
    steps, distances = series.step[chosen], series.value[chosen]
    order = np.argsort(steps, kind="stable")
    steps, distances = steps[order], distances[order]
    advances = np.maximum(np.diff(distances, prepend=0.0), 0.0)
    undecided = np.isin(steps, series.within_steps("advance"))
    return dict(zip(steps.tolist(), np.cumsum(np.where(undecided, advances, 0.0)).tolist(), strict=True))


def _layer_within(series: CriterionSeries, undecided: dict[int, float]) -> set[int]:
    """The steps at which ``layer`` was within its accuracy widened by the undecided advances."""
    chosen = np.flatnonzero(series.name == "layer")
    widened = series.accuracy[chosen] + np.array([undecided.get(int(s), 0.0) for s in series.step[chosen]])
    hits = np.abs(series.value[chosen] - series.threshold[chosen]) <= widened
    return set(series.step[chosen][hits].tolist())


def _widened(criterion: Criterion, extra: float) -> Criterion:
    """``criterion`` with ``extra`` added to its accuracy."""
    return Criterion(
        criterion.name, criterion.value, criterion.threshold, criterion.accuracy + extra, criterion.unit
    )
