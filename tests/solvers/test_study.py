"""The solver study runs end to end on small planted problems (run.py writes HDF5, plot.py reads it only)."""

import importlib.util
from pathlib import Path

import h5py
import numpy as np
import pytest

STUDY = Path(__file__).resolve().parents[2] / "studies" / "solvers"


def _module(name):
    spec = importlib.util.spec_from_file_location(f"solver_study_{name}", STUDY / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_shifted_geometric_mean():
    plot = _module("plot")
    # shift 10: exp(mean(log([10, 1000] + 10))) − 10 = sqrt(20 · 1010) − 10
    assert plot.shifted_geometric_mean([10.0, 1000.0]) == pytest.approx(np.sqrt(20 * 1010) - 10)
    assert plot.shifted_geometric_mean([5.0, 5.0]) == pytest.approx(5.0)


def test_study_runs_on_given_problems(planted, rng, tmp_path):
    run = _module("run")
    plot = _module("plot")
    problems = [
        ("planted", planted(rng, unilateral=4, contacts=2)[0]),
        ("planted", planted(rng, bilateral=2, box=3, rank=3)[0]),
    ]
    output = run.run_study(problems, tmp_path / "study.h5")
    with h5py.File(output) as handle:
        assert handle.attrs["schema"] == run.SCHEMA
        assert sorted(handle["problems"]) == ["planted__planted", "planted__planted_1"]  # same name twice
        runs = handle["problems/planted__planted/gauss_seidel/tolerance_runs"][()]
        assert runs.shape == (len(run.GS_TOLERANCES), 7)
    data = plot.load(output)
    assert len(data["problems"]) == 2
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "solver_study.md").write_text("# head\n")
    plot.figure(data, docs / "figures" / "solvers_convergence.png")
    plot.write_tables(plot.tables(data), docs / "solver_study.md")
    text = (docs / "solver_study.md").read_text()
    assert text.startswith("# head") and "planted/planted_1" in text and plot.END in text
    assert (docs / "figures" / "solvers_convergence.png").stat().st_size > 0
