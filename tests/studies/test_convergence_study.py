"""The convergence and Pareto studies are executable: run.py writes their study files, plot.py pages and
figures."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

from refsim.sweep import read_study

STUDIES = Path(__file__).resolve().parents[2] / "studies"


def _load(study: str, name: str):
    spec = importlib.util.spec_from_file_location(f"{study}_{name}", STUDIES / study / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_convergence_study_files_are_valid():
    specs = _load("convergence", "run").studies(quick=False)
    assert {spec.name for spec in specs} == {
        "cube_spacing",
        "cube_mesh",
        "cube_cut_spacing",
        "cube_cut_point_spacing",
        "cube_cut_mesh",
    }
    assert all(len(spec.runs()) >= 3 for spec in specs)
    liver = _load("convergence", "run").studies(quick=False, liver=True)
    assert {"liver_rigid_spacing", "liver_rigid_point_spacing", "liver_flexible_spacing"} < {
        s.name for s in liver
    }


def test_quick_convergence_study_runs_and_plots(tmp_path):
    _load("convergence", "run").main(["--output", str(tmp_path / "out"), "--quick", "--workers", "1", "-q"])
    files = sorted((tmp_path / "out").glob("*.h5"))
    assert [f.stem for f in files] == ["cube_mesh_quick", "cube_spacing_quick"]
    for path in files:
        study = read_study(path)
        assert study["runs"]["status"] == ["complete"] * 3
        assert study["convergence"], "three complete levels give a convergence row per finite quantity"
    _load("convergence", "plot").main(["--output", str(tmp_path / "out"), "--docs", str(tmp_path / "docs")])
    assert (tmp_path / "docs" / "figures" / "convergence_cube_mesh_quick.png").stat().st_size > 10_000
    assert "| quantity | type | observed order" in (tmp_path / "docs" / "convergence.md").read_text()


def test_pareto_front():
    front = _load("pareto", "plot").pareto_front([1.0, 2.0, 3.0, 4.0, 0.5], [1e-2, 1e-3, 5e-3, 1e-4, np.nan])
    assert front.tolist() == [0, 1, 3]


def test_pareto_options_are_data():
    run = _load("pareto", "run")
    table = run.options()
    cube = {label for label, _ in run.study("cube", table).cases}
    cut = {label for label, _ in run.study("cube_cut", table).cases}
    assert "d_c 1 mm" in cut and "d_c 1 mm" not in cube  # an option limited to the scenes that have it
    assert table["reference"][1][0] == 'solver.method="exact"'


def test_quick_pareto_study_runs_and_plots(tmp_path):
    _load("pareto", "run").main(["--output", str(tmp_path / "out"), "--quick", "--workers", "1", "-q"])
    study = read_study(tmp_path / "out" / "pareto_cube_quick.h5")
    assert study["reference"]["status"] == "complete"
    errors = study["runs"]["errors"]["force_history"]
    assert np.all(np.isfinite(errors)) and np.all(errors >= 0.0)
    _load("pareto", "plot").main(["--output", str(tmp_path / "out"), "--docs", str(tmp_path / "docs")])
    assert (tmp_path / "docs" / "figures" / "pareto_cube_quick.png").stat().st_size > 10_000
    assert "force history error" in (tmp_path / "docs" / "pareto.md").read_text()
