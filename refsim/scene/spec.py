"""The scene description: frozen, keyword-only, validated dataclasses, one per TOML section.

Every parameter of the paper is a key here, in SI units (angles of the triangulation in degrees, as the paper
states them). A field's metadata gives its unit, its valid range and its meaning; `refsim.scene.load_scene`
reads a TOML file into a :class:`Scene` and names the file, the key, the value and the valid range on any error.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from refsim.scene.fields import check_fields, spec

__all__ = [
    "MeshSpec",
    "TissueSpec",
    "NeedleSpec",
    "TrajectorySpec",
    "TimeSpec",
    "InsertionSpec",
    "CuttingSpec",
    "SolverSpec",
    "OutputSpec",
    "Scene",
    "FACE_NAMES",
]

FACE_NAMES = ("xmin", "xmax", "ymin", "ymax", "zmin", "zmax")


class _Validated:
    def __post_init__(self) -> None:
        check_fields(self)
        self.validate()

    def validate(self) -> None:
        """Checks across fields; raise ValueError naming the field."""


@dataclass(frozen=True, kw_only=True)
class MeshSpec(_Validated):
    """The tissue mesh: a generated box or a file, and which of its nodes are fixed."""

    generator: str | None = spec(None, doc="mesh generator, 'box', or none when `file` is given", choices=("box",))
    size: tuple | None = spec(None, unit="m", doc="box edge lengths", low=0.0, low_open=True, length=3)
    cells: tuple | None = spec(None, doc="box cells per axis (6 tets each)", low=1, high=256, length=3)
    origin: tuple = spec((0.0, 0.0, 0.0), unit="m", doc="box corner with the smallest coordinates", length=3)
    file: str | None = spec(None, doc="volume mesh file (any format meshio reads, or Gmsh v1); relative to the scene")
    scale: float = spec(1.0, unit="-", doc="factor applied to the file's coordinates to get metres", low=0.0, low_open=True)
    fixed_faces: tuple = spec((), doc="bounding-box faces whose nodes are fixed: xmin, xmax, ymin, ymax, zmin, zmax")
    fixed_box: tuple | None = spec(None, doc="nodes inside this box [[xmin, ymin, zmin], [xmax, ymax, zmax]] [m] are fixed")
    face_tolerance: float = spec(1e-9, unit="m", doc="distance to a bounding-box face within which a node is on it", low=0.0)

    def validate(self) -> None:
        if (self.generator is None) == (self.file is None):
            raise ValueError(f"give exactly one of generator or file, got generator={self.generator!r}, file={self.file!r}")
        if self.generator == "box":
            if self.size is None or self.cells is None:
                raise ValueError("the box generator needs size [m] (3 numbers) and cells (3 integers)")
            if not all(isinstance(c, int) and not isinstance(c, bool) for c in self.cells):
                raise ValueError(f"cells = {self.cells!r}: expected 3 integers in [1, 256]")
        for face in self.fixed_faces:
            if face not in FACE_NAMES:
                raise ValueError(f"fixed_faces contains {face!r}: expected names from {', '.join(FACE_NAMES)}")
        if self.fixed_box is not None:
            box = np.asarray(self.fixed_box, dtype=float)
            if box.shape != (2, 3) or not np.all(np.isfinite(box)) or np.any(box[0] > box[1]):
                raise ValueError(f"fixed_box = {self.fixed_box!r}: expected [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min <= max")
        if not self.fixed_faces and self.fixed_box is None:
            raise ValueError("no fixed nodes: give fixed_faces or fixed_box (a free tissue has no static equilibrium)")


@dataclass(frozen=True, kw_only=True)
class TissueSpec(_Validated):
    """Tissue material (co-rotational linear tetrahedra, Hooke's law) and damping."""

    youngs_modulus: float = spec(unit="Pa", doc="Young's modulus E", low=0.0, low_open=True)
    poisson_ratio: float = spec(unit="-", doc="Poisson's ratio ν", low=-1.0, high=0.5, low_open=True, high_open=True)
    density: float = spec(unit="kg/m^3", doc="mass density", low=0.0, low_open=True)
    rayleigh_mass: float = spec(0.0, unit="1/s", doc="Rayleigh damping α (C = αM + βK)", low=0.0)
    rayleigh_stiffness: float = spec(0.0, unit="s", doc="Rayleigh damping β (C = αM + βK)", low=0.0)
    gravity: tuple = spec((0.0, 0.0, 0.0), unit="m/s^2", doc="gravity acceleration", length=3)


@dataclass(frozen=True, kw_only=True)
class NeedleSpec(_Validated):
    """The needle: co-rotational Timoshenko beams with 6-DoF nodes, or a rigid body driven by its base."""

    length: float = spec(unit="m", doc="needle length", low=0.0, low_open=True)
    radius: float = spec(unit="m", doc="radius of the solid circular section", low=0.0, low_open=True)
    element_count: int = spec(unit="-", doc="number of beam elements", low=1, high=10000)
    youngs_modulus: float = spec(unit="Pa", doc="Young's modulus E", low=0.0, low_open=True)
    poisson_ratio: float = spec(unit="-", doc="Poisson's ratio ν", low=-1.0, high=0.5, low_open=True, high_open=True)
    density: float = spec(unit="kg/m^3", doc="mass density", low=0.0, low_open=True)
    rigid: bool = spec(doc="true: the needle is a rigid body moved by the trajectory (no beam solve)")
    rayleigh_mass: float = spec(0.0, unit="1/s", doc="Rayleigh damping α of the beam", low=0.0)
    rayleigh_stiffness: float = spec(0.0, unit="s", doc="Rayleigh damping β of the beam", low=0.0)

    def validate(self) -> None:
        if not isinstance(self.rigid, bool):
            raise ValueError(f"rigid = {self.rigid!r}: expected true or false")
        if not isinstance(self.element_count, int) or isinstance(self.element_count, bool):
            raise ValueError(f"element_count = {self.element_count!r}: expected an integer in [1, 10000]")
        if self.radius >= self.length:
            raise ValueError(f"radius = {self.radius!r} m must be smaller than length = {self.length!r} m")


@dataclass(frozen=True, kw_only=True)
class TrajectorySpec(_Validated):
    """Motion of the needle base: piecewise-linear waypoints, or a sampled file (a robot's precomputed motion).

    The needle points from its base along ``direction``; the tip is at base + length · direction at rest.
    Directions are interpolated linearly and normalised (for a constant direction they are exact).
    """

    times: tuple | None = spec(None, unit="s", doc="waypoint times, increasing, first 0")
    base_positions: tuple | None = spec(None, unit="m", doc="base position at each waypoint, (w, 3)")
    directions: tuple | None = spec(None, unit="-", doc="needle direction (base to tip) at each waypoint, (w, 3)")
    file: str | None = spec(None, doc="CSV file with columns t, x, y, z, dx, dy, dz [s, m, -]; relative to the scene")

    def validate(self) -> None:
        if (self.file is None) == (self.times is None):
            raise ValueError("give either file, or times with base_positions and directions")
        if self.file is not None:
            return
        times = np.asarray(self.times, dtype=float)
        if times.ndim != 1 or times.size < 1 or not np.all(np.isfinite(times)):
            raise ValueError(f"times = {self.times!r}: expected a list of finite numbers [s]")
        if times[0] != 0.0 or np.any(np.diff(times) <= 0.0):
            raise ValueError(f"times = {self.times!r}: expected strictly increasing times starting at 0 s")
        for name in ("base_positions", "directions"):
            value = getattr(self, name)
            array = np.asarray(value if value is not None else [], dtype=float)
            if array.shape != (times.size, 3) or not np.all(np.isfinite(array)):
                raise ValueError(f"{name} = {value!r}: expected {times.size} rows of 3 finite numbers (one per time)")
        norms = np.linalg.norm(np.asarray(self.directions, dtype=float), axis=1)
        if np.any(norms < 1e-12):
            raise ValueError(f"directions = {self.directions!r}: every direction must be non-zero")


@dataclass(frozen=True, kw_only=True)
class TimeSpec(_Validated):
    """Time integration: implicit Euler, one Newton step per time step."""

    dt: float = spec(unit="s", doc="time step", low=0.0, high=1.0, low_open=True)
    duration: float = spec(unit="s", doc="simulated time", low=0.0, low_open=True)

    def validate(self) -> None:
        if self.duration < self.dt:
            raise ValueError(f"duration = {self.duration!r} s is shorter than one time step dt = {self.dt!r} s")

    @property
    def step_count(self) -> int:
        """Number of steps, round(duration / dt)."""
        return int(round(self.duration / self.dt))


@dataclass(frozen=True, kw_only=True)
class InsertionSpec(_Validated):
    """Penetration at the tip and insertion constraints along the path (paper, section 3)."""

    puncture_force: float = spec(unit="N", doc="f_p: normal tip force that punctures the surface", low=0.0)
    surface_friction_coefficient: float = spec(unit="-", doc="μ_p: Coulomb friction of the tip on the surface", low=0.0)
    shaft_friction_coefficient: float = spec(unit="-", doc="μ_i: Coulomb friction along the shaft", low=0.0)
    spacing: float = spec(unit="m", doc="d_i: distance between insertion constraints", low=0.0, low_open=True)
    shaft_normal_force: float = spec(
        0.0,
        unit="N/m",
        doc="radial force per unit inserted length of the tissue on the needle (its grip, which the centreline "
        "rows do not see), added to the lateral forces in the shaft Coulomb bound: preload f d_i per insertion "
        "point; 0 gives the paper's model",
        low=0.0,
    )
    contact_distance: float = spec(
        unit="m", doc="tip-surface distance under which the penetration constraint is built", low=0.0, low_open=True
    )
    coupling: str = spec(
        "ring",
        doc="needle-tissue coupling: 'ring' (well posed: rows average the tissue over a ring of radius max(r, h) and "
        "carry the sub-grid compliance of the annulus, docs/coupling.md) or 'paper' (rows on the centreline)",
        choices=("ring", "paper"),
    )
    shaft_contact: bool = spec(
        True,
        doc="before puncture, keep the whole needle's centreline out of the tissue (unilateral rows on shaft samples "
        "near the surface), not only the tip",
    )
    interference: float = spec(
        0.0,
        unit="m",
        doc="δ_r: radial interference of the needle in its channel; the grip 2π r p₀ d_i (Lamé, p₀ = 2G δ_r/r) is "
        "added to each point's shaft Coulomb bound, with shaft_normal_force d_i",
        low=0.0,
    )

    def validate(self) -> None:
        if not isinstance(self.shaft_contact, bool):
            raise ValueError(f"shaft_contact = {self.shaft_contact!r}: expected true or false")


@dataclass(frozen=True, kw_only=True)
class CuttingSpec(_Validated):
    """Laceration (paper, section 4): criteria, cut surface resolution and triangulation parameters."""

    enabled: bool = spec(doc="whether the scene can cut the tissue")
    cutting_force: float = spec(unit="N", doc="f_c: mean lateral force per insertion constraint that starts the cut", low=0.0)
    tearing_force: float = spec(unit="N", doc="f_t: border contact force that extends the cut", low=0.0)
    point_spacing: float = spec(unit="m", doc="d_c: distance between points of the cut surface", low=0.0, low_open=True)
    extent: float = spec(unit="m", doc="d_t: extent of the cut surface beyond the path, and of each tear", low=0.0, low_open=True)
    min_angle: float = spec(unit="deg", doc="θ_min: smallest triangle angle", low=0.0, high=60.0)
    max_angle: float = spec(unit="deg", doc="θ_max: largest triangle angle", low=60.0, high=180.0, high_open=True)
    max_normal_angle: float = spec(unit="deg", doc="θ_s: largest angle between neighbouring triangle normals", low=0.0, high=180.0)

    def validate(self) -> None:
        if not isinstance(self.enabled, bool):
            raise ValueError(f"enabled = {self.enabled!r}: expected true or false")


@dataclass(frozen=True, kw_only=True)
class SolverSpec(_Validated):
    """The constraint solver of each step."""

    method: str = spec(doc="constraint solver", choices=("gauss_seidel", "exact"))
    tolerance: float = spec(unit="-", doc="natural residual to reach", low=0.0, high=1.0, low_open=True)
    max_iterations: int = spec(unit="-", doc="iteration cap (Gauss–Seidel sweeps)", low=1, high=10_000_000)
    backend: str = spec("clarabel", doc="QP backend of the exact solver (qpsolvers name)")
    criterion: str = spec(
        "residual",
        doc="Gauss–Seidel stopping test: the natural residual, or SOFA's increment Σ|W_jj Δλ_j| < tolerance·(rows+1) [m]",
        choices=("residual", "increment"),
    )

    def validate(self) -> None:
        if not isinstance(self.max_iterations, int) or isinstance(self.max_iterations, bool):
            raise ValueError(f"max_iterations = {self.max_iterations!r}: expected an integer >= 1")


@dataclass(frozen=True, kw_only=True)
class OutputSpec(_Validated):
    """What the results file records."""

    tissue_every: int = spec(1, unit="-", doc="record tissue positions every k-th step (and the last)", low=1, high=1_000_000)
    record_problems: bool = spec(False, doc="record each step's constraint problem (W, δ_free, kinds)")

    def validate(self) -> None:
        if not isinstance(self.record_problems, bool):
            raise ValueError(f"record_problems = {self.record_problems!r}: expected true or false")


@dataclass(frozen=True, kw_only=True)
class Scene:
    """A whole scene. Built once, never mutated (STYLE.md pattern 6)."""

    name: str
    mesh: MeshSpec
    tissue: TissueSpec
    needle: NeedleSpec
    trajectory: TrajectorySpec
    time: TimeSpec
    insertion: InsertionSpec
    cutting: CuttingSpec
    solver: SolverSpec
    output: OutputSpec = dataclasses.field(default_factory=OutputSpec)
    source: str = "<memory>"
    base_directory: str = "."

    def to_dict(self) -> dict:
        """The scene as plain data (TOML sections), for the results file and for overrides."""
        out: dict = {"name": self.name}
        for section in SECTIONS:
            out[section] = dataclasses.asdict(getattr(self, section))
        return out


SECTIONS = {
    "mesh": MeshSpec,
    "tissue": TissueSpec,
    "needle": NeedleSpec,
    "trajectory": TrajectorySpec,
    "time": TimeSpec,
    "insertion": InsertionSpec,
    "cutting": CuttingSpec,
    "solver": SolverSpec,
    "output": OutputSpec,
}


def scene_reference() -> str:
    """Every scene key, with its unit, default and valid range, as Markdown (docs/scenes.md is generated by this)."""
    from refsim.scene.fields import describe_field

    lines = [
        "# Scene keys",
        "",
        "Generated by `refsim.scene.spec.scene_reference()`; `tests/scene/test_docs.py` checks this page is current.",
        "Every key is in SI units (angles of the triangulation in degrees). A key without a default is required.",
        "",
    ]
    for section, cls in SECTIONS.items():
        lines += [f"## [{section}]", "", (cls.__doc__ or "").strip().splitlines()[0], "", "| key | meaning | unit | default | valid |", "|---|---|---|---|---|"]
        for field in dataclasses.fields(cls):
            meta = field.metadata
            default = "required" if field.default is dataclasses.MISSING else repr(field.default)
            valid = describe_field(field) if (meta.get("low") is not None or meta.get("high") is not None or meta.get("choices") or meta.get("length")) else "see meaning"
            lines.append(f"| `{field.name}` | {meta.get('doc', '')} | {meta.get('unit', '') or '-'} | {default} | {valid} |")
        lines.append("")
    return "\n".join(lines)
