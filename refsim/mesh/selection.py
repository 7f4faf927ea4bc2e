"""Choosing tissue nodes on a mesh surface: a patch near a point or a plane (e.g. an organ's fixed nodes),
or the part of the surface facing a direction (e.g. an organ's face under the diaphragm)."""

from __future__ import annotations

import numpy as np

__all__ = ["facing_surface", "surface_patch"]


def surface_patch(
    rest_positions: np.ndarray,
    boundary_faces: np.ndarray,
    *,
    distance: float,
    point=None,
    plane=None,
) -> np.ndarray:
    """Surface nodes within a distance of a point or of a plane.

    Only nodes of the boundary surface are candidates, so a patch never takes a node inside the organ (unlike
    a box). Give exactly one of ``point`` and ``plane``.

    Parameters
    ----------
    rest_positions : Node positions at rest [m], shape (node_count, 3).
    boundary_faces : Boundary triangles (node indices), shape (face_count, 3), e.g.
        ``TetMesh.boundary_faces``.
    distance : Largest distance [m] from the point (Euclidean) or from the plane (unsigned,
        |(x − p)·n|), >= 0.
    point : Centre of a spherical patch [m], shape (3,).
    plane : ``(origin, normal)``: a point of the plane [m], shape (3,), and its normal, shape (3,), non-zero
        (normalised here).

    Returns
    -------
    Sorted indices of the selected surface nodes, shape (selected_count,), int64; empty when none is near.

    Raises
    ------
    ValueError
        When both or neither of ``point`` and ``plane`` are given, or a value has the wrong shape, is not
        finite, or ``distance`` is negative, naming the argument and the value.
    """
    positions, faces = _checked_surface(rest_positions, boundary_faces)
    if not (np.isfinite(distance) and distance >= 0.0):
        raise ValueError(f"distance = {distance} m: expected a finite distance >= 0")
    if (point is None) == (plane is None):
        raise ValueError("give exactly one of point= (a spherical patch) and plane= (origin, normal)")
    nodes = np.unique(faces)
    candidates = positions[nodes]
    if point is not None:
        centre = _vector(point, "point")
        gap = np.linalg.norm(candidates - centre, axis=1)
    else:
        try:
            origin, normal = plane
        except (TypeError, ValueError):
            raise ValueError(f"plane = {plane!r}: expected (origin, normal), two 3-vectors") from None
        origin, normal = _vector(origin, "plane origin"), _vector(normal, "plane normal")
        length = np.linalg.norm(normal)
        if length == 0.0:
            raise ValueError("plane normal is zero: expected a non-zero 3-vector")
        gap = np.abs((candidates - origin) @ (normal / length))
    return nodes[gap <= distance].astype(np.int64)


def facing_surface(
    rest_positions: np.ndarray, boundary_faces: np.ndarray, *, direction, angle: float
) -> np.ndarray:
    """Surface nodes whose outward normal lies within ``angle`` of ``direction``.

    A node's outward normal is the area-weighted sum of the outward normals of the boundary triangles that
    use it (the triangles' ``(b − a) × (c − a)``, which `refsim.mesh.boundary_faces` points out of the
    mesh), normalised. The selection is a face of the organ whatever its size or position: e.g. its
    superior (diaphragmatic) face for ``direction`` cranial and ``angle`` 45°.

    Parameters
    ----------
    rest_positions : Node positions at rest [m], shape (node_count, 3).
    boundary_faces : Boundary triangles oriented outward (node indices), shape (face_count, 3).
    direction : The direction the selected face looks towards, shape (3,), non-zero (normalised here).
    angle : Largest angle [degrees] between a node's outward normal and ``direction``, in (0, 180).

    Returns
    -------
    Sorted indices of the selected surface nodes, shape (selected_count,), int64; empty when none faces
    ``direction``.

    Raises
    ------
    ValueError
        When a value has the wrong shape, is not finite, the direction is zero or the angle is outside
        (0, 180) degrees, naming the argument and the value.
    """
    positions, faces = _checked_surface(rest_positions, boundary_faces)
    axis = _vector(direction, "direction")
    length = np.linalg.norm(axis)
    if length == 0.0:
        raise ValueError("direction is zero: expected a non-zero 3-vector")
    if not (np.isfinite(angle) and 0.0 < angle < 180.0):
        raise ValueError(f"angle = {angle} degrees: expected an angle in (0, 180)")
    corners = positions[faces]
    area_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals = np.zeros_like(positions)
    for corner in range(3):  # three scatter-adds over the faces, vectorised
        np.add.at(normals, faces[:, corner], area_normals)
    nodes = np.unique(faces)
    lengths = np.linalg.norm(normals[nodes], axis=1)
    cosines = (normals[nodes] @ (axis / length)) / np.where(lengths > 0.0, lengths, 1.0)
    return nodes[(lengths > 0.0) & (cosines >= np.cos(np.radians(angle)))].astype(np.int64)


def _checked_surface(rest_positions, boundary_faces) -> tuple[np.ndarray, np.ndarray]:
    positions = np.asarray(rest_positions, dtype=float)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"rest_positions must have shape (node_count, 3), got {positions.shape}")
    faces = np.asarray(boundary_faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(
            f"boundary_faces must be integers of shape (face_count, 3), got {faces.dtype} {faces.shape}"
        )
    if faces.size and (faces.min() < 0 or faces.max() >= positions.shape[0]):
        raise ValueError(f"boundary_faces hold node indices outside [0, {positions.shape[0] - 1}]")
    return positions, faces


def _vector(value, name: str) -> np.ndarray:
    try:
        vector = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} = {value!r}: expected 3 numbers [m]") from None
    if vector.shape != (3,) or not np.all(np.isfinite(vector)):
        raise ValueError(f"{name} = {value!r}: expected 3 finite numbers [m]")
    return vector
