"""The resolution study is executable: run.py writes its HDF5 files and summary, plot.py its page and
figure."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

STUDY = Path(__file__).resolve().parents[2] / "studies" / "resolution"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"resolution_{name}", STUDY / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_quick_study_runs_and_plots(tmp_path):
    _load("run").main(["--output", str(tmp_path / "out"), "--quick"])
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert set(summary) == {"mesh", "spacing"}
    for rows in summary.values():
        assert rows[-1]["error"] == 0.0  # the reference is the finest run
        assert all(row["lateral_force"] > 0.0 and Path(row["file"]).is_file() for row in rows)
    _load("plot").main(["--output", str(tmp_path / "out"), "--docs", str(tmp_path / "docs")])
    assert (tmp_path / "docs" / "figures" / "resolution.png").stat().st_size > 10_000
    assert "| run |" in (tmp_path / "docs" / "resolution.md").read_text()
