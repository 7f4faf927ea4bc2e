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


def test_pareto_labels_overlap_neither_each_other_nor_the_markers():
    """A crowded cluster (the cube_cut study's options near the exact mode's time): every label is placed
    inside the axes where it covers no other label and no marker."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xs = np.array([24.4, 24.7, 24.68, 26.2, 25.9, 27.3, 25.0, 25.1, 24.8, 25.7, 11.0, 11.2])
    ys = np.array(
        [1.1e-3, 3.5e-2, 4.2e-2, 5.8e-2, 6.3e-2, 2.9e-1, 3.6e-4, 8.1e-4, 1.6e-6, 1.6e-6, 2.4e-4, 2.5e-4]
    )
    labels = [f"option {i}" for i in range(xs.size)]
    figure, axis = plt.subplots(figsize=(6.4, 4.6))
    axis.loglog(xs, ys, "o", ms=6)
    figure.tight_layout()
    annotations = _load("pareto", "plot").place_labels(axis, labels, xs, ys)
    figure.canvas.draw()
    renderer = figure.canvas.get_renderer()
    boxes = [annotation.get_window_extent(renderer) for annotation in annotations]
    assert len(boxes) == xs.size
    frame = axis.get_window_extent(renderer)
    centres = axis.transData.transform(np.column_stack([xs, ys]))
    for k, box in enumerate(boxes):
        assert frame.x0 <= box.x0 and box.x1 <= frame.x1 and frame.y0 <= box.y0 and box.y1 <= frame.y1
        assert not any(box.overlaps(other) for other in boxes[k + 1 :])
        assert not any(box.contains(x, y) for x, y in centres)
    plt.close(figure)


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
