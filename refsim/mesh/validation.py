"""Validation of tetrahedral meshes, with errors that name the mesh and the defect."""

from __future__ import annotations

import logging

import numpy as np

from refsim.geometry.barycentric import signed_volumes

__all__ = [
    "DEGENERATE_VOLUME_RATIO",
    "DUPLICATE_NODE_TOLERANCE",
    "MeshError",
    "degenerate_tets",
    "merge_duplicate_nodes",
    "validate_mesh",
]

logger = logging.getLogger(__name__)

# A tetrahedron is degenerate when |volume| <= DEGENERATE_VOLUME_RATIO × (longest edge)³. A regular
# tetrahedron has volume / edge³ = 0.118 and a Kuhn tetrahedron of the box generator 0.032. The determinant's
# round-off is ~1e-16 relative, but an element with a ratio of 1e-10 already makes the stiffness matrix's
# condition number grow by ~1e9 and its rotation (polar decomposition) unreliable: such elements are refused.
# This is the one threshold of refsim: the mesh validation and the tissue model (refsim.fem.tissue) both use
# it.
DEGENERATE_VOLUME_RATIO = 1e-10
#: Nodes closer than this fraction of the mesh's bounding-box diagonal are duplicates (merged by `read_mesh`).
DUPLICATE_NODE_TOLERANCE = 1e-9
# Tetrahedron edges as pairs of local node indices.
_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
_TET_FACES = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
# The faces of a positively oriented tetrahedron, each ordered so that its right-hand normal points out of it
# (for the unit tetrahedron 0, e1, e2, e3: (e2 − e1) × (e3 − e1) = (1, 1, 1) for the face opposite node 0).
_TET_OUTWARD_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


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
    merge_duplicates: bool = False,
    return_node_map: bool = False,
) -> tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Check a tetrahedral mesh and return it as float64 positions and int64 tets.

    Parameters
    ----------
    rest_positions : Node positions [m], shape (node_count, 3).
    tets : Node indices of the tetrahedra, shape (tet_count, 4).
    source : File name or description, used in error messages.
    fix_orientation : Reorder the nodes of inverted (negative-volume) tetrahedra, swapping their last two
        nodes, with a logged warning; otherwise inverted tetrahedra are an error. Only a wrong node order
        is fixed: a tetrahedron inverted by the motion of a node (a tangled mesh: after the swap it lies on
        the same side of a face as its neighbour, the two overlap) is an error either way.
    drop_unused_nodes : Remove nodes used by no tetrahedron and renumber, with a logged warning; otherwise
        unused nodes are an error (they would make the stiffness matrix singular).
    merge_duplicates : Merge coincident nodes (`merge_duplicate_nodes`) with a logged warning; otherwise
        coincident nodes are an error.
    return_node_map : Also return where each input node went (merges and dropped nodes renumber them).

    Returns
    -------
    rest_positions : Node positions [m], shape (node_count, 3), float64.
    tets : Node indices, shape (tet_count, 4), int64, every tetrahedron of positive volume.
    node_map : Only with ``return_node_map``: the index in the returned mesh of each input node, shape
        (input node count,), int64; -1 for a node dropped as unused.

    Raises
    ------
    MeshError
        For bad shapes, no nodes or no tetrahedra, non-finite coordinates, indices out of range, zero-volume
        (degenerate) tetrahedra, faces shared by more than two tetrahedra, tangled (overlapping) tetrahedra,
        and, unless fixed, inverted tetrahedra and unused nodes.
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
    node_map = np.arange(node_count, dtype=np.int64)
    if merge_duplicates:
        merged_positions, merged_tets, merged = merge_duplicate_nodes(positions, tets, source=source)
        if merged:
            node_map = _merge_map(positions)
        positions, tets = merged_positions, merged_tets
    else:
        _check_duplicates(positions, source)
    tets = _check_volumes(positions, tets, source, fix_orientation)
    _check_faces(tets, source)
    positions, tets, renumber = _check_unused(positions, tets, source, drop_unused_nodes)
    if return_node_map:
        return positions, tets, renumber[node_map]
    return positions, tets


