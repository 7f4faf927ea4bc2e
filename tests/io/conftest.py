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
