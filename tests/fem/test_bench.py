"""refsim.fem.bench: its helpers compute what they say (no timing is asserted)."""

from __future__ import annotations

import numpy as np

from refsim.fem.bench import bench_scaling, bench_strategies, compare_runs, growth_exponent
from refsim.fem.compliance import STRATEGY_VARIANTS


def test_growth_exponent_recovers_a_power_law():
    sizes = np.array([1e3, 4e3, 1.6e4, 6.4e4])
    assert abs(growth_exponent(sizes, 3.0 * sizes**1.7) - 1.7) < 1e-12


def test_compare_runs_reports_positions_forces_and_events():
    reference = {
        "tissue_positions": np.zeros((3, 2, 3)),
        "needle_force": np.zeros((3, 3)),
        "events": [(4, "puncture"), (9, "cut_start")],
    }
    candidate = {
        "tissue_positions": np.full((3, 2, 3), 1e-6),
        "needle_force": np.array([[0, 0, 0], [3, 4, 0], [0, 0, 0]]),
        "events": [(4, "puncture"), (8, "cut_start")],
    }
    errors = compare_runs(reference, candidate)
    assert errors["position_error"] == 1e-6 and errors["force_error"] == 5.0
    assert errors["same_events"] is False and "event 1" in errors["event_shift"]
    assert compare_runs(reference, reference)["same_events"] is True


def test_strategy_bench_measures_errors_against_exact():
    reference_ms, rows = bench_strategies(2, steps=3, refresh_every=2)
    assert reference_ms > 0.0
    by_name = {row["strategy"]: row for row in rows}
    assert set(by_name) == set(STRATEGY_VARIANTS)  # every strategy, with each W update of refreshed
    # PCG-corrected W is exact to its tolerance; the stale and precomputed ones are not (measured).
    assert by_name["refreshed"]["compliance_error"] < 1e-8
    assert (
        by_name["refreshed_first_order"]["compliance_error"] < by_name["refreshed_stale"]["compliance_error"]
    )
    assert by_name["precomputed"]["compliance_error"] > by_name["refreshed"]["compliance_error"]
    scaling = bench_scaling((2, 3), steps=2, refresh_every=2)
    assert [row["cells_per_axis"] for row in scaling] == [2, 3]
    assert scaling[1]["free_dofs"] > scaling[0]["free_dofs"]


def test_the_superlu_reference_times_a_factorisation_at_every_repeat(monkeypatch):
    # Every ratio of `refsim bench` is to this time: each repeat must factorise (a solver keeps the factor of
    # the values it factorised last, so reusing one would time a comparison of arrays).
    import refsim.fem.linear as linear
    from refsim.fem.bench import cube_model, superlu_reference_ms

    calls = []
    original = linear.spla.splu
    monkeypatch.setattr(linear.spla, "splu", lambda *a, **k: (calls.append(1), original(*a, **k))[1])
    superlu_reference_ms(cube_model(4), repeats=3)
    assert len(calls) == 3
