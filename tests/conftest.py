"""Shared fixtures: scenes built from the paper's cube with overrides, and the shared data folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

from refsim.scene import load_scene

# Hypothesis profiles. "ci" (the default) is derandomised: the same examples on every run, so a property test
# cannot fail at random on a fresh clone; a defect it finds is found every time. "slow" draws fresh random
# examples, many more of them: HYPOTHESIS_PROFILE=slow python -m pytest tests/geometry tests/fuzz
# Tests give no max_examples of their own (or scale the profile's, see tests/fuzz), so the profile decides.
settings.register_profile(
    "ci",
    max_examples=40,
    derandomize=True,
    database=None,
    deadline=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile(
    "slow",
    max_examples=2000,
    derandomize=False,
    database=None,
    deadline=None,
    print_blob=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

# A `refsim run` in a test starts no process compiling kernels beside it (refsim.kernel_warmup): the suite's
# workers already use the cores.
os.environ.setdefault("REFSIM_BACKGROUND_COMPILE", "0")


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
