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
from refsim.scene.controls import BOUNDARY_MOTIONS, Controls, read_displacement_csv
from refsim.scene.fields import FieldError
from refsim.scene.loader import InstrumentsOverlap, SceneError
from refsim.scene.spec import (
    FACE_NAMES,
    RESOLVED_DIGITS,
    ConsistencyError,
    MeshSpec,
    Scene,
    check_scene_lengths,
    resolvable_length,
    scene_scale,
)
from refsim.scene.trajectory import Trajectory, aimed

__all__ = [
    "SceneModels",
    "boundary_nodes",
    "InstrumentModels",
    "build_controls",
    "build_models",
    "build_mesh",
    "check_boundary_motion",
    "check_held",
    "check_insertion_spacing",
    "check_mesh_lengths",
    "check_models",
    "check_time_resolution",
    "fixed_nodes",
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
    instruments : Each instrument's models, in the scene's order (``needle`` and ``trajectory`` are the
        first's); empty: one instrument, "needle", of ``scene.needle`` with ``needle`` and ``trajectory``.
    """

    mesh: TetMesh
    tissue: TissueModel
    needle: object | None
    trajectory: Trajectory
    boundary_nodes: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    instruments: tuple = ()


@dataclasses.dataclass(frozen=True)
class InstrumentModels:
    """The static models of one instrument.

    Attributes
    ----------
    name : The instrument's name (its body's).
    needle : Its needle's section and material (the scene's [needle] with the instrument's overrides).
    model : Its beam model when flexible, else None.
    trajectory : The motion of its base.
    cuts : Whether it may cut.
    """

    name: str
    needle: object
    model: object | None
    trajectory: Trajectory
    cuts: bool


#: Peak memory of a run per tetrahedron [bytes]: the marginal peak RSS of the cube scene (5 steps) between
#: 4³ and 20³ cells was 9,184 to 12,822 bytes per tetrahedron (docs/faults.md, "Memory"); the largest,
#: rounded up. The factorisation's fill grows faster than the tet count, so for larger meshes it
#: underestimates: a mesh it refuses certainly does not fit.
BYTES_PER_TET = 13_000


def available_memory() -> int | None:
    """Memory the system can give this process now [bytes] (MemAvailable of /proc/meminfo), or None."""
    try:
        with open("/proc/meminfo", encoding="ascii") as stream:
            for line in stream:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError):
        return None
    return None


def check_memory(tets: int, key: str, value) -> None:
    """Refuse a mesh whose run would need more memory than the machine has available now.

    Parameters
    ----------
    tets : Number of tetrahedra.
    key, value : The scene key that sets the mesh size and its value, for the message.

    Raises
    ------
    SceneError
        Naming the key, the value, the estimate (tets × BYTES_PER_TET) and the memory available.
    """
    free = available_memory()
    needed = tets * BYTES_PER_TET
    if free is None or needed <= free:
        return
    raise SceneError(
        f"{key} = {value!r}: {tets} tetrahedra need about {needed / 2**30:.3g} GiB ({BYTES_PER_TET} bytes "
        f"per tetrahedron, measured) and this machine has {free / 2**30:.3g} GiB available; at most about "
        f"{free // BYTES_PER_TET} tetrahedra fit"
    )


def build_mesh(spec: MeshSpec, base_directory: str = ".") -> TetMesh:
    """The tissue mesh of a [mesh] section (a file path is relative to the scene file).

    Raises
    ------
    SceneError
        When the run of the mesh would need more memory than available (:func:`check_memory`), for a box
        before it is generated.
    """
    if spec.generator == "box":
        check_memory(6 * int(np.prod(spec.cells)), "mesh.cells", list(spec.cells))
        return box_mesh(size=spec.size, cells=spec.cells, origin=spec.origin)
    path = Path(spec.file)
    if not path.is_absolute():
        path = Path(base_directory) / path
    mesh = read_mesh(path)
    check_memory(mesh.tet_count, "mesh.file", str(path))
    if spec.scale != 1.0:
        mesh = mesh.scaled(spec.scale)
    return mesh


def fixed_nodes(spec: MeshSpec, rest_positions: np.ndarray, mesh: TetMesh | None = None) -> np.ndarray:
    """Nodes on the named bounding-box faces, inside the fixed box or listed by index, sorted, shape (k,).

    Parameters
    ----------
    spec : The [mesh] section.
    rest_positions : Node positions [m], shape (n, 3).
    mesh : The mesh as read: ``mesh.fixed_nodes`` are in the file's numbering and go through
        ``mesh.file_nodes`` (the reader may have merged or dropped nodes); without it they are taken as
        indices of ``rest_positions``.

    Raises
    ------
    ValueError
        When the selection is empty or every node, or an index is out of range or names a dropped node
        (naming the keys).
    """
    lower, upper = rest_positions.min(axis=0), rest_positions.max(axis=0)
    selected = np.zeros(len(rest_positions), dtype=bool)
    if spec.fixed_nodes is not None:
        indices = _node_indices(spec.fixed_nodes, "mesh.fixed_nodes")
        if mesh is not None:
            indices = mesh.file_nodes(indices, key="mesh.fixed_nodes")
        elif indices.size and (indices.min() < 0 or indices.max() >= len(rest_positions)):
            bad = indices[(indices < 0) | (indices >= len(rest_positions))]
            raise ValueError(
                f"mesh.fixed_nodes contains {int(bad[0])}: the mesh has {len(rest_positions)} nodes "
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


def _node_indices(values, key: str) -> np.ndarray:
    """Node indices from a scene key, checked: integers (not booleans, not 2.5), shape (k,)."""
    values = tuple(values)
    bad = [v for v in values if isinstance(v, bool) or not isinstance(v, (int, np.integer))]
    if bad:
        raise ValueError(f"{key} contains {bad[0]!r}: expected node indices, integers >= 0")
    return np.asarray(values, dtype=np.int64).reshape(-1)


def check_held(scene: Scene, mesh: TetMesh, held: np.ndarray) -> None:
    """Every connected part of the mesh must be held in place: at least three of its nodes, not on one line,
    fixed or moved by the boundary motion. A part held by fewer (or by collinear nodes) keeps a rigid-body
    motion (a translation, or a rotation about the held point or line): it drifts away, falls under gravity or
    spins when the needle pushes it, and has no static equilibrium.

    Raises
    ------
    SceneError
        Naming the part (its node and tet counts, its centre) and the keys that choose the held nodes.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    count = mesh.node_count
    tets = mesh.tets
    rows = np.repeat(tets[:, 0], 3)
    cols = tets[:, 1:].reshape(-1)
    graph = coo_matrix((np.ones(rows.size, dtype=np.int8), (rows, cols)), shape=(count, count))
    parts, labels = connected_components(graph, directed=False)
    rest = mesh.rest_positions
    extent = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    held = np.unique(np.asarray(held, dtype=np.int64))
    part_of = labels[held]
    anchors = np.bincount(part_of, minlength=parts)
    # Spread of each part's held nodes: the eigenvalues of their covariance (sums per part, no loop): the
    # second largest is zero when they lie on one line.
    points = rest[held]
    mean = np.stack([np.bincount(part_of, points[:, i], parts) for i in range(3)], axis=1)
    mean /= np.maximum(anchors, 1)[:, None]
    centred = points - mean[part_of]
    outer = np.einsum("ki,kj->kij", centred, centred).reshape(-1, 9)
    covariance = np.stack([np.bincount(part_of, outer[:, i], parts) for i in range(9)], axis=1)
    spread = np.linalg.eigvalsh(covariance.reshape(parts, 3, 3) / np.maximum(anchors, 1)[:, None, None])
    flat = np.sqrt(np.maximum(spread[:, 1], 0.0)) <= 1e-9 * extent
    loose = np.flatnonzero((anchors < 3) | flat)
    if loose.size == 0:
        return
    part = int(loose[0])
    members = labels == part
    nodes = int(np.count_nonzero(members))
    elements = int(np.count_nonzero(members[tets[:, 0]]))
    centre = rest[members].mean(axis=0).round(6).tolist()
    which = f"part {part + 1} of {parts}" if parts > 1 else "the tissue"
    how = (
        "no held node"
        if anchors[part] == 0
        else f"only {anchors[part]} held node(s)" + (" on one line" if anchors[part] >= 3 else "")
    )
    raise SceneError(
        f"{scene.source}: mesh: {which} ({nodes} nodes, {elements} tetrahedra, centred at {centre} m) "
        f"has {how}: it keeps a rigid-body motion (it would drift, fall under gravity or spin about the "
        "held nodes). Hold at least three non-collinear nodes of every part (mesh.fixed_faces, "
        "mesh.fixed_box, mesh.fixed_nodes, or a boundary motion), or remove the loose part from the mesh"
        + (f"; {loose.size} parts are loose" if loose.size > 1 else "")
    )


def build_models(scene: Scene) -> SceneModels:
    """Build the mesh, the tissue model, the needle model (flexible needles only) and the trajectory."""
    try:
        mesh = build_mesh(scene.mesh, scene.base_directory)
    except ValueError as error:  # MeshError names the file and the defect
        raise SceneError(f"{scene.source}: mesh: {error}") from None
    check_mesh_lengths(scene, mesh)
    moving = boundary_nodes(scene, mesh)
    held = np.union1d(_fixed_nodes_or_error(scene, mesh), moving)
    check_held(scene, mesh, held)
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
        fixed_nodes=held,
        gravity=tissue_spec.gravity,
    )
    report_fixed_set(scene, mesh, tissue.fixed_nodes)
    instruments = tuple(
        _instrument_models(scene, mesh, index, spec) for index, spec in enumerate(scene.instrument_specs)
    )
    check_instruments_apart(scene, instruments)
    first = instruments[0]
    needle, trajectory = first.model, first.trajectory
    return SceneModels(
        mesh=mesh,
        tissue=tissue,
        needle=needle,
        trajectory=trajectory,
        boundary_nodes=moving,
        instruments=instruments,
    )


