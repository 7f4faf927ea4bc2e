"""A liver phantom made by refsim: a smooth closed organ shape meshed with tetrahedra by Gmsh.

The shape is a loft (OpenCASCADE ``ThruSections``, a smooth B-spline skin) through closed cross-sections taken
across the long axis. Axes: x is the long (left-right) axis, y the antero-posterior axis (anterior edge at
+y), z the cranio-caudal axis (the convex diaphragmatic face at +z, the visceral face at −z). The
right lobe is at x < 0 (thick, about 10 cm), the left lobe at x > 0 (thinner, tapering to its tip), the two
separated by a dip of the thickness and an anterior notch; the visceral face is concave (pushed up into the
organ) between the lobes. Size 24.3 × 13.9 × 10.0 cm, volume 1.0 L. The shape is a plausible organ, not an
anatomical model.

Shipped meshes (package data, ``refsim/mesh/data/liver_phantom_<resolution>.vtu``) are read with
:func:`liver_phantom`; :func:`generate_liver_phantom` regenerates them (it needs the ``gmsh`` package, an
optional dependency: ``pip install gmsh``) and ``studies/liver_phantom/generate.py`` writes them.
"""

from __future__ import annotations

import signal
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from refsim.mesh.tetmesh import TetMesh

__all__ = [
    "GENERATED_WITH_GMSH",
    "LIVER_PHANTOM_RESOLUTIONS",
    "MeshQuality",
    "PHANTOM_QUALITY",
    "generate_liver_phantom",
    "liver_cross_section",
    "liver_phantom",
    "liver_phantom_path",
    "mesh_quality",
]

#: Target element size [m] of each shipped resolution.
LIVER_PHANTOM_RESOLUTIONS = {"coarse": 0.020, "medium": 0.009}
#: The Gmsh version that generated the shipped meshes (another version may place nodes differently).
GENERATED_WITH_GMSH = "4.15.2"

# Half length of the organ along x [mm] (the geometry is built in millimetres, then scaled to metres: Gmsh's
# geometric tolerances are absolute, 1e-8 by default, so millimetres keep them far below the features).
_HALF_LENGTH = 122.0
# Cross-sections of the loft: x stations [mm], denser towards the tips where the sections shrink fast.
_STATION_COUNT = 21
# Points per cross-section (interpolated by a closed spline).
_SECTION_POINTS = 36
# The tips' end caps are about 8 × 1.5 mm: elements of the organ's size there are slivers. The element size
# grows from a tip size at the two tip centres to the target size 10 mm away (a Gmsh Threshold field); each
# try's tip size [mm] is used until the mesh meets the quality below (Gmsh's output differs between machines
# and versions, so the quality is checked, not assumed).
_TIP_SIZES_MM = (4.0, 3.0, 2.0, 1.5)
_TIP_GRADING_MM = 10.0
#: The quality every generated phantom meets: no sliver, that is dihedral angles within (10°, 160°) and
#: radius ratios 3 r_in / r_circ above 0.15 (a sliver's tends to 0; the regular tet's is 1).
PHANTOM_QUALITY = {"min_dihedral": 10.0, "max_dihedral": 160.0, "min_radius_ratio": 0.15}


def _bump(x: np.ndarray, centre: float, width: float) -> np.ndarray:
    return np.exp(-(((x - centre) / width) ** 2))


