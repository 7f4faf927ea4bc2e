"""Validation of tetrahedral meshes, with errors that name the mesh and the defect."""

from __future__ import annotations

import logging

import numpy as np

from refsim.geometry.barycentric import signed_volumes

__all__ = ["MeshError", "validate_mesh"]

logger = logging.getLogger(__name__)

# A tetrahedron is degenerate when |volume| <= _DEGENERATE_VOLUME × (longest edge)³. A regular tetrahedron has
# volume / edge³ = 0.118 and a Kuhn tetrahedron of the box generator 0.032; the determinant's round-off is
# ~1e-16 relative, so 1e-12 flags only elements that are flat to within round-off of their own size.
_DEGENERATE_VOLUME = 1e-12
# Tetrahedron edges as pairs of local node indices.
_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
_TET_FACES = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])


class MeshError(ValueError):
    """A mesh (file or arrays) with a defect; the message names the source and the defect.

    Parameters
    ----------
    source : File name or description of the mesh.
    defect : What is wrong, with the offending indices or values.
    """

    def __init__(self, source: str, defect: str):
        super().__init__(f"{source}: {defect}")
        self.source = source
        self.defect = defect


def _first(indices: np.ndarray, limit: int = 5) -> str:
    shown = ", ".join(str(int(i)) for i in indices[:limit])
    return shown + (", ..." if indices.shape[0] > limit else "")


def _check_shapes(rest_positions, tets, source: str) -> tuple[np.ndarray, np.ndarray]:
    try:
        positions = np.array(rest_positions, dtype=float)
    except (TypeError, ValueError) as error:
        raise MeshError(source, f"node coordinates are not numbers ({error})") from None
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise MeshError(source, f"rest_positions must have shape (node_count, 3), got {positions.shape}")
    if positions.shape[0] == 0:
        raise MeshError(source, "the mesh has no nodes")
    tets = np.asarray(tets)
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise MeshError(source, f"tets must have shape (tet_count, 4), got {tets.shape}")
    if tets.shape[0] == 0:
        raise MeshError(source, "the mesh has no tetrahedra")
    if not np.issubdtype(tets.dtype, np.integer):
        raise MeshError(source, f"tets must hold integer node indices, got dtype {tets.dtype}")
    return positions, tets.astype(np.int64)


def validate_mesh(
    rest_positions: np.ndarray,
    tets: np.ndarray,
    *,
    source: str = "<array>",
    fix_orientation: bool = False,
    drop_unused_nodes: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Check a tetrahedral mesh and return it as float64 positions and int64 tets.

    Parameters
    ----------
    rest_positions : Node positions [m], shape (node_count, 3).
    tets : Node indices of the tetrahedra, shape (tet_count, 4).
    source : File name or description, used in error messages.
    fix_orientation : Reorder the nodes of inverted (negative-volume) tetrahedra, swapping their last two
        nodes, with a logged warning; otherwise inverted tetrahedra are an error.
    drop_unused_nodes : Remove nodes used by no tetrahedron and renumber, with a logged warning; otherwise
        unused nodes are an error (they would make the stiffness matrix singular).

    Returns
    -------
    rest_positions : Node positions [m], shape (node_count, 3), float64.
    tets : Node indices, shape (tet_count, 4), int64, every tetrahedron of positive volume.

    Raises
    ------
    MeshError
        For bad shapes, no nodes or no tetrahedra, non-finite coordinates, indices out of range, zero-volume
        (degenerate) tetrahedra, faces shared by more than two tetrahedra, and, unless fixed, inverted
        tetrahedra and unused nodes.
    """
    positions, tets = _check_shapes(rest_positions, tets, source)
    node_count = positions.shape[0]
    bad_nodes = np.flatnonzero(~np.all(np.isfinite(positions), axis=1))
    if bad_nodes.size:
        raise MeshError(
            source, f"{bad_nodes.size} node(s) with non-finite coordinates: nodes {_first(bad_nodes)}"
        )
    out_of_range = np.flatnonzero(np.any((tets < 0) | (tets >= node_count), axis=1))
    if out_of_range.size:
        values = tets[out_of_range][(tets[out_of_range] < 0) | (tets[out_of_range] >= node_count)]
        raise MeshError(
            source,
            f"{out_of_range.size} tetrahedra with node indices out of range [0, {node_count - 1}]: "
            f"tets {_first(out_of_range)} (indices {_first(values)})",
        )
    tets = _check_volumes(positions, tets, source, fix_orientation)
    _check_faces(tets, source)
    return _check_unused(positions, tets, source, drop_unused_nodes)


def _check_volumes(positions: np.ndarray, tets: np.ndarray, source: str, fix_orientation: bool) -> np.ndarray:
    vertices = positions[tets]
    volumes = signed_volumes(vertices)
    edges = vertices[:, _TET_EDGES[:, 1]] - vertices[:, _TET_EDGES[:, 0]]
    longest = np.sqrt(np.max(np.einsum("mei,mei->me", edges, edges), axis=1))
    degenerate = np.flatnonzero(np.abs(volumes) <= _DEGENERATE_VOLUME * longest**3)
    if degenerate.size:
        raise MeshError(
            source,
            f"{degenerate.size} degenerate (zero-volume) tetrahedra: tets {_first(degenerate)} "
            f"(volumes {', '.join(f'{v:.3g}' for v in volumes[degenerate[:5]])} m³)",
        )
    inverted = np.flatnonzero(volumes < 0.0)
    if inverted.size:
        if not fix_orientation:
            raise MeshError(
                source, f"{inverted.size} inverted (negative-volume) tetrahedra: tets {_first(inverted)}"
            )
        logger.warning(
            "%s: fixed the orientation of %d inverted tetrahedra (swapped two nodes)", source, inverted.size
        )
        tets = tets.copy()
        tets[inverted] = tets[inverted][:, [0, 1, 3, 2]]
    return tets


def _check_faces(tets: np.ndarray, source: str) -> None:
    keys = np.sort(tets[:, _TET_FACES].reshape(-1, 3), axis=1)
    unique, counts = np.unique(keys, axis=0, return_counts=True)
    overused = np.flatnonzero(counts > 2)
    if overused.size:
        raise MeshError(
            source,
            f"{overused.size} faces shared by more than two tetrahedra (overlapping or duplicated elements), "
            f"e.g. nodes {unique[overused[0]].tolist()}",
        )


def _check_unused(
    positions: np.ndarray, tets: np.ndarray, source: str, drop_unused_nodes: bool
) -> tuple[np.ndarray, np.ndarray]:
    used = np.zeros(positions.shape[0], dtype=bool)
    used[tets.reshape(-1)] = True
    unused = np.flatnonzero(~used)
    if unused.size == 0:
        return positions, tets
    if not drop_unused_nodes:
        raise MeshError(source, f"{unused.size} node(s) used by no tetrahedron: nodes {_first(unused)}")
    logger.warning("%s: dropped %d node(s) used by no tetrahedron and renumbered", source, unused.size)
    renumber = np.cumsum(used) - 1
    return positions[used], renumber[tets]