#: Most times at which :func:`check_instruments_apart` compares two commanded shafts: every step's end up to
#: this count, else this many evenly spaced times; each trajectory's waypoint times are added in every case.
APART_SAMPLES = 20_000


def check_instruments_apart(scene: Scene, instruments) -> None:
    """No two instruments' commanded shafts (the straight segment from the base along the direction, the
    needle's length; the radius around it) come closer than the sum of their radii at any step's end or
    waypoint: refsim models no contact between instruments, so such a scene would have two needles pass
    through each other without a word.

    Raises
    ------
    InstrumentsOverlap
        A :class:`SceneError` naming both instruments, the time, the distance of their axes and the sum of
        their radii.
    """
    if len(instruments) < 2:
        return
    steps = scene.time.step_count
    if steps <= APART_SAMPLES:
        times = scene.time.dt * np.arange(steps + 1)
    else:
        times = np.linspace(0.0, scene.time.duration, APART_SAMPLES + 1)
    knots = np.concatenate([instrument.trajectory.times for instrument in instruments])
    times = np.unique(np.concatenate([times, knots[knots <= scene.time.duration]]))
    shafts = []
    for instrument in instruments:
        base, direction = instrument.trajectory.poses(times)
        shafts.append((base, instrument.needle.length * direction, instrument.needle.radius))
    for i in range(len(instruments)):
        for j in range(i + 1, len(instruments)):
            (p, u, r_i), (q, v, r_j) = shafts[i], shafts[j]
            distance = segment_distances(p, u, q, v)
            closest = int(np.argmin(distance))
            if distance[closest] < r_i + r_j:
                raise InstrumentsOverlap(
                    f"{scene.source}: instruments {instruments[i].name!r} and {instruments[j].name!r} "
                    f"overlap at t = {times[closest]:.6g} s: the axes of their shafts are "
                    f"{distance[closest]:.3g} m apart, less than the sum of their radii {r_i + r_j:.3g} m "
                    "(refsim models no contact between instruments: move their trajectories apart)"
                )