def liver_cross_section(x: float, point_count: int = _SECTION_POINTS) -> np.ndarray:
    """The closed cross-section of the phantom at station x, in millimetres.

    Parameters
    ----------
    x : Station along the long axis [mm], in (−122, 122); the right lobe is at x < 0.
    point_count : Number of points, >= 8.

    Returns
    -------
    Points (x, y, z) [mm] going once around the section, shape (point_count, 3), not repeating the first.

    Notes
    -----
    With the envelope e(x) = sqrt(1 − (x / 122)²) and the lobe bumps g(x) = exp(−((x − c)/w)²), g_R
    (c = −50 mm, w = 45 mm) and g_L (c = 55 mm, w = 35 mm), the section is a superellipse-like curve of
    posterior half-width W = e (41 + 34 g_R + 30 g_L) (the anterior half-width has a 22 % notch at x = 18 mm),
    upper height T = e (8 + 54 g_R + 22 g_L) and lower depth B = e (6 + 44 g_R + 18 g_L) [mm]: the thickness
    T + B has one maximum per lobe (about 10 cm and 5 cm) and a dip between them. The lower half is pushed
    up by the visceral concavity D (1 − (y/W)²)² |sin θ|, D = 22 e exp(−((x − 8)/40)²) mm.
    """
    if point_count < 8:
        raise ValueError(f"point_count = {point_count}: expected at least 8")
    if not abs(x) < _HALF_LENGTH:
        raise ValueError(f"x = {x} mm: expected a station in (-{_HALF_LENGTH}, {_HALF_LENGTH})")
    envelope = np.sqrt(1.0 - (x / _HALF_LENGTH) ** 2)
    right, left = _bump(x, -50.0, 45.0), _bump(x, 55.0, 35.0)
    back = envelope * (41.0 + 34.0 * right + 30.0 * left)
    front = back * (1.0 - 0.22 * _bump(x, 18.0, 14.0))
    top = envelope * (8.0 + 54.0 * right + 22.0 * left)
    bottom = envelope * (6.0 + 44.0 * right + 18.0 * left)
    concavity = 22.0 * envelope * _bump(x, 8.0, 40.0)

    theta = np.linspace(0.0, 2.0 * np.pi, point_count, endpoint=False)
    cos, sin = np.cos(theta), np.sin(theta)
    half_width = np.where(cos >= 0.0, front, back)
    y = half_width * np.sign(cos) * np.abs(cos) ** 0.8
    upper = top * np.abs(sin) ** 0.9
    lower = -bottom * np.abs(sin) ** 0.9 + concavity * (1.0 - (y / half_width) ** 2) ** 2 * np.abs(sin)
    z = np.where(sin >= 0.0, upper, lower)
    return np.column_stack([np.full(point_count, float(x)), y, z])


def _stations() -> np.ndarray:
    # Chebyshev-like spacing: the end sections at ±0.995 of the half length leave tip caps ~1 mm across.
    angles = np.linspace(np.pi, 0.0, _STATION_COUNT)
    return 0.995 * _HALF_LENGTH * np.cos(angles)


def generate_liver_phantom(mesh_size: float, *, optimize: bool = True) -> TetMesh:
    """Mesh the liver phantom with Gmsh (OpenCASCADE loft, Delaunay tetrahedra, Netgen optimisation).

    Parameters
    ----------
    mesh_size : Target (largest) element size [m], in [0.003, 0.05]; the shipped coarse (0.020) and medium
        (0.009) meshes have 536 nodes and 1,735 tetrahedra, 2,582 nodes and 10,523 tetrahedra. Elements are
        smaller near the two tips, whose end caps are about 8 × 1.5 mm.
    optimize : Run Gmsh's and Netgen's tetrahedron optimisation (improves the worst elements); with
        ``optimize=False`` the quality is not checked.

    Returns
    -------
    The mesh in metres, centred on the loft's axis (x along the long axis, see the module notes). Its quality
    meets :data:`PHANTOM_QUALITY`: the tips are meshed finer (4, 3, 2, then 1.5 mm at the tip centres, grading
    to ``mesh_size`` over 10 mm) until it does. Gmsh runs on one thread, but its node placement differs
    between machines and versions: node and tet counts are not part of the contract.

    Raises
    ------
    ImportError
        When the ``gmsh`` package is not installed (``pip install gmsh``).
    ValueError
        When ``mesh_size`` is out of range.
    RuntimeError
        When no tip size gives that quality (naming Gmsh's version and the best quality reached).
    """
    if not 0.003 <= mesh_size <= 0.05:
        raise ValueError(f"mesh_size = {mesh_size} m: expected a size in [0.003, 0.05] m")
    try:
        import gmsh
    except ImportError as error:
        raise ImportError("generating the liver phantom needs the gmsh package: pip install gmsh") from error

    size_mm = 1e3 * mesh_size
    tip_sizes = [t for t in _TIP_SIZES_MM if t < size_mm] or [size_mm]
    failures = []
    for tip_mm in tip_sizes:
        mesh = _generate(gmsh, size_mm, tip_mm, optimize)
        if not optimize:
            return mesh
        quality = mesh_quality(mesh)
        problems = phantom_quality_problems(quality)
        if not problems:
            return mesh
        failures.append(f"tip size {tip_mm:g} mm: {', '.join(problems)}")
    raise RuntimeError(
        f"gmsh {gmsh.__version__} did not mesh the liver phantom at mesh_size = {mesh_size:g} m to the "
        f"quality PHANTOM_QUALITY asks ({'; '.join(failures)})"
    )


