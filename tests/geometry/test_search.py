"""Spatial search: point location in tetrahedra and closest points on surfaces, against brute force."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial import Delaunay

from refsim.geometry import (
    SurfaceProjector,
    TetLocator,
    closest_points_on_triangles,
    search,
    tet_barycentric,
    tet_boundary_faces,
)
from refsim.geometry.grid import tet_spheres, triangle_spheres
from refsim.geometry.search import _RadiusClasses
from refsim.mesh import box_mesh

OFFSETS = [-1e-12, 0.0, 1e-12]


@pytest.fixture(scope="module")
def box():
    """The unit cube, 4 × 3 × 2 cells, and its locator."""
    mesh = box_mesh(size=(1.0, 1.0, 1.0), cells=(4, 3, 2))
    return mesh, TetLocator(mesh.rest_positions, mesh.tets)


@pytest.fixture(scope="module")
def graded():
    """A Delaunay mesh of points clustered near the origin: element sizes span several radius classes."""
    rng = np.random.default_rng(7)
    points = rng.uniform(size=(400, 3)) ** 3
    delaunay = Delaunay(points)
    return delaunay, TetLocator(delaunay.points, delaunay.simplices)


def _brute_force_locate(points, positions, tets, tolerance):
    """Every (point, tet) pair evaluated; the rule of TetLocator: max of the smallest coordinate, then lowest
    tet index, among tets with all coordinates >= −tolerance."""
    count, tet_count = points.shape[0], tets.shape[0]
    coordinates = tet_barycentric(
        np.repeat(points, tet_count, axis=0), np.tile(positions[tets], (count, 1, 1))
    ).reshape(count, tet_count, 4)
    smallest = coordinates.min(axis=2)
    smallest = np.where(smallest >= -tolerance, smallest, -np.inf)
    best = np.argmax(smallest, axis=1)  # first maximum: lowest index among ties
    found = np.isfinite(smallest[np.arange(count), best])
    return np.where(found, best, -1)


def _brute_force_surface_distance(points, positions, faces):
    count, face_count = points.shape[0], faces.shape[0]
    repeated = np.repeat(points, face_count, axis=0)
    closest, _ = closest_points_on_triangles(repeated, np.tile(positions[faces], (count, 1, 1)))
    return np.linalg.norm(closest - repeated, axis=1).reshape(count, face_count).min(axis=1)


def test_locate_matches_brute_force_on_box(box):
    mesh, locator = box
    rng = np.random.default_rng(0)
    points = rng.uniform(-0.1, 1.1, size=(300, 3))
    tet_index, barycentric = locator.locate(points)
    np.testing.assert_array_equal(
        tet_index, _brute_force_locate(points, mesh.rest_positions, mesh.tets, 1e-12)
    )
    inside = np.all((points >= 0) & (points <= 1), axis=1)
    np.testing.assert_array_equal(tet_index >= 0, inside)
    assert np.all(np.isnan(barycentric[~inside]))
    found = tet_index >= 0
    rebuilt = np.einsum("qk,qki->qi", barycentric[found], mesh.rest_positions[mesh.tets[tet_index[found]]])
    np.testing.assert_allclose(rebuilt, points[found], atol=1e-15)


def test_locate_matches_brute_force_and_delaunay_on_graded_mesh(graded):
    delaunay, locator = graded
    rng = np.random.default_rng(1)
    points = np.concatenate([rng.uniform(size=(120, 3)) ** 3, rng.uniform(-0.2, 1.2, size=(60, 3))])
    tet_index, barycentric = locator.locate(points)
    np.testing.assert_array_equal(
        tet_index, _brute_force_locate(points, delaunay.points, delaunay.simplices, 1e-12)
    )
    # Independent reference for points clearly inside one tet: scipy's Delaunay.find_simplex.
    clear = (tet_index >= 0) & (np.nan_to_num(barycentric, nan=-1.0).min(axis=1) > 1e-9)
    clear |= tet_index < 0
    np.testing.assert_array_equal(tet_index[clear], delaunay.find_simplex(points[clear]))
    assert len(_RadiusClasses(locator.centroids, locator._radii).classes) > 2  # the mesh really is graded


@pytest.mark.parametrize("tolerance", [0.0, 1e-12, 1e-6])
def test_grid_candidates_give_the_kd_trees_answer_bit_for_bit(graded, tolerance):
    # Tolerances up to 1e-6 take the grid, larger ones the KD-trees per radius class; both hold every tet
    # whose grown bounding sphere holds the point, so the answers (tet, barycentric) are the same bits.
    delaunay, locator = graded
    rng = np.random.default_rng(5)
    points = np.concatenate(
        [rng.uniform(size=(150, 3)) ** 3, delaunay.points[:40], rng.uniform(-0.2, 1.2, size=(30, 3))]
    )
    kd = TetLocator(delaunay.points, delaunay.simplices)
    kd._candidates = lambda p, t: _RadiusClasses(kd.centroids, kd._radii).pairs(p, 6.0 * t * kd._radii.max())
    for got, expected in zip(
        locator._locate_vectorised(points, tolerance),
        kd._locate_vectorised(points, tolerance),
        strict=True,
    ):
        np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("tolerance", [0.0, 1e-12, 1e-6])
def test_compiled_location_gives_the_vectorised_answer_bit_for_bit(graded, box, tolerance):
    # locate's compiled pass (tolerances up to 1e-6) repeats tet_barycentric's operations in its order and
    # the lexicographic choice of the vectorised path (largest smallest coordinate, then lowest tet): the same
    # tets and the same bits, on a graded mesh and on the box's vertices, edges and faces (ties).
    rng = np.random.default_rng(11)
    delaunay, locator = graded
    mesh, box_locator = box
    positions, tets = mesh.rest_positions, mesh.tets
    cases = [
        (locator, np.concatenate([rng.uniform(size=(300, 3)) ** 3, delaunay.points[:60]])),
        (locator, rng.uniform(-0.2, 1.2, size=(100, 3))),
        (box_locator, np.concatenate([positions, positions[tets[:, 1:]].mean(axis=1)])),
        (box_locator, rng.uniform(-0.1, 1.1, size=(200, 3))),
    ]
    for which, points in cases:
        got = which.locate(points, tolerance=tolerance)
        expected = which._locate_vectorised(points, tolerance)
        assert np.count_nonzero(expected[0] >= 0) > 0.2 * points.shape[0]  # many points are inside
        np.testing.assert_array_equal(got[0], expected[0])
        np.testing.assert_array_equal(got[1], expected[1])


def test_tet_spheres_are_the_numpy_centroids_and_radii(graded):
    delaunay, _ = graded
    vertices = delaunay.points[delaunay.simplices]
    centroids = vertices.mean(axis=1)
    radii = np.linalg.norm(vertices - centroids[:, None, :], axis=2).max(axis=1)
    got = tet_spheres(delaunay.points, delaunay.simplices)
    np.testing.assert_array_equal(got[0], centroids)
    np.testing.assert_array_equal(got[1], radii)


def test_triangle_spheres_are_the_numpy_centroids_and_radii(graded):
    # SurfaceProjector's centroids and bounding radii, compiled: the bits of its former NumPy expressions,
    # on the graded mesh's boundary and on random triangles far from the origin (round-off in the offsets).
    delaunay, _ = graded
    faces, _ = tet_boundary_faces(delaunay.simplices, delaunay.points)
    rng = np.random.default_rng(3)
    for triangles in (
        delaunay.points[faces],
        rng.standard_normal((5000, 3, 3)) * 1e-3 + rng.standard_normal(3) * 10.0,
    ):
        centroids = triangles.mean(axis=1)
        radii = np.linalg.norm(triangles - centroids[:, None, :], axis=2).max(axis=1)
        got = triangle_spheres(triangles)
        np.testing.assert_array_equal(got[0], centroids)
        np.testing.assert_array_equal(got[1], radii)


@pytest.mark.parametrize("tolerance", [0.0, 1e-12])
def test_locate_nodes_edges_and_faces(box, tolerance):
    mesh, locator = box
    positions, tets = mesh.rest_positions, mesh.tets
    edge_points = 0.5 * (positions[tets[:, 0]] + positions[tets[:, 3]])  # the cells' main diagonals
    face_points = positions[tets[:, 1:]].mean(axis=1)
    points = np.concatenate([positions, edge_points, face_points])
    tet_index, barycentric = locator.locate(points, tolerance=tolerance)
    assert np.all(tet_index >= 0)
    assert barycentric.min() >= -1e-15
    rebuilt = np.einsum("qk,qki->qi", barycentric, positions[tets[tet_index]])
    np.testing.assert_allclose(rebuilt, points, atol=1e-15)
    np.testing.assert_array_equal(tet_index, _brute_force_locate(points, positions, tets, tolerance))
    # A node gets the coordinate 1 exactly at itself.
    np.testing.assert_array_equal(barycentric[: mesh.node_count].max(axis=1), 1.0)
    # Determinism: the same points in another order get the same tets.
    order = np.random.default_rng(2).permutation(points.shape[0])
    again, _ = locator.locate(points[order], tolerance=tolerance)
    np.testing.assert_array_equal(again, tet_index[order])


@pytest.mark.parametrize("offset", OFFSETS)
def test_locate_across_shared_interior_faces(box, offset):
    mesh, locator = box
    positions, tets = mesh.rest_positions, mesh.tets
    # Interior faces: those used twice. Put a point on each, moved by offset along the normal pointing into
    # the tet that lists the face first.
    local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    faces = tets[:, local].reshape(-1, 3)
    keys = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    shared = np.flatnonzero(counts[inverse] == 2)
    owner = shared // 4
    opposite = tets.reshape(-1)[shared]
    a, b, c = (positions[faces[shared, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    normal *= np.sign(np.einsum("ij,ij->i", normal, positions[opposite] - a))[:, None]  # into the owner
    points = (a + b + c) / 3.0 + offset * normal
    tet_index, barycentric = locator.locate(points)
    assert np.all(tet_index >= 0)
    if offset > 0:
        np.testing.assert_array_equal(tet_index, owner)
    elif offset < 0:
        assert not np.any(tet_index == owner)
    assert barycentric.min() >= -1e-12


@pytest.mark.parametrize("offset", OFFSETS)
def test_locate_at_the_boundary(box, offset):
    mesh, locator = box
    positions = mesh.rest_positions
    faces = mesh.boundary_faces
    normal = np.cross(
        positions[faces[:, 1]] - positions[faces[:, 0]], positions[faces[:, 2]] - positions[faces[:, 0]]
    )
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    points = positions[faces].mean(axis=1) + offset * normal  # outward for offset > 0
    # 1e-12 [m] on a 0.25 m cell is a coordinate of about −4e-12, beyond the default tolerance of 1e-12.
    tet_index, _ = locator.locate(points)
    assert np.all(tet_index >= 0) if offset <= 0 else np.all(tet_index == -1)
    tet_index, _ = locator.locate(points, tolerance=0.0)
    assert np.all(tet_index >= 0) if offset <= 0 else np.all(tet_index == -1)


def test_locate_nearest_clamps_outside_points(box):
    mesh, locator = box
    rng = np.random.default_rng(3)
    points = rng.uniform(-0.5, 1.5, size=(200, 3))
    tet_index, barycentric, distance = locator.locate_nearest(points)
    assert np.all(tet_index >= 0)
    clamped = np.clip(points, 0.0, 1.0)  # the closest point of the unit cube
    np.testing.assert_allclose(distance, np.linalg.norm(points - clamped, axis=1), atol=1e-15)
    rebuilt = np.einsum("qk,qki->qi", barycentric, mesh.rest_positions[mesh.tets[tet_index]])
    np.testing.assert_allclose(rebuilt, clamped, atol=1e-15)
    outside = distance > 0
    assert outside.any() and barycentric[outside].min() >= 0.0
    np.testing.assert_allclose(barycentric.sum(axis=1), 1.0, atol=1e-15)


def test_locate_rejects_bad_input(box):
    _, locator = box
    with pytest.raises(ValueError, match="tolerance"):
        locator.locate(np.zeros((1, 3)), tolerance=-1.0)
    with pytest.raises(ValueError, match="points"):
        locator.locate(np.zeros((1, 2)))
    with pytest.raises(ValueError, match="out of range"):
        TetLocator(np.zeros((3, 3)), np.array([[0, 1, 2, 3]]))


def test_tet_boundary_faces_single_tet_points_outward():
    positions = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    for tets in (np.array([[0, 1, 2, 3]]), np.array([[0, 2, 1, 3]])):  # either orientation
        faces, owners = tet_boundary_faces(tets, positions)
        assert faces.shape == (4, 3) and np.all(owners == 0)
        corners = positions[faces]
        normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        outward = corners.mean(axis=1) - positions.mean(axis=0)
        assert np.all(np.einsum("ij,ij->i", normal, outward) > 0)


def test_projector_matches_brute_force(graded):
    delaunay, _ = graded
    faces, _ = tet_boundary_faces(delaunay.simplices, delaunay.points)
    projector = SurfaceProjector(delaunay.points, faces)
    rng = np.random.default_rng(4)
    points = np.concatenate([rng.uniform(-0.3, 1.3, size=(150, 3)), rng.normal(scale=20.0, size=(20, 3))])
    result = projector.closest(points)
    np.testing.assert_allclose(
        result.distance, _brute_force_surface_distance(points, delaunay.points, faces), rtol=1e-14, atol=1e-16
    )
    triangles = delaunay.points[faces[result.face_index]]
    np.testing.assert_allclose(
        np.einsum("qk,qki->qi", result.barycentric, triangles), result.closest, atol=1e-15
    )
    assert result.barycentric.min() >= 0.0
    np.testing.assert_allclose(np.linalg.norm(result.normal, axis=1), 1.0, atol=1e-14)


@pytest.mark.parametrize("offset", [0.0, 1e-12, 0.05])
def test_projector_scan_and_kd_trees_give_the_same_bits(graded, box, offset):
    # Small queries scan every face (compiled), large ones use KD-trees; both keep every face that can hold
    # the closest point, so face, barycentric coordinates and closest point are the same bits, ties included
    # (the box's vertices and edges are equidistant from several faces).
    rng = np.random.default_rng(9)
    delaunay, _ = graded
    mesh, _ = box
    box_points = mesh.rest_positions[mesh.boundary_nodes]
    cases = [
        (
            delaunay.points,
            tet_boundary_faces(delaunay.simplices, delaunay.points)[0],
            rng.uniform(-0.3, 1.3, (80, 3)),
        ),
        (
            mesh.rest_positions,
            mesh.boundary_faces,
            box_points + offset * rng.standard_normal(box_points.shape),
        ),
    ]
    # A soup of slivers and degenerate triangles (NumPy's careful path): nearly collinear vertices.
    sliver_positions = rng.uniform(size=(40, 3)) * np.array([1.0, 1e-7, 1e-9])
    sliver_faces = rng.integers(0, 40, size=(120, 3))
    cases.append((sliver_positions, sliver_faces, rng.uniform(-0.1, 1.1, (60, 3)) * [1.0, 1e-6, 1e-6]))
    for positions, faces, points in cases:
        projector = SurfaceProjector(positions, faces)
        queries, candidates = projector._indexed_candidates(points)
        indexed = _closest_of_pairs(projector, points, queries, candidates)
        # The scan's bound over every face's corners, or over the faces' distinct points (vertex_indices: the
        # same least distance; the positions hold points off the surface too, the Delaunay's inner ones)
        distinct = SurfaceProjector(positions, faces, vertex_indices=np.unique(faces))
        for scanner in (projector, distinct):
            for compiled in (False, True):
                scanned = scanner._closest_chunk(points, compiled)
                for got, expected in zip(scanned, indexed, strict=True):
                    np.testing.assert_array_equal(got, expected)
        assert projector.faces.shape[0] * points.shape[0] <= search._SCAN_PAIRS  # the scan was taken


def test_compiled_scan_is_the_numpy_pairs_answer_and_leaves_thin_candidates_to_it(box):
    # Reference: SurfaceProjector._closest_pairs, the NumPy path (Ericson's coordinates, the careful path for
    # thin triangles, np.lexsort of the squared distances, ties to the lowest face). The compiled scan
    # (refsim.geometry.grid.closest_faces_scan) settles the queries whose candidates are all regular in the
    # same operations and order, so the tolerance is zero; a query with a thin candidate goes to the NumPy
    # path. The box's top with a fan of slivers glued to one corner has both kinds of query, and ties (its
    # vertices and edges).
    from refsim.geometry.grid import closest_faces_scan

    rng = np.random.default_rng(11)
    mesh, _ = box
    top = mesh.boundary_faces[np.all(mesh.rest_positions[mesh.boundary_faces][:, :, 2] == 1.0, axis=1)]
    count = mesh.rest_positions.shape[0]
    slivers = rng.uniform(size=(10, 3)) * [1e-7, 1.0, 1e-9] + [1.0, 0.0, 1.0]
    positions = np.concatenate([mesh.rest_positions, slivers])
    fan = np.column_stack([count + np.arange(9), count + np.arange(1, 10), np.full(9, count)])
    faces = np.concatenate([top, fan])
    grid = rng.integers(0, 5, (60, 2)) / np.array([4.0, 3.0])
    points = np.concatenate(
        [
            np.column_stack([grid + rng.choice([0.0, 1e-12], grid.shape), 1.0 + rng.uniform(0, 0.3, 60)]),
            rng.uniform([0.9, -0.1, 0.9], [1.1, 1.1, 1.1], (40, 3)),
        ]
    )
    projector = SurfaceProjector(positions, faces)
    _, _, settled = closest_faces_scan(
        points,
        projector.triangles,
        projector.centroids,
        projector.radii,
        search._RADIUS_SLACK,
        search._THIN_AREA,
    )
    assert settled.any() and not settled.all()
    compiled = projector.closest_faces(points, compiled_choice=True)
    for got, expected in zip(compiled, projector._closest_pairs(points), strict=True):
        np.testing.assert_array_equal(got, expected)


def test_scan_keeps_only_the_nearest_faces_of_well_shaped_surfaces(box):
    # The scan evaluates well-shaped faces (|ab × ac| ≥ thin L², NumPy's Ericson path) by their distance and
    # keeps the nearest and its ties only: above the box's top, at most the faces around one grid vertex (8),
    # not the cap of faces within the distance (the whole top at this height).
    from refsim.geometry.closest import _THIN_AREA
    from refsim.geometry.grid import surface_candidates

    mesh, _ = box
    projector = SurfaceProjector(mesh.rest_positions, mesh.boundary_faces)
    rng = np.random.default_rng(4)
    points = np.column_stack([rng.uniform(0.0, 1.0, (40, 2)), np.full(40, 1.5)])
    queries, faces = surface_candidates(
        points, projector.triangles, projector.centroids, projector.radii, search._RADIUS_SLACK, _THIN_AREA
    )
    counts = np.bincount(queries, minlength=points.shape[0])
    assert counts.min() >= 1 and counts.max() <= 8
    scanned = projector._closest_chunk(points)
    every_pair = np.nonzero(np.ones((points.shape[0], projector.faces.shape[0]), dtype=bool))
    expected = _closest_of_pairs(projector, points, *every_pair)  # brute force over every face
    for got, want in zip(scanned, expected, strict=True):
        np.testing.assert_array_equal(got, want)


def _closest_of_pairs(projector, points, queries, faces):
    """The projector's choice among candidate pairs (its _closest_chunk after the search)."""
    closest, coordinates = closest_points_on_triangles(points[queries], projector.triangles[faces])
    distance2 = np.sum((closest - points[queries]) ** 2, axis=1)
    order = np.lexsort((faces, distance2, queries))
    found, best = search._first_per_query(queries, order)
    face_index = np.zeros(points.shape[0], dtype=np.int64)
    barycentric = np.zeros((points.shape[0], 3))
    face_index[found], barycentric[found] = faces[best], coordinates[best]
    return face_index, barycentric


