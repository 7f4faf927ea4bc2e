"""Inverted tetrahedra: a wrong node order is repaired, a tangled mesh is refused; renumbered meshes keep the
file's node indices usable (issue 25).

Reference for the tangle check: two positively oriented tetrahedra sharing a face lie on its two sides, so
they see it with opposite orientations (the interior faces of a valid mesh cancel in the divergence theorem:
Σ|V| equals the enclosed volume). A node moved through a face breaks that: Σ|V| after "fixing" the
orientation exceeds the volume of the box the mesh fills, which the tests check to show the overlap is real.
"""

from __future__ import annotations

import logging

import meshio
import numpy as np
import pytest

from refsim.geometry.barycentric import signed_volumes
from refsim.mesh import MeshError, box_mesh, read_mesh, validate_mesh


@pytest.fixture(scope="module")
def box():
    mesh = box_mesh(size=(1.0, 1.0, 1.0), cells=(3, 3, 3))
    return np.array(mesh.rest_positions), np.array(mesh.tets)


def _tangled(box, shift: float):
    positions, tets = box
    moved = positions.copy()
    node = int(np.flatnonzero(np.all(np.isclose(positions, 1.0 / 3.0), axis=1))[0])  # an interior node
    moved[node, 0] += shift
    return moved, tets


@pytest.mark.parametrize("shift", [0.4, 0.5])
def test_a_node_moved_through_a_face_is_refused_not_fixed(box, shift, caplog):
    positions, tets = _tangled(box, shift)
    volumes = signed_volumes(positions[tets])
    assert np.count_nonzero(volumes < 0) > 0
    assert np.abs(volumes).sum() > 1.0 + 1e-3  # the overlap: more volume than the unit box holds
    with caplog.at_level(logging.WARNING), pytest.raises(MeshError, match=r"organ.vtu: the mesh is tangled"):
        validate_mesh(positions, tets, source="organ.vtu", fix_orientation=True)
    assert "fixed the orientation" not in caplog.text  # no claim of a repair before the refusal


def test_a_node_moved_within_its_cell_is_a_valid_mesh(box):
    positions, tets = _tangled(box, 0.2)
    validate_mesh(positions, tets, fix_orientation=True)
    assert np.abs(signed_volumes(positions[tets])).sum() == pytest.approx(1.0, rel=1e-12)


@pytest.mark.parametrize("fraction", [1.0, 0.5])
def test_a_wrong_node_order_is_repaired(box, fraction, caplog):
    """All tets, or a random half of them, written with the other node order (an exporter's convention):
    the orientation is fixed, and the repaired mesh fills exactly the unit box."""
    positions, tets = box
    rng = np.random.default_rng(3)
    flipped = rng.random(tets.shape[0]) < fraction
    written = tets.copy()
    written[flipped] = written[flipped][:, [1, 0, 2, 3]]
    with caplog.at_level(logging.WARNING):
        _, fixed = validate_mesh(positions, written, source="organ.vtu", fix_orientation=True)
    assert f"fixed the orientation of {np.count_nonzero(flipped)} inverted" in caplog.text
    volumes = signed_volumes(positions[fixed])
    assert volumes.min() > 0 and volumes.sum() == pytest.approx(1.0, rel=1e-12)


def test_a_tangled_file_is_refused_by_read_mesh(tmp_path, box):
    positions, tets = _tangled(box, 0.5)
    path = tmp_path / "tangled.vtu"
    meshio.write(path, meshio.Mesh(positions, [("tetra", tets)]))
    with pytest.raises(MeshError, match=r"tangled.vtu: the mesh is tangled"):
        read_mesh(path)


# ---------------------------------------------------------------------- renumbering


def _renumbered_file(tmp_path, box):
    """The box with an unused node first and a duplicate of node 5 last: the reader drops one, merges the
    other, and renumbers."""
    positions, tets = box
    extra = np.array([[9.0, 9.0, 9.0]])
    written = np.vstack([extra, positions, positions[5:6]])
    written_tets = tets + 1  # node i of the mesh is node i + 1 of the file
    duplicate = written.shape[0] - 1
    first = np.flatnonzero(np.any(tets == 5, axis=1))[0]
    row = written_tets[first]  # a view: one tet uses the duplicate instead of node 5 (file node 6)
    row[tets[first] == 5] = duplicate
    path = tmp_path / "renumbered.vtu"
    meshio.write(path, meshio.Mesh(written, [("tetra", written_tets)]))
    return path, written


def test_file_node_indices_name_the_same_points_after_renumbering(tmp_path, box):
    path, written = _renumbered_file(tmp_path, box)
    mesh = read_mesh(path)
    assert mesh.node_count == box[0].shape[0] and mesh.node_map is not None
    used = np.arange(1, written.shape[0])
    np.testing.assert_array_equal(mesh.rest_positions[mesh.file_nodes(used)], written[used])
    assert mesh.file_nodes([written.shape[0] - 1])[0] == mesh.file_nodes([6])[0]  # the merged duplicate
    with pytest.raises(ValueError, match="mesh.fixed_nodes contains 0: node 0 .* used by no tetrahedron"):
        mesh.file_nodes([0, 3], key="mesh.fixed_nodes")
    with pytest.raises(ValueError, match=r"contains -1: .* \(indices 0 \.\. 65\)"):
        mesh.file_nodes([-1], key="mesh.fixed_nodes")
    np.testing.assert_array_equal(mesh.scaled(2.0).node_map, mesh.node_map)


def test_a_mesh_read_without_renumbering_has_no_map(tmp_path, box):
    path = tmp_path / "plain.vtu"
    meshio.write(path, meshio.Mesh(box[0], [("tetra", box[1])]))
    mesh = read_mesh(path)
    assert mesh.node_map is None
    np.testing.assert_array_equal(mesh.file_nodes([0, 7]), [0, 7])