def phantom_quality_problems(quality: MeshQuality) -> list[str]:
    """What of :data:`PHANTOM_QUALITY` a mesh's quality misses (empty when it meets it)."""
    limits = PHANTOM_QUALITY
    problems = []
    if quality.min_dihedral <= limits["min_dihedral"] or quality.max_dihedral >= limits["max_dihedral"]:
        problems.append(
            f"dihedral angles {quality.min_dihedral:.2f}-{quality.max_dihedral:.2f} deg, expected within "
            f"({limits['min_dihedral']:g}, {limits['max_dihedral']:g})"
        )
    if quality.radius_ratio.min() <= limits["min_radius_ratio"]:
        problems.append(
            f"least radius ratio {quality.radius_ratio.min():.3f}, "
            f"expected above {limits['min_radius_ratio']:g}"
        )
    return problems


def _generate(gmsh, size_mm: float, tip_mm: float, optimize: bool) -> TetMesh:
    """One Gmsh meshing of the loft: target size ``size_mm``, ``tip_mm`` at the tip centres."""
    # Gmsh's initialisation resets SIGPIPE to its default (kill the process); keep the caller's handler.
    sigpipe = signal.getsignal(signal.SIGPIPE) if hasattr(signal, "SIGPIPE") else None
    gmsh.initialize(["refsim"], readConfigFiles=False)
    if sigpipe is not None:
        signal.signal(signal.SIGPIPE, sigpipe)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.add("liver_phantom")
        occ = gmsh.model.occ
        wires = []
        stations = _stations()
        for x in stations:
            points = [occ.addPoint(*p) for p in liver_cross_section(x)]
            wires.append(occ.addWire([occ.addSpline(points + [points[0]])]))
        occ.addThruSections(wires, makeSolid=True, makeRuled=False)
        tips = [occ.addPoint(*liver_cross_section(x).mean(axis=0)) for x in (stations[0], stations[-1])]
        occ.synchronize()
        field = gmsh.model.mesh.field
        distance = field.add("Distance")
        field.setNumbers(distance, "PointsList", tips)
        grading = field.add("Threshold")
        field.setNumber(grading, "InField", distance)
        field.setNumber(grading, "SizeMin", tip_mm)
        field.setNumber(grading, "SizeMax", size_mm)
        field.setNumber(grading, "DistMin", 0.0)
        field.setNumber(grading, "DistMax", _TIP_GRADING_MM)
        field.setAsBackgroundMesh(grading)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size_mm)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)  # no curvature refinement: sizes stay even
        gmsh.option.setNumber("Mesh.Algorithm3D", 1)  # Delaunay
        gmsh.option.setNumber("Mesh.Optimize", int(optimize))
        gmsh.option.setNumber("Mesh.OptimizeNetgen", int(optimize))
        gmsh.model.mesh.generate(3)
        node_tags, coordinates, _ = gmsh.model.mesh.getNodes()
        _, element_tags, element_nodes = gmsh.model.mesh.getElements(3)
    finally:
        gmsh.finalize()
    positions = 1e-3 * np.asarray(coordinates, dtype=float).reshape(-1, 3)
    tet_nodes = np.concatenate([np.asarray(nodes, dtype=np.int64) for nodes in element_nodes]).reshape(-1, 4)
    # Gmsh node tags are arbitrary positive integers: map them to rows of `positions`.
    tags = np.asarray(node_tags, dtype=np.int64)
    order = np.argsort(tags)
    tets = order[np.searchsorted(tags[order], tet_nodes)]
    used = np.zeros(positions.shape[0], dtype=bool)
    used[tets.ravel()] = True  # Gmsh keeps the geometry's construction points as unused nodes
    renumber = np.cumsum(used) - 1
    volumes = _signed_volumes(positions[used], renumber[tets])
    tets = renumber[tets]
    tets[volumes < 0] = tets[volumes < 0][:, [0, 1, 3, 2]]
    return TetMesh(
        positions[used],
        tets,
        source=(
            f"refsim liver phantom, gmsh {gmsh.__version__}, mesh size {1e-3 * size_mm:g} m, "
            f"tips {tip_mm:g} mm"
        ),
    )


