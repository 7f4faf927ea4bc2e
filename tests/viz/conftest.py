"""Shared results files for the figure tests: a short cube insertion, and the same with a lateral motion."""

from __future__ import annotations

import pytest

from refsim.io import ResultWriter
from refsim.simulation import Simulation


def _run(path, overrides):
    from refsim.scene import load_scene

    scene = load_scene("cube", overrides)
    simulation = Simulation(scene)
    with ResultWriter(path, scene, simulation.models) as writer:
        simulation.run(on_step=lambda state, record: writer.append(record))
    return path


@pytest.fixture(scope="session")
def insertion_file(tmp_path_factory):
    """The cube (4³ cells) with the needle inserted 3 mm: 50 steps, tissue recorded every 10 (of 0.5 s)."""
    return _run(
        tmp_path_factory.mktemp("viz") / "insertion.h5", ["mesh.cells=[4, 4, 4]", "time.duration=0.5"]
    )


@pytest.fixture(scope="session")
def lateral_file(tmp_path_factory):
    """The cube (4³ cells): 8 mm insertion, then the base moves 3 mm along +x: 40 steps."""
    return _run(
        tmp_path_factory.mktemp("viz") / "lateral.h5",
        [
            "mesh.cells=[4, 4, 4]",
            "time.duration=0.4",
            "time.dt=0.01",
            "trajectory.times=[0.0, 0.25, 0.4]",
            "trajectory.base_positions=[[0.00123, 0.00231, 0.422], [0.00123, 0.00231, 0.412], "
            "[0.00423, 0.00231, 0.412]]",
            "trajectory.directions=[[0, 0, -1], [0, 0, -1], [0, 0, -1]]",
        ],
    )


@pytest.fixture(scope="session")
def organ_file(tmp_path_factory):
    """studies/liver_phantom/demo.toml (a 1 mm needle into the coarse liver phantom), 1 s: 5 mm deep."""
    from pathlib import Path

    from refsim.scene import load_scene

    scene_path = Path(__file__).resolve().parents[2] / "studies" / "liver_phantom" / "demo.toml"
    scene = load_scene(str(scene_path), ["time.duration=1.0"])
    simulation = Simulation(scene)
    path = tmp_path_factory.mktemp("viz") / "organ.h5"
    with ResultWriter(path, scene, simulation.models) as writer:
        simulation.run(on_step=lambda state, record: writer.append(record))
    return path
