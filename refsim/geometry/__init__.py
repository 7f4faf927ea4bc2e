"""Geometry kernels (layer 0): rotations, barycentric coordinates, closest points and spatial search."""

from refsim.geometry.barycentric import signed_volumes, tet_barycentric
from refsim.geometry.closest import closest_points_on_segments, closest_points_on_triangles, triangle_normals
from refsim.geometry.rotations import (
    needle_rest_frame,
    polar_rotation,
    rotation_matrix,
    rotation_vector,
    skew,
)
from refsim.geometry.search import ClosestSurfacePoints, SurfaceProjector, TetLocator, tet_boundary_faces

__all__ = [
    "needle_rest_frame",
    "ClosestSurfacePoints",
    "SurfaceProjector",
    "TetLocator",
    "closest_points_on_segments",
    "closest_points_on_triangles",
    "polar_rotation",
    "rotation_matrix",
    "rotation_vector",
    "signed_volumes",
    "skew",
    "tet_barycentric",
    "tet_boundary_faces",
    "triangle_normals",
]