def _signed_volumes(positions: np.ndarray, tets: np.ndarray) -> np.ndarray:
    a, b, c, d = (positions[tets[:, i]] for i in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


def liver_phantom_path(resolution: str = "coarse") -> Path:
    """Path of a shipped phantom mesh (a VTU file in the package data).

    Parameters
    ----------
    resolution : "coarse" (536 nodes, 1,735 tetrahedra, for tests) or "medium" (2,582 nodes,
        10,523 tetrahedra, for scenes).
    """
    if resolution not in LIVER_PHANTOM_RESOLUTIONS:
        raise ValueError(
            f"resolution = {resolution!r}: expected one of {', '.join(map(repr, LIVER_PHANTOM_RESOLUTIONS))}"
        )
    return Path(str(resources.files("refsim.mesh").joinpath("data", f"liver_phantom_{resolution}.vtu")))


def liver_phantom(resolution: str = "coarse") -> TetMesh:
    """The shipped liver phantom mesh [m], read and validated by :func:`refsim.mesh.read_mesh`.

    Parameters
    ----------
    resolution : "coarse" or "medium" (see :data:`LIVER_PHANTOM_RESOLUTIONS`).
    """
    from refsim.mesh.io import read_mesh

    return read_mesh(liver_phantom_path(resolution), fix_orientation=False)


@dataclass(frozen=True)
class MeshQuality:
    """Quality of a tetrahedral mesh.

    Attributes
    ----------
    node_count, tet_count : Sizes.
    min_dihedral, max_dihedral : Smallest and largest dihedral angle over all tetrahedra [degrees]
        (70.53° for the regular tetrahedron).
    radius_ratio : Radius ratio ρ = 3 r_in / r_circ of each tetrahedron, shape (tet_count,) (1 for the
        regular tetrahedron, 0 for a flat one).
    edge_length_range : Shortest and longest edge [m].
    """

    node_count: int
    tet_count: int
    min_dihedral: float
    max_dihedral: float
    radius_ratio: np.ndarray
    edge_length_range: tuple[float, float]

    def radius_ratio_quantiles(self, quantiles=(0.0, 0.01, 0.05, 0.5)) -> dict[float, float]:
        """Quantiles of the radius ratio (0 is the minimum)."""
        return {float(q): float(np.quantile(self.radius_ratio, q)) for q in quantiles}

    def format(self) -> str:
        """A short report: sizes, dihedral range, radius-ratio quantiles and histogram."""
        quantiles = self.radius_ratio_quantiles()
        counts, edges = np.histogram(self.radius_ratio, bins=np.linspace(0.0, 1.0, 11))
        histogram = "  ".join(
            f"{lo:.1f}-{hi:.1f}: {c}" for lo, hi, c in zip(edges[:-1], edges[1:], counts, strict=True) if c
        )
        return "\n".join(
            [
                f"{self.node_count} nodes, {self.tet_count} tetrahedra, edges "
                f"{1e3 * self.edge_length_range[0]:.2f}-{1e3 * self.edge_length_range[1]:.2f} mm",
                f"dihedral angles {self.min_dihedral:.2f}-{self.max_dihedral:.2f} deg",
                "radius ratio 3 r_in/r_circ: min {:.3f}, 1% {:.3f}, 5% {:.3f}, median {:.3f}".format(
                    *quantiles.values()
                ),
                f"radius ratio histogram: {histogram}",
            ]
        )


_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
# The faces opposite each node; the dihedral angle at edge (i, j) is between the two faces containing the
# edge, i.e. the faces opposite the two other nodes k, l.
_OPPOSITE = np.array([[2, 3], [1, 3], [1, 2], [0, 3], [0, 2], [0, 1]])


def mesh_quality(mesh: TetMesh) -> MeshQuality:
    """Dihedral angles, radius ratios and edge lengths of a tetrahedral mesh (vectorised).

    Parameters
    ----------
    mesh : The mesh.

    Notes
    -----
    With the outward area vectors n_k of the faces opposite node k, the dihedral angle at the edge shared by
    faces k and l is π − angle(n_k, n_l). The inradius is r_in = 3V / Σ|n_k| (|n_k| the face areas), the
    circumradius r_circ = |a² (b × c) + b² (c × a) + c² (a × b)| / (12 V) with a, b, c the edges from node 0.
    """
    vertices = mesh.rest_positions[mesh.tets]  # (m, 4, 3)
    origin = vertices[:, 0]
    a, b, c = (vertices[:, i] - origin for i in (1, 2, 3))
    volume = np.einsum("ij,ij->i", np.cross(a, b), c) / 6.0
    # Area vectors (times 2) of the faces opposite each node, pointing outward for a positive tet.
    normals = np.stack(
        [
            np.cross(vertices[:, 2] - vertices[:, 1], vertices[:, 3] - vertices[:, 1]),
            np.cross(vertices[:, 3] - vertices[:, 0], vertices[:, 2] - vertices[:, 0]),
            np.cross(vertices[:, 1] - vertices[:, 0], vertices[:, 3] - vertices[:, 0]),
            np.cross(vertices[:, 2] - vertices[:, 0], vertices[:, 1] - vertices[:, 0]),
        ],
        axis=1,
    )
    areas = np.linalg.norm(normals, axis=2)  # 2 × face areas
    unit = normals / areas[:, :, None]
    cosines = np.einsum("mej,mej->me", unit[:, _OPPOSITE[:, 0]], unit[:, _OPPOSITE[:, 1]])
    dihedral = np.degrees(np.pi - np.arccos(np.clip(cosines, -1.0, 1.0)))
    inradius = 3.0 * volume / (0.5 * areas.sum(axis=1))
    squared = [np.einsum("ij,ij->i", e, e)[:, None] for e in (a, b, c)]
    circumradius = np.linalg.norm(
        squared[0] * np.cross(b, c) + squared[1] * np.cross(c, a) + squared[2] * np.cross(a, b), axis=1
    ) / (12.0 * volume)
    edges = np.linalg.norm(vertices[:, _TET_EDGES[:, 1]] - vertices[:, _TET_EDGES[:, 0]], axis=2)
    return MeshQuality(
        node_count=mesh.node_count,
        tet_count=mesh.tet_count,
        min_dihedral=float(dihedral.min()),
        max_dihedral=float(dihedral.max()),
        radius_ratio=3.0 * inradius / circumradius,
        edge_length_range=(float(edges.min()), float(edges.max())),
    )
