"""Constraint builders (layer 3): rows of H, gaps and kinds for penetration, insertion and cutting."""

from refsim.constraints.friction import FrictionRows, friction_rows, slip_gaps
from refsim.constraints.insertion import InsertionPath, grow_path, insertion_block, points_beyond_tip
from refsim.constraints.needle_geometry import (
    BeamNeedleGeometry,
    NeedleGeometry,
    RigidNeedleGeometry,
    needle_rows,
)
from refsim.constraints.penetration import SurfaceContact, find_surface_contact, penetration_block
from refsim.constraints.rows import (
    BILATERAL,
    CUT_BORDER,
    CUT_SLIDE,
    FRICTION,
    INSERTION,
    PENETRATION,
    ROW_KIND_NAMES,
    SHAFT_CONTACT,
    SOURCE_NAMES,
    UNILATERAL,
    RowBlock,
    concatenate,
    empty_block,
    orthonormal_basis,
    point_rows,
)
from refsim.constraints.step_geometry import StepGeometry

__all__ = [
    "BILATERAL",
    "CUT_BORDER",
    "CUT_SLIDE",
    "FRICTION",
    "INSERTION",
    "ROW_KIND_NAMES",
    "PENETRATION",
    "SHAFT_CONTACT",
    "SOURCE_NAMES",
    "UNILATERAL",
    "BeamNeedleGeometry",
    "FrictionRows",
    "StepGeometry",
    "InsertionPath",
    "NeedleGeometry",
    "RigidNeedleGeometry",
    "RowBlock",
    "SurfaceContact",
    "concatenate",
    "empty_block",
    "find_surface_contact",
    "friction_rows",
    "slip_gaps",
    "grow_path",
    "insertion_block",
    "needle_rows",
    "orthonormal_basis",
    "penetration_block",
    "points_beyond_tip",
    "point_rows",
]
