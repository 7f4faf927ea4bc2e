"""Checks across the sections of a scene that need no mesh (the mesh-dependent ones are in
`refsim.scene.build`): instruments, the lengths positions resolve, the step against the contact zone."""

from __future__ import annotations

import dataclasses
import logging
from typing import TYPE_CHECKING

import numpy as np

from refsim.scene.fields import FieldError
from refsim.scene.sections import LARGEST_COORDINATE, SECTIONS, TrajectorySpec

if TYPE_CHECKING:
    from refsim.scene.spec import Scene

__all__ = [
    "ConsistencyError",
    "RESOLVED_DIGITS",
    "check_consistency",
    "check_instruments",
    "check_scene_lengths",
    "is_scene_length",
    "max_tip_speed",
    "resolvable_length",
    "scene_lengths",
    "scene_scale",
]


class ConsistencyError(FieldError):
    """Keys of different sections that contradict each other; ``section`` and ``key`` name the one to
    change."""

    def __init__(self, section: str, key: str, message: str, related: tuple[tuple[str, str], ...] = ()):
        super().__init__(key, message)
        self.section = section
        self.related_keys = tuple(related)


def max_tip_speed(trajectory: TrajectorySpec, needle_length: float) -> float | None:
    """Largest speed of the needle tip between waypoints [m/s]: base speed plus length × turning rate (None
    for a trajectory file, checked when it is read)."""
    if trajectory.entry is not None:  # an aimed insertion moves the tip at its speed along the needle
        return float(trajectory.speed)
    if trajectory.times is None or len(trajectory.times) < 2:
        return 0.0 if trajectory.times is not None else None
    times = np.asarray(trajectory.times, dtype=float)
    bases = np.asarray(trajectory.base_positions, dtype=float)
    directions = np.asarray(trajectory.directions, dtype=float)
    directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    turn = np.arccos(np.clip(np.einsum("ij,ij->i", directions[:-1], directions[1:]), -1.0, 1.0))
    speeds = (np.linalg.norm(np.diff(bases, axis=0), axis=1) + needle_length * turn) / np.diff(times)
    return float(speeds.max())


#: Digits of a length that positions must keep: a length of the scene (a spacing, a radius, a distance), or a
#: step's motion, must be at least 10**RESOLVED_DIGITS float64 epsilons of the scene's largest coordinate.
RESOLVED_DIGITS = 3


def resolvable_length(scale: float) -> float:
    """The shortest length [m] positions of magnitude up to ``scale`` [m] resolve: 10**RESOLVED_DIGITS float64
    epsilons of ``scale``.

    Added to a position of size ``scale``, a shorter length keeps fewer than RESOLVED_DIGITS of its digits (a
    spacing of 1e-300 m between insertion or cut points makes points that coincide, a radius of 1e-300 m a
    section whose area underflows to 0), and the ratio of a scene length to a shorter one (points per d_c) is
    then beyond what any memory holds.
    """
    return 10.0**RESOLVED_DIGITS * float(np.finfo(float).eps) * float(scale)


def is_scene_length(field: dataclasses.Field) -> bool:
    """A strictly positive length key (unit m, range (0, ...]): a length the geometry adds to positions or
    divides lengths by."""
    meta = field.metadata
    return meta.get("unit") == "m" and meta.get("low") == 0.0 and bool(meta.get("low_open"))


def scene_lengths(scene: Scene):
    """Every length of the scene (section, key, value [m]): the strictly positive length keys of every
    section, each item of a vector key, which are set."""
    for section in SECTIONS:
        part = getattr(scene, section)
        for field in dataclasses.fields(part):
            value = getattr(part, field.name)
            if value is None or not is_scene_length(field):
                continue
            for item in np.ravel(np.asarray(value, dtype=float)):
                yield section, field.name, float(item)


def scene_scale(scene: Scene) -> float:
    """The scene's largest coordinate known without its mesh [m]: the needle's length, the box's far corner,
    the trajectory's base positions (plus the needle) or aimed entry (plus standoff and needle). A mesh file's
    coordinates are added when the mesh is read (refsim.scene.build)."""
    scale = scene.needle.length
    mesh = scene.mesh
    if mesh.size is not None:
        far = np.abs(np.asarray(mesh.origin, dtype=float)) + np.abs(np.asarray(mesh.size, dtype=float))
        scale = max(scale, float(far.max()))
    for instrument in scene.instrument_specs:
        trajectory, length = instrument.trajectory, instrument.needle.length
        scale = max(scale, length)
        if trajectory.base_positions is not None:
            bases = np.abs(np.asarray(trajectory.base_positions, dtype=float))
            scale = max(scale, float(bases.max()) + length)
        if trajectory.entry is not None:
            reach = float(np.abs(np.asarray(trajectory.entry, dtype=float)).max()) + trajectory.standoff
            scale = max(scale, reach + length)
    return scale