def segment_distances(p: np.ndarray, u: np.ndarray, q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Distances between the segments p + s u and q + t v (s, t in [0, 1]), row by row, shapes (m, 3) → (m,).

    The closest pair minimises |p + s u − q − t v|² over the unit square: the interior stationary point when
    the segments are not parallel and it lies inside, else the least of the four edges (one parameter held at
    0 or 1, the other clamped), which is where a convex quadratic's minimum over a square lies otherwise."""
    w = p - q
    a, b, c = np.vecdot(u, u), np.vecdot(u, v), np.vecdot(v, v)
    d, e = np.vecdot(u, w), np.vecdot(v, w)
    det = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(det > 1e-12 * a * c, (b * e - c * d) / det, -1.0)
        t = np.where(det > 1e-12 * a * c, (a * e - b * d) / det, -1.0)
    inside = (s >= 0.0) & (s <= 1.0) & (t >= 0.0) & (t <= 1.0)
    best = np.where(inside, np.linalg.norm(w + s[:, None] * u - t[:, None] * v, axis=1), np.inf)
    for fixed_s in (0.0, 1.0):  # s held, t clamped
        t_edge = np.clip((e + fixed_s * b) / c, 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(w + fixed_s * u - t_edge[:, None] * v, axis=1))
    for fixed_t in (0.0, 1.0):  # t held, s clamped
        s_edge = np.clip((fixed_t * b - d) / a, 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(w + s_edge[:, None] * u - fixed_t * v, axis=1))
    return best


def _instrument_models(scene: Scene, mesh: TetMesh, index: int, spec) -> InstrumentModels:
    """One instrument's trajectory (aimed on the mesh, read from its file or its waypoints, checked against
    the mesh) and, for a flexible needle, its beam model posed at the trajectory's first pose."""
    where = f"instruments[{index}].trajectory" if scene.instruments else "trajectory"
    if spec.trajectory.entry is not None:
        try:
            aim = aimed(spec.trajectory, mesh.rest_positions, mesh.boundary_faces, spec.needle.length)
        except ValueError as error:
            raise SceneError(f"{scene.source}: {error}") from None
        load_logger.info("%s: %s", scene.source, aim.describe())
        trajectory = aim.trajectory
    else:
        try:
            trajectory = Trajectory.from_spec(spec.trajectory, scene.base_directory)
        except ValueError as error:
            raise SceneError(f"{scene.source}: {where}.file: {error}") from None
    check_models(scene, mesh, trajectory)
    check_time_resolution(scene, mesh, trajectory)
    check_insertion_spacing(scene, mesh, trajectory)
    model = None
    if not spec.needle.rigid:
        from refsim.fem.needle import NeedleModel  # only flexible needles need the beam model

        base, direction = trajectory.pose(0.0)
        needle = spec.needle
        model = NeedleModel(
            length=needle.length,
            radius=needle.radius,
            element_count=needle.element_count,
            youngs_modulus=needle.youngs_modulus,
            poisson_ratio=needle.poisson_ratio,
            density=needle.density,
            base_position=base,
            direction=direction,
        )
    return InstrumentModels(spec.name, spec.needle, model, trajectory, bool(spec.cuts))


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
        try:
            nodes = np.unique(mesh.file_nodes(_node_indices(spec.nodes, "nodes"), key="nodes"))
        except ValueError as error:
            raise SceneError(f"{where}.{error}") from None
        key = "nodes"
    elif spec.box is not None:
        box = np.asarray(spec.box, dtype=float)
        nodes = np.flatnonzero(np.all((rest >= box[0]) & (rest <= box[1]), axis=1))
        key = "box"
    elif spec.facing is not None:
        from refsim.mesh.selection import facing_surface

        nodes = facing_surface(rest, mesh.boundary_faces, direction=spec.facing, angle=spec.facing_angle)
        key = "facing"
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


def build_controls(scene: Scene, models: SceneModels) -> Controls:
    """The controls of a scene: the needle base trajectory and, when the scene declares one, the tissue
    boundary motion of ``models.boundary_nodes``."""
    spec = scene.boundary
    trajectories = tuple(instrument.trajectory for instrument in models.instruments)
    trajectories = trajectories if len(trajectories) > 1 else ()
    if spec.motion == "none":
        return Controls(trajectory=models.trajectory, trajectories=trajectories)
    try:
        motion = BOUNDARY_MOTIONS[spec.motion].from_section(spec, models.boundary_nodes, scene.base_directory)
    except FieldError as error:
        raise SceneError(f"{scene.source}: boundary.{error.key}: {error}") from None
    check_boundary_motion(scene, models.mesh, motion)
    return Controls(trajectory=models.trajectory, boundary=motion, trajectories=trajectories)


def check_mesh_lengths(scene: Scene, mesh: TetMesh) -> None:
    """The lengths of the scene against the largest coordinate including the mesh's
    (:func:`refsim.scene.spec.check_scene_lengths`; a mesh file's coordinates are only known here).

    Raises
    ------
    SceneError
        Naming the file, the key, its value and the valid range.
    """
    scale = max(scene_scale(scene), float(np.abs(mesh.rest_positions).max()))
    try:
        check_scene_lengths(scene, scale)
    except ConsistencyError as error:
        raise SceneError(f"{scene.source}: {error.section}.{error}") from None


def check_time_resolution(scene: Scene, mesh: TetMesh, trajectory: Trajectory) -> None:
    """The smallest time step the program can represent: the needle tip's fastest travel in one step (speed ×
    dt) must be at least 10**RESOLVED_DIGITS × float64's epsilon × the largest coordinate of the scene
    (tissue and trajectory), otherwise adding it to a position loses it in round-off and the run makes no
    progress (dt = 1e-300 s ended in a ZeroDivisionError at step 1). A trajectory that never moves is not
    checked (there is no motion to resolve).

    Raises
    ------
    SceneError
        Naming time.dt, the travel, the resolution and the smallest dt that resolves it.
    """
    times = np.asarray(trajectory.times, dtype=float)
    if times.size < 2:
        return
    directions = np.asarray(trajectory.directions, dtype=float)
    turn = np.arccos(np.clip(np.einsum("ij,ij->i", directions[:-1], directions[1:]), -1.0, 1.0))
    speeds = (
        np.linalg.norm(np.diff(trajectory.base_positions, axis=0), axis=1) + scene.needle.length * turn
    ) / np.diff(times)
    speed = float(speeds.max())
    if speed == 0.0:
        return
    largest = max(
        float(np.abs(mesh.rest_positions).max()),
        float(np.abs(trajectory.base_positions).max()) + scene.needle.length,
    )
    resolution = resolvable_length(largest)
    if speed * scene.time.dt < resolution:
        raise SceneError(
            f"{scene.source}: time.dt = {scene.time.dt!r} s: the needle tip moves at most "
            f"{speed * scene.time.dt:.3g} m per step, below what positions of up to {largest:.3g} m resolve "
            f"({resolution:.3g} m: {10**RESOLVED_DIGITS} float64 epsilons of them); the run would make no "
            f"progress: use time.dt >= {resolution / speed:.3g} s"
        )


#: Constraint rows per insertion point: two bilateral rows normal to the needle and one shaft friction row
#: (refsim.constraints.insertion).
ROWS_PER_INSERTION_POINT = 3
#: Constraint rows per cut sample (one every d_c of inserted needle in a cut): a sliding and a front row, and
#: two friction rows when the cut faces have friction (refsim.constraints.cut.strip_cut_block).
ROWS_PER_CUT_SAMPLE = 2
ROWS_PER_CUT_SAMPLE_WITH_FRICTION = 4


def _tip_travel(scene: Scene, trajectory: Trajectory) -> float:
    """An upper bound of the needle tip's path length over the run [m]: base travel plus length × angle
    turned, per trajectory segment, over [0, duration]."""
    times = np.asarray(trajectory.times, dtype=float)
    if times.size < 2:
        return 0.0
    directions = np.asarray(trajectory.directions, dtype=float)
    turn = np.arccos(np.clip(np.einsum("ij,ij->i", directions[:-1], directions[1:]), -1.0, 1.0))
    lengths = np.linalg.norm(np.diff(trajectory.base_positions, axis=0), axis=1) + scene.needle.length * turn
    covered = np.clip((scene.time.duration - times[:-1]) / np.diff(times), 0.0, 1.0)  # the run's share
    return float(np.sum(lengths * covered))


def check_insertion_spacing(scene: Scene, mesh: TetMesh, trajectory: Trajectory) -> None:
    """The smallest spacings d_i (insertion.spacing) and d_c (cutting.point_spacing) the machine can run:
    every d_i of inserted needle adds ROWS_PER_INSERTION_POINT constraint rows, and, in a cut, every d_c adds
    ROWS_PER_CUT_SAMPLE rows (ROWS_PER_CUT_SAMPLE_WITH_FRICTION with cutting.friction_coefficient > 0); the
    compliance W of the rows is a dense matrix of 8-byte numbers, so the rows the run can create (the inserted
    length over each spacing) must leave W within the memory available now. The inserted length is bounded
    by the needle's length, the tissue's size (bounding-box diagonal) and the tip's path over the run.

    Raises
    ------
    SceneError
        Naming the spacing whose rows are the most (insertion.spacing or cutting.point_spacing), the rows and
        the memory W would need, the memory available and the smallest value of that spacing that fits with
        the other's rows.
    """
    free = available_memory()
    if free is None:
        return
    rest = mesh.rest_positions
    inserted = min(
        scene.needle.length,
        float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0))),
        _tip_travel(scene, trajectory),
    )
    cutting = scene.cutting
    per_cut = ROWS_PER_CUT_SAMPLE_WITH_FRICTION if cutting.friction_coefficient > 0.0 else ROWS_PER_CUT_SAMPLE
    spacings = {
        "insertion.spacing": (scene.insertion.spacing, ROWS_PER_INSERTION_POINT, "d_i", "insertion points")
    }
    if cutting.enabled:
        spacings["cutting.point_spacing"] = (cutting.point_spacing, per_cut, "d_c", "cut samples")
    rows = {key: per * (inserted / value + 1.0) for key, (value, per, _, _) in spacings.items()}
    total = sum(rows.values())
    needed = 8.0 * total**2
    if needed <= free:
        return
    key = max(rows, key=rows.get)
    value, per, symbol, what = spacings[key]
    room = np.sqrt(free / 8.0) - (total - rows[key]) - per  # rows left for this spacing's points beyond one
    fits = f"use {key} >= {per * inserted / room:.3g} m" if room > 0.0 else "no value of it fits"
    raise SceneError(
        f"{scene.source}: {key} = {value!r} m ({symbol}): up to {rows[key] / per:.3g} {what} along the "
        f"{inserted:.3g} m the needle can enter (the least of needle.length, the tissue's size and the tip's "
        f"path over the run), {per} constraint rows each, {total:.3g} rows in all, whose dense compliance "
        f"matrix needs {needed / 2**30:.3g} GiB; {free / 2**30:.3g} GiB are available: {fits}"
    )


