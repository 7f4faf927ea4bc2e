"""Boundary surfaces: outward orientation, closedness, and the divergence theorem."""

import numpy as np
import pytest

from refsim.mesh import TetMesh, boundary_faces, box_mesh, is_closed_surface, surface_edges

UNIT = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])


def _flux_volume(positions, faces):
    """Volume from the divergence theorem, V = (1/3) ∮ x·n dA, over outward triangles."""
    corners = positions[faces]
    doubled_area_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return np.einsum("fi,fi->", corners.mean(axis=1), doubled_area_normals) / 6.0


def test_two_tets_have_six_outward_faces():
    faces = boundary_faces(np.array([[0, 1, 2, 3], [1, 2, 3, 4]]), UNIT)
    assert faces.shape == (6, 3)
    assert not any(sorted(face) == [1, 2, 3] for face in faces.tolist())  # the shared face is inside
    assert _flux_volume(UNIT, faces) == pytest.approx(1 / 6 + 1 / 3, rel=1e-14)
    assert is_closed_surface(faces)


def test_orientation_does_not_depend_on_tet_orientation():
    # boundary_faces orients from positions, so inverted input tets still give outward faces.
    positive = boundary_faces(np.array([[0, 1, 2, 3]]), UNIT)
    inverted = boundary_faces(np.array([[0, 2, 1, 3]]), UNIT)
    assert _flux_volume(UNIT, positive) == pytest.approx(1 / 6, rel=1e-14)
    assert _flux_volume(UNIT, inverted) == pytest.approx(1 / 6, rel=1e-14)


def test_box_surface_is_closed_and_outward():
    mesh = box_mesh(size=(0.1, 0.2, 0.3), cells=(3, 2, 4), origin=(1.0, 1.0, 1.0))
    assert _flux_volume(mesh.rest_positions, mesh.boundary_faces) == pytest.approx(0.006, rel=1e-12)
    edges, counts = surface_edges(mesh.boundary_faces)
    assert np.all(counts == 2) and np.all(edges[:, 0] < edges[:, 1])
    assert is_closed_surface(mesh.boundary_faces)
    # Outward: the normal of a face on the plane x = 1.0 points to −x.
    corners = mesh.rest_positions[mesh.boundary_faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    on_low_x = np.all(corners[:, :, 0] == 1.0, axis=1)
    assert on_low_x.sum() == 2 * 2 * 4 and np.all(normals[on_low_x, 0] < 0)


def test_open_or_flipped_surfaces_are_not_closed():
    faces = box_mesh(cells=(2, 2, 2)).boundary_faces
    assert not is_closed_surface(faces[1:])
    flipped = faces.copy()
    flipped[0] = flipped[0, [0, 2, 1]]
    assert not is_closed_surface(flipped)
    assert not is_closed_surface(np.zeros((0, 3), dtype=int))


def test_boundary_faces_are_cached_and_read_only():
    mesh = TetMesh(UNIT, np.array([[0, 1, 2, 3], [1, 2, 3, 4]]))
    assert mesh.boundary_faces is mesh.boundary_faces
    np.testing.assert_array_equal(mesh.boundary_nodes, np.arange(5))
    with pytest.raises(ValueError):
        mesh.boundary_faces[0, 0] = 1
