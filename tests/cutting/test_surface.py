"""CutSurface: rest-state storage (the paper's equation 4), deformed mapping, border, closest points; surfaces
laid as strips (refsim.cutting.strip: layers of points joined column by column)."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.cutting import CutSurface
from refsim.cutting.strip import append_points, strip_triangles

SPACING = 0.5e-3  # [m]


def kuhn_box(cells: int, size: float) -> tuple[np.ndarray, np.ndarray]:
    """Cube [0, size]³ cut into cells³ cubes of six tetrahedra (Kuhn): positions (n, 3), tets (m, 4)."""
    axis = np.linspace(0.0, size, cells + 1)
    positions = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    node = np.arange((cells + 1) ** 3).reshape(cells + 1, cells + 1, cells + 1)
    paths = [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]
    tets = []
    for i, j, k in np.ndindex(cells, cells, cells):
        for path in paths:
            offset = np.zeros(3, int)
            chain = [node[i, j, k]]
            for axis_index in path:
                offset[axis_index] = 1
                chain.append(node[i + offset[0], j + offset[1], k + offset[2]])
            tets.append(chain)
    return positions, np.array(tets)


def locate(points: np.ndarray, positions: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force tet and barycentric coordinates of each point (test helper), shapes (p,), (p, 4)."""
    corners = positions[tets]  # (m, 4, 3)
    matrix = np.concatenate([corners.transpose(0, 2, 1), np.ones((len(tets), 1, 4))], axis=1)  # (m, 4, 4)
    rhs = np.concatenate([points, np.ones((len(points), 1))], axis=1)  # (p, 4)
    coordinates = np.einsum("mij,pj->pmi", np.linalg.inv(matrix), rhs)  # (p, m, 4)
    tet = np.argmax(coordinates.min(axis=2), axis=1)
    return tet, coordinates[np.arange(len(points)), tet]


@pytest.fixture(scope="module")
def mesh():
    return kuhn_box(3, 10 * SPACING)


def grid_triangles(layers: np.ndarray) -> np.ndarray:
    """Triangles joining consecutive layers (point indices, shape (l, c)), shape (2(l − 1)(c − 1), 3)."""
    pairs = zip(layers[:-1], layers[1:], strict=True)
    return np.concatenate([strip_triangles(back, front) for back, front in pairs])


@pytest.fixture(scope="module")
def strip(mesh):
    """A 6 × 8 planar grid (z = 2.3 spacings, in the box) laid in two batches of three layers of 8 columns,
    with its tissue mapping."""
    positions, tets = mesh
    i, j = np.meshgrid(np.arange(6), np.arange(8), indexing="ij")
    points = np.stack([(j + 1) * SPACING, (i + 2) * SPACING, np.full(i.shape, 2.3 * SPACING)], -1).reshape(
        -1, 3
    )
    tet, barycentric = locate(points, positions, tets)
    layers = np.arange(48).reshape(6, 8)
    surface = CutSurface.empty()
    for step, rows in enumerate((slice(0, 3), slice(2, 6))):  # the second batch joins on layer 2
        part = np.arange(24) + 24 * step
        rest = np.einsum("pk,pki->pi", barycentric[part], positions[tets[tet[part]]])  # equation 4
        triangles = grid_triangles(layers[rows])
        surface = append_points(surface, rest, tet[part], barycentric[part], 10 * step, triangles)
    return surface, points


def test_rest_points_are_the_mapped_rest_positions(strip, mesh):
    surface, points = strip
    positions, tets = mesh
    np.testing.assert_allclose(surface.rest_points, points, rtol=0, atol=1e-15)
    np.testing.assert_allclose(surface.deformed_points(positions, tets), points, rtol=0, atol=1e-15)
    assert surface.point_count == 48 and surface.triangle_count == 2 * 5 * 7
    assert np.array_equal(np.unique(surface.created_step), [0, 10])
    assert np.sum(surface.triangle_created_step == 0) == 2 * 2 * 7  # 3 rows of 8 after step 0


def test_affine_tissue_deformation_moves_cut_points_by_the_same_map(strip, mesh):
    surface, points = strip
    positions, tets = mesh
    rest_before = surface.rest_points.copy()
    rng = np.random.default_rng(5)
    matrix = np.eye(3) + 0.3 * rng.standard_normal((3, 3))
    shift = rng.standard_normal(3) * 1e-3
    deformed = surface.deformed_points(positions @ matrix.T + shift, tets)
    # Barycentric interpolation is exact for affine maps: error at round-off of |A x + b| ~ 1e-2 m.
    np.testing.assert_allclose(deformed, points @ matrix.T + shift, rtol=0, atol=1e-15)
    assert np.array_equal(surface.rest_points, rest_before)  # the rest state does not move