#: Steps evaluated at once by the boundary motion check (bounds its memory: 3 arrays of this many rows).
_CHECK_CHUNK = 1_000_000


def check_boundary_motion(scene: Scene, mesh: TetMesh, motion) -> None:
    """Check a boundary motion the way the needle's trajectory is checked, on the run's own step times.

    Errors (SceneError naming the keys, the value and the limit):
    - a displacement larger than the tissue (its bounding-box diagonal): not a deformation of this tissue
      (the run's divergence guard would stop it, or the mesh tangles first); usually a unit error;
    - a move of the held nodes in one step longer than insertion.contact_distance, the bound of the needle
      tip's travel per step: a faster boundary carries the tissue across the contact zone in one step (a 5 cm
      jump of the clamped face gave 1,153 N and 66 insertion points in one step);
    - a periodic motion with fewer than 4 steps per period of its highest harmonic (n / T for cos^{2n}):
      sampled by the steps below Nyquist's 2, it aliases (a period equal to dt is exactly zero motion);
    - a sampled (file) motion that the steps do not resolve: its samples deviate from the motion the run
      applies (the file's motion seen at the step times, linear between them) by more than
      insertion.contact_distance (an oscillation faster than the steps).
    """
    dt, steps = scene.time.dt, scene.time.step_count
    where = f"{scene.source}: boundary"
    contact = scene.insertion.contact_distance
    rest = mesh.rest_positions
    size = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
    if scene.boundary.motion == "periodic":
        harmonic = int(scene.boundary.exponent)
        if dt > scene.boundary.period / (4 * harmonic):
            raise SceneError(
                f"{where}.period = {scene.boundary.period!r} s: with exponent n = {harmonic} the motion's "
                f"highest harmonic has period T/n = {scene.boundary.period / harmonic:.3g} s, which "
                f"time.dt = {dt!r} s samples {scene.boundary.period / harmonic / dt:.3g} times (Nyquist: "
                f"more than 2; refsim asks at least 4, or the motion aliases): use period >= "
                f"{4 * harmonic * dt:.3g} s or a smaller dt"
            )
    largest, jump, jump_time = 0.0, 0.0, 0.0
    previous = None
    for start in range(0, steps + 1, _CHECK_CHUNK):
        times = dt * np.arange(start, min(start + _CHECK_CHUNK, steps + 1))
        values = motion.history(times)
        largest = max(largest, float(np.linalg.norm(values, axis=1).max()))
        if previous is not None:
            values = np.vstack([previous, values])
            times = np.concatenate([[times[0] - dt], times])
        if values.shape[0] > 1:
            moves = np.linalg.norm(np.diff(values, axis=0), axis=1)
            at = int(np.argmax(moves))
            if moves[at] > jump:
                jump, jump_time = float(moves[at]), float(times[at])
        previous = values[-1:]
    if largest > size:
        raise SceneError(
            f"{where}: the boundary motion moves its nodes by up to {largest:.3g} m, more than the tissue's "
            f"size ({size:.3g} m, its bounding-box diagonal): check boundary.amplitude or the file's "
            "displacements (units are metres)"
        )
    if jump > contact:
        raise SceneError(
            f"{where}: the boundary motion moves its nodes by {jump:.3g} m in one step (from t = "
            f"{jump_time:.6g} s to {jump_time + dt:.6g} s), more than insertion.contact_distance = "
            f"{contact!r} m, the limit of the needle tip's travel per step too: use a smaller time.dt or a "
            "slower motion (boundary.amplitude, boundary.period, or the file's samples)"
        )
    if scene.boundary.motion == "file":
        samples = motion.times[motion.times <= steps * dt]
        before = np.minimum(np.floor(samples / dt), max(steps - 1, 0)) * dt  # the steps around each sample
        weight = np.clip((samples - before) / dt, 0.0, 1.0)[:, None]
        applied = (1.0 - weight) * motion.history(before) + weight * motion.history(before + dt)
        errors = np.linalg.norm(applied - motion.history(samples), axis=1)
        worst = int(np.argmax(errors)) if errors.size else 0
        if errors.size and errors[worst] > contact:
            raise SceneError(
                f"{where}.file: the motion changes faster than the steps resolve: at t = "
                f"{samples[worst]:.6g} s the file's displacement differs by {errors[worst]:.3g} m from the "
                f"one the run applies (the file seen every time.dt = {dt!r} s), more than "
                f"insertion.contact_distance = {contact!r} m: use a smaller time.dt"
            )


