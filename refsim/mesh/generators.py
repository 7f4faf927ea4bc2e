"""Mesh generators."""

from __future__ import annotations

import itertools

import numpy as np

from refsim.mesh.tetmesh import TetMesh

__all__ = ["box_mesh"]


def _kuhn_tets() -> np.ndarray:
    """The six Kuhn (Freudenthal) tetrahedra of the unit cube as local corner numbers, positively oriented.

    Corner (a, b, c) ∈ {0, 1}³ has local number a + 2 b + 4 c. Tetrahedron π runs from corner (0, 0, 0) to
    (1, 1, 1) adding one unit vector at a time, in the order of the axis permutation π; all six share the main
    diagonal, and the same split in every cell is conforming (the faces on each cell face match those of the
    neighbour). Its orientation is the sign of π, so odd permutations swap their last two nodes.
    """
    tets = []
    for permutation in itertools.permutations(range(3)):
        corner = np.zeros(3, dtype=int)
        path = [0]
        for axis in permutation:
            corner[axis] = 1
            path.append(int(corner @ [1, 2, 4]))
        inversions = sum(permutation[i] > permutation[j] for i in range(3) for j in range(i + 1, 3))
        if inversions % 2:
            path[2], path[3] = path[3], path[2]
        tets.append(path)
    return np.array(tets, dtype=np.int64)


_KUHN_TETS = _kuhn_tets()


def box_mesh(
    *,
    size: tuple[float, float, float] = (0.1, 0.1, 0.1),
    cells: tuple[int, int, int] = (8, 8, 8),
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> TetMesh:
    """An axis-aligned box of hexahedral cells, each split into six tetrahedra (Kuhn split).

    Parameters
    ----------
    size : Edge lengths of the box along x, y, z [m], each > 0.
    cells : Number of hexahedral cells along x, y, z, each an integer >= 1. The default (8, 8, 8) on a
        0.1 m cube is the paper's mesh: 729 nodes, 3,072 tetrahedra.
    origin : Position of the box corner with the smallest coordinates [m].

    Returns
    -------
    The mesh; node (i, j, k) of the grid has index i + (nx + 1) (j + (ny + 1) k).
    """
    size_array = np.asarray(size, dtype=float)
    origin_array = np.asarray(origin, dtype=float)
    if size_array.shape != (3,) or not np.all(np.isfinite(size_array)) or not np.all(size_array > 0):
        raise ValueError(f"size must be 3 finite lengths > 0 [m], got {size!r}")
    if origin_array.shape != (3,) or not np.all(np.isfinite(origin_array)):
        raise ValueError(f"origin must be 3 finite coordinates [m], got {origin!r}")
    cells_array = np.asarray(cells)
    if (
        cells_array.shape != (3,)
        or not np.issubdtype(cells_array.dtype, np.integer)
        or not np.all(cells_array >= 1)
    ):
        raise ValueError(f"cells must be 3 integers >= 1, got {cells!r}")
    nx, ny, nz = (int(c) for c in cells_array)

    axes = [
        origin_array[d] + size_array[d] * np.linspace(0.0, 1.0, int(cells_array[d]) + 1) for d in range(3)
    ]
    grid_z, grid_y, grid_x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    positions = np.stack([grid_x.ravel(), grid_y.ravel(), grid_z.ravel()], axis=1)

    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    base = (i + (nx + 1) * (j + (ny + 1) * k)).ravel()  # (cell_count,) lowest corner of each cell
    corner_offsets = np.array(
        [a + (nx + 1) * (b + (ny + 1) * c) for c in (0, 1) for b in (0, 1) for a in (0, 1)]
    )
    tets = (base[:, None, None] + corner_offsets[_KUHN_TETS][None, :, :]).reshape(-1, 4)
    source = f"box_mesh(size={size_array.tolist()} m, cells={[nx, ny, nz]}, origin={origin_array.tolist()} m)"
    return TetMesh(positions, tets, source=source)
