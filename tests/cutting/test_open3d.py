"""Loading open3d through refsim's libusb loader, and open3d's normal estimation."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from refsim.cutting import TriangulationParameters, estimate_normals, estimate_normals_open3d

REPO = Path(__file__).resolve().parents[2]


def run_fresh(code: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120, check=False
    )


def test_import_refsim_cutting_does_not_import_open3d():
    result = run_fresh("import sys, refsim.cutting; print('open3d' in sys.modules)")
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "False"


def test_open3d_imports_in_a_fresh_process_through_the_loader():
    code = (
        "import sys, refsim.cutting as c\n"
        "o3d = c.import_open3d()\n"
        "assert c.import_open3d() is o3d\n"
        "assert 'open3d' in sys.modules\n"
        "pc = o3d.geometry.PointCloud()\n"
        "print(o3d.__version__)\n"
    )
    result = run_fresh(code)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip()


def curved_cloud() -> tuple[np.ndarray, np.ndarray]:
    """Jittered points on a cylinder of radius 5 mm (no distance ties), with the exact outward normals."""
    rng = np.random.default_rng(7)
    i, j = np.meshgrid(np.arange(12), np.arange(9), indexing="ij")
    u = (j.reshape(-1) + rng.uniform(-0.2, 0.2, 108)) * 0.5e-3
    v = (i.reshape(-1) + rng.uniform(-0.2, 0.2, 108)) * 0.5e-3
    radius = 5e-3
    points = np.column_stack([radius * np.sin(u / radius), v, radius * (1 - np.cos(u / radius))])
    exact = np.column_stack([-np.sin(u / radius), np.zeros(108), np.cos(u / radius)])
    return points, exact


def test_open3d_normals_agree_with_the_numpy_plane_fit():
    points, exact = curved_cloud()
    triangles = np.zeros((0, 3), dtype=np.int64)
    from_open3d = estimate_normals(points, triangles, TriangulationParameters(normal_estimation="open3d"))
    from_numpy = estimate_normals(points, triangles, TriangulationParameters(normal_estimation="pca"))
    # Same neighbourhoods, same covariance: equal to the round-off of a 3×3 eigenvector (~1e-12).
    np.testing.assert_allclose(from_open3d, from_numpy, rtol=0, atol=1e-9)
    # Consistently oriented (one sign for the whole cloud), and close to the exact normals: a plane fit over
    # a neighbourhood of radius r ≈ 1.25 mm on a cylinder of radius R = 5 mm tilts by at most ~r/R.
    cosines = np.einsum("pi,pi->p", from_open3d, exact)
    assert np.all(cosines > 0) or np.all(cosines < 0)
    assert np.abs(cosines).min() > np.cos(1.25e-3 / 5e-3)


def test_open3d_normals_of_a_plane_are_its_normal():
    rng = np.random.default_rng(8)
    points = np.column_stack([rng.uniform(0, 5e-3, (60, 2)), np.zeros(60)])
    normals = estimate_normals_open3d(points, radius=2e-3, max_neighbours=12)
    np.testing.assert_allclose(np.abs(normals[:, 2]), 1.0, rtol=0, atol=1e-12)
