"""Barycentric coordinates in tetrahedra: exactness on vertices and faces, agreement with a linear solve."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from refsim.geometry import signed_volumes, tet_barycentric


def _random_tets(rng: np.random.Generator, count: int) -> np.ndarray:
    """Random tetrahedra with volumes bounded away from zero (both orientations)."""
    tets = rng.normal(size=(4 * count, 4, 3))
    edges = tets[:, 1:] - tets[:, :1]
    keep = np.abs(np.linalg.det(edges)) > 0.1
    return tets[keep][:count]


def _reference(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Barycentric coordinates from the linear system [v1−v0, v2−v0, v3−v0] λ' = p − v0."""
    edges = np.transpose(tets[:, 1:] - tets[:, :1], (0, 2, 1))
    rest = np.linalg.solve(edges, (points - tets[:, 0])[:, :, None])[:, :, 0]
    return np.concatenate([1.0 - rest.sum(axis=1, keepdims=True), rest], axis=1)


def test_signed_volume_of_unit_tet_and_its_mirror():
    unit = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    # V = det[e1, e2, e3] / 6 = 1/6, and swapping two vertices flips the sign.
    assert signed_volumes(unit[None])[0] == pytest.approx(1.0 / 6.0, rel=1e-15)
    assert signed_volumes(unit[None, [0, 2, 1, 3]])[0] == pytest.approx(-1.0 / 6.0, rel=1e-15)


def test_matches_linear_solve_on_random_points():
    rng = np.random.default_rng(0)
    tets = _random_tets(rng, 500)
    points = rng.normal(size=(tets.shape[0], 3)) * 2.0
    coordinates = tet_barycentric(points, tets)
    np.testing.assert_allclose(coordinates, _reference(points, tets), atol=1e-11)
    np.testing.assert_allclose(coordinates.sum(axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(np.einsum("qk,qki->qi", coordinates, tets), points, atol=1e-12)


@pytest.mark.parametrize("vertex", range(4))
def test_exact_on_vertices(vertex):
    tets = _random_tets(np.random.default_rng(1), 200)
    coordinates = tet_barycentric(tets[:, vertex], tets)
    expected = np.zeros((tets.shape[0], 4))
    expected[:, vertex] = 1.0
    np.testing.assert_array_equal(coordinates, expected)


def test_exact_zero_on_axis_aligned_face():
    # Face opposite vertex 0 lies in the plane z = 0.25; any point of that plane has coordinate 0 exactly.
    tet = np.array([[0.1, 0.2, 0.9], [0.0, 0.0, 0.25], [1.0, 0.0, 0.25], [0.0, 1.0, 0.25]])
    rng = np.random.default_rng(2)
    points = np.column_stack([rng.uniform(0, 0.5, 50), rng.uniform(0, 0.5, 50), np.full(50, 0.25)])
    coordinates = tet_barycentric(points, np.broadcast_to(tet, (50, 4, 3)))
    np.testing.assert_array_equal(coordinates[:, 0], 0.0)


def test_inside_iff_nonnegative():
    rng = np.random.default_rng(3)
    tets = _random_tets(rng, 300)
    weights = rng.dirichlet(np.ones(4), size=tets.shape[0])
    inside = np.einsum("qk,qki->qi", weights, tets)
    assert np.all(tet_barycentric(inside, tets) >= -1e-14)
    outside_weights = weights.copy()
    outside_weights[:, 0] = -0.05
    outside_weights[:, 1] += 0.05 + weights[:, 0]
    outside = np.einsum("qk,qki->qi", outside_weights, tets)
    assert np.all(tet_barycentric(outside, tets).min(axis=1) < 0)


def test_degenerate_gives_nan_and_bad_shapes_raise():
    flat = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]])
    assert np.all(np.isnan(tet_barycentric(np.zeros((1, 3)), flat)))
    with pytest.raises(ValueError, match="points"):
        tet_barycentric(np.zeros(3), flat)
    with pytest.raises(ValueError, match="tet_vertices"):
        tet_barycentric(np.zeros((2, 3)), flat)


@settings(deadline=None)
@given(
    arrays(np.float64, (4, 3), elements=st.floats(-10, 10)),
    arrays(np.float64, (4,), elements=st.floats(0.01, 1.0)),
)
def test_property_reproduces_convex_combinations(tet, weights):
    volume = abs(signed_volumes(tet[None])[0])
    scale = np.max(np.abs(tet - tet.mean(axis=0)))
    if scale < 1e-3 or volume < 1e-3 * scale**3:
        return  # nearly flat: the coordinates are ill-conditioned
    weights = weights / weights.sum()
    point = weights @ tet
    coordinates = tet_barycentric(point[None], tet[None])[0]
    np.testing.assert_allclose(coordinates, weights, atol=1e-9)
    assert coordinates.sum() == pytest.approx(1.0, abs=1e-14)
