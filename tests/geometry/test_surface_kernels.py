"""The compiled surface and polyline passes against their NumPy references, bit for bit.

References: the area-weighted vertex normals as ``np.add.at`` sums the faces' ``np.cross`` vectors (corner 0
of every triangle, then 1, then 2) divided by ``np.linalg.norm``; the closest segment of a polyline as the
broadcast NumPy evaluation ``refsim.constraints.cut`` made before (clamped projection, ``np.argmin`` of the
distances). The kernels do the same operations in the same order, so the tolerance is zero: on random
inputs of mixed magnitudes another order of the additions rounds differently.
"""

import numpy as np
import pytest

from refsim.geometry.surface_kernels import polyline_closest, vertex_normals


def _numpy_vertex_normals(points, triangles):
    corners = points[triangles]
    face = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    summed = np.zeros_like(points)
    for corner in range(3):
        np.add.at(summed, triangles[:, corner], face)
    return summed / np.maximum(np.linalg.norm(summed, axis=1, keepdims=True), 1e-300)


def _numpy_polyline_closest(points, polyline):
    start, along = polyline[:-1], polyline[1:] - polyline[:-1]
    lengths = np.einsum("sj,sj->s", along, along)
    offsets = points[:, None, :] - start[None]
    raw = np.einsum("ksj,sj->ks", offsets, along) / np.where(lengths > 0, lengths, 1.0)
    t = np.clip(raw, 0.0, 1.0)
    distance = np.linalg.norm(points[:, None, :] - (start[None] + t[..., None] * along[None]), axis=2)
    segment = np.argmin(distance, axis=1)
    rows = np.arange(points.shape[0])
    return segment, t[rows, segment], raw[rows, segment]


@pytest.mark.parametrize("seed", range(20))
def test_vertex_normals_are_numpys_bits(seed):
    rng = np.random.default_rng(seed)
    count = int(rng.integers(3, 120))
    points = rng.standard_normal((count, 3)) * 10.0 ** rng.uniform(-6, 2, size=(count, 1))
    triangles = rng.integers(0, count, size=(int(rng.integers(1, 300)), 3))
    got = vertex_normals(points, triangles)
    np.testing.assert_array_equal(got, _numpy_vertex_normals(points, triangles))
    used = np.unique(triangles)
    unused = np.setdiff1d(np.arange(count), used)
    np.testing.assert_array_equal(got[unused], 0.0)  # a vertex in no triangle stays zero


@pytest.mark.parametrize("seed", range(20))
def test_polyline_closest_is_numpys_bits(seed):
    rng = np.random.default_rng(100 + seed)
    polyline = np.cumsum(rng.standard_normal((int(rng.integers(2, 25)), 3)) * 1e-3, axis=0)
    if polyline.shape[0] > 3:
        polyline[2] = polyline[1]  # a zero-length segment
    points = polyline.mean(axis=0) + rng.standard_normal((int(rng.integers(1, 50)), 3)) * 3e-3
    expected = _numpy_polyline_closest(points, polyline)
    for got, reference in zip(polyline_closest(points, polyline), expected, strict=True):
        np.testing.assert_array_equal(got, reference)


def test_polyline_closest_takes_the_first_of_equal_distances():
    # A point equidistant from two segments' clamped ends: np.argmin's first.
    polyline = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    segment, parameter, raw = polyline_closest(np.array([[2.0, -1.0, 0.0]]), polyline)
    assert segment.tolist() == [0] and parameter.tolist() == [1.0] and raw.tolist() == [2.0]