def test_arrays_are_read_only(strip):
    surface, _ = strip
    with pytest.raises(ValueError):
        surface.rest_points[0, 0] = 1.0
    with pytest.raises(ValueError):
        surface.triangles[0, 0] = 1


def test_border_of_a_grid(strip):
    surface, points = strip
    edges = surface.border_edges()
    assert edges.shape == (2 * 5 + 2 * 7, 2)
    on_rim = (
        np.isclose(points[:, 0], SPACING)
        | np.isclose(points[:, 0], 8 * SPACING)
        | np.isclose(points[:, 1], 2 * SPACING)
        | np.isclose(points[:, 1], 7 * SPACING)
    )
    assert np.array_equal(surface.border_points(), np.flatnonzero(on_rim))
    # Each border edge is one of the unit-length rim edges, and keeps the winding of its triangle.
    np.testing.assert_allclose(np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1), SPACING)
    directed = {tuple(e) for t in surface.triangles.tolist() for e in zip(t, t[1:] + t[:1], strict=True)}
    assert all(tuple(edge) in directed for edge in edges.tolist())


def test_closest_points_inside_and_outside(strip, mesh):
    surface, _ = strip
    positions, tets = mesh
    z = 2.3 * SPACING
    queries = np.array(
        [
            [3.3 * SPACING, 4.6 * SPACING, z + 1e-3],  # above a triangle's interior
            [3.0 * SPACING, 4.0 * SPACING, z - 2e-4],  # below an interior vertex
            [3.5 * SPACING, 4.0 * SPACING, z + 1e-4],  # above an interior edge
            [0.5 * SPACING, 4.2 * SPACING, z + 1e-4],  # beyond the border x = SPACING
            [SPACING - 1e-9, 4.2 * SPACING, z],  # just outside, in the plane
            [SPACING + 1e-9, 4.2 * SPACING, z + 1e-4],  # just inside, above
            [9.0 * SPACING, 8.0 * SPACING, z],  # beyond a corner
        ]
    )
    triangle, closest, barycentric, inside = surface.closest_points(queries, surface.rest_points)
    assert inside.tolist() == [True, True, True, False, False, True, False]
    expected = queries.copy()
    expected[:, 2] = z
    expected[3, 0] = expected[4, 0] = SPACING
    expected[6, :2] = (8 * SPACING, 7 * SPACING)
    np.testing.assert_allclose(closest, expected, rtol=0, atol=1e-15)
    np.testing.assert_allclose(barycentric.sum(axis=1), 1.0, rtol=0, atol=1e-14)
    corners = surface.rest_points[surface.triangles[triangle]]
    np.testing.assert_allclose(np.einsum("qk,qki->qi", barycentric, corners), closest, rtol=0, atol=1e-15)
    # The same queries through a rigid motion of the tissue give the moved answers.
    angle = 0.4
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    moved = surface.deformed_points(positions @ rotation.T + 0.01, tets)
    _, closest_moved, _, inside_moved = surface.closest_points(queries @ rotation.T + 0.01, moved)
    assert np.array_equal(inside_moved, inside)
    np.testing.assert_allclose(closest_moved, closest @ rotation.T + 0.01, rtol=0, atol=1e-14)


def test_closest_points_is_vectorised_over_many_queries(strip):
    surface, _ = strip
    rng = np.random.default_rng(6)
    queries = rng.uniform([0, SPACING, 0], [9 * SPACING, 8 * SPACING, 4 * SPACING], size=(500, 3))
    triangle, closest, _, inside = surface.closest_points(queries, surface.rest_points)
    # Reference: the plane z = 2.3 spacings clamped to the grid's rectangle; inside iff the foot lies in it.
    foot = queries.copy()
    foot[:, 2] = 2.3 * SPACING
    clamped = foot.copy()
    clamped[:, 0] = np.clip(foot[:, 0], SPACING, 8 * SPACING)
    clamped[:, 1] = np.clip(foot[:, 1], 2 * SPACING, 7 * SPACING)
    np.testing.assert_allclose(closest, clamped, rtol=0, atol=1e-15)
    assert np.array_equal(inside, np.all(foot == clamped, axis=1))
    assert triangle.shape == (500,)


