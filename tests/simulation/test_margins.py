"""Event margins (issue 24, item 7): each event's criterion against its threshold and the solver's accuracy,
and the knife-edge flag (refsim.simulation.margins)."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.scene import load_scene
from refsim.simulation import Simulation
from refsim.simulation.margins import (
    KNIFE_EDGE_STEPS,
    Criterion,
    CriterionSeries,
    MarginWatch,
    _spectral_norm,
    assess,
    force_accuracy,
)
from refsim.solvers import ConstraintProblem

# The cube's entry (off the grid lines) and its needle (tests/simulation/test_life_cycle.py).
ENTRY = (0.00123, 0.00231)
NEEDLE_LENGTH = 0.32
TOP = 0.1


def _approach(theta_degrees: float, *overrides):
    """The cube on 4³ cells, the needle tilted by θ from the top face's normal in the xz plane, its tip moved
    from 1 nm above the face to 70 µm below it in 0.15 s at dt = 1 ms (the normal force builds over tens of
    steps before f_p); returns the scene and the records."""
    theta = np.radians(theta_degrees)
    direction = np.array([np.sin(theta), 0.0, -np.cos(theta)])
    top = np.array([*ENTRY, TOP])
    bases = [top + d * direction - NEEDLE_LENGTH * direction for d in (-1e-9, 7e-5)]
    fmt = lambda v: "[" + ", ".join(repr(float(x)) for x in v) + "]"  # noqa: E731
    scene = load_scene(
        "cube",
        [
            "mesh.cells=[4, 4, 4]",
            "time.dt=0.001",
            "time.duration=0.15",
            "trajectory.times=[0.0, 0.15]",
            "trajectory.base_positions=[" + ", ".join(fmt(b) for b in bases) + "]",
            f"trajectory.directions=[{fmt(direction)}, {fmt(direction)}]",
            *overrides,
        ],
    )
    records = []
    Simulation(scene).run(on_step=lambda state, record: records.append(record))
    return scene, records


def _margins(records):
    series = CriterionSeries.of(
        [r.step for r in records for _ in r.criteria], [c for r in records for c in r.criteria]
    )
    events = [(r.step, e.name) for r in records for e in r.events]
    return series, assess(events, series)


def test_force_accuracy_of_one_row_is_the_residual_bound_over_its_compliance():
    # One unilateral row, W = 1e-3 m/N: a gap error e [m] is a force error e / W [N] (W Δλ = e); a clamped
    # row's force error is e itself; the bound takes the larger.
    compliance = np.array([[1e-3]])
    assert force_accuracy(compliance, np.array([0]), 1e-6) == pytest.approx(1e-3)
    assert force_accuracy(np.array([[10.0]]), np.array([0]), 1e-6) == pytest.approx(1e-6)


def test_force_accuracy_reads_the_smallest_eigenvalue_of_the_rows_block():
    # W_BB of rows (0, 2) of a 3 × 3 W: [[2, 0.5], [0.5, 1]] 1e-3 m/N, its smallest eigenvalue
    # (3 − √2) / 2 · 1e-3 (the characteristic polynomial); the bound is e / σ_min.
    compliance = 1e-3 * np.array([[2.0, 7.0, 0.5], [7.0, 9.0, 7.0], [0.5, 7.0, 1.0]])
    smallest = 0.5 * (3.0 - np.sqrt(2.0)) * 1e-3
    assert force_accuracy(compliance, np.array([0, 2]), 1e-6) == pytest.approx(1e-6 / smallest, rel=1e-12)


@pytest.mark.parametrize("rows", [1, 2, 5, 40])
def test_the_spread_of_the_lateral_rows_is_their_largest_singular_value(rows):
    # ‖D‖₂ by the 3 × 3 Gram matrix equals the SVD's σ_max (LAPACK's, np.linalg.norm(ord=2)) to round-off:
    # both are σ_max of D to a few ulps of ‖D‖² (Golub and Van Loan, 8.6).
    directions = np.random.default_rng(rows).normal(size=(rows, 3))
    expected = np.linalg.norm(directions, ord=2)
    assert _spectral_norm(directions) == pytest.approx(expected, rel=1e-13)


def test_watch_reads_a_capped_puncture_row_as_the_force_it_asks_for():
    # A normal row capped at f_p = 1 N with W = 1e-2 m/N and a free gap of −0.03 m: the unconstrained force
    # is 3 N; held at 1 N the gap is −0.02 m, so the row asks for 1 + 0.02 / 0.01 = 3 N (its excess over the
    # cap), and the accuracy is τ D / W with D = max(‖δ_free‖, ‖λ‖, ‖δ‖) = 1 (‖λ‖).
    problem = ConstraintProblem(
        compliance=np.array([[1e-2]]),
        free_gap=np.array([-0.03]),
        box_rows=np.array([0]),
        box_lower=np.array([0.0]),
        box_upper=np.array([1.0]),
    )

    class Rows:
        source = np.array([0])
        kind = np.array([1])

    watch = MarginWatch(1e-6)
    watch.begin(problem, Rows(), np.array([1.0]), None)
    watch.puncture(np.array([0]), 1.0)
    (criterion,) = watch.taken()
    assert criterion.name == "puncture" and criterion.unit == "N"
    assert criterion.value == pytest.approx(3.0) and criterion.threshold == 1.0
    assert criterion.accuracy == pytest.approx(1e-6 * 1.0 / 1e-2)


def test_watch_reads_a_capped_row_on_held_nodes_as_asking_for_any_force(recwarn):
    # A normal row with no compliance (W = 0: every node it moves is held, a needle pressed on the clamped
    # part of an organ) held at its cap f_p = 1 N with its gap below zero asks for any force: the demand is
    # +inf (above f_p: the tip goes through), and a row with a closed gap asks for its own force; neither
    # divides by zero (the liver's random lives warned of a division by zero and read NaN).
    class Rows:
        source = np.array([0])
        kind = np.array([1])

    for free_gap, demand in ((-0.03, np.inf), (0.0, 1.0)):
        problem = ConstraintProblem(
            compliance=np.array([[0.0]]),
            free_gap=np.array([free_gap]),
            box_rows=np.array([0]),
            box_lower=np.array([0.0]),
            box_upper=np.array([1.0]),
        )
        watch = MarginWatch(1e-6)
        watch.begin(problem, Rows(), np.array([1.0]), None)
        watch.puncture(np.array([0]), 1.0)
        (criterion,) = watch.taken()
        assert criterion.value == demand
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]


def test_assess_counts_the_steps_within_accuracy_before_the_event():
    # A criterion within its accuracy of the threshold at steps 7, 8, 9 (and not at 6) before an event at
    # step 10 whose own value is beyond it: it could have fired 3 steps earlier, none later.
    steps = [6, 7, 8, 9, 10]
    values = [0.5, 0.999, 0.998, 0.9999, 1.2]
    criteria = [Criterion("puncture", v, 1.0, 0.01, "N") for v in values]
    (margin,) = assess([(10, "puncture")], CriterionSeries.of(steps, criteria))
    assert (margin.earlier, margin.later, margin.knife_edge) == (3, 0, True)
    assert margin.before.value == 0.9999 and margin.at_event.value == 1.2
    # The same run with an accuracy ten times finer: only step 9 is within 1e-3; one step, not knife-edge.
    fine = [Criterion("puncture", v, 1.0, 1e-3, "N") for v in values]
    (margin,) = assess([(10, "puncture")], CriterionSeries.of(steps, fine))
    assert (margin.steps, margin.knife_edge) == (1, 1 >= KNIFE_EDGE_STEPS)


def test_straight_puncture_fires_at_f_p_within_the_solver_accuracy():
    # Reference: with the cap (insertion.puncture_within_step) the tip's normal force of the puncture step is
    # f_p; the solve returns it within its accuracy (the criterion's accuracy, τ D max(1, 1/W_nn)). A straight
    # entry (no friction load) is decided by the normal force alone, which grows by far more than its accuracy
    # per step: not knife-edge.
    scene, records = _approach(0.0)
    series, margins = _margins(records)
    (puncture,) = [r for r in records for e in r.events if e.name == "puncture"]
    (margin,) = margins
    force = next(e.force for e in puncture.events if e.name == "puncture")
    assert abs(force - scene.insertion.puncture_force) <= margin.at_event.accuracy
    assert margin.at_event.accuracy < 1e-2 * scene.insertion.puncture_force
    # The force grows by more than twice its accuracy per step, so at most the step before can lie within
    # the accuracy of f_p: the window is one step at most.
    assert margin.at_event.value - margin.before.value > 2.0 * margin.at_event.accuracy
    assert margin.earlier <= 1 and not margin.knife_edge, margin.text()


@pytest.mark.parametrize("theta", [35.0])
def test_tilted_entry_at_the_stick_limit_is_flagged_knife_edge(theta):
    # A tilted tip that sticks carries a friction ratio ‖λ_t‖/λ_n set by the tissue's stiffness under it
    # (the tangential over the normal stiffness times tan θ, not tan θ itself; measured 0.314 for
    # tan θ = 0.7 here), steady once the contact is established (the tip starts 1 nm above the face, so the
    # first step presses over all of it). With μ_p = 2, far above it, the tip sticks throughout and nothing
    # feeds the puncture but its own force: not knife-edge. The same entry with μ_p half an accuracy below
    # the ratio the stuck tip carried the step before its puncture is built at the stick limit: the tip
    # slips over the first steps, sticks, and its ratio creeps back up to μ_p, where it stays within the
    # solver's accuracy of it (a solve within tolerance may let it stick or slip) for tens of steps; the
    # puncture is flagged knife-edge, its window covering those steps.
    _, far = _approach(theta, "insertion.surface_friction_coefficient=2.0")
    series, (margin,) = _margins(far)
    assert not margin.knife_edge, margin.text()
    slip = series.at("tip_slip", margin.step - 1)
    assert slip.value < slip.threshold - slip.accuracy
    mu = float(slip.value - 0.5 * slip.accuracy)
    _, edge = _approach(theta, f"insertion.surface_friction_coefficient={mu!r}")
    series, margins = _margins(edge)
    (margin,) = margins
    assert margin.knife_edge and "tip_slip" in margin.feeding, margin.text()
    within = series.within_steps("tip_slip")
    assert margin.earlier >= KNIFE_EDGE_STEPS and set(
        range(margin.step - margin.earlier, margin.step)
    ) <= set(within.tolist())


def test_a_tear_is_read_on_the_criterion_its_law_decides_it_by():
    # Energy law: a tear is a new layer, laid when the crack tip is d_c from the last one ('layer', fed by the
    # front's force, 'tear'); paper law: the front's force alone ('tear'). The event's own criterion is the
    # first of CRITERIA_OF_EVENT["tear"] evaluated at its step.
    layer = [Criterion("layer", 0.9e-3, 1e-3, 1e-9, "m"), Criterion("layer", 1.2e-3, 1e-3, 1e-9, "m")]
    front = [Criterion("tear", 1.3, 1.0, 1e-4, "1"), Criterion("tear", 1.3, 1.0, 1e-4, "1")]
    series = CriterionSeries.of([4, 5, 4, 5], [*layer, *front])
    (margin,) = assess([(5, "tear")], series)
    assert margin.at_event.name == "layer" and margin.before.value == 0.9e-3 and not margin.knife_edge
    series = CriterionSeries.of([4, 5], front)
    (margin,) = assess([(5, "tear")], series)
    assert margin.at_event.name == "tear" and margin.at_event.value == 1.3


def test_an_undecided_crack_tip_advance_widens_the_layer_margin():
    # Energy law: the layer distance sums the crack tip's advances since the last layer. A tear at step 75
    # whose distance was 9.6 µm short of d_c = 1 mm at step 74 (the liver_tilted_+z pattern), with the
    # distance's own accuracy 3 nm, is not a knife edge when every advance was decided; when the advance of
    # step 73 (0.3 mm) was within its accuracy of the give-way threshold, another solver may not have made
    # it, and the tear can move: the distance at 73 and 74 lies within the undecided 0.3 mm of d_c.
    steps = [72, 73, 74, 75]
    distances = [0.4e-3, 0.7e-3, 0.99043e-3, 1.35e-3]
    layer = [Criterion("layer", d, 1e-3, 3e-9, "m") for d in distances]

    def margin(advance_at_73: float):
        advances = [Criterion("advance", v, 1.0, 1e-7, "1") for v in (1.5, advance_at_73, 1.4, 1.6)]
        series = CriterionSeries.of(steps + steps, layer + advances)
        (tear,) = assess([(75, "tear")], series)
        return tear

    decided = margin(1.2)
    assert (decided.earlier, decided.later, decided.knife_edge) == (0, 0, False)
    undecided = margin(1.0 + 5e-8)
    assert undecided.before.accuracy == pytest.approx(3e-9 + 0.3e-3)
    assert undecided.earlier == 2 and undecided.knife_edge
    assert undecided.feeding == ("advance", "layer")


def test_an_advance_before_the_last_tear_does_not_widen_the_next_one():
    # The distance restarts at each layer: an undecided advance before the previous tear (step 71) moved
    # that tear, not the next one, whose distance it does not contain.
    steps = [70, 71, 72, 73]
    layer = [Criterion("layer", d, 1e-3, 3e-9, "m") for d in (0.6e-3, 1.1e-3, 0.5e-3, 1.05e-3)]
    advances = [Criterion("advance", v, 1.0, 1e-7, "1") for v in (1.0, 1.3, 1.3, 1.3)]
    series = CriterionSeries.of(steps + steps, layer + advances)
    first, second = assess([(71, "tear"), (73, "tear")], series)
    assert first.before.accuracy == pytest.approx(3e-9 + 0.6e-3)
    assert second.before.accuracy == pytest.approx(3e-9) and not second.knife_edge


def test_watch_records_the_front_row_nearest_its_give_way_decision():
    # Energy law, two front rows with strength G_c ℓ = 1 N, W = diag(1e-2, 1e-2) m/N: row 0 held at its
    # strength with the needle 0.02 m through (it asks for 1 + 0.02/0.01 = 3 N: it gave way, far from the
    # decision), row 1 at 0.99 N with its gap closed (it holds, 1 % below). The 'tear' criterion is the
    # strongest (3, against 1); 'advance' the nearest to its decision relative to its accuracy: row 1, 0.99
    # against 1, accuracy (ε_λ + τ D / W_11) / 1 N.
    from refsim.cutting.laws import EnergyLaw

    problem = ConstraintProblem(
        compliance=np.diag([1e-2, 1e-2]),
        free_gap=np.array([-0.03, -0.0099]),
        box_rows=np.array([0, 1]),
        box_lower=np.array([0.0, 0.0]),
        box_upper=np.array([1.0, 1.0]),
    )
    watch = MarginWatch(1e-6)
    watch.begin(problem, None, np.array([1.0, 0.99]), None)
    watch.tear(EnergyLaw(fracture_energy=1000.0), np.array([0, 1]))
    tear, advance = watch.taken()
    assert (tear.name, advance.name) == ("tear", "advance")
    assert tear.value == pytest.approx(3.0) and advance.value == pytest.approx(0.99)
    bound = 1e-6 * float(np.linalg.norm([1.0, 0.99]))  # τ D, D = ‖λ‖ here
    epsilon = force_accuracy(problem.compliance, np.array([0, 1]), bound)
    assert advance.accuracy == pytest.approx(epsilon + bound / 1e-2)
    assert advance.threshold == 1.0 and not advance.within