def check_scene_lengths(scene: Scene, scale: float | None = None) -> None:
    """Every length of the scene (:func:`scene_lengths`) at least :func:`resolvable_length` of the scene's
    largest coordinate, and at most LARGEST_COORDINATE.

    Parameters
    ----------
    scene : The scene.
    scale : The largest coordinate [m]; :func:`scene_scale` by default (with the mesh: also its coordinates).

    Raises
    ------
    ConsistencyError
        Naming the key, its value, the valid range and the scale it is relative to.
    """
    lengths = list(scene_lengths(scene))
    for section, key, value in lengths:  # first: the scale below is made of lengths too
        if value > LARGEST_COORDINATE:
            raise ConsistencyError(
                section,
                key,
                message=f"{key} = {value!r} m: expected a length <= {LARGEST_COORDINATE:g} m (the largest "
                "length and coordinate of a scene; beyond it squares and products of lengths approach "
                "float64's overflow)",
            )
    scale = scene_scale(scene) if scale is None else scale
    floor = resolvable_length(scale)
    for section, key, value in lengths:
        if value < floor:
            raise ConsistencyError(
                section,
                key,
                message=f"{key} = {value!r} m is below the shortest length the scene's positions resolve: "
                f"expected a length >= {floor:.3g} m ({10**RESOLVED_DIGITS} float64 epsilons of the scene's "
                f"largest coordinate, {scale:.3g} m); a shorter length is lost in round-off when added to "
                "positions",
            )


def check_instruments(scene: Scene) -> None:
    """Names unique; no instrument that cuts unless cutting.enabled."""
    seen: set[str] = set()
    for index, instrument in enumerate(scene.instruments):
        if instrument.name in seen:
            raise ConsistencyError(
                f"instruments[{index}]",
                "name",
                f"name = {instrument.name!r}: another instrument has this name; names must be unique",
            )
        seen.add(instrument.name)
        if instrument.cuts and not scene.cutting.enabled:
            raise ConsistencyError(
                f"instruments[{index}]",
                "cuts",
                "cuts = true: cutting.enabled is false (enable cutting, or leave cuts out)",
            )


def check_consistency(scene: Scene) -> None:
    """Checks across sections that need no mesh (the mesh-dependent ones are in `refsim.scene.build`).

    - d_i (insertion.spacing) shorter than the needle: otherwise at most one insertion point fits;
    - the tip's travel in one step (largest tip speed × dt) within insertion.contact_distance: a faster tip
      can jump across the contact zone, and the puncture force is never measured (dt = 1 s gave 139 N instead
      of 3.5 N). Travel beyond d_i is allowed (several points per step are created) but logged as a warning;
    - the cut surface spacing d_c shorter than the needle;
    - the channel's interference δ_r smaller than the needle's radius;
    - every length of the scene resolvable by its positions (:func:`check_scene_lengths`).

    Raises
    ------
    ConsistencyError
        Naming both keys, their values and what would be consistent.
    """
    logger = logging.getLogger("refsim.scene")
    check_instruments(scene)
    check_scene_lengths(scene)
    mesh = scene.mesh
    if (
        not mesh.fixed_faces
        and mesh.fixed_box is None
        and mesh.fixed_nodes is None
        and scene.boundary.motion == "none"
    ):
        raise ConsistencyError(
            "mesh",
            "fixed_faces",
            related=(("boundary", "motion"),),
            message="no fixed nodes: give mesh.fixed_faces, fixed_box or fixed_nodes, or a [boundary] motion "
            "(a free tissue "
            "has no static equilibrium)",
        )
    length = scene.needle.length
    spacing = scene.insertion.spacing
    if spacing >= length:
        raise ConsistencyError(
            "insertion",
            "spacing",
            related=(("needle", "length"),),
            message=f"spacing = {spacing!r} m (d_i) is not shorter than needle.length = {length!r} m: at "
            f"most one insertion "
            "point would fit on the needle; d_i is a fraction of a millimetre in the paper (0.5 mm)",
        )
    interference = scene.insertion.interference
    if interference >= scene.needle.radius:
        raise ConsistencyError(
            "insertion",
            "interference",
            related=(("needle", "radius"),),
            message=f"interference = {interference!r} m (the channel's radial interference delta_r) is not "
            f"smaller than "
            f"needle.radius = {scene.needle.radius!r} m: the channel's radius r - delta_r must be positive; "
            "delta_r is micrometres for a tight channel",
        )
    if scene.cutting.enabled and scene.cutting.point_spacing >= length:
        raise ConsistencyError(
            "cutting",
            "point_spacing",
            related=(("needle", "length"),),
            message=f"point_spacing = {scene.cutting.point_spacing!r} m (d_c) is not shorter than "
            f"needle.length = {length!r} m",
        )
    speeds = [max_tip_speed(each.trajectory, each.needle.length) for each in scene.instrument_specs]
    speed = max((value for value in speeds if value is not None), default=None)
    if speed:
        travel = speed * scene.time.dt
        contact = scene.insertion.contact_distance
        if travel > contact:
            raise ConsistencyError(
                "time",
                "dt",
                related=(
                    ("insertion", "contact_distance"),
                    ("trajectory", "times"),
                    ("trajectory", "base_positions"),
                    ("trajectory", "directions"),
                ),
                message=f"dt = {scene.time.dt!r} s: the needle tip moves up to {travel:.3g} m in one step "
                f"(speed {speed:.3g} "
                f"m/s along trajectory.times and base_positions), more than insertion.contact_distance = "
                f"{contact!r} m, so it can cross the contact zone "
                f"without its force being measured; use dt <= {contact / speed:.3g} s",
            )
        if travel > spacing:
            logger.warning(
                "time.dt = %g s: the needle tip moves up to %.3g m per step, more than insertion.spacing = "
                "%g m "
                "(d_i): several insertion points are created per step; dt <= %.3g s keeps one per step",
                scene.time.dt,
                travel,
                spacing,
                spacing / speed,
            )