def report_fixed_set(scene: Scene, mesh: TetMesh, fixed: np.ndarray) -> None:
    """Log the fixed set (how many nodes, their bounding box) at load; :func:`check_held` refuses a fixed set
    that cannot hold every part of the tissue."""
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


def _fixed_nodes_or_error(scene: Scene, mesh: TetMesh) -> np.ndarray:
    try:
        return fixed_nodes(scene.mesh, mesh.rest_positions, mesh)
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
    _warn_mesh_units(scene, bounds)
    _check_needle_outside(scene, mesh, trajectory, bounds)
    _warn_unreachable(scene, trajectory, bounds)
    _warn_spacing_against_edges(scene, mesh)
    if scene.trajectory.file is not None:  # the speed check of the scene needs the file's samples
        _check_file_tip_speed(scene, trajectory)


def _warn_mesh_units(scene: Scene, bounds: np.ndarray) -> None:
    """Warn when the mesh size and the needle length differ by more than 30 times (other units?)."""
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


def _check_needle_outside(scene: Scene, mesh: TetMesh, trajectory: Trajectory, bounds: np.ndarray) -> None:
    """Refuse a needle thicker than the tissue, or inside it at t = 0."""
    extent = bounds[1] - bounds[0]
    needle = scene.needle
    where = scene.source
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


