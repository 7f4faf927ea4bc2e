"""The cut surface (layer 2): rest-state point cloud, incremental triangulation, mapping into the tissue.

``import refsim.cutting`` does not import open3d; `import_open3d` does, on first use.
"""

from refsim.cutting.growth import (
    CutGrowth,
    resample_polyline,
)
from refsim.cutting.open3d_support import estimate_normals_open3d, import_open3d
from refsim.cutting.surface import ClosestCutPoints, CutSurface, TriangulationReport
from refsim.cutting.triangulation import (
    TriangulationParameters,
    estimate_normals,
    orient_normals,
    triangulate_incremental,
)

__all__ = [
    "ClosestCutPoints",
    "CutGrowth",
    "resample_polyline",
    "CutSurface",
    "TriangulationParameters",
    "TriangulationReport",
    "estimate_normals",
    "estimate_normals_open3d",
    "import_open3d",
    "orient_normals",
    "triangulate_incremental",
]
