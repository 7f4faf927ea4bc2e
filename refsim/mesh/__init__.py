"""Tetrahedral meshes (layer 1): the mesh record, generators (a box, a liver phantom), file I/O,
validation, quality, boundary surfaces and surface patches."""

from refsim.mesh.generators import box_mesh
from refsim.mesh.io import read_mesh, write_mesh
from refsim.mesh.phantom import (
    LIVER_PHANTOM_RESOLUTIONS,
    MeshQuality,
    generate_liver_phantom,
    liver_phantom,
    liver_phantom_path,
    mesh_quality,
)
from refsim.mesh.selection import facing_surface, surface_patch
from refsim.mesh.surface import boundary_faces, is_closed_surface, surface_edges
from refsim.mesh.tetmesh import TetMesh
from refsim.mesh.validation import MeshError, validate_mesh

__all__ = [
    "LIVER_PHANTOM_RESOLUTIONS",
    "MeshQuality",
    "generate_liver_phantom",
    "liver_phantom",
    "liver_phantom_path",
    "mesh_quality",
    "facing_surface",
    "surface_patch",
    "MeshError",
    "TetMesh",
    "boundary_faces",
    "box_mesh",
    "is_closed_surface",
    "read_mesh",
    "surface_edges",
    "validate_mesh",
    "write_mesh",
]
