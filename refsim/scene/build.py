"""The models a scene declares, built once: tissue mesh and model, needle, trajectory.

Only what the scene uses is built: a rigid needle has no beam model (it is moved kinematically by its base).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from refsim.fem.tissue import TissueModel
from refsim.materials import HookeMaterial
from refsim.mesh import TetMesh, box_mesh, read_mesh
from refsim.scene.controls import Controls
from refsim.scene.loader import SceneError
from refsim.scene.spec import FACE_NAMES, MeshSpec, Scene
from refsim.scene.trajectory import Trajectory, aimed, read_numeric_csv

__all__ = [
    "SceneModels",
    "boundary_nodes",
    "build_controls",
    "build_models",
    "build_mesh",
    "check_models",
    "fixed_nodes",
    "fixed_set_holds",
    "read_displacement_csv",
]

logger = logging.getLogger("refsim.scene")
#: The load report (fixed set, aimed insertion), at INFO level; `refsim run` shows it.
load_logger = logging.getLogger("refsim.scene.load")


@dataclass(frozen=True)
class SceneModels:
    """Static models of a scene (built once, never mutated).

    Attributes
    ----------
    mesh : Tissue mesh (rest positions [m], tets).
    tissue : Co-rotational tetrahedral model.
    needle : Beam model of a flexible needle, or None for a rigid needle.
    trajectory : Motion of the needle base.
    boundary_nodes : Tissue nodes a boundary motion moves (a subset of the tissue's fixed nodes), shape (b,);
        empty without a [boundary] motion.
    """

    mesh: TetMesh
    tissue: TissueModel
    needle: object | None
    trajectory: Trajectory
    boundary_nodes: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=np.int64))


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
    if spec.fixed_nodes is not None:
        indices = np.asarray(spec.fixed_nodes, dtype=np.int64)
        if indices.size and indices.max() >= len(rest_positions):
            raise ValueError(
                f"mesh.fixed_nodes contains {int(indices.max())}: the mesh has {len(rest_positions)} nodes "
                f"(indices 0 .. {len(rest_positions) - 1})"
            )
        selected[indices] = True
    if not spec.fixed_faces and spec.fixed_box is None and spec.fixed_nodes is None:
        return np.zeros(0, dtype=np.int64)  # the boundary motion holds the tissue
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
            f"mesh.fixed_faces = {list(spec.fixed_faces)!r}, mesh.fixed_box = {spec.fixed_box!r}, "
            f"mesh.fixed_nodes = {spec.fixed_nodes!r} select no node "
            f"(mesh bounding box {lower.tolist()} .. {upper.tolist()} m)"
        )
    if nodes.size == len(rest_positions):
        raise ValueError(
            f"mesh.fixed_faces = {list(spec.fixed_faces)!r}, mesh.fixed_box = {spec.fixed_box!r}, "
            f"mesh.face_tolerance = {spec.face_tolerance!r} m fix every node of the mesh: nothing could move "
            f"(mesh bounding box {lower.tolist()} .. {upper.tolist()} m)"
        )
    return nodes


def build_models(scene: Scene) -> SceneModels:
    """Build the mesh, the tissue model, the needle model (flexible needles only) and the trajectory."""
    try:
        mesh = build_mesh(scene.mesh, scene.base_directory)
    except ValueError as error:  # MeshError names the file and the defect
        raise SceneError(f"{scene.source}: mesh: {error}") from None
    moving = boundary_nodes(scene, mesh)
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
        fixed_nodes=np.union1d(_fixed_nodes_or_error(scene, mesh), moving),
        gravity=tissue_spec.gravity,
    )
    report_fixed_set(scene, mesh, tissue.fixed_nodes)
    if scene.trajectory.entry is not None:
        try:
            aim = aimed(scene.trajectory, mesh.rest_positions, mesh.boundary_faces, scene.needle.length)
        except ValueError as error:
            raise SceneError(f"{scene.source}: {error}") from None
        load_logger.info("%s: %s", scene.source, aim.describe())
        trajectory = aim.trajectory
    else:
        try:
            trajectory = Trajectory.from_spec(scene.trajectory, scene.base_directory)
        except ValueError as error:
            raise SceneError(f"{scene.source}: trajectory.file: {error}") from None
    check_models(scene, mesh, trajectory)
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
    return SceneModels(mesh=mesh, tissue=tissue, needle=needle, trajectory=trajectory, boundary_nodes=moving)


def boundary_nodes(scene: Scene, mesh: TetMesh) -> np.ndarray:
    """The nodes a [boundary] motion moves, sorted, shape (b,) (empty without a motion).

    Raises
    ------
    SceneError
        When the selection is empty or an index is out of range, naming the key.
    """
    spec = scene.boundary
    if spec.motion == "none":
        return np.zeros(0, dtype=np.int64)
    rest = mesh.rest_positions
    where = f"{scene.source}: boundary"
    if spec.nodes is not None:
        nodes = np.unique(np.asarray(spec.nodes, dtype=np.int64))
        if nodes.size and nodes.max() >= len(rest):
            raise SceneError(f"{where}.nodes contains {int(nodes.max())}: the mesh has {len(rest)} nodes")
        key = "nodes"
    elif spec.box is not None:
        box = np.asarray(spec.box, dtype=float)
        nodes = np.flatnonzero(np.all((rest >= box[0]) & (rest <= box[1]), axis=1))
        key = "box"
    else:
        from refsim.mesh.selection import surface_patch

        if spec.patch_point is not None:
            nodes = surface_patch(
                rest, mesh.boundary_faces, distance=spec.patch_distance, point=spec.patch_point
            )
            key = "patch_point"
        else:
            origin, normal = np.asarray(spec.patch_plane, dtype=float)
            nodes = surface_patch(
                rest, mesh.boundary_faces, distance=spec.patch_distance, plane=(origin, normal)
            )
            key = "patch_plane"
    if nodes.size == 0:
        lower, upper = rest.min(axis=0), rest.max(axis=0)
        raise SceneError(
            f"{where}.{key} selects no node (mesh bounding box {lower.round(6).tolist()} .. "
            f"{upper.round(6).tolist()} m)"
        )
    return np.asarray(nodes, dtype=np.int64)


def read_displacement_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A displacement history: columns t, dx, dy, dz [s, m]; '#' comment lines and one header line allowed.

    Returns
    -------
    (times (w,), displacements (w, 3)).

    Raises
    ------
    ValueError
        Naming the file and the defect.
    """
    data = read_numeric_csv(path, ("t", "dx", "dy", "dz"), "boundary motion")
    return data[:, 0], data[:, 1:]


def build_controls(scene: Scene, models: SceneModels) -> Controls:
    """The controls of a scene: the needle base trajectory and, when the scene declares one, the tissue
    boundary motion of ``models.boundary_nodes``."""
    from refsim.scene.controls import PeriodicBoundaryMotion, SampledBoundaryMotion

    spec = scene.boundary
    if spec.motion == "none":
        return Controls(trajectory=models.trajectory)
    if spec.motion == "periodic":
        motion = PeriodicBoundaryMotion(
            nodes=models.boundary_nodes,
            amplitude=spec.amplitude,
            period=spec.period,
            exponent=spec.exponent,
            phase=spec.phase,
        )
    else:
        path = Path(spec.file)
        if not path.is_absolute():
            path = Path(scene.base_directory) / path
        try:
            times, displacements = read_displacement_csv(path)
            motion = SampledBoundaryMotion(
                nodes=models.boundary_nodes, times=times, displacements=displacements
            )
        except ValueError as error:
            raise SceneError(f"{scene.source}: boundary.file: {error}") from None
    return Controls(trajectory=models.trajectory, boundary=motion)


def fixed_set_holds(rest_positions: np.ndarray, tets: np.ndarray, fixed: np.ndarray) -> list[tuple[int, int]]:
    """The connected parts of the mesh the fixed nodes cannot hold: fewer than 3 non-collinear fixed nodes
    (a part held at one node, or along one line, can still turn about it).

    Parameters
    ----------
    rest_positions : Nodes [m], (n, 3). tets : Tetrahedra, (m, 4). fixed : Fixed node indices, (k,).

    Returns
    -------
    (node count of the part, fixed nodes in it) of each part that is not held, largest part first.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = rest_positions.shape[0]
    pairs = tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2)  # tet edges
    graph = coo_matrix((np.ones(pairs.shape[0]), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    count, labels = connected_components(graph, directed=False)
    used = np.zeros(n, dtype=bool)
    used[tets.ravel()] = True
    size = float(np.linalg.norm(rest_positions.max(axis=0) - rest_positions.min(axis=0)))
    loose = []
    for part in np.unique(labels[used]):  # one iteration per connected part (a handful)
        held = fixed[labels[fixed] == part]
        points = rest_positions[held] - rest_positions[held].mean(axis=0) if held.size else np.zeros((0, 3))
        singular = np.linalg.svd(points, compute_uv=False) if held.size >= 3 else np.zeros(1)
        if held.size < 3 or singular[1] <= 1e-9 * size * np.sqrt(held.size):
            loose.append((int(np.count_nonzero(labels == part)), int(held.size)))
    return sorted(loose, reverse=True)


def report_fixed_set(scene: Scene, mesh: TetMesh, fixed: np.ndarray) -> None:
    """Log the fixed set (how many nodes, their bounding box) at load, and warn when it cannot hold a part of
    the tissue (:func:`fixed_set_holds`): such a part has no static equilibrium."""
    if fixed.size == 0:
        return
    box = mesh.rest_positions[fixed]
    load_logger.info(
        "%s: %d fixed tissue nodes of %d, within %s .. %s m",
        scene.source,
        fixed.size,
        mesh.rest_positions.shape[0],
        np.round(box.min(axis=0), 6).tolist(),
        np.round(box.max(axis=0), 6).tolist(),
    )
    for nodes, held in fixed_set_holds(mesh.rest_positions, mesh.tets, fixed):
        logger.warning(
            "%s: the fixed set (mesh.fixed_faces = %s, fixed_box = %s, fixed_nodes = %s) holds a connected "
            "part of %d nodes by %d node(s)%s: it can turn about them; fix at least 3 non-collinear nodes "
            "of each part (e.g. mesh.fixed_box around a face of the organ)",
            scene.source,
            list(scene.mesh.fixed_faces),
            scene.mesh.fixed_box,
            "given" if scene.mesh.fixed_nodes is not None else None,
            nodes,
            held,
            "" if held < 3 else " on one line",
        )


def _fixed_nodes_or_error(scene: Scene, mesh: TetMesh) -> np.ndarray:
    try:
        return fixed_nodes(scene.mesh, mesh.rest_positions)
    except ValueError as error:
        raise SceneError(f"{scene.source}: {error}") from None


def _needle_samples(base: np.ndarray, direction: np.ndarray, length: float, count: int) -> np.ndarray:
    return base + np.linspace(0.0, length, count)[:, None] * direction


def check_models(scene: Scene, mesh: TetMesh, trajectory: Trajectory) -> None:
    """Checks of the scene against its mesh and trajectory, before anything runs.

    Errors (SceneError, naming the keys):
    - the needle (its centreline, sampled every min(d_i, shortest mesh extent / 50)) inside the tissue at t =
      0: the penetration constraint assumes the tip starts outside (a needle inside gave a 282 N "puncture");
    - the needle diameter not smaller than the tissue's smallest extent;
    - the tip never within insertion.contact_distance of the mesh's bounding box during the trajectory (no
      contact could ever happen), checked on the waypoints and the segments between them.
    Warnings (logged, naming the likely cause):
    - the mesh size against the needle length off by more than 30 times: the mesh is probably in other units,
      with the factor that would make them agree (mesh.scale = 0.001 for millimetres);
    - d_i larger than the mean mesh edge: insertion points skip elements.
    """
    bounds = np.stack([mesh.rest_positions.min(axis=0), mesh.rest_positions.max(axis=0)])
    extent = bounds[1] - bounds[0]
    needle = scene.needle
    where = scene.source
    size = float(np.linalg.norm(extent))
    ratio = size / needle.length
    if ratio > 30.0 or ratio < 1.0 / 30.0:
        exponent = int(np.round(np.log10(1.0 / ratio)))
        likely = {
            -3: "millimetres (mesh.scale = 0.001)",
            -2: "centimetres (mesh.scale = 0.01)",
            -1: "decimetres or the needle in other units (mesh.scale = 0.1)",
            3: "kilometres? or the needle in millimetres (mesh.scale = 1000)",
        }
        hint = likely.get(exponent, f"a scale of 1e{exponent} (mesh.scale = {10.0**exponent:g})")
        logger.warning(
            "%s: the tissue mesh is %.3g m across but the needle is %.3g m long (%.0f times): are the mesh "
            "coordinates in %s?",
            where,
            size,
            needle.length,
            ratio if ratio > 1 else 1 / ratio,
            hint,
        )
    smallest = float(extent.min())
    if 2.0 * needle.radius >= smallest:
        raise SceneError(
            f"{where}: needle.radius = {needle.radius!r} m: the needle (diameter {2 * needle.radius:.3g} m) "
            f"is not "
            f"thinner than the tissue (smallest extent of the mesh {smallest:.3g} m, see mesh.size or "
            f"mesh.scale); "
            "the radius enters the contact geometry"
        )
    base, direction = trajectory.pose(0.0)
    step = min(scene.insertion.spacing, smallest / 50.0)
    count = int(min(20_000, max(needle.element_count + 1, np.ceil(needle.length / step) + 1)))
    from refsim.geometry import TetLocator

    samples = _needle_samples(base, direction, needle.length, count)
    inside = TetLocator(mesh.rest_positions, mesh.tets).locate(samples)[0] >= 0
    if np.any(inside):
        depth = float(needle.length * (1.0 - np.argmax(inside) / max(count - 1, 1)))
        raise SceneError(
            f"{where}: trajectory: at t = 0 the needle is inside the tissue ({depth:.3g} m of it from the "
            f"tip, "
            f"tip at {samples[-1].round(6).tolist()} m; the tissue spans {bounds[0].round(6).tolist()} .. "
            f"{bounds[1].round(6).tolist()} m): start the needle outside (trajectory.base_positions[0]) so "
            f"that "
            "the puncture is simulated; check mesh.scale if the mesh is in other units"
        )
    times = np.asarray(trajectory.times, dtype=float)
    tips = trajectory.base_positions + needle.length * trajectory.directions
    if times.size > 1:  # also the points between waypoints, at 20 per segment
        fractions = np.linspace(0.0, 1.0, 21)
        between = np.concatenate(
            [
                [
                    trajectory.pose(t)[0] + needle.length * trajectory.pose(t)[1]
                    for t in times[i] + fractions * (times[i + 1] - times[i])
                ]
                for i in range(times.size - 1)
            ]
        )
        tips = np.vstack([tips, between])
    reach = scene.insertion.contact_distance + needle.radius
    gaps = np.maximum(np.maximum(bounds[0] - tips, tips - bounds[1]), 0.0)
    if np.all(np.linalg.norm(gaps, axis=1) > reach):
        logger.warning(
            "%s: the needle tip never comes within insertion.contact_distance of the tissue (closest %.3g m "
            "from "
            "its bounding box): the run will record no contact",
            where,
            float(np.linalg.norm(gaps, axis=1).min()),
        )
    edges = (
        mesh.rest_positions[mesh.tets[:, [1, 2, 3, 2, 3, 3]]]
        - mesh.rest_positions[mesh.tets[:, [0, 0, 0, 1, 1, 2]]]
    )
    mean_edge = float(np.linalg.norm(edges, axis=2).mean())
    if scene.insertion.spacing > mean_edge:
        logger.warning(
            "%s: insertion.spacing = %g m (d_i) is longer than the mean mesh edge %.3g m: insertion points "
            "skip "
            "elements and the coupling force depends on where they fall",
            where,
            scene.insertion.spacing,
            mean_edge,
        )
    if scene.trajectory.file is not None:  # the speed check of the scene needs the file's samples
        speeds = np.linalg.norm(
            np.diff(trajectory.base_positions, axis=0), axis=1
        ) + needle.length * np.arccos(
            np.clip(np.einsum("ij,ij->i", trajectory.directions[:-1], trajectory.directions[1:]), -1.0, 1.0)
        )
        if speeds.size:
            speed = float((speeds / np.diff(times)).max())
            if speed * scene.time.dt > scene.insertion.contact_distance:
                raise SceneError(
                    f"{where}: time.dt = {scene.time.dt!r} s: the needle tip moves up to "
                    f"{speed * scene.time.dt:.3g} m "
                    f"per step along trajectory.file, more than insertion.contact_distance = "
                    f"{scene.insertion.contact_distance!r} m; use dt <= "
                    f"{scene.insertion.contact_distance / speed:.3g} s"
                )
