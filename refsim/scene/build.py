"""The models a scene declares, built once: tissue mesh and model, needle, trajectory.

Only what the scene uses is built: a rigid needle has no beam model (it is moved kinematically by its base).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from refsim.fem.tissue import TissueModel
from refsim.materials import HookeMaterial
from refsim.mesh import TetMesh, box_mesh, read_mesh
from refsim.scene.controls import Controls
from refsim.scene.spec import FACE_NAMES, MeshSpec, Scene
from refsim.scene.trajectory import Trajectory

__all__ = ["SceneModels", "build_controls", "build_models", "build_mesh", "fixed_nodes"]


@dataclass(frozen=True)
class SceneModels:
    """Static models of a scene (built once, never mutated).

    Attributes
    ----------
    mesh : Tissue mesh (rest positions [m], tets).
    tissue : Co-rotational tetrahedral model.
    needle : Beam model of a flexible needle, or None for a rigid needle.
    trajectory : Motion of the needle base.
    """

    mesh: TetMesh
    tissue: TissueModel
    needle: object | None
    trajectory: Trajectory


def build_mesh(spec: MeshSpec, base_directory: str = ".") -> TetMesh:
    """The tissue mesh of a [mesh] section (a file path is relative to the scene file)."""
    if spec.generator == "box":
        return box_mesh(size=spec.size, cells=spec.cells, origin=spec.origin)
    path = Path(spec.file)
    if not path.is_absolute():
        path = Path(base_directory) / path
    mesh = read_mesh(path)
    if spec.scale != 1.0:
        mesh = mesh.scaled(spec.scale)
    return mesh


def fixed_nodes(spec: MeshSpec, rest_positions: np.ndarray) -> np.ndarray:
    """Nodes on the named bounding-box faces or inside the fixed box, sorted, shape (k,).

    Raises
    ------
    ValueError
        When the selection is empty (naming the keys).
    """
    lower, upper = rest_positions.min(axis=0), rest_positions.max(axis=0)
    selected = np.zeros(len(rest_positions), dtype=bool)
    for face in spec.fixed_faces:
        axis = FACE_NAMES.index(face) // 2
        bound = lower[axis] if face.endswith("min") else upper[axis]
        selected |= np.abs(rest_positions[:, axis] - bound) <= spec.face_tolerance
    if spec.fixed_box is not None:
        box = np.asarray(spec.fixed_box, dtype=float)
        selected |= np.all((rest_positions >= box[0]) & (rest_positions <= box[1]), axis=1)
    nodes = np.flatnonzero(selected)
    if nodes.size == 0:
        raise ValueError(
            f"mesh.fixed_faces = {list(spec.fixed_faces)!r}, mesh.fixed_box = {spec.fixed_box!r} select no node "
            f"(mesh bounding box {lower.tolist()} .. {upper.tolist()} m)"
        )
    return nodes


def build_models(scene: Scene) -> SceneModels:
    """Build the mesh, the tissue model, the needle model (flexible needles only) and the trajectory."""
    mesh = build_mesh(scene.mesh, scene.base_directory)
    tissue_spec = scene.tissue
    tissue = TissueModel(
        mesh.rest_positions,
        mesh.tets,
        HookeMaterial(
            youngs_modulus=tissue_spec.youngs_modulus,
            poisson_ratio=tissue_spec.poisson_ratio,
            density=tissue_spec.density,
        ),
        rayleigh_mass=tissue_spec.rayleigh_mass,
        rayleigh_stiffness=tissue_spec.rayleigh_stiffness,
        fixed_nodes=fixed_nodes(scene.mesh, mesh.rest_positions),
        gravity=tissue_spec.gravity,
    )
    trajectory = Trajectory.from_spec(scene.trajectory, scene.base_directory)
    needle = None
    if not scene.needle.rigid:
        from refsim.fem.needle import NeedleModel  # only flexible needles need the beam model

        base, direction = trajectory.pose(0.0)
        spec = scene.needle
        needle = NeedleModel(
            length=spec.length,
            radius=spec.radius,
            element_count=spec.element_count,
            youngs_modulus=spec.youngs_modulus,
            poisson_ratio=spec.poisson_ratio,
            density=spec.density,
            base_position=base,
            direction=direction,
        )
    return SceneModels(mesh=mesh, tissue=tissue, needle=needle, trajectory=trajectory)


def build_controls(scene: Scene, models: SceneModels) -> Controls:
    """The controls of a scene: the needle base trajectory (and, when the scene declares one, the tissue
    boundary motion)."""
    return Controls(trajectory=models.trajectory)