@pytest.mark.parametrize("offset", OFFSETS)
def test_projector_on_box_vertices_edges_faces(box, offset):
    mesh, _ = box
    positions, faces = mesh.rest_positions, mesh.boundary_faces
    projector = SurfaceProjector(positions, faces)
    nodes = positions[mesh.boundary_nodes]
    edges = 0.5 * (positions[faces[:, 0]] + positions[faces[:, 1]])
    centroids = positions[faces].mean(axis=1)
    surface_points = np.concatenate([nodes, edges, centroids])
    # Move each point along the outward normal of the cube face it lies on (exact off the cube's edges).
    cube_normal = np.where(np.isclose(surface_points, 1.0), 1.0, 0.0) - np.where(
        np.isclose(surface_points, 0.0), 1.0, 0.0
    )
    on_one_face = np.abs(cube_normal).sum(axis=1) == 1
    points = surface_points + offset * cube_normal
    result = projector.closest(points)
    expected = np.linalg.norm(points - np.clip(points, 0.0, 1.0), axis=1)
    inside_distance = np.minimum(points, 1.0 - points).min(axis=1)
    expected = np.where(np.all((points >= 0) & (points <= 1), axis=1), inside_distance, expected)
    # Coordinates are O(1): centroids and offsets carry a few ulp(1) = 2.2e-16 of round-off.
    roundoff = 4 * np.finfo(float).eps
    np.testing.assert_allclose(result.distance, expected, atol=roundoff)
    np.testing.assert_allclose(result.distance[on_one_face], abs(offset), atol=roundoff)
    np.testing.assert_allclose(result.closest[on_one_face], surface_points[on_one_face], atol=roundoff)
    # Outward normals: the face normal is the cube face's normal.
    np.testing.assert_allclose(result.normal[on_one_face], cube_normal[on_one_face], atol=1e-15)


