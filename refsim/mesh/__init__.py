"""Tetrahedral meshes (layer 1): the mesh record, generators, file I/O, validation and boundary surfaces."""

from refsim.mesh.generators import box_mesh
from refsim.mesh.io import read_mesh, write_mesh
from refsim.mesh.surface import boundary_faces, is_closed_surface, surface_edges
from refsim.mesh.tetmesh import TetMesh
from refsim.mesh.validation import MeshError, validate_mesh

__all__ = [
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
