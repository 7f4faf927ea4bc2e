"""Shared fixtures: scenes built from the paper's cube with overrides, and the shared data folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from refsim.scene import load_scene


def shared_data() -> Path:
    """The shared external data folder (`../shared/data`, or $REFSIM_SHARED_DATA)."""
    env = os.environ.get("REFSIM_SHARED_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def cube_scene(*overrides: str, name: str = "cube"):
    """A built-in scene with `section.key=value` overrides."""
    return load_scene(name, list(overrides))


@pytest.fixture(name="cube_scene")
def cube_scene_fixture():
    """The function `cube_scene(*overrides, name="cube")`."""
    return cube_scene


@pytest.fixture(scope="session")
def shared_data_dir() -> Path:
    path = shared_data()
    if not path.is_dir():
        pytest.skip(f"shared data folder {path} is absent")
    return path