@settings(deadline=None)
@given(arrays(np.float64, (8, 3), elements=st.floats(-3.0, 3.0)), st.integers(0, 2**32 - 1))
def test_property_projector_and_locator_against_brute_force(points, seed):
    rng = np.random.default_rng(seed)
    cloud = rng.normal(size=(30, 3))
    delaunay = Delaunay(cloud)
    faces, _ = tet_boundary_faces(delaunay.simplices, delaunay.points)
    result = SurfaceProjector(delaunay.points, faces).closest(points)
    np.testing.assert_allclose(
        result.distance, _brute_force_surface_distance(points, delaunay.points, faces), rtol=1e-13, atol=1e-15
    )
    tet_index, _ = TetLocator(delaunay.points, delaunay.simplices).locate(points)
    np.testing.assert_array_equal(
        tet_index, _brute_force_locate(points, delaunay.points, delaunay.simplices, 1e-12)
    )


def test_projector_normals_of_the_chosen_faces_are_the_faces_normals(graded):
    # closest() computes the normals of the chosen faces only; they are the rows of the faces' normals.
    delaunay, _ = graded
    faces, _ = tet_boundary_faces(delaunay.simplices, delaunay.points)
    projector = SurfaceProjector(delaunay.points, faces)
    points = np.random.default_rng(12).uniform(-0.3, 1.3, size=(60, 3))
    result = projector.closest(points)
    np.testing.assert_array_equal(result.normal, projector.normals[result.face_index])


