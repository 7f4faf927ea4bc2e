"""The box generator: counts, volumes, conformity (Kuhn split) and argument checks."""

import numpy as np
import pytest

from refsim.mesh import box_mesh, is_closed_surface


def test_paper_cube():
    # DESIGN.md: a 0.10 m cube, 8 × 8 × 8 hexahedra, 6 tets each: 3,072 tets on 9³ = 729 nodes.
    mesh = box_mesh(size=(0.1, 0.1, 0.1), cells=(8, 8, 8))
    assert (mesh.node_count, mesh.tet_count) == (729, 3072)
    # Every Kuhn tet has volume h³/6, h = 0.0125 m.
    np.testing.assert_allclose(mesh.volumes, 0.0125**3 / 6.0, rtol=1e-12)
    assert mesh.volumes.sum() == pytest.approx(1e-3, rel=1e-13)


@pytest.mark.parametrize("cells", [(1, 1, 1), (2, 3, 4), (5, 1, 2)])
def test_conforming_closed_box(cells):
    nx, ny, nz = cells
    size = (0.3, 0.2, 0.05)
    mesh = box_mesh(size=size, cells=cells, origin=(-1.0, 2.0, 0.5))
    assert mesh.tet_count == 6 * nx * ny * nz
    assert mesh.volumes.sum() == pytest.approx(np.prod(size), rel=1e-13)
    np.testing.assert_allclose(mesh.bounds, [[-1.0, 2.0, 0.5], [-0.7, 2.2, 0.55]], rtol=1e-15)
    # Conforming: each interior face is shared by exactly two tets, so only the box faces are boundary, two
    # triangles per cell face; a non-conforming split would leave unmatched faces inside.
    assert mesh.boundary_faces.shape[0] == 4 * (nx * ny + ny * nz + nz * nx)
    assert is_closed_surface(mesh.boundary_faces)
    interior = max(nx - 1, 0) * max(ny - 1, 0) * max(nz - 1, 0)
    assert mesh.boundary_nodes.shape[0] == mesh.node_count - interior
    corners = mesh.rest_positions[mesh.boundary_faces]
    on_box = np.isclose(corners, mesh.bounds[0]) | np.isclose(corners, mesh.bounds[1])
    assert np.all(np.any(np.all(on_box, axis=1), axis=1))  # each boundary face lies in a box face


def test_node_numbering():
    mesh = box_mesh(size=(1.0, 2.0, 3.0), cells=(2, 3, 4))
    i, j, k = 1, 2, 3
    np.testing.assert_allclose(mesh.rest_positions[i + 3 * (j + 4 * k)], [0.5, 4 / 3, 2.25], rtol=1e-15)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"size": (1.0, 0.0, 1.0)}, "size"),
        ({"size": (1.0, 1.0)}, "size"),
        ({"size": (1.0, np.inf, 1.0)}, "size"),
        ({"cells": (1, 0, 1)}, "cells"),
        ({"cells": (1.5, 1, 1)}, "cells"),
        ({"origin": (0.0, np.nan, 0.0)}, "origin"),
    ],
)
def test_bad_arguments(kwargs, field):
    with pytest.raises(ValueError, match=field):
        box_mesh(**kwargs)
