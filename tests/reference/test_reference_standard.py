"""The reference set at the standard level (slow: minutes on one machine): every case builds, the package is
intact, and every quantity has a stated answer with its uncertainty."""

from __future__ import annotations

import math

import numpy as np
import pytest

from refsim.reference import build_reference, case_names, check_manifest, read_case_reference


@pytest.mark.slow
def test_standard_level_builds_every_case(tmp_path):
    folder = tmp_path / "reference"
    manifest = build_reference(folder, level="standard", workers=1, command="slow test")
    assert set(manifest["cases"]) == set(case_names())
    assert check_manifest(folder) == []
    for name in manifest["cases"]:
        for quantity, entry in read_case_reference(folder, name)["quantities"].items():
            assert "missing" not in entry["method"], (name, quantity)
            assert np.all(np.isfinite(entry["value"])) and np.all(np.isfinite(entry["uncertainty"]))
    # The needle alone converges at second order (Timoshenko elements, smooth solution): its answers are
    # Richardson values with a GCI below 1e-3 of the value at 8, 16, 32 elements.
    for quantity, row in manifest["cases"]["cantilever"]["quantities"].items():
        assert row["methods"] == ["richardson"], quantity
        assert row["largest_relative_uncertainty"] < 1e-3 and math.isfinite(
            row["largest_relative_uncertainty"]
        )


@pytest.mark.slow
def test_paper_coupling_as_another_implementation(tmp_path):
    """The paper's bare line coupling (insertion.coupling = "paper") run as another implementation of the
    insertion case. Its redundant rows leave null-space multipliers whose self-equilibrated lateral forces
    inflate the shaft's Coulomb bound (docs/architecture.md, known limits), so its axial force is not the
    well-posed coupling's: compare must fail it at every sampling point of the curve."""
    from refsim.reference import compare, load_case
    from refsim.scene import load_scene
    from refsim.sweep.worker import run_scene

    folder = tmp_path / "reference"
    build_reference(folder, level="coarse", cases=["insertion"], workers=1, command="slow test")
    case = load_case("insertion")
    levels = case.level("coarse")
    overrides = [f"{k}={[v[-1]] * 3 if k == 'mesh.cells' else v[-1]}" for k, v in levels.items()]
    paper = tmp_path / "paper.h5"
    run_scene(load_scene(case.scene_path, [*overrides, 'insertion.coupling="paper"']), paper)
    item = next(c for c in compare("insertion", paper, folder) if c.quantity == "axial_force_depth")
    assert not np.any(item.passed)
