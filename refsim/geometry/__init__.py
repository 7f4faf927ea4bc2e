"""Geometry kernels (layer 0): rotations, barycentric coordinates, closest points and spatial search."""

from refsim.geometry.rotations import polar_rotation, rotation_matrix, rotation_vector, skew

__all__ = ["polar_rotation", "rotation_matrix", "rotation_vector", "skew"]
