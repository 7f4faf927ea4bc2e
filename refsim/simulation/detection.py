"""Detection: the rows of one step from the free positions, by phase (DESIGN.md, step 3).

- approach: the tip against the closest surface point (penetration), when within the contact distance;
- insertion: the insertion points along the path;
- cutting: the entry point's rows, and the sliding and border rows of the cut surface.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from refsim.constraints import (
    RowBlock,
    StepGeometry,
    SurfaceContact,
    concatenate,
    empty_block,
    find_surface_contact,
    insertion_block,
    penetration_block,
)
from refsim.constraints.cut import FrontRows, strip_cut_block
from refsim.geometry import SurfaceProjector
from refsim.scene import Scene
from refsim.simulation.state import Phase, SimulationState

__all__ = ["Detection", "Detector"]


@dataclass(frozen=True)
class Detection:
    """The rows of a step and what the events need to know about them.

    Attributes
    ----------
    rows : The step's rows, in solver order.
    contact : The tip's closest surface point (approach phase), else None.
    front : Where the front rows press on the crack tip (cutting phase); their indices are into ``rows``.
    """

    rows: RowBlock
    contact: SurfaceContact | None = None
    front: FrontRows = field(default_factory=FrontRows.empty)


class Detector:
    """Builds the rows of each step for a scene.

    Parameters
    ----------
    scene : The validated scene.
    faces : Tissue surface triangles, shape (f, 3).
    needle_dof_count : DoFs of the needle in the constraint problem, None for a rigid needle.
    mesh_size : Typical tet size h [m] (the cut rows' sub-grid compliance depends on it).
    """

    def __init__(self, scene: Scene, faces: np.ndarray, needle_dof_count: int | None, mesh_size: float = 0.0) -> None:
        self.insertion = scene.insertion
        self.cutting = scene.cutting
        self.faces = faces
        self.needle_dof_count = needle_dof_count
        self.slide_compliance = _slide_compliance(scene, mesh_size) if scene.cutting.enabled else 0.0

    def detect(self, state: SimulationState, geometry: StepGeometry) -> Detection:
        """The rows of the step that starts from ``state``, on the free positions of ``geometry``."""
        spec = self.insertion
        blocks: list[RowBlock] = []
        contact = None
        front = FrontRows.empty()
        if state.phase == Phase.APPROACH:
            projector = SurfaceProjector(geometry.tissue_free, self.faces)
            contact = find_surface_contact(projector, self.faces, geometry.needle_free.tip)
            if contact.gap < spec.contact_distance:
                blocks.append(
                    penetration_block(contact, geometry, friction_coefficient=spec.surface_friction_coefficient)
                )
        elif state.path.point_count and not (state.phase == Phase.CUTTING and self.cutting.law == "energy"):
            # In the energy law's cutting phase the cut holds the needle (sliding rows, crack tip) and the entry
            # point only marks the inserted length: anchored there, it would drag the tissue along the stroke.
            blocks.append(
                insertion_block(
                    state.path,
                    geometry,
                    friction_coefficient=spec.shaft_friction_coefficient,
                    normal_preload=spec.shaft_normal_force * spec.spacing,
                )
            )
        if state.phase == Phase.CUTTING and state.cut_strip is not None:
            entry = state.path.positions(state.tissue.positions, geometry.mesh_tets)[:1]
            entry_arc_length = float(geometry.needle_previous.project(entry)[0][0])
            offset = sum(block.row_count for block in blocks)
            cutting = self.cutting
            strength = cutting.fracture_energy if cutting.law == "energy" else np.inf
            block, front = strip_cut_block(
                state.cut,
                state.cut_strip,
                geometry,
                entry_arc_length=entry_arc_length,
                spacing=cutting.point_spacing,
                cut_direction=state.cut_direction,
                front_strength=strength,
                slide_compliance=self.slide_compliance,
            )
            if block is not None:
                blocks.append(block)
            front = replace(front, rows=front.rows + offset)
        if not blocks:
            rows = empty_block(geometry.tissue_dof_count, self.needle_dof_count)
        else:
            rows = concatenate(blocks)
        return Detection(rows, contact, front)


def _slide_compliance(scene: Scene, mesh_size: float) -> float:
    """Sub-grid compliance of one sliding row [m/N]: the annulus between the needle (r) and the equivalent
    radius of the mesh a = max(r, h) + h/4 under a lateral line load over d_c (Peaceman's well model, the
    Kelvin plane-strain solution; see docs/coupling.md), C = (3 − 4ν) ln(a/r) / (8πG(1 − ν) d_c)."""
    import math

    nu = scene.tissue.poisson_ratio
    shear = scene.tissue.youngs_modulus / (2.0 * (1.0 + nu))
    radius = scene.needle.radius
    if mesh_size <= 0.0:
        return 0.0
    equivalent = max(radius, mesh_size) + 0.25 * mesh_size
    return (3.0 - 4.0 * nu) * math.log(equivalent / radius) / (
        8.0 * math.pi * shear * (1.0 - nu) * scene.cutting.point_spacing
    )