def test_the_strip_is_oriented(strip):
    # Every triangle of a planar strip has the same unit normal, and the interpolated normals (the cut rows')
    # at any point of any triangle are that normal.
    surface, _ = strip
    corners = surface.rest_points[surface.triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    np.testing.assert_allclose(normals, np.tile(normals[0], (surface.triangle_count, 1)), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.abs(normals[0]), [0.0, 0.0, 1.0], rtol=0, atol=1e-12)
    weights = np.random.default_rng(7).dirichlet(np.ones(3), size=surface.triangle_count)
    interpolated = surface.interpolated_normals(
        surface.rest_points, np.arange(surface.triangle_count), weights
    )
    np.testing.assert_allclose(interpolated, normals, rtol=0, atol=1e-12)


def test_deformed_points_reject_a_mesh_that_does_not_match(strip, mesh):
    surface, _ = strip
    positions, tets = mesh
    with pytest.raises(ValueError, match="tets"):
        surface.deformed_points(positions, tets[:5])
    with pytest.raises(ValueError, match="positions"):
        surface.deformed_points(positions[:, :2], tets)


def test_closest_points_need_triangles():
    with pytest.raises(ValueError, match="no triangle"):
        CutSurface.empty().closest_points(np.zeros((1, 3)), np.zeros((0, 3)))


def test_report_of_the_last_addition(strip):
    surface, _ = strip
    report = surface.last_triangulation
    assert report.step == 10 and report.new_point_count == 24
    assert report.new_triangle_count == surface.triangle_count - int(
        np.sum(surface.triangle_created_step == 0)
    )
    assert report.new_triangle_count == 2 * 3 * 7


def test_closest_point_on_an_interior_ridge_edge_is_inside():
    # A roof z = −tan(10°)|x − 3 h| (a convex ridge along x = 3 h); a point above the ridge has its closest
    # point on the ridge edge and its orthogonal projection on either plane beyond that edge, yet it is inside
    # the surface. Above a border edge of the same ridge it is outside.
    i, j = np.meshgrid(np.arange(5), np.arange(7), indexing="ij")
    x, y = j.reshape(-1) * SPACING, i.reshape(-1) * SPACING
    points = np.column_stack([x, y, -np.tan(np.radians(10.0)) * np.abs(x - 3 * SPACING)])
    triangles = grid_triangles(np.arange(35).reshape(5, 7))  # layers along y, the ridge on column 3
    surface = append_points(
        CutSurface.empty(), points, np.zeros(35, int), np.full((35, 4), 0.25), 0, triangles
    )
    assert surface.triangle_count == 2 * 4 * 6
    queries = np.array([[3 * SPACING, 2.5 * SPACING, 1e-3], [3 * SPACING, -0.5 * SPACING, 1e-3]])
    _, closest, _, inside = surface.closest_points(queries, surface.rest_points)
    np.testing.assert_allclose(closest, [[3 * SPACING, 2.5 * SPACING, 0], [3 * SPACING, 0, 0]], atol=1e-15)
    assert inside.tolist() == [True, False]


@pytest.mark.parametrize("seed", range(6))
def test_inside_is_the_numpy_reference_bit_for_bit_on_edges_and_vertices(seed):
    # Reference: CutSurface._inside_reference, the NumPy evaluation (plane coordinates, then the edge-use and
    # border-vertex lookups) that the compiled pass (refsim.geometry.surface_kernels.inside_surface) does in
    # the same operations and order, so the tolerance is zero. A twisted pyramid sheet puts closest points
    # on interior and border edges and at interior and border vertices; queries snapped to the sheet's
    # vertices and edge midpoints (then lifted) reach each branch, and the test checks that they did.
    rng = np.random.default_rng(300 + seed)
    i, j = np.meshgrid(np.arange(5), np.arange(7), indexing="ij")
    x, y = j.reshape(-1) * SPACING, i.reshape(-1) * SPACING
    slopes = np.tan(np.radians(rng.uniform(5, 40, 2)))
    z = -slopes[0] * np.abs(x - 3 * SPACING) - slopes[1] * np.abs(y - 2 * SPACING)  # a peak at node 17
    z += rng.uniform(-0.1, 0.1) * x * y / SPACING
    points = np.column_stack([x, y, z])
    triangles = grid_triangles(np.arange(35).reshape(5, 7))
    surface = append_points(
        CutSurface.empty(), points, np.zeros(35, int), np.full((35, 4), 0.25), 0, triangles
    )
    edges = surface.triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    anchors = np.concatenate([points, points[edges].mean(axis=1), rng.uniform(-1, 7, (40, 3)) * SPACING])
    queries = anchors + rng.normal(0.0, 0.6 * SPACING, anchors.shape) * [0.05, 0.05, 1.0]
    found = surface.closest_points(queries, points)
    local = surface.triangles[found.triangle]
    reference = surface._inside_reference(queries, points[local], found.barycentric, local)
    np.testing.assert_array_equal(found.inside, reference)
    zeros = (found.barycentric <= 1e-9).sum(axis=1)
    plane_inside = surface._inside_reference(queries, points[local], np.ones_like(found.barycentric), local)
    for branch in (1, 2):  # closest point on an edge, at a vertex: decided by the lookups, both ways
        decided = ~plane_inside & (zeros == branch)
        assert found.inside[decided].any() and not found.inside[decided].all()
    assert found.inside.any() and not found.inside.all()
