"""Scene description (layer 4): frozen, validated dataclasses loaded from TOML, and the models built from
them."""

from refsim.scene.controls import (
    BoundaryMotion,
    Controls,
    ControlValues,
    PeriodicBoundaryMotion,
    SampledBoundaryMotion,
)
from refsim.scene.loader import (
    InstrumentsOverlap,
    SceneError,
    builtin_scenes,
    load_scene,
    parse_override,
    scene_from_dict,
    scene_to_json,
)
from refsim.scene.spec import (
    CuttingSpec,
    InsertionSpec,
    MeshSpec,
    NeedleSpec,
    OutputSpec,
    Scene,
    SolverSpec,
    TimeSpec,
    TissueSpec,
    TrajectorySpec,
)

__all__ = [
    "BoundaryMotion",
    "ControlValues",
    "Controls",
    "PeriodicBoundaryMotion",
    "SampledBoundaryMotion",
    "CuttingSpec",
    "InsertionSpec",
    "MeshSpec",
    "NeedleSpec",
    "OutputSpec",
    "Scene",
    "SceneError",
    "InstrumentsOverlap",
    "SolverSpec",
    "TimeSpec",
    "TissueSpec",
    "TrajectorySpec",
    "builtin_scenes",
    "load_scene",
    "parse_override",
    "scene_from_dict",
    "scene_to_json",
]
