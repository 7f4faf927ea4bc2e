"""Incremental greedy triangulation of the cut surface (issue 5, paper section 4).

The checks below are computed independently of the implementation: angles by the law of cosines, edge uses by
counting, overlaps by sampling the surface's parameter domain.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from refsim.cutting import CutSurface, TriangulationParameters, triangulate_incremental

SPACING = 0.5e-3  # the paper's d_c [m]


def grow(surface: CutSurface, batches: list[np.ndarray]) -> list[CutSurface]:
    """Surfaces after each batch of points (tet index and barycentric coordinates are placeholders)."""
    history = []
    for step, batch in enumerate(batches):
        count = batch.shape[0]
        surface = surface.with_points(batch, np.zeros(count, int), np.tile([1.0, 0, 0, 0], (count, 1)), step)
        history.append(surface)
    return history


def grid_uv(rows: int, columns: int) -> np.ndarray:
    """Regular grid in the parameter plane, row by row, shape (rows * columns, 2) [m]."""
    i, j = np.meshgrid(np.arange(rows), np.arange(columns), indexing="ij")
    return np.stack([j * SPACING, i * SPACING], axis=-1).reshape(-1, 2).astype(float)


def rows_of(points: np.ndarray, columns: int) -> list[np.ndarray]:
    return [points[start : start + columns] for start in range(0, points.shape[0], columns)]


def triangle_angles(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Angles [rad] by the law of cosines, shape (t, 3)."""
    a, b, c = (points[triangles[:, k]] for k in range(3))
    la, lb, lc = (np.linalg.norm(x - y, axis=1) for x, y in ((b, c), (c, a), (a, b)))
    alpha = np.arccos(np.clip((lb**2 + lc**2 - la**2) / (2 * lb * lc), -1, 1))
    beta = np.arccos(np.clip((la**2 + lc**2 - lb**2) / (2 * la * lc), -1, 1))
    return np.stack([alpha, beta, np.pi - alpha - beta], axis=1)


