"""The fast-against-exact scaling study (studies/scaling/modes.py): a tiny case measured, and its page."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

STUDY = Path(__file__).resolve().parents[2] / "studies" / "scaling" / "modes.py"


def _load():
    spec = importlib.util.spec_from_file_location("scaling_modes", STUDY)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_tiny_case_is_measured_in_both_modes_and_paged(monkeypatch, tmp_path):
    # The cube on 3 cells for 0.3 s (the needle indents, punctures and inserts): both modes run, the fast
    # run is compared with the exact one (the same events; the needle force to the fast mode's error, far
    # below the peak), and the page and figure are written from the JSON file alone (--page-only).
    modes = _load()
    monkeypatch.setattr(
        modes, "CASES", {"tiny": ("cube", ("mesh.cells=[3, 3, 3]", "time.duration=0.3"), "cube, 3 cells")}
    )
    out, docs = str(tmp_path / "out"), str(tmp_path)
    modes.main(["--cases", "tiny", "--rounds", "1", "--output", out, "--docs", docs])
    data = json.loads((tmp_path / "out" / "modes.json").read_text(encoding="utf-8"))
    header, row = data
    assert header["rounds"] == 1 and header["elapsed_s"] > 0 and header["machine"]
    assert row["case"] == "tiny" and row["tets"] == 6 * 27 and row["steps"] == 30
    assert set(row["modes"]) == {"exact", "fast"}
    for mode in row["modes"].values():  # every stage of the step timed
        assert set(mode["stages_ms"]) >= {"free_motion", "detection", "compliance", "solve", "events"}
    assert row["ratio"] == row["modes"]["fast"]["cpu_ms"] / row["modes"]["exact"]["cpu_ms"]
    assert row["same_events"] and 0.0 <= row["force_error"] < 0.02 * row["peak_force"]
    page = (tmp_path / "fast_scaling.md").read_text(encoding="utf-8")
    assert "| cube, 3 cells | 162 |" in page
    assert (tmp_path / "figures" / "fast_scaling.png").stat().st_size > 0
    (tmp_path / "fast_scaling.md").unlink()
    modes.main(["--page-only", "--output", out, "--docs", docs])
    assert (tmp_path / "fast_scaling.md").read_text(encoding="utf-8") == page
