"""Mesh files: meshio formats, Gmsh legacy v1, defects named with the file, and the shared organ meshes."""

import logging
import os
from pathlib import Path

import numpy as np
import pytest

from refsim.mesh import MeshError, TetMesh, box_mesh, is_closed_surface, read_mesh, surface_edges, write_mesh

REPO = Path(__file__).resolve().parents[2]
COMMITTED = REPO / "meshes"
SHARED_MESHES = Path(os.environ.get("REFSIM_SHARED_DATA", REPO / ".." / "shared" / "data")) / "meshes"


def gmsh_v1_text(positions, tets, labels, *, extra_elements=()) -> str:
    """A Gmsh legacy v1 file: $NOD with 'label x y z', $ELM with 'number type phys elem count nodes...'."""
    node_lines = [
        f"{label} {x:.17g} {y:.17g} {z:.17g}" for label, (x, y, z) in zip(labels, positions, strict=True)
    ]
    element_lines = [f"4 1 1 4 {' '.join(str(labels[i]) for i in tet)}" for tet in tets]
    element_lines += list(extra_elements)
    element_lines = [f"{number} {line}" for number, line in enumerate(element_lines, start=1)]
    return "\n".join(
        [
            "$NOD",
            str(len(node_lines)),
            *node_lines,
            "$ENDNOD",
            "$ELM",
            str(len(element_lines)),
            *element_lines,
            "$ENDELM",
            "",
        ]
    )


def _same_mesh(a: TetMesh, b: TetMesh) -> None:
    np.testing.assert_array_equal(a.rest_positions, b.rest_positions)
    np.testing.assert_array_equal(a.tets, b.tets)


@pytest.fixture(scope="module")
def cube():
    return box_mesh(size=(0.02, 0.03, 0.01), cells=(2, 3, 1), origin=(0.0, -0.01, 0.5))


@pytest.mark.parametrize("name", ["cube.vtu", "cube.msh", "cube22.msh", "cube.vtk", "cube.xdmf"])
def test_meshio_round_trip(tmp_path, cube, name):
    path = tmp_path / name
    write_mesh(path, cube, file_format="gmsh22" if name == "cube22.msh" else None)
    mesh = read_mesh(path)
    _same_mesh(mesh, cube)
    assert mesh.source == str(path)


def test_gmsh_v1_with_arbitrary_labels_and_other_elements(tmp_path, cube):
    labels = 1000 - 7 * np.arange(cube.node_count)  # decreasing, non-contiguous
    extra = ["2 1 1 3 " + " ".join(str(labels[i]) for i in cube.boundary_faces[0]), f"15 1 1 1 {labels[0]}"]
    path = tmp_path / "legacy.mesh"  # recognised by content, not extension
    path.write_text(gmsh_v1_text(cube.rest_positions, cube.tets, labels, extra_elements=extra))
    _same_mesh(read_mesh(path), cube)


def test_inverted_tets_are_fixed_with_a_warning_or_refused(tmp_path, cube, caplog):
    tets = cube.tets.copy()
    tets[::3] = tets[::3][:, [1, 0, 2, 3]]
    path = tmp_path / "inverted.msh"
    path.write_text(gmsh_v1_text(cube.rest_positions, tets, np.arange(1, cube.node_count + 1)))
    with caplog.at_level(logging.WARNING, logger="refsim.mesh"):
        mesh = read_mesh(path)
    assert "inverted" in caplog.text and str(path) in caplog.text
    assert np.all(mesh.volumes > 0)
    np.testing.assert_allclose(mesh.volumes, cube.volumes, rtol=1e-14)
    with pytest.raises(MeshError, match=r"inverted.*tets 0, 3, 6"):
        read_mesh(path, fix_orientation=False)


def test_unused_nodes_are_dropped_with_a_warning(tmp_path, cube, caplog):
    positions = np.concatenate([[[9.0, 9.0, 9.0]], cube.rest_positions])
    path = tmp_path / "unused.msh"
    path.write_text(gmsh_v1_text(positions, cube.tets + 1, np.arange(1, cube.node_count + 2)))
    with caplog.at_level(logging.WARNING, logger="refsim.mesh"):
        mesh = read_mesh(path)
    assert "dropped 1 node" in caplog.text
    _same_mesh(mesh, cube)