def unit_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    a, b, c = (points[triangles[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


# Round-off allowance on angles computed by arccos for well-shaped triangles (|dθ| ~ 1e-16 / sin θ).
ANGLE_ROUND_OFF = 1e-9


def assert_valid(surface: CutSurface) -> None:
    """θ_min <= angles <= θ_max, neighbouring normals within θ_s, edge-manifold and consistently oriented."""
    points, triangles, parameters = surface.rest_points, surface.triangles, surface.parameters
    assert triangles.shape[0] > 0
    angles = triangle_angles(points, triangles)
    assert angles.min() >= parameters.min_angle - ANGLE_ROUND_OFF
    assert angles.max() <= parameters.max_angle + ANGLE_ROUND_OFF
    directed = Counter(map(tuple, triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2).tolist()))
    undirected = Counter(tuple(sorted(edge)) for edge in directed.elements())
    assert max(undirected.values()) <= 2, "an edge is used by more than two triangles"
    assert max(directed.values()) == 1, "two triangles traverse an edge the same way (inconsistent winding)"
    normals = unit_normals(points, triangles)
    owner = {}
    for index, triangle in enumerate(triangles.tolist()):
        for e in range(3):
            owner.setdefault(tuple(sorted((triangle[e], triangle[(e + 1) % 3]))), []).append(index)
    pairs = np.array([users for users in owner.values() if len(users) == 2])
    if pairs.size:
        cosines = np.einsum("ij,ij->i", normals[pairs[:, 0]], normals[pairs[:, 1]])
        assert np.arccos(np.clip(cosines, -1, 1)).max() <= parameters.max_surface_angle + ANGLE_ROUND_OFF
    vertex_cosines = np.einsum("tj,tkj->tk", normals, surface.normals[triangles])
    assert np.arccos(np.clip(vertex_cosines, -1, 1)).max() <= parameters.max_surface_angle + ANGLE_ROUND_OFF


def assert_history(history: list[CutSurface]) -> None:
    """Each addition keeps every existing point and triangle and adds triangles only around new points."""
    for before, after in zip(history, history[1:], strict=False):
        assert np.array_equal(after.rest_points[: before.point_count], before.rest_points)
        assert np.array_equal(after.triangles[: before.triangle_count], before.triangles)
        assert np.array_equal(
            after.triangle_created_step[: before.triangle_count], before.triangle_created_step
        )
        new = after.triangles[before.triangle_count :]
        assert np.all(new.max(axis=1) >= before.point_count), "a new triangle has no new vertex"


def coverage_counts(uv: np.ndarray, triangles: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """How many triangles (mapped to the parameter plane) hold each sample point, shape (s,)."""
    a, b, c = (uv[triangles[:, k]] for k in range(3))

    def cross(p, q, r):
        return (q[:, None, 0] - p[:, None, 0]) * (r[None, :, 1] - p[:, None, 1]) - (
            q[:, None, 1] - p[:, None, 1]
        ) * (r[None, :, 0] - p[:, None, 0])

    signs = np.stack([cross(a, b, samples), cross(b, c, samples), cross(c, a, samples)])
    inside = np.all(signs > 0, axis=0) | np.all(signs < 0, axis=0)
    return inside.sum(axis=0)


def uv_area(uv: np.ndarray, triangles: np.ndarray) -> float:
    a, b, c = (uv[triangles[:, k]] for k in range(3))
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    return float(0.5 * np.abs(cross).sum())


@pytest.fixture(scope="module", params=["pca", "open3d"])
def planar_history(request):
    """The paper's final size: 110 points (11 rows of 10, 0.5 mm apart), grown row by row in z = 0."""
    uv = grid_uv(11, 10)
    points = np.column_stack([uv, np.zeros(len(uv))])
    surface = CutSurface.empty(TriangulationParameters(normal_estimation=request.param))
    return uv, grow(surface, rows_of(points, 10))


def test_planar_grid_meets_every_criterion(planar_history):
    _, history = planar_history
    for surface in history[1:]:
        assert_valid(surface)
    assert_history(history)


def test_planar_grid_is_covered_exactly_once(planar_history):
    uv, history = planar_history
    surface = history[-1]
    # Any triangulation of the grid using all points has 2(r−1)(c−1) triangles (Euler: t = 2n − b − 2).
    assert surface.triangle_count == 2 * 10 * 9
    # A missing triangle would leave at least the smallest admissible area, SPACING²/2, uncovered.
    hull = ConvexHull(uv).volume
    assert abs(uv_area(uv, surface.triangles) - hull) < 0.5 * SPACING**2
    samples = np.random.default_rng(0).uniform([0, 0], [9 * SPACING, 10 * SPACING], size=(2000, 2))
    assert np.all(coverage_counts(uv, surface.triangles, samples) == 1)


def test_curved_strip_is_valid_and_complete():
    # A strip bent on a cylinder of radius 5 mm: 0.1 rad (5.7°) between neighbouring points, under θ_s = 45°.
    radius, rows, columns = 5e-3, 20, 8
    uv = grid_uv(rows, columns)
    points = np.column_stack(
        [radius * np.sin(uv[:, 0] / radius), uv[:, 1], radius * (1 - np.cos(uv[:, 0] / radius))]
    )
    history = grow(
        CutSurface.empty(TriangulationParameters(normal_estimation="pca")), rows_of(points, columns)
    )
    for surface in history[1:]:
        assert_valid(surface)
    assert_history(history)
    assert history[-1].triangle_count == 2 * (rows - 1) * (columns - 1)
    samples = np.random.default_rng(1).uniform([0, 0], [7 * SPACING, 19 * SPACING], size=(2000, 2))
    assert np.all(coverage_counts(uv, history[-1].triangles, samples) == 1)


def test_tearing_extension_stitches_only_beyond_the_border():
    # A strip 10 × 8, then a tear 60° from the border, sampled every d_c (a sheared lattice).
    rows, columns = 8, 10
    uv = grid_uv(rows, columns)
    direction = np.array([math.cos(math.radians(60)), math.sin(math.radians(60))])
    top = uv[-columns:]
    tear = np.concatenate([top + k * SPACING * direction for k in range(1, 5)])
    all_uv = np.concatenate([uv, tear])
    points = np.column_stack([all_uv, np.zeros(len(all_uv))])
    parameters = TriangulationParameters(normal_estimation="pca")
    history = grow(
        CutSurface.empty(parameters), [*rows_of(points[: rows * columns], columns), points[rows * columns :]]
    )
    before, after = history[-2], history[-1]
    assert_valid(after)
    assert_history(history)
    new = after.triangles[before.triangle_count :]
    assert np.any(new.min(axis=1) < before.point_count), "the extension is not stitched to the old border"
    # Nothing is added on the old side of the border (y below the top row, in the parameter plane).
    centroids = all_uv[new].mean(axis=1)
    assert np.all(centroids[:, 1] > top[0, 1])
    # The rhombi of a 60° lattice split into two equilateral triangles; with the stitching band (a band of
    # parallelograms between the top row and the first torn row) everything is covered: the union's area is
    # the rectangle plus the parallelogram, to less than the smallest triangle (√3/4 · SPACING²).
    expected = (columns - 1) * SPACING * ((rows - 1) * SPACING + 4 * SPACING * direction[1])
    assert abs(uv_area(all_uv, after.triangles) - expected) < math.sqrt(3) / 4 * SPACING**2
    samples = np.random.default_rng(2).uniform([0, 0], [12 * SPACING, 11 * SPACING], size=(3000, 2))
    assert coverage_counts(all_uv, after.triangles, samples).max() == 1


def test_fold_sharper_than_surface_angle_is_not_bridged():
    # Two half-planes meeting at 90° along column 5, with their exact normals given (the fold column takes the
    # flat sheet's). θ_s = 30°: a triangle bridging the fold tilts 45° from the normals of its vertices.
    uv = grid_uv(10, 12)
    column = np.rint(uv[:, 0] / SPACING).astype(int)
    folded = column > 5
    points = np.column_stack([uv, np.zeros(len(uv))])
    points[folded, 0] = 5 * SPACING
    points[folded, 2] = (column[folded] - 5) * SPACING
    normals = np.tile([0.0, 0.0, 1.0], (len(uv), 1))
    normals[folded] = (-1.0, 0.0, 0.0)
    parameters = TriangulationParameters.from_degrees(
        min_angle=10.0, max_angle=120.0, max_surface_angle=30.0, normal_estimation="pca"
    )
    surface = CutSurface.empty(parameters)
    for step, rows in enumerate(np.split(np.arange(len(uv)), 10)):
        count = rows.size
        surface = surface.with_points(
            points[rows],
            np.zeros(count, int),
            np.tile([1.0, 0, 0, 0], (count, 1)),
            step,
            normals=normals[rows],
        )
    assert_valid(surface)
    sides = column[surface.triangles]
    assert not np.any((sides.min(axis=1) < 5) & (sides.max(axis=1) > 5)), "a triangle bridges the fold"
    assert np.any(sides.max(axis=1) <= 5) and np.any(sides.min(axis=1) > 5)


def test_ridge_steeper_than_surface_angle_is_not_joined():
    # A roof z = tan(20°)|x − x5| with all point normals given as +z: every triangle is 20° from its vertex
    # normals (allowed by θ_s = 30°), but triangles on both sides of the ridge would meet at 40° > θ_s.
    uv = grid_uv(8, 11)
    column = np.rint(uv[:, 0] / SPACING).astype(int)
    points = np.column_stack([uv, math.tan(math.radians(20.0)) * np.abs(uv[:, 0] - 5 * SPACING)])
    parameters = TriangulationParameters.from_degrees(
        min_angle=10.0, max_angle=120.0, max_surface_angle=30.0, normal_estimation="pca"
    )
    surface = CutSurface.empty(parameters)
    for step, rows in enumerate(np.split(np.arange(len(uv)), 8)):
        count = rows.size
        surface = surface.with_points(
            points[rows],
            np.zeros(count, int),
            np.tile([1.0, 0, 0, 0], (count, 1)),
            step,
            normals=np.tile([0.0, 0.0, 1.0], (count, 1)),
        )
    assert_valid(surface)
    sides = column[surface.triangles]
    assert np.any(sides.max(axis=1) <= 5) and np.any(sides.min(axis=1) >= 5)


def test_jittered_grid_and_tight_angles_meet_the_criteria():
    rng = np.random.default_rng(3)
    uv = grid_uv(15, 8) + rng.uniform(-0.2, 0.2, size=(120, 2)) * SPACING
    points = np.column_stack([uv, 1e-4 * np.sin(uv[:, 1] / 2e-3)])
    parameters = TriangulationParameters.from_degrees(
        min_angle=30.0, max_angle=100.0, max_surface_angle=20.0, normal_estimation="pca"
    )
    history = grow(CutSurface.empty(parameters), rows_of(points, 8))
    for surface in history[1:]:
        if surface.triangle_count:
            assert_valid(surface)
    assert history[-1].triangle_count > 100
    assert_history(history)
    samples = rng.uniform(uv.min(axis=0), uv.max(axis=0), size=(3000, 2))
    assert coverage_counts(uv, history[-1].triangles, samples).max() == 1


def test_same_input_gives_same_triangles():
    uv = grid_uv(6, 7) + np.random.default_rng(4).uniform(-0.15, 0.15, size=(42, 2)) * SPACING
    points = np.column_stack([uv, np.zeros(42)])
    first = grow(CutSurface.empty(TriangulationParameters(normal_estimation="pca")), rows_of(points, 7))[-1]
    second = grow(CutSurface.empty(TriangulationParameters(normal_estimation="pca")), rows_of(points, 7))[-1]
    assert np.array_equal(first.triangles, second.triangles)
    assert np.array_equal(first.normals, second.normals)


def test_no_new_points_means_no_triangulation():
    uv = grid_uv(3, 4)
    surface = grow(
        CutSurface.empty(TriangulationParameters(normal_estimation="pca")),
        [np.column_stack([uv, np.zeros(12)])],
    )[-1]
    same = surface.with_points(np.zeros((0, 3)), np.zeros(0, int), np.zeros((0, 4)), 5)
    assert same is surface


def test_collinear_first_row_is_triangulated_with_the_second():
    uv = grid_uv(2, 6)
    points = np.column_stack([uv, np.zeros(12)])
    history = grow(CutSurface.empty(TriangulationParameters(normal_estimation="pca")), rows_of(points, 6))
    assert history[0].triangle_count == 0  # a single row spans no plane
    assert history[1].triangle_count == 2 * 5
    assert_valid(history[1])


def test_triangulate_incremental_rejects_bad_input():
    points = np.column_stack([grid_uv(2, 2), np.zeros(4)])
    normals = np.tile([0.0, 0, 1], (4, 1))
    with pytest.raises(ValueError, match="first_new_point"):
        triangulate_incremental(points, normals, np.zeros((0, 3), int), 7)
    with pytest.raises(ValueError, match="existing triangles"):
        triangulate_incremental(points, normals, np.array([[0, 1, 3]]), 2)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("min_angle", 0.0),
        ("min_angle", 1.2),
        ("max_angle", 3.2),
        ("max_surface_angle", 2.0),
        ("neighbour_multiplier", 0.5),
        ("max_neighbours", 2),
        ("search_radius", -1.0),
        ("normal_estimation", "mls"),
        ("min_angle", float("nan")),
    ],
)
def test_parameters_are_validated(field, value):
    with pytest.raises(ValueError, match=field):
        TriangulationParameters(**{field: value})
