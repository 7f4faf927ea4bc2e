"""Small hand-made geometries for the constraint builders."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.constraints import RigidNeedleGeometry, StepGeometry
from refsim.mesh import box_mesh


@pytest.fixture(scope="module")
def block():
    """A 20 mm box of 2 × 2 × 2 Kuhn cells (48 tets), origin at 0."""
    return box_mesh(size=(0.02, 0.02, 0.02), cells=(2, 2, 2))


def rigid_needle(tip, direction, length=0.05) -> RigidNeedleGeometry:
    direction = np.asarray(direction, dtype=float)
    direction = direction / np.linalg.norm(direction)
    return RigidNeedleGeometry(np.asarray(tip, dtype=float) - length * direction, direction, length)


def still_geometry(mesh, needle_previous, needle_free=None, tissue_free=None) -> StepGeometry:
    """Tissue at rest at the start of the step; optional free motion of either body."""
    return StepGeometry(
        mesh_tets=mesh.tets,
        tissue_previous=mesh.rest_positions,
        tissue_free=mesh.rest_positions if tissue_free is None else tissue_free,
        needle_previous=needle_previous,
        needle_free=needle_previous if needle_free is None else needle_free,
    )