@pytest.mark.parametrize(
    ("content", "defect"),
    [
        ("", "empty"),
        ("   \n\n", "empty"),
        ("this is not a mesh\n", "cannot read it as a Gmsh"),
        ("$NOD\n2\n1 0 0 0\n$ENDNOD\n", "announces 2 nodes"),
        ("$NOD\n1\n1 0 0 0\n", "not closed by"),
        ("$NOD\n1\n1 0 0 nan\n$ENDNOD\n$ELM\n0\n$ENDELM\n", "no tetrahedra"),
        ("$NOD\n1\n1 0 0 zero\n$ENDNOD\n$ELM\n0\n$ENDELM\n", "not a number"),
        ("$NOD\n1\n1 0 0 0\n$ENDNOD\n$ELM\n1\n1 4 1 1 4 1 2 3 4\n$ENDELM\n", "node labels not in"),
        ("$NOD\n1\n1 0 0 0\n$ENDNOD\n$ELM\n1\n1 4 1 1 3 1 1 1\n$ENDELM\n", "exactly 4 nodes"),
    ],
)
def test_defective_files_are_named(tmp_path, content, defect):
    path = tmp_path / "bad.msh"
    path.write_text(content)
    with pytest.raises(MeshError, match=defect) as error:
        read_mesh(path)
    assert str(path) in str(error.value)


@pytest.mark.parametrize(
    ("edit", "defect"),
    [
        (lambda p, t: (np.where(np.arange(p.shape[0])[:, None] == 3, np.inf, p), t), "non-finite.*nodes 3"),
        (lambda p, t: (p, np.where(t == t[5, 2], t[5, 1], t)), "degenerate"),
        (lambda p, t: (p.copy(), t), None),
    ],
)
def test_defective_arrays_in_files(tmp_path, cube, edit, defect):
    positions, tets = edit(cube.rest_positions, cube.tets)
    path = tmp_path / "arrays.vtu"
    import meshio

    meshio.write(path, meshio.Mesh(positions, [("tetra", tets)]))
    if defect is None:
        _same_mesh(read_mesh(path), cube)
        return
    with pytest.raises(MeshError, match=defect) as error:
        read_mesh(path)
    assert str(path) in str(error.value)


def test_missing_file_directory_and_no_tetra(tmp_path, cube):
    with pytest.raises(MeshError, match="does not exist"):
        read_mesh(tmp_path / "nothing.msh")
    with pytest.raises(MeshError, match="not a regular file"):
        read_mesh(tmp_path)
    import meshio

    path = tmp_path / "surface.vtu"
    meshio.write(path, meshio.Mesh(cube.rest_positions, [("triangle", cube.boundary_faces)]))
    with pytest.raises(MeshError, match="no tetrahedra.*triangle"):
        read_mesh(path)


@pytest.mark.parametrize("name", ["cube_gmsh_v1.msh", "cube.vtu", "cube_gmsh41.msh"])
def test_committed_meshes(name):
    # meshes/README.md: the same 2 × 2 × 2-cell, 0.02 m cube, written in three formats.
    mesh = read_mesh(COMMITTED / name)
    _same_mesh(mesh, box_mesh(size=(0.02, 0.02, 0.02), cells=(2, 2, 2)))


def _shared(name: str) -> Path:
    path = SHARED_MESHES / name
    if not path.is_file():
        pytest.skip(f"shared mesh {path} absent")
    return path


def test_liver_gmsh_v1_is_a_closed_positive_volume():
    # README of the shared meshes: 181 nodes, 596 linear tets, all positively oriented, Gmsh legacy v1.
    mesh = read_mesh(_shared("liver.msh"), fix_orientation=False)
    assert (mesh.node_count, mesh.tet_count) == (181, 596)
    assert np.all(mesh.volumes > 0)
    _, counts = surface_edges(mesh.boundary_faces)
    assert np.all(counts == 2)
    assert is_closed_surface(mesh.boundary_faces)
    # Divergence theorem on the outward boundary: V = (1/3) Σ_faces (centroid · normal) area.
    corners = mesh.rest_positions[mesh.boundary_faces]
    doubled_area_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    flux = np.einsum("fi,fi->", corners.mean(axis=1), doubled_area_normals) / 6.0
    assert flux == pytest.approx(mesh.volumes.sum(), rel=1e-12)


def test_liver_gmsh22_equals_the_v1_file():
    _same_mesh(read_mesh(_shared("liver_gmsh22.msh")), read_mesh(_shared("liver.msh")))


@pytest.mark.parametrize(
    ("name", "node_count", "tet_count"),
    [("liver_volumetric.vtk", 98, 273), ("tissue_volume.msh", 493, 1432)],
)
def test_other_shared_volume_meshes(name, node_count, tet_count):
    mesh = read_mesh(_shared(name))
    assert (mesh.node_count, mesh.tet_count) == (node_count, tet_count)
    assert np.all(mesh.volumes > 0)
    assert is_closed_surface(mesh.boundary_faces)