def degenerate_tets(rest_positions: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Indices of the degenerate tetrahedra: |volume| <= DEGENERATE_VOLUME_RATIO × (longest of 6 edges)³,
    (d,).

    Parameters
    ----------
    rest_positions : Node positions [m], shape (n, 3).
    tets : Node indices, shape (m, 4).
    """
    vertices = np.asarray(rest_positions, dtype=float)[np.asarray(tets)]
    volumes = signed_volumes(vertices)
    edges = vertices[:, _TET_EDGES[:, 1]] - vertices[:, _TET_EDGES[:, 0]]
    longest = np.sqrt(np.max(np.einsum("mei,mei->me", edges, edges), axis=1))
    return np.flatnonzero(np.abs(volumes) <= DEGENERATE_VOLUME_RATIO * longest**3)


def merge_duplicate_nodes(
    rest_positions: np.ndarray, tets: np.ndarray, *, source: str = "<array>"
) -> tuple[np.ndarray, np.ndarray, int]:
    """Merge nodes closer than DUPLICATE_NODE_TOLERANCE × the bounding-box diagonal; renumber the tets.

    Unmerged duplicates (a mesh exported without "coherence") split the tissue into loose elements that share
    no node: its stiffness falls apart. They are merged onto the first node of each cluster, with a logged
    warning giving the count; elements that become degenerate (two of their nodes merged) are then refused by
    the volume check.

    Returns
    -------
    rest_positions : Positions of the kept nodes [m], (n', 3).
    tets : Renumbered tets, (m, 4).
    merged : Number of nodes merged away.
    """
    positions = np.asarray(rest_positions, dtype=float)
    diagonal = float(np.linalg.norm(positions.max(axis=0) - positions.min(axis=0)))
    mapping = _merge_map(positions)
    count = positions.shape[0]
    keep = np.zeros(count, dtype=bool)
    keep[np.unique(mapping, return_index=True)[1]] = True  # each cluster keeps its smallest index
    merged = int(count - keep.sum())
    if merged == 0:
        return positions, np.asarray(tets), 0
    logger.warning(
        "%s: merged %d duplicate node(s) (closer than %.1e of the mesh size %.3g m); the mesh had "
        "unconnected "
        "elements at those nodes",
        source,
        merged,
        DUPLICATE_NODE_TOLERANCE,
        diagonal,
    )
    return positions[keep], mapping[np.asarray(tets)], merged


def _merge_map(positions: np.ndarray) -> np.ndarray:
    """The index of each node after merging duplicates (clusters onto their smallest index, then
    renumbered in order), shape (n,)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    count = positions.shape[0]
    diagonal = float(np.linalg.norm(positions.max(axis=0) - positions.min(axis=0)))
    pairs = cKDTree(positions).query_pairs(
        DUPLICATE_NODE_TOLERANCE * max(diagonal, 1e-300), output_type="ndarray"
    )
    if pairs.size == 0:
        return np.arange(count, dtype=np.int64)
    # Union the pairs (connected components) and map each node onto the smallest index of its cluster.
    graph = coo_matrix((np.ones(pairs.shape[0]), (pairs[:, 0], pairs[:, 1])), shape=(count, count))
    _, labels = connected_components(graph, directed=False)
    first = np.full(labels.max() + 1, count, dtype=np.int64)
    np.minimum.at(first, labels, np.arange(count))
    representative = first[labels]
    keep = representative == np.arange(count)
    renumber = np.cumsum(keep) - 1
    return renumber[representative].astype(np.int64)


def _check_volumes(positions: np.ndarray, tets: np.ndarray, source: str, fix_orientation: bool) -> np.ndarray:
    vertices = positions[tets]
    volumes = signed_volumes(vertices)
    degenerate = degenerate_tets(positions, tets)
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
        tets = tets.copy()
        tets[inverted] = tets[inverted][:, [0, 1, 3, 2]]
        _check_folds(tets, inverted, source)
        logger.warning(
            "%s: fixed the orientation of %d inverted tetrahedra (swapped two nodes: the file listed them in "
            "the other order; no element overlaps another)",
            source,
            inverted.size,
        )
    return tets


def _check_folds(tets: np.ndarray, swapped: np.ndarray, source: str) -> None:
    """Refuse a tangled mesh: two positively oriented tetrahedra that share a face must lie on its two sides,
    so they see the face with opposite orientations; the same orientation means both lie on one side and
    overlap (a node was moved through a face of its element). ``tets`` are oriented (all volumes > 0);
    ``swapped`` the tetrahedra whose nodes were reordered."""
    faces = tets[:, _TET_OUTWARD_FACES].reshape(-1, 3)
    # Orientation of each face relative to its sorted node order: the parity of the sorting permutation.
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    parity = ((a > b).astype(np.int8) + (a > c) + (b > c)) % 2
    _, inverse, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    shared = counts[inverse[order]] == 2
    pairs = order[shared].reshape(-1, 2)  # the two (tet, face) entries of every interior face
    folded = pairs[parity[pairs[:, 0]] == parity[pairs[:, 1]]]
    if folded.size == 0:
        return
    tets_folded = np.unique(folded // 4)
    first = folded[0] // 4
    face = np.sort(faces[folded[0, 0]]).tolist()
    raise MeshError(
        source,
        f"the mesh is tangled: {tets_folded.size} tetrahedra overlap a neighbour (tets "
        f"{_first(tets_folded)}; "
        f"e.g. tets {int(first[0])} and {int(first[1])} lie on the same side of their shared face {face}). "
        f"{np.isin(tets_folded, swapped).sum()} of them had a negative volume: a node moved through a face "
        "of its element (a smoothing or a morph), which swapping nodes cannot repair (the overlap would be "
        "counted twice); untangle the mesh in the mesher",
    )


def _check_duplicates(positions: np.ndarray, source: str) -> None:
    from scipy.spatial import cKDTree

    diagonal = float(np.linalg.norm(positions.max(axis=0) - positions.min(axis=0)))
    pairs = cKDTree(positions).query_pairs(
        DUPLICATE_NODE_TOLERANCE * max(diagonal, 1e-300), output_type="ndarray"
    )
    if pairs.size:
        raise MeshError(
            source,
            f"{pairs.shape[0]} pair(s) of coincident nodes (closer than {DUPLICATE_NODE_TOLERANCE:g} of the "
            f"mesh "
            f"size), e.g. nodes {pairs[0].tolist()}: elements there share no node (read_mesh merges them)",
        )


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
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions, tets and the new index of each node (-1 when dropped), after dropping unused nodes."""
    used = np.zeros(positions.shape[0], dtype=bool)
    used[tets.reshape(-1)] = True
    unused = np.flatnonzero(~used)
    if unused.size == 0:
        return positions, tets, np.arange(positions.shape[0], dtype=np.int64)
    if not drop_unused_nodes:
        raise MeshError(source, f"{unused.size} node(s) used by no tetrahedron: nodes {_first(unused)}")
    logger.warning(
        "%s: dropped %d node(s) used by no tetrahedron (nodes %s) and renumbered the others; node indices "
        "given in the scene (mesh.fixed_nodes, boundary.nodes) refer to the file's numbering and are "
        "renumbered with them",
        source,
        unused.size,
        _first(unused),
    )
    renumber = np.where(used, np.cumsum(used) - 1, -1).astype(np.int64)
    return positions[used], renumber[tets], renumber
