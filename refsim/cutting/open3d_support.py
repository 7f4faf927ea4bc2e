"""Loading open3d safely, and open3d's normal estimation.

open3d's Linux wheels link ``libusb-1.0`` dynamically, and a bare ``import open3d`` fails on machines
without the system library (``ImportError: libusb-1.0.so.0: cannot open shared object file``). The pip package
``libusb-package`` ships that library; `import_open3d` loads it into the global symbol namespace with ctypes
before importing open3d, so no system package is needed. open3d is imported only inside the functions of this
module, never when ``refsim.cutting`` is imported.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging
import platform
from types import ModuleType

import numpy as np

__all__ = ["import_open3d", "estimate_normals_open3d"]

logger = logging.getLogger(__name__)


def _libusb_path() -> str | None:
    """Path of a libusb-1.0 shared library: the one of ``libusb-package``, else the system's, else None."""
    try:
        import libusb_package
    except ImportError:
        libusb_package = None
    if libusb_package is not None:
        path = libusb_package.get_library_path()
        if path is not None:
            return str(path)
    return ctypes.util.find_library("usb-1.0")


@functools.cache
def import_open3d() -> ModuleType:
    """Import open3d, first loading the libusb-1.0 library it needs on Linux; cached.

    Returns
    -------
    The ``open3d`` module.

    Raises
    ------
    ImportError
        If open3d is not installed, or if libusb-1.0 cannot be found or loaded; the message names what is
        missing and how to install it.
    """
    if platform.system() == "Linux":
        path = _libusb_path()
        if path is None:
            raise ImportError(
                "open3d needs the shared library libusb-1.0, which was not found: install the pip package "
                "'libusb-package' (it ships the library) or the system package libusb-1.0-0"
            )
        try:
            ctypes.CDLL(path, mode=ctypes.RTLD_GLOBAL)
        except OSError as error:
            raise ImportError(f"open3d needs libusb-1.0, but loading {path} failed: {error}") from error
        logger.debug("loaded libusb-1.0 from %s for open3d", path)
    try:
        import open3d
    except ImportError as error:
        raise ImportError(
            f"open3d could not be imported ({error}); install it with 'pip install open3d' (refsim's "
            "dependencies include it)"
        ) from error
    logger.debug("imported open3d %s", open3d.__version__)
    return open3d


def estimate_normals_open3d(points: np.ndarray, *, radius: float, max_neighbours: int) -> np.ndarray:
    """Unoriented unit normals by open3d's local plane fit (PCA of the neighbourhood covariance).

    Parameters
    ----------
    points : Point cloud [m], shape (p, 3).
    radius : Neighbourhood radius [m], > 0 (open3d's hybrid search: at most ``max_neighbours`` points within
        ``radius``).
    max_neighbours : Largest neighbourhood size, >= 3.

    Returns
    -------
    Unit normals, shape (p, 3), with an arbitrary sign per point; orient them afterwards. For a neighbourhood
    with fewer than three points or collinear points the direction is arbitrary (open3d's choice).
    """
    points = np.ascontiguousarray(points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (p, 3), got {points.shape}")
    if not (np.isfinite(radius) and radius > 0.0):
        raise ValueError(f"radius must be finite and > 0 [m], got {radius}")
    if max_neighbours < 3:
        raise ValueError(f"max_neighbours must be >= 3, got {max_neighbours}")
    if points.shape[0] == 0:
        return np.zeros((0, 3))
    o3d = import_open3d()
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(points)
    cloud.estimate_normals(
        o3d.geometry.KDTreeSearchParamHybrid(radius=float(radius), max_nn=int(max_neighbours)),
        fast_normal_computation=False,
    )
    normals = np.asarray(cloud.normals, dtype=float).copy()
    lengths = np.linalg.norm(normals, axis=1)
    bad = ~(lengths > 0.0)
    normals[bad] = (0.0, 0.0, 1.0)
    normals[~bad] /= lengths[~bad, None]
    return normals
