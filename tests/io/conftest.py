"""A results file shared by the sidecar and export tests."""

from __future__ import annotations

import pytest

from refsim.cli import main


@pytest.fixture(scope="session")
def cut_run(tmp_path_factory):
    """cube_cut on 4 cells per axis, tissue recorded every 25 steps, written by `refsim run` (which writes the
    XDMF sidecar at the end)."""
    path = tmp_path_factory.mktemp("xdmf") / "cut.h5"
    code = main(
        [
            "run",
            "cube_cut",
            "-o",
            str(path),
            "-q",
            "--set",
            "mesh.cells=[4, 4, 4]",
            "--set",
            "output.tissue_every=25",
        ]
    )
    assert code == 0
    return path


@pytest.fixture(scope="session")
def two_needle_run(tmp_path_factory):
    """two_needles on 3 cells per axis for 1.2 s (both needles puncture), tissue recorded every 25 steps,
    written by `refsim run` with its XDMF sidecar."""
    path = tmp_path_factory.mktemp("xdmf_two") / "two.h5"
    code = main(
        [
            "run",
            "two_needles",
            "-o",
            str(path),
            "-q",
            "--set",
            "mesh.cells=[3, 3, 3]",
            "--set",
            "time.duration=1.2",
            "--set",
            "output.tissue_every=25",
        ]
    )
    assert code == 0
    return path
