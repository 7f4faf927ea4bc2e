"""The exact-solver benchmark (studies/solvers/run.py --benchmark) runs: its timing harness and its rounds."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import h5py
import numpy as np

from tests.solvers.conftest import planted_problem

STUDY = Path(__file__).resolve().parents[2] / "studies" / "solvers"


def _load_run():
    spec = importlib.util.spec_from_file_location("solvers_run", STUDY / "run.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_best_time_uses_fresh_copies_made_before_the_timed_calls(monkeypatch):
    import dataclasses

    run = _load_run()
    problem, _, _ = planted_problem(np.random.default_rng(1), contacts=2)
    events = []
    replace = dataclasses.replace
    monkeypatch.setattr(dataclasses, "replace", lambda *a, **k: events.append("copy") or replace(*a, **k))
    seen = []

    def solver(copy):
        assert copy is not problem and all(copy is not other for other in seen)  # a new copy for every call
        assert "_block_arrays" not in copy.__dict__  # nothing cached on it
        events.append("call")
        seen.append(copy)
        return copy.row_count

    seconds, result = run._best_time(solver, problem, repeats=3)
    assert events == ["copy"] * 3 + ["call"] * 3  # nothing but the loop between the timed calls
    assert result == problem.row_count and 0.0 < seconds < np.inf


def test_benchmark_rounds_keep_each_solvers_best_time(tmp_path, monkeypatch):
    run = _load_run()
    monkeypatch.setattr(run, "legacy_solve_exact", lambda: None)  # no git checkout of the old solver here
    monkeypatch.setattr(run, "_siconos", lambda problems, tolerance: {})  # Siconos: optional, not timed here
    calls = []
    original = run._best_time

    def recording(function, problem, repeats=3):
        seconds, result = original(function, problem, repeats)
        calls.append(seconds)
        return seconds, result

    monkeypatch.setattr(run, "_best_time", recording)
    problems = [
        ("planted", planted_problem(np.random.default_rng(seed), contacts=2, unilateral=1)[0])
        for seed in (2, 3)
    ]
    output = tmp_path / "benchmark.h5"
    text = run.benchmark_exact(problems, output, rounds=2)
    assert "refsim exact" in text and output.is_file()
    assert len(calls) == 2 * 2 * 2  # two refsim solvers, two problems, two rounds
    with h5py.File(output) as handle:
        table = handle["refsim exact (Newton first)"][()]
    # per problem the best of its two rounds (calls: round 1 exact, GS, exact, GS; round 2 likewise)
    exact_times = np.array(calls).reshape(2, 2, 2)[:, :, 0]
    np.testing.assert_array_equal(table[:, 0], exact_times.min(axis=0))
    assert (table[:, 1] <= 1e-8).all()  # both solved, errors recorded