def _warn_unreachable(scene: Scene, trajectory: Trajectory, bounds: np.ndarray) -> None:
    """Warn when the tip never comes within insertion.contact_distance of the mesh's bounding box (on the
    waypoints and 20 points per segment)."""
    needle = scene.needle
    where = scene.source
    times = np.asarray(trajectory.times, dtype=float)
    tips = trajectory.base_positions + needle.length * trajectory.directions
    if times.size > 1:  # also the points between waypoints, at 20 per segment, all in one evaluation
        fractions = np.linspace(0.0, 1.0, 21)
        between = (times[:-1, None] + fractions * np.diff(times)[:, None]).ravel()
        bases, directions = trajectory.poses(between)
        tips = np.vstack([tips, bases + needle.length * directions])
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


def _warn_spacing_against_edges(scene: Scene, mesh: TetMesh) -> None:
    """Warn when d_i is longer than the mean mesh edge (insertion points skip elements)."""
    where = scene.source
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


def _check_file_tip_speed(scene: Scene, trajectory: Trajectory) -> None:
    """The tip's travel per step along a trajectory file within insertion.contact_distance."""
    needle = scene.needle
    where = scene.source
    times = np.asarray(trajectory.times, dtype=float)
    speeds = np.linalg.norm(np.diff(trajectory.base_positions, axis=0), axis=1) + needle.length * np.arccos(
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