def test_a_locator_takes_over_the_previous_configurations_grid_and_gives_a_fresh_locators_bits(box):
    # Reference: a TetLocator built on the configuration alone. A locator given the previous configuration's
    # locator takes that grid over while every tet's box lies in its box there (the boxes only propose
    # candidates; each is tested on the current configuration and the choice does not depend on their
    # order), so the answers are a fresh locator's bit for bit. Small moves (well within the margin) keep
    # the grid; a move of a node by more than the margin, or other tets, build a new one.
    mesh, _ = box
    rng = np.random.default_rng(21)
    rest = mesh.rest_positions
    size = 0.25  # the box's element size along x (4 cells)
    points = np.concatenate(
        [rng.uniform(-0.05, 1.05, (300, 3)), rest[rng.integers(0, rest.shape[0], 40)]]  # nodes: ties
    )
    previous = TetLocator(rest, mesh.tets, previous=None)
    previous.locate(points)
    grids = []
    positions = rest.copy()
    for step in range(6):
        positions = positions + rng.normal(0.0, 1e-4 * size, positions.shape)
        if step == 4:
            positions[13] += [1.5, 0.0, 0.0]  # one node moves by far more than the margin (radii 0.36-0.42)
        locator = TetLocator(positions, mesh.tets, previous=previous)
        for got, expected in zip(
            locator.locate(points), TetLocator(positions, mesh.tets).locate(points), strict=True
        ):
            np.testing.assert_array_equal(got, expected)
        grids.append(locator._grid)
        previous = locator
    assert grids[1] is grids[0] and grids[3] is grids[0]  # taken over (the first chained locator built it)
    assert grids[4] is not grids[3]  # the large move: a new grid
    assert grids[5] is grids[4]
    other = TetLocator(positions, mesh.tets[::-1].copy(), previous=previous)
    other.locate(points[:5])
    assert other._grid is not grids[5]  # other tets: never taken over
