"""The tetrahedral mesh record."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from refsim.geometry.barycentric import signed_volumes
from refsim.mesh.surface import boundary_faces
from refsim.mesh.validation import validate_mesh

__all__ = ["TetMesh"]


@dataclass(frozen=True, eq=False)
class TetMesh:
    """A validated linear tetrahedral mesh in its rest configuration.

    Construction validates the arrays (`validate_mesh`, strict: no inverted tetrahedra, no unused nodes) and
    stores read-only float64 / int64 copies.
    """

    rest_positions: np.ndarray
    """Node positions at rest [m], shape (node_count, 3)."""
    tets: np.ndarray
    """Node indices of the tetrahedra, shape (tet_count, 4), positively oriented."""
    source: str = "<array>"
    """File the mesh was read from, or a description of the generator and its parameters."""
    node_map: np.ndarray | None = None
    """For a mesh read from a file whose nodes were renumbered (duplicates merged, unused nodes dropped): the
    index in this mesh of each node of the file, shape (file node count,), -1 for a dropped node; None when
    the numbering is the file's. Node indices a scene gives in the file's numbering go through it."""

    def __post_init__(self) -> None:
        positions, tets = validate_mesh(self.rest_positions, self.tets, source=self.source)
        positions = positions.copy()
        tets = tets.copy()
        positions.flags.writeable = False
        tets.flags.writeable = False
        object.__setattr__(self, "rest_positions", positions)
        object.__setattr__(self, "tets", tets)
        if self.node_map is not None:
            node_map = np.array(self.node_map, dtype=np.int64)
            if node_map.ndim != 1 or np.any(node_map < -1) or np.any(node_map >= positions.shape[0]):
                raise ValueError(
                    f"{self.source}: node_map must be 1-D with values in [-1, {positions.shape[0] - 1}]"
                )
            node_map.flags.writeable = False
            object.__setattr__(self, "node_map", node_map)

    def file_nodes(self, indices, *, key: str = "node indices") -> np.ndarray:
        """Mesh node indices of nodes given in the file's numbering (``node_map``), shape (k,).

        Parameters
        ----------
        indices : Node indices as the mesh file numbers them, 0-based, shape (k,).
        key : What the indices are (e.g. "mesh.fixed_nodes"), for messages.

        Raises
        ------
        ValueError
            Naming ``key``, the index and the valid range, when an index is out of the file's range or names
            a node that was dropped (used by no tetrahedron).
        """
        indices = np.asarray(indices, dtype=np.int64).reshape(-1)
        count = self.node_count if self.node_map is None else self.node_map.shape[0]
        bad = indices[(indices < 0) | (indices >= count)]
        if bad.size:
            raise ValueError(
                f"{key} contains {int(bad[0])}: the mesh {self.source} has {count} nodes (indices 0 .. "
                f"{count - 1})"
            )
        if self.node_map is None:
            return indices
        mapped = self.node_map[indices]
        dropped = indices[mapped < 0]
        if dropped.size:
            raise ValueError(
                f"{key} contains {int(dropped[0])}: node {int(dropped[0])} of {self.source} is used by no "
                "tetrahedron (dropped when the mesh was read), so it is not part of the tissue"
            )
        return mapped

    @property
    def node_count(self) -> int:
        """Number of nodes."""
        return int(self.rest_positions.shape[0])

    @property
    def tet_count(self) -> int:
        """Number of tetrahedra."""
        return int(self.tets.shape[0])

    @cached_property
    def volumes(self) -> np.ndarray:
        """Rest volumes of the tetrahedra [m³], shape (tet_count,), all positive."""
        volumes = signed_volumes(self.rest_positions[self.tets])
        volumes.flags.writeable = False
        return volumes

    @property
    def bounds(self) -> np.ndarray:
        """Axis-aligned bounding box [m], shape (2, 3): minimum corner, maximum corner."""
        return np.stack([self.rest_positions.min(axis=0), self.rest_positions.max(axis=0)])

    @cached_property
    def boundary_faces(self) -> np.ndarray:
        """Boundary triangles oriented outward, shape (face_count, 3) (see `refsim.mesh.boundary_faces`)."""
        faces = boundary_faces(self.tets, self.rest_positions)
        faces.flags.writeable = False
        return faces

    @cached_property
    def boundary_nodes(self) -> np.ndarray:
        """Sorted indices of the nodes on the boundary surface, shape (boundary_node_count,)."""
        nodes = np.unique(self.boundary_faces)
        nodes.flags.writeable = False
        return nodes

    def translated(self, offset: np.ndarray) -> TetMesh:
        """The mesh moved by an offset.

        Parameters
        ----------
        offset : Translation [m], shape (3,).
        """
        offset = np.asarray(offset, dtype=float)
        if offset.shape != (3,) or not np.all(np.isfinite(offset)):
            raise ValueError(f"offset must be 3 finite numbers [m], got {offset!r}")
        return TetMesh(
            self.rest_positions + offset,
            self.tets,
            source=f"{self.source}, translated by {offset.tolist()} m",
            node_map=self.node_map,
        )

    def scaled(self, factor: float | np.ndarray) -> TetMesh:
        """The mesh scaled about the origin (e.g. 1e-3 to convert millimetres to metres).

        Parameters
        ----------
        factor : Scale factor (dimensionless, > 0), a number or one per axis, shape (3,).
        """
        factor = np.asarray(factor, dtype=float)
        if factor.shape not in ((), (3,)) or not np.all(np.isfinite(factor)) or not np.all(factor > 0):
            raise ValueError(f"factor must be a positive finite number or 3 of them, got {factor!r}")
        return TetMesh(
            self.rest_positions * factor,
            self.tets,
            source=f"{self.source}, scaled by {factor.tolist()}",
            node_map=self.node_map,
        )
