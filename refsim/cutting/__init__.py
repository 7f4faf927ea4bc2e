"""The cut (layer 2): the cut surface in rest coordinates, grown as a strip with a crack tip, and its mapping
into the tissue."""

from refsim.cutting.growth import (
    CutGrowth,
    resample_polyline,
)
from refsim.cutting.surface import ClosestCutPoints, CutSurface, TriangulationReport

__all__ = [
    "ClosestCutPoints",
    "CutGrowth",
    "resample_polyline",
    "CutSurface",
    "TriangulationReport",
]
