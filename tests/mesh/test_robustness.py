"""Meshes of issue 10: duplicated nodes (merged with a warning), truncated files (a clear message), and the
one degeneracy threshold shared by the mesh validation and the tissue model."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from refsim.mesh import MeshError, TetMesh, box_mesh, read_mesh, validate_mesh, write_mesh
from refsim.mesh.validation import DEGENERATE_VOLUME_RATIO, degenerate_tets, merge_duplicate_nodes


def _unmerged(mesh: TetMesh) -> tuple[np.ndarray, np.ndarray]:
    """Every tet with its own 4 nodes (an export without coherence): 4 m nodes, no node shared."""
    positions = mesh.rest_positions[mesh.tets].reshape(-1, 3)
    return positions, np.arange(positions.shape[0]).reshape(-1, 4)


def test_duplicate_nodes_are_merged_with_a_warning_into_the_same_mesh(tmp_path, caplog):
    cube = box_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2))
    positions, tets = _unmerged(cube)
    path = tmp_path / "loose.vtu"
    import meshio

    meshio.write(path, meshio.Mesh(positions, [("tetra", tets)]))
    with caplog.at_level(logging.WARNING):
        mesh = read_mesh(path)
    assert any("merged" in record.message and "duplicate" in record.message for record in caplog.records)
    assert mesh.node_count == cube.node_count and mesh.tet_count == cube.tet_count
    # The same surface as the connected mesh: 2·6·2² boundary triangles, not 4 per tet.
    assert mesh.boundary_faces.shape[0] == cube.boundary_faces.shape[0] == 48
    np.testing.assert_allclose(np.sort(mesh.volumes), np.sort(cube.volumes), rtol=1e-15)


def test_duplicate_nodes_in_arrays_are_refused_unless_merged():
    cube = box_mesh(size=(0.1, 0.1, 0.1), cells=(1, 1, 1))
    positions, tets = _unmerged(cube)
    with pytest.raises(MeshError, match="coincident nodes"):
        TetMesh(positions, tets)
    merged_positions, merged_tets, merged = merge_duplicate_nodes(positions, tets)
    assert merged == positions.shape[0] - cube.node_count
    TetMesh(merged_positions, merged_tets)


def test_merging_that_collapses_an_element_is_refused_as_degenerate():
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1e-13, 0, 0]], dtype=float)
    tets = np.array([[0, 1, 2, 3], [4, 0, 2, 3]])  # node 4 coincides with node 0
    with pytest.raises(MeshError, match="degenerate"):
        validate_mesh(positions, tets, merge_duplicates=True)


@pytest.mark.parametrize(
    ("fmt", "suffix"), [("vtu", ".vtu"), ("gmsh22", ".msh"), ("gmsh", ".msh"), ("vtk", ".vtk")]
)
@pytest.mark.parametrize("fraction", [0.3, 0.7, 0.95])
def test_truncated_files_get_a_clear_message(tmp_path, capfd, fmt, suffix, fraction):
    path = tmp_path / f"mesh_{fmt}{suffix}"
    write_mesh(path, box_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2)), file_format=fmt)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(MeshError) as caught:
        read_mesh(path)
    message = str(caught.value)
    assert str(path) in message and "cannot read it as a" in message
    assert "truncated" in message
    assert "SystemExit" not in message and "IndexError" not in message
    printed = capfd.readouterr()
    assert "Error" not in printed.out + printed.err  # meshio's own prints are captured


def test_one_degeneracy_threshold_for_mesh_and_tissue():
    """A tet flatter than the threshold is refused by both; one just above it is accepted by both."""
    from refsim.fem.tissue import TissueModel
    from refsim.materials import HookeMaterial

    material = HookeMaterial(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    for height, refused in ((0.5 * DEGENERATE_VOLUME_RATIO, True), (20.0 * DEGENERATE_VOLUME_RATIO, False)):
        positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, height]], dtype=float)
        tets = np.array([[0, 1, 2, 3]])
        assert (degenerate_tets(positions, tets).size == 1) == refused
        if refused:
            with pytest.raises(MeshError, match="degenerate"):
                validate_mesh(positions, tets)
            with pytest.raises(ValueError, match="zero volume"):
                TissueModel(positions, tets, material, fixed_nodes=np.array([0]))
        else:
            validate_mesh(positions, tets)
            TissueModel(positions, tets, material, fixed_nodes=np.array([0]))
