"""The scene's sections: frozen, keyword-only, validated dataclasses, one per TOML section.

Every parameter of the paper that the simulation uses is a key here, in SI units. A field's metadata gives its
unit, its valid range and its meaning; a section checks its own keys (``validate``), and the checks across
sections are in `refsim.scene.consistency`. The whole scene, `Scene`, is in `refsim.scene.spec`.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from refsim.constraints.coupling_models import COUPLING_MODELS, Coupling
from refsim.cutting.laws import CUTTING_LAWS, CuttingLaw
from refsim.fem.compliance import STRATEGIES, W_UPDATES
from refsim.materials import MATERIAL_LIMITS
from refsim.scene.controls import BOUNDARY_MOTIONS
from refsim.scene.declared import boundary_motion_keys, cutting_law_keys, declared_section
from refsim.scene.fields import FieldError, check_fields, spec

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
    "ComplianceSpec",
    "BoundarySpec",
    "InstrumentSpec",
    "SECTIONS",
    "FACE_NAMES",
    "LARGEST_COORDINATE",
    "check_directions",
    "numbers_array",
]

FACE_NAMES = ("xmin", "xmax", "ymin", "ymax", "zmin", "zmax")

#: The largest coordinate and length of a scene [m]: a needle's base and every length of the scene
#: (:func:`check_scene_lengths`) stay within it, so that products and squares of lengths (areas, second
#: moments, squared distances) stay far from float64's overflow and underflow.
LARGEST_COORDINATE = 1e3


class _Validated:
    def __post_init__(self) -> None:
        check_fields(self)
        self.validate()

    def validate(self) -> None:
        """Checks across fields; raise ValueError naming the field."""


@dataclass(frozen=True, kw_only=True)
class MeshSpec(_Validated):
    """The tissue mesh: a generated box or a file, and which of its nodes are fixed."""

    generator: str | None = spec(
        None,
        doc="mesh generator, 'box', or none when `file` is given; set by --set on a scene with a file, it "
        "replaces the file (and its scale)",
        choices=("box",),
    )
    size: tuple | None = spec(None, unit="m", doc="box edge lengths", low=0.0, low_open=True, length=3)
    cells: tuple | None = spec(
        None, doc="box cells per axis (6 tets each)", low=1, high=256, length=3, integer=True
    )
    origin: tuple = spec((0.0, 0.0, 0.0), unit="m", doc="box corner with the smallest coordinates", length=3)
    file: str | None = spec(
        None,
        doc="volume mesh file (any format meshio reads, or Gmsh v1); relative to the scene; set by --set on "
        "a scene with a generated box, it replaces the box (its generator, size, cells and origin)",
    )
    scale: float = spec(
        1.0, unit="-", doc="factor applied to the file's coordinates to get metres", low=0.0, low_open=True
    )
    fixed_faces: tuple = spec(
        (), doc="bounding-box faces whose nodes are fixed: xmin, xmax, ymin, ymax, zmin, zmax"
    )
    fixed_box: tuple | None = spec(
        None, doc="nodes inside this box [[xmin, ymin, zmin], [xmax, ymax, zmax]] [m] are fixed"
    )
    fixed_nodes: tuple | None = spec(
        None,
        doc="indices of fixed nodes (as SOFA's FixedConstraint lists them), in the mesh file's order",
        low=0,
        integer=True,
    )
    face_tolerance: float = spec(
        1e-9, unit="m", doc="distance to a bounding-box face within which a node is on it", low=0.0
    )

    def validate(self) -> None:
        if (self.generator is None) == (self.file is None):
            raise FieldError(
                "generator",
                f"give exactly one of generator or file, got generator={self.generator!r}, "
                f"file={self.file!r}",
            )
        if self.generator == "box":
            if self.size is None or self.cells is None:
                raise FieldError(
                    "size" if self.size is None else "cells",
                    "the box generator needs size [m] (3 numbers) and cells (3 integers)",
                )
        if self.file is not None and not self.file.strip():
            raise FieldError("file", "file = '': expected the path of a volume mesh file")
        if np.any(np.abs(np.asarray(self.origin, dtype=float)) > LARGEST_COORDINATE):
            raise FieldError(
                "origin",
                f"origin = {list(self.origin)!r}: expected coordinates within ±{LARGEST_COORDINATE:g} m",
            )
        for face in self.fixed_faces:
            if face not in FACE_NAMES:
                raise FieldError(
                    "fixed_faces",
                    f"fixed_faces contains {face!r}: expected names from {', '.join(FACE_NAMES)}",
                )
        if len(set(self.fixed_faces)) != len(self.fixed_faces):
            raise FieldError("fixed_faces", f"fixed_faces = {list(self.fixed_faces)!r} names a face twice")
        if self.fixed_box is not None:
            box = numbers_array(
                "fixed_box", self.fixed_box, (2, 3), "[[xmin, ymin, zmin], [xmax, ymax, zmax]] [m]"
            )
            if np.any(box[0] > box[1]):
                raise FieldError(
                    "fixed_box",
                    f"fixed_box = {self.fixed_box!r}: expected [[xmin, ymin, zmin], [xmax, ymax, zmax]] with "
                    f"min <= max",
                )
        if self.fixed_nodes is not None and len(set(self.fixed_nodes)) != len(self.fixed_nodes):
            raise FieldError("fixed_nodes", "fixed_nodes lists a node twice")


@dataclass(frozen=True, kw_only=True)
class TissueSpec(_Validated):
    """Tissue material (co-rotational linear tetrahedra, Hooke's law) and damping."""

    youngs_modulus: float = spec(doc="Young's modulus E", **MATERIAL_LIMITS["youngs_modulus"])
    poisson_ratio: float = spec(doc="Poisson's ratio ν", **MATERIAL_LIMITS["poisson_ratio"])
    density: float = spec(doc="mass density", **MATERIAL_LIMITS["density"])
    rayleigh_mass: float = spec(0.0, unit="1/s", doc="Rayleigh damping α (C = αM + βK)", low=0.0, high=1e6)
    rayleigh_stiffness: float = spec(0.0, unit="s", doc="Rayleigh damping β (C = αM + βK)", low=0.0, high=1e3)
    gravity: tuple = spec(
        (0.0, 0.0, 0.0), unit="m/s^2", doc="gravity acceleration", low=-1e4, high=1e4, length=3
    )


@dataclass(frozen=True, kw_only=True)
class NeedleSpec(_Validated):
    """The needle: co-rotational Timoshenko beams with 6-DoF nodes, or a rigid body driven by its base."""

    length: float = spec(unit="m", doc="needle length", low=0.0, high=10.0, low_open=True)
    radius: float = spec(
        unit="m",
        doc="radius of the solid circular section; a length of the scene (at least `resolvable_length` of "
        "the scene's largest coordinate, or contact distances and the section are lost in round-off; "
        "below the diameter of the tissue, checked with the mesh)",
        low=0.0,
        low_open=True,
    )
    element_count: int = spec(unit="-", doc="number of beam elements", low=1, high=10000)
    youngs_modulus: float = spec(doc="Young's modulus E", **MATERIAL_LIMITS["youngs_modulus"])
    poisson_ratio: float = spec(doc="Poisson's ratio ν", **MATERIAL_LIMITS["poisson_ratio"])
    density: float = spec(doc="mass density", **MATERIAL_LIMITS["density"])
    rigid: bool = spec(doc="true: the needle is a rigid body moved by the trajectory (no beam solve)")
    rayleigh_mass: float = spec(0.0, unit="1/s", doc="Rayleigh damping α of the beam", low=0.0, high=1e6)
    rayleigh_stiffness: float = spec(0.0, unit="s", doc="Rayleigh damping β of the beam", low=0.0, high=1e3)

    def validate(self) -> None:
        if self.radius >= self.length:
            raise FieldError(
                "radius",
                f"radius = {self.radius!r} m must be smaller than length = {self.length!r} m",
                related=("length",),
            )


@dataclass(frozen=True, kw_only=True)
class TrajectorySpec(_Validated):
    """Motion of the needle base: piecewise-linear waypoints, a sampled file (a robot's precomputed motion),
    or an aimed straight insertion (``entry`` and its keys).

    The needle points from its base along ``direction``; the tip is at base + length · direction at rest.
    Directions are interpolated linearly and normalised (for a constant direction they are exact).

    Aiming (``entry``, turned into two waypoints when the mesh is built, refsim.scene.trajectory.aimed): the
    needle enters at the point of the tissue's boundary surface closest to ``entry``, along
    ``entry_direction`` or at ``entry_angle`` to the inward surface normal there (tilted towards
    ``tilt_towards``; along the normal by default). At t = 0 the tip is ``standoff`` before the entry; it
    moves at ``speed`` along the needle until it is ``depth`` past the entry, then holds still. Example: into
    the cube's top face 1 cm off centre, 20° from the normal towards +x, 10 mm deep at 5 mm/s:
    ``entry = [0.01, 0.0, 0.1]``, ``entry_angle = 20.0``, ``tilt_towards = [1.0, 0.0, 0.0]``,
    ``depth = 0.01``, ``speed = 0.005`` (`refsim run` prints the entry and direction it resolved).
    """

    times: tuple | None = spec(None, unit="s", doc="waypoint times, increasing, first 0")
    base_positions: tuple | None = spec(None, unit="m", doc="base position at each waypoint, (w, 3)")
    directions: tuple | None = spec(
        None, unit="-", doc="needle direction (base to tip) at each waypoint, (w, 3)"
    )
    file: str | None = spec(
        None, doc="CSV file with columns t, x, y, z, dx, dy, dz [s, m, -]; relative to the scene"
    )
    entry: tuple | None = spec(
        None,
        unit="m",
        length=3,
        doc="aim: the needle enters the tissue at the point of its boundary surface closest to this point "
        "(a point on the surface, or a target near it)",
    )
    entry_direction: tuple | None = spec(
        None,
        unit="-",
        length=3,
        doc="aim: insertion direction (base to tip); it must point into the tissue at the entry; default: "
        "entry_angle to the inward surface normal",
    )
    entry_angle: float = spec(
        0.0,
        unit="deg",
        low=0.0,
        high=80.0,
        doc="aim: angle between the needle and the inward surface normal at the entry (without "
        "entry_direction)",
    )
    tilt_towards: tuple | None = spec(
        None,
        unit="-",
        length=3,
        doc="aim: the needle tilts from the normal by entry_angle towards this direction (its part along "
        "the surface); required when entry_angle > 0",
    )
    standoff: float = spec(
        2e-3, unit="m", low=0.0, low_open=True, doc="aim: distance of the tip before the entry at t = 0"
    )
    depth: float | None = spec(
        None, unit="m", low=0.0, low_open=True, doc="aim: final tip depth past the entry, along the needle"
    )
    speed: float | None = spec(
        None, unit="m/s", low=0.0, low_open=True, doc="aim: tip speed along the needle"
    )

    def validate(self) -> None:
        modes = [name for name in ("times", "file", "entry") if getattr(self, name) is not None]
        if len(modes) != 1:
            key = modes[-1] if modes else "times"
            raise FieldError(
                key,
                f"{key}: give one of: times with base_positions and directions; file; entry (aim) with depth "
                f"and speed (given: {', '.join(modes) or 'none'})",
            )
        aim_keys = ("entry_direction", "tilt_towards", "depth", "speed")
        if self.entry is None:
            for name in aim_keys:
                if getattr(self, name) is not None:
                    raise FieldError(name, f"{name} aims the needle: it needs trajectory.entry")
        else:
            self._validate_aim()
            return
        if self.file is not None:
            if self.base_positions is not None or self.directions is not None:
                raise FieldError(
                    "file", "give either file, or times with base_positions and directions, not both"
                )
            if not self.file.strip():
                raise FieldError("file", "file = '': expected the path of a CSV trajectory")
            return
        times = numbers_array("times", self.times, (None,), "a list of finite times [s]")
        if times.size < 1:
            raise FieldError("times", f"times = {self.times!r}: expected at least one time [s]")
        if times[0] != 0.0 or np.any(np.diff(times) <= 0.0):
            raise FieldError(
                "times", f"times = {self.times!r}: expected strictly increasing times starting at 0 s"
            )
        for name in ("base_positions", "directions"):
            value = getattr(self, name)
            if value is None:
                raise FieldError(
                    name, f"{name} is missing: expected {times.size} rows of 3 numbers (one per time)"
                )
            array = numbers_array(
                name, value, (times.size, 3), f"{times.size} rows of 3 finite numbers (one per time)"
            )
            if name == "base_positions" and np.any(np.abs(array) > LARGEST_COORDINATE):
                raise FieldError(
                    name, f"{name} = {value!r}: expected coordinates within ±{LARGEST_COORDINATE:g} m"
                )
        directions = np.asarray(self.directions, dtype=float)
        check_directions(directions, "directions", times)

    def _validate_aim(self) -> None:
        if np.any(np.abs(np.asarray(self.entry, dtype=float)) > LARGEST_COORDINATE):
            raise FieldError(
                "entry",
                f"entry = {list(self.entry)!r}: expected coordinates within ±{LARGEST_COORDINATE:g} m",
            )
        for name in ("base_positions", "directions"):
            if getattr(self, name) is not None:
                raise FieldError(name, f"{name}: give either waypoints (times, ...) or entry (aim), not both")
        for name in ("depth", "speed"):
            if getattr(self, name) is None:
                raise FieldError(
                    name, f"{name} is missing: the aimed insertion (entry) needs depth and speed"
                )
        for name in ("entry_direction", "tilt_towards"):
            value = getattr(self, name)
            if value is not None and np.linalg.norm(np.asarray(value, dtype=float)) < 1e-12:
                raise FieldError(name, f"{name} = {list(value)!r}: expected a non-zero direction")
        if self.entry_direction is not None and (self.entry_angle != 0.0 or self.tilt_towards is not None):
            raise FieldError(
                "entry_direction",
                "entry_direction: give either entry_direction, or entry_angle with tilt_towards, not both",
            )
        if self.entry_angle > 0.0 and self.tilt_towards is None:
            raise FieldError(
                "tilt_towards",
                f"tilt_towards is missing: entry_angle = {self.entry_angle!r} deg needs the direction the "
                "needle tilts towards",
            )


def check_directions(directions: np.ndarray, name: str, times: np.ndarray) -> None:
    """Non-zero needle directions, and consecutive ones less than 90° apart.

    Directions are interpolated linearly and normalised: at 180° the interpolation passes through zero (an
    undefined direction, NaN), and near it the needle swings half a turn within a small fraction of the
    interval (measured: a 180° flip in one step inside the tissue). Above 90° insert intermediate waypoints.

    Raises
    ------
    FieldError
        Naming the waypoints and the angle.
    """
    norms = np.linalg.norm(directions, axis=1)
    if np.any(norms < 1e-12):
        row = int(np.argmax(norms < 1e-12))
        raise FieldError(
            name,
            f"{name}: the direction at t = {times[row]:g} s (row {row + 1}) is zero; every direction must be "
            f"non-zero",
        )
    unit = directions / norms[:, None]
    cosines = np.einsum("ij,ij->i", unit[:-1], unit[1:])
    if np.any(cosines < 0.0):
        row = int(np.argmax(cosines < 0.0))
        angle = float(np.degrees(np.arccos(np.clip(cosines[row], -1.0, 1.0))))
        raise FieldError(
            name,
            f"{name}: the needle turns {angle:.1f} degrees between t = {times[row]:g} s and "
            f"t = {times[row + 1]:g} s "
            "(rows {0} and {1}); consecutive directions must be less than 90 degrees apart (linear "
            "interpolation of "
            "antiparallel directions is undefined): add intermediate waypoints".format(row + 1, row + 2),
        )


def numbers_array(name: str, value, shape: tuple, expected: str) -> np.ndarray:
    """``value`` as a float array of ``shape`` (None: any length) with finite entries, else a FieldError."""
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise FieldError(name, f"{name} = {value!r}: expected {expected}") from None
    if array.ndim != len(shape) or any(
        n is not None and n != m for n, m in zip(shape, array.shape, strict=False)
    ):
        raise FieldError(name, f"{name} = {value!r}: expected {expected}")
    if not np.all(np.isfinite(array)):
        raise FieldError(name, f"{name} = {value!r}: expected finite numbers ({expected})")
    items = np.asarray(value, dtype=object).ravel()
    if any(isinstance(item, bool) for item in items):
        raise FieldError(name, f"{name} = {value!r}: expected numbers, not true/false ({expected})")
    text = next((item for item in items if isinstance(item, str)), None)
    if text is not None:  # numpy reads "0.5" as 0.5; a string in a numeric key is refused everywhere else
        raise FieldError(name, f"{name} = {value!r}: expected numbers, not the string {text!r} ({expected})")
    return array


@dataclass(frozen=True, kw_only=True)
class TimeSpec(_Validated):
    """Time integration: implicit Euler, one Newton step per time step."""

    dt: float = spec(unit="s", doc="time step", low=0.0, high=1.0, low_open=True)
    duration: float = spec(
        unit="s", doc="simulated time, a whole number of time steps", low=0.0, high=1e6, low_open=True
    )

    def validate(self) -> None:
        if self.duration < self.dt:
            raise FieldError(
                "duration",
                f"duration = {self.duration!r} s is shorter than one time step dt = {self.dt!r} s",
                related=("dt",),
            )
        steps = self.duration / self.dt
        if abs(steps - round(steps)) > 1e-6 * max(1.0, steps):
            below, above = int(steps) * self.dt, (int(steps) + 1) * self.dt
            raise FieldError(
                "duration",
                related=("dt",),
                message=f"duration = {self.duration!r} s is not a whole number of time steps dt = "
                f"{self.dt!r} s "
                f"({steps:.4g} steps): use {below:.6g} or {above:.6g}",
            )
        if round(steps) > 10_000_000:
            raise FieldError("duration", f"duration / dt = {steps:.3g} steps: at most 1e7 steps per run")

    @property
    def step_count(self) -> int:
        """Number of steps, round(duration / dt)."""
        return int(round(self.duration / self.dt))


@dataclass(frozen=True, kw_only=True)
class InsertionSpec(_Validated):
    """Penetration at the tip and insertion constraints along the path (paper, section 3)."""

    puncture_force: float = spec(
        unit="N",
        doc="f_p: normal tip force that punctures the surface (> 0: with 0 the tip would puncture in "
        "the air as soon as its contact row is built)",
        low=0.0,
        low_open=True,
    )
    surface_friction_coefficient: float = spec(
        unit="-", doc="μ_p: Coulomb friction of the tip on the surface", low=0.0
    )
    shaft_friction_coefficient: float = spec(
        unit="-",
        doc="μ_i: Coulomb friction along the shaft (the dynamic coefficient μ_d, of a slipping point)",
        low=0.0,
    )
    shaft_static_friction_coefficient: float = spec(
        0.0,
        unit="-",
        doc="μ_s: static shaft friction, the coefficient of a point that stuck at the last step (new points "
        "start "
        "stuck); ≥ shaft_friction_coefficient, or 0 (default): μ_s = μ_i, one coefficient as in the paper",
        low=0.0,
    )
    spacing: float = spec(unit="m", doc="d_i: distance between insertion constraints", low=0.0, low_open=True)
    shaft_normal_force: float = spec(
        0.0,
        unit="N/m",
        doc="radial force per unit inserted length of the tissue on the needle (its grip, which the "
        "centreline rows do not see): with the interference's, the grip g = f d_i of each insertion point, "
        "whose shaft Coulomb bound is μ max(g, ‖λ_lateral‖) (a lateral force redistributes a closed "
        "channel's pressure, it does not add to it); 0 gives the paper's model",
        low=0.0,
    )
    contact_distance: float = spec(
        unit="m",
        doc="tip-surface distance under which the penetration constraint is built",
        low=0.0,
        low_open=True,
    )
    coupling: str = spec(
        "ring",
        doc="needle-tissue coupling: 'ring' (well posed: rows average the tissue over a ring of radius "
        "max(r, h) and "
        "carry the sub-grid compliance of the annulus, docs/coupling.md) or 'paper' (rows on the centreline)",
        choices=tuple(COUPLING_MODELS),
    )
    subgrid_line: str = spec(
        "infinite",
        doc="sub-grid compliance of the ring rows: 'infinite' (the plane-strain and antiplane values of an "
        "infinite "
        "line) or 'finite' (3-D: the inserted line's own length, its mirror across the entry surface; "
        "converges "
        "better on short insertions and coarse meshes, docs/coupling.md; applied before the cut starts)",
        choices=("infinite", "finite"),
    )
    tip_cutting_force: float = spec(
        0.0,
        unit="N",
        doc="f_cut: after puncture, the force the tissue opposes to the tip advancing (one row along the "
        "needle at "
        "the tip, its force in [0, f_cut]: the tip sticks below, cuts at f_cut); 0 gives the paper's model "
        "(none)",
        low=0.0,
    )
    puncture_within_step: bool = spec(
        True,
        doc="cap the tip contact's force at f_p, so the tip punctures within the step at exactly f_p (for "
        "any dt "
        "and speed); false: the tip contact is a plain Coulomb contact and puncture is declared after the "
        "step",
    )
    shaft_contact: bool = spec(
        True,
        doc="before puncture, keep the whole needle's centreline out of the tissue (unilateral rows on shaft "
        "samples "
        "near the surface), not only the tip",
    )
    interference: float = spec(
        0.0,
        unit="m",
        doc="δ_r: radial interference of the needle in its channel; the grip 2π r p₀ d_i (Lamé, p₀ = 2G "
        "δ_r/r), with shaft_normal_force d_i, is the normal force of each point's shaft Coulomb bound while "
        "its lateral force is smaller (μ max(grip, ‖λ_lateral‖))",
        low=0.0,
    )
    tip_radius: float = spec(
        0.0,
        unit="m",
        doc="a: radius of a flat tip's face before puncture: the tip contact's row spreads its load over "
        "the disc of radius a with the pressure of a rigid flat punch (Sneddon: its limit under refinement "
        "is the punch's stiffness 2 a E δ/(1 − ν²) on a half-space); 0 (default): a point tip, the paper's "
        "model",
        low=0.0,
    )

    def validate(self) -> None:
        for name in ("shaft_contact", "puncture_within_step"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} = {getattr(self, name)!r}: expected true or false")
        static, dynamic = self.shaft_static_friction_coefficient, self.shaft_friction_coefficient
        if static != 0.0 and static < dynamic:
            raise FieldError(
                "shaft_static_friction_coefficient",
                related=("shaft_friction_coefficient",),
                message=f"shaft_static_friction_coefficient = {static!r} is below shaft_friction_coefficient "
                f"= "
                f"{dynamic!r}: the static coefficient must be >= the dynamic one (or 0: the same)",
            )

        if self.tip_cutting_force > self.puncture_force:
            logging.getLogger("refsim.scene").warning(
                "insertion.tip_cutting_force = %g N is above insertion.puncture_force = %g N: the tip needs "
                "more force to advance after puncture than to puncture (measured profiles drop after the "
                "puncture, Okamura et al. 2004); the puncture is then followed by a rise, not a drop",
                self.tip_cutting_force,
                self.puncture_force,
            )

    @property
    def static_friction_coefficient(self) -> float:
        """μ_s of the shaft: the static key, or μ_i when it is 0."""
        return self.shaft_static_friction_coefficient or self.shaft_friction_coefficient

    @property
    def coupling_model(self) -> Coupling:
        """The chosen coupling with its parameters (`refsim.constraints.coupling_models`)."""
        return COUPLING_MODELS[self.coupling]()


@dataclass(frozen=True, kw_only=True)
class _CuttingSpec(_Validated):
    """Laceration (paper, section 4): cut law, criteria and cut surface resolution.

    The law (`refsim.cutting.laws`) holds its own keys: `fracture_energy` belongs to the energy law,
    `cutting_force`, `tearing_force` and `extent` to the paper's. Only the chosen law's keys may be given (a
    key of the other law is an error naming it); a key of the chosen law left out takes the law's default,
    and the other law's keys stay unset (none)."""

    enabled: bool = spec(doc="whether the scene can cut the tissue")
    law: str = spec(
        "energy",
        doc="cut law: 'energy' (the cut starts and its crack tip advances where the needle pushes with more "
        "than G_c per unit length: independent of d_i, d_c and the mesh) or 'paper' (equation 3 with f_c per "
        "insertion point, tears of d_t at a front row force f_t)",
        choices=tuple(CUTTING_LAWS),
    )
    friction_coefficient: float = spec(
        0.0,
        unit="-",
        doc="μ_c: Coulomb friction of the needle on the cut faces (0: frictionless, the paper's model)",
        low=0.0,
        high=10.0,
    )
    point_spacing: float = spec(
        unit="m", doc="d_c: distance between points of the cut surface", low=0.0, low_open=True
    )

    def validate(self) -> None:
        """A key of the law not chosen is an error naming it, its law and the chosen law; the chosen law's
        keys left out take the law's defaults."""
        chosen = CUTTING_LAWS[self.law]
        for name, law in CUTTING_LAWS.items():
            if law is chosen:
                continue
            for key in law.keys:
                value = getattr(self, key)
                if value is not None:
                    raise FieldError(
                        key,
                        f"{key} = {value!r} is a key of the {name!r} cutting law, but law = {self.law!r} "
                        f"(the keys of the {self.law!r} law: {', '.join(chosen.keys)}): remove {key}, or "
                        f"choose law = {name!r}",
                        related=("law",),
                    )
        for key, value in chosen.defaults().items():
            if getattr(self, key) is None:
                object.__setattr__(self, key, value)

    @property
    def cutting_law(self) -> CuttingLaw:
        """The chosen law with its parameters (`refsim.cutting.laws`)."""
        law = CUTTING_LAWS[self.law]
        return law(**{key: getattr(self, key) for key in law.keys})


#: ``[cutting]``: the common keys, then each law's own keys, generated from the laws' declarations.
CuttingSpec = declared_section(_CuttingSpec, cutting_law_keys())


@dataclass(frozen=True, kw_only=True)
class SolverSpec(_Validated):
    """The constraint solver of each step."""

    method: str = spec(doc="constraint solver", choices=("gauss_seidel", "exact"))
    tolerance: float = spec(unit="-", doc="natural residual to reach", low=0.0, high=1.0, low_open=True)
    max_iterations: int = spec(unit="-", doc="iteration cap (Gauss–Seidel sweeps)", low=1, high=10_000_000)
    backend: str = spec(
        "clarabel",
        doc="QP backend of the exact solver's cone route: a qpsolvers name installed here "
        "(qpsolvers.available_solvers)",
    )
    exact_method: str = spec(
        "auto",
        doc="exact solver: auto (semismooth Newton on the natural map, then a Gauss–Seidel finish, a "
        "monotone "
        "Newton retry and the cone route; the report says which answered), newton, or cone (Clarabel/OSQP)",
        choices=("auto", "newton", "cone"),
    )
    criterion: str = spec(
        "residual",
        doc="Gauss–Seidel stopping test: the natural residual, or SOFA's increment Σ|W_jj Δλ_j| < "
        "tolerance·(rows+1) [m]",
        choices=("residual", "increment"),
    )

    def validate(self) -> None:
        import qpsolvers

        available = tuple(qpsolvers.available_solvers)
        if self.backend not in available:
            raise FieldError(
                "backend",
                f"backend = {self.backend!r}: expected one of the installed qpsolvers backends "
                f"{', '.join(repr(name) for name in available)}"
                + (" (OSQP installs with: pip install 'refsim[osqp]')" if self.backend == "osqp" else ""),
            )


@dataclass(frozen=True, kw_only=True)
class OutputSpec(_Validated):
    """What the results file records."""

    tissue_every: int = spec(
        1, unit="-", doc="record tissue positions every k-th step (and the last)", low=1, high=1_000_000
    )
    record_problems: bool = spec(False, doc="record each step's constraint problem (W, δ_free, kinds)")


@dataclass(frozen=True, kw_only=True)
class ComplianceSpec(_Validated):
    """How each body's compliance is computed (refsim.fem.compliance) and by which sparse solver; optional
    section."""

    strategy: str = spec(
        "exact",
        doc="exact: factorise every step (the factor is kept while A is unchanged, bit for bit); refreshed: "
        "factorise every refresh_every steps, free motion and W's columns by PCG on the current matrix; "
        "precomputed: the rest compliance rotated per node (SOFA-like); fast: "
        "no matrix assembled or factorised during the run, W and the correction from the rest compliance "
        "rotated per node, free motion by CG on the co-rotated operator; close to exact on stiff tissue, "
        "early events on soft (docs/speed.md, docs/fast_stiffness.md)",
        choices=STRATEGIES,
    )
    refresh_every: int = spec(
        10, unit="-", doc="steps between factorisations of the refreshed strategy", low=1, high=1_000_000
    )
    w_update: str = spec(
        "pcg",
        doc="refreshed strategy: W's columns solved by PCG on the current matrix (pcg, corrected to the PCG "
        "tolerance), corrected to first order in the change of the matrix since the factorisation with the "
        "correction by PCG (first_order), or taken from the stale factor (stale); errors by refsim bench "
        "--against-exact",
        choices=W_UPDATES,
    )
    tolerance: float | None = spec(
        None,
        unit="-",
        doc="relative residual ‖b − A x‖/‖b‖ at which the iterative strategies' PCG stops: refreshed and "
        "precomputed (free motion and W's columns; unset: 1e-10), fast (free motion; unset: 1e-2); the "
        "exact strategy solves directly and does not read it",
        low=0.0,
        high=1.0,
        low_open=True,
        high_open=True,
    )
    linear_solver: str = spec(
        "auto",
        doc="sparse solver: auto (PARDISO where its wheel installs, else refsim's own supernodal Cholesky; "
        "$REFSIM_LINEAR_SOLVER overrides auto), or one of pardiso, supernodal, cholmod, superlu",
        choices=("auto", "pardiso", "supernodal", "cholmod", "superlu"),
    )

    def validate(self) -> None:
        if not isinstance(self.refresh_every, int) or isinstance(self.refresh_every, bool):
            raise ValueError(f"refresh_every = {self.refresh_every!r}: expected an integer >= 1")


@dataclass(frozen=True, kw_only=True)
class _BoundarySpec(_Validated):
    """A tissue boundary motion (breathing, a moving support): chosen nodes follow a prescribed displacement;
    optional section."""

    motion: str = spec(
        "none",
        doc="none; periodic: d(t) = a (1 − cos^{2n}(π t/T − φ)) offset to 0 at t = 0 (Lujan et al. 1999); "
        "file: displacement samples t, dx, dy, dz from a CSV file",
        choices=("none", *BOUNDARY_MOTIONS),
    )
    nodes: tuple | None = spec(None, doc="indices of the moving nodes", low=0, integer=True)
    box: tuple | None = spec(
        None, doc="the nodes inside this box [[xmin, ymin, zmin], [xmax, ymax, zmax]] [m] move"
    )
    patch_point: tuple | None = spec(
        None, unit="m", doc="surface nodes within patch_distance of this point move", length=3
    )
    patch_plane: tuple | None = spec(
        None, unit="m", doc="surface nodes within patch_distance of the plane [[origin], [normal]] move"
    )
    patch_distance: float = spec(
        0.0, unit="m", doc="distance of a surface patch from its point or plane", low=0.0
    )
    facing: tuple | None = spec(
        None,
        unit="-",
        doc="surface nodes whose outward normal lies within facing_angle of this direction move (a face of "
        "the organ, e.g. [0, 0, 1] its superior face)",
        length=3,
    )
    facing_angle: float | None = spec(
        None,
        unit="deg",
        doc="largest angle between a facing node's outward normal and facing",
        low=0.0,
        high=180.0,
        low_open=True,
        high_open=True,
    )

    #: The keys each motion reads beyond the node selection (nodes, box, patch_point, patch_plane,
    #: patch_distance, facing, facing_angle, which every motion but none reads): the keys it declares
    #: (``keys``), each a field of the section generated from that declaration.
    MOTION_KEYS = {"none": ()} | {name: tuple(motion.keys) for name, motion in BOUNDARY_MOTIONS.items()}
    SELECTION_KEYS = (
        "nodes",
        "box",
        "patch_point",
        "patch_plane",
        "patch_distance",
        "facing",
        "facing_angle",
    )

    def validate(self) -> None:
        self._check_unused_keys()
        selections = [
            self.nodes is not None,
            self.box is not None,
            self.patch_point is not None,
            self.patch_plane is not None,
            self.facing is not None,
        ]
        if self.motion == "none":
            return
        if sum(selections) != 1:
            raise FieldError(
                "nodes", "a boundary motion needs exactly one of nodes, box, patch_point, patch_plane, facing"
            )
        if self.facing is not None and not np.any(np.asarray(self.facing, dtype=float)):
            raise FieldError("facing", f"facing = {list(self.facing)!r}: the direction is zero")
        if (self.facing is None) != (self.facing_angle is None):
            raise FieldError(
                "facing_angle" if self.facing is not None else "facing",
                "a facing selection needs both facing (a direction) and facing_angle (degrees)",
            )
        if self.box is not None:
            box = numbers_array("box", self.box, (2, 3), "[[xmin, ymin, zmin], [xmax, ymax, zmax]] [m]")
            if np.any(box[0] > box[1]):
                raise FieldError("box", f"box = {self.box!r}: expected min <= max")
        if self.patch_plane is not None:
            plane = numbers_array(
                "patch_plane", self.patch_plane, (2, 3), "[[origin x, y, z], [normal x, y, z]] [m]"
            )
            if np.linalg.norm(plane[1]) == 0.0:
                raise FieldError("patch_plane", "patch_plane: the normal is zero")
        if (self.patch_point is not None or self.patch_plane is not None) and self.patch_distance <= 0.0:
            raise FieldError("patch_distance", "a surface patch needs patch_distance > 0 [m]")
        if self.motion == "file" and not self.file:
            raise FieldError("file", "motion = 'file' needs file, a CSV of t, dx, dy, dz")
        if self.motion == "periodic" and not np.any(np.asarray(self.amplitude, dtype=float)):
            raise FieldError("amplitude", "a periodic motion needs a non-zero amplitude [m]")

    def _check_unused_keys(self) -> None:
        """A key the chosen motion does not read, set to other than its default, is an error naming the
        motion that reads it: ``file = ...`` without ``motion = "file"`` ran with no motion and no message.
        The motion is not inferred from the keys: ``motion`` is the one choice, and a key left over from
        another motion is as likely as a forgotten ``motion``."""
        used = self.MOTION_KEYS[self.motion] + (self.SELECTION_KEYS if self.motion != "none" else ())
        for field in dataclasses.fields(self):
            name = field.name
            if name == "motion" or name in used or getattr(self, name) == field.default:
                continue
            readers = [motion for motion, keys in self.MOTION_KEYS.items() if name in keys] or [
                motion for motion in self.MOTION_KEYS if motion != "none"
            ]
            raise FieldError(
                name,
                f"{name} = {getattr(self, name)!r} is given but motion = {self.motion!r} does not read it: "
                f"set motion = {' or '.join(repr(m) for m in readers)} to apply it, or remove {name}",
                related=("motion",),
            )


#: ``[boundary]``: the node selection, then each motion's keys, generated from the motions' declarations
#: (`refsim.scene.declared.boundary_motion_keys`).
BoundarySpec = declared_section(_BoundarySpec, boundary_motion_keys())


#: Names an instrument cannot take: the tissue's body name and the other collections of the XDMF sidecar
#: (refsim.io.xdmf names each instrument's needle collection by the instrument).
RESERVED_NAMES = ("tissue", "cut")
_NAME_CHARACTERS = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-")


@dataclass(frozen=True, kw_only=True)
class InstrumentSpec(_Validated):
    """One instrument (a needle) of a scene with several: an array of tables ``[[instruments]]``, each with
    its ``name``, its own ``trajectory`` sub-table (``[instruments.trajectory]``, the keys of [trajectory]),
    optional overrides of any [needle] key (e.g. ``radius``, ``rigid``) and whether it may cut. A scene has
    either [trajectory] (one instrument, named "needle") or [[instruments]], not both. The instruments meet
    only through the tissue (its compliance couples their rows; the cut surface one makes is met by the
    others' rows): needles do not touch each other. Several may cut, each its own strip of the one cut
    surface, which the others meet as a cut they are not cutting.
    """

    name: str = spec(
        doc="the instrument's name: letters, digits, _ and -; unique in the scene; not 'tissue' or 'cut';"
        " its results are under instruments/<name>/ (the first instrument's at the one-needle paths)"
    )
    cuts: bool | None = spec(
        None, doc="whether the instrument may cut (default: cutting.enabled); several may"
    )
    trajectory: TrajectorySpec | None = None
    needle: NeedleSpec | None = None

    def validate(self) -> None:
        if not self.name or not set(self.name) <= _NAME_CHARACTERS:
            raise FieldError("name", f"name = {self.name!r}: expected letters, digits, _ and - (not empty)")
        if self.name in RESERVED_NAMES:
            raise FieldError(
                "name",
                f"name = {self.name!r}: reserved ({', '.join(RESERVED_NAMES)} name the tissue and the cut); "
                "choose another",
            )


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
    "compliance": ComplianceSpec,
    "boundary": BoundarySpec,
}
