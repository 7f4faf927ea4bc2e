"""Mesh validation: every defect gives a MeshError naming the source and the defect; the TetMesh record."""

import logging

import numpy as np
import pytest

from refsim.mesh import MeshError, TetMesh, validate_mesh

UNIT = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
TWO_TETS = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])  # positively oriented, sharing face (1, 2, 3)


def test_valid_mesh_is_returned_as_float64_and_int64():
    positions, tets = validate_mesh(UNIT.astype(np.float32), TWO_TETS.astype(np.int32))
    assert positions.dtype == np.float64 and tets.dtype == np.int64
    np.testing.assert_array_equal(tets, TWO_TETS)


@pytest.mark.parametrize(
    ("positions", "tets", "defect"),
    [
        (UNIT[:, :2], TWO_TETS, r"shape \(node_count, 3\)"),
        (np.zeros((0, 3)), TWO_TETS, "no nodes"),
        (UNIT, TWO_TETS[:, :3], r"shape \(tet_count, 4\)"),
        (UNIT, np.zeros((0, 4), dtype=int), "no tetrahedra"),
        (UNIT, TWO_TETS.astype(float), "integer"),
        (np.where(np.arange(5)[:, None] == 2, np.nan, UNIT), TWO_TETS, "non-finite coordinates: nodes 2"),
        (UNIT, np.array([[0, 1, 2, 3], [1, 2, 3, 5]]), r"out of range \[0, 4\]: tets 1 \(indices 5\)"),
        (UNIT, np.array([[0, 1, 2, 3], [-1, 2, 3, 4]]), r"out of range.*indices -1"),
        (UNIT, np.array([[0, 1, 2, 3], [1, 2, 2, 4]]), "degenerate.*tets 1"),
        (np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 1e-13]]), TWO_TETS[:1], "degenerate"),
        (UNIT, np.array([[0, 1, 2, 3], [1, 3, 2, 4]]), "inverted.*tets 1"),
        (UNIT, np.array([[0, 1, 2, 3], [0, 1, 2, 3], [1, 2, 3, 4]]), "more than two"),
        (np.concatenate([UNIT, [[5.0, 5, 5]]]), TWO_TETS, "used by no tetrahedron: nodes 5"),
    ],
)
def test_defects_are_named(positions, tets, defect):
    with pytest.raises(MeshError, match=defect) as error:
        validate_mesh(positions, tets, source="organ.msh")
    assert str(error.value).startswith("organ.msh: ")
    assert isinstance(error.value, ValueError)


def test_fix_orientation_swaps_two_nodes_with_a_warning(caplog):
    inverted = np.array([[0, 1, 2, 3], [1, 3, 2, 4]])
    with caplog.at_level(logging.WARNING, logger="refsim.mesh"):
        _, tets = validate_mesh(UNIT, inverted, source="organ.msh", fix_orientation=True)
    assert "organ.msh" in caplog.text and "1 inverted" in caplog.text
    np.testing.assert_array_equal(tets[0], inverted[0])
    assert sorted(tets[1]) == sorted(inverted[1])
    assert TetMesh(UNIT, tets).volumes.min() > 0


def test_drop_unused_nodes_renumbers():
    positions = np.concatenate([[[5.0, 5, 5]], UNIT[:2], [[6.0, 6, 6]], UNIT[2:]])
    tets = np.array([[1, 2, 4, 5], [2, 4, 5, 6]])
    new_positions, new_tets = validate_mesh(positions, tets, drop_unused_nodes=True)
    np.testing.assert_array_equal(new_positions, UNIT)
    np.testing.assert_array_equal(new_tets, TWO_TETS)


def test_tetmesh_record():
    mesh = TetMesh(UNIT, TWO_TETS, source="two tets")
    assert (mesh.node_count, mesh.tet_count) == (5, 2)
    # V = det[e1, e2, e3]/6: 1/6 for the unit corner; the second tet (1, 2, 3, 4) has edges
    # (−1, 1, 0), (−1, 0, 1), (0, 1, 1) from node 1, det = 2, V = 1/3.
    np.testing.assert_allclose(mesh.volumes, [1 / 6, 1 / 3], rtol=1e-15)
    np.testing.assert_array_equal(mesh.bounds, [[0, 0, 0], [1, 1, 1]])
    with pytest.raises(ValueError):
        mesh.rest_positions[0, 0] = 3.0  # read-only
    with pytest.raises(AttributeError):
        mesh.tets = TWO_TETS  # frozen
    with pytest.raises(MeshError, match="inverted"):
        TetMesh(UNIT, TWO_TETS[:, [0, 2, 1, 3]])


def test_translated_and_scaled():
    mesh = TetMesh(UNIT, TWO_TETS, source="two tets")
    moved = mesh.translated([1.0, -2.0, 0.5])
    np.testing.assert_array_equal(moved.rest_positions, UNIT + [1.0, -2.0, 0.5])
    np.testing.assert_allclose(moved.volumes, mesh.volumes, rtol=1e-15)
    assert "translated" in moved.source and mesh.rest_positions[0, 0] == 0.0
    millimetres = mesh.scaled(1e-3)
    np.testing.assert_allclose(millimetres.volumes, mesh.volumes * 1e-9, rtol=1e-15)
    stretched = mesh.scaled([1.0, 2.0, 3.0])
    np.testing.assert_allclose(stretched.volumes, mesh.volumes * 6.0, rtol=1e-15)
    np.testing.assert_array_equal(stretched.boundary_faces, mesh.boundary_faces)
    for bad in (0.0, -1.0, [1.0, 1.0], np.nan):
        with pytest.raises(ValueError, match="factor"):
            mesh.scaled(bad)
    with pytest.raises(ValueError, match="offset"):
        mesh.translated([1.0, 2.0])
