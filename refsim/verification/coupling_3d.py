"""The needle's stiffness in 3-D under mesh refinement: the paper's cube and a clamped box (issue 9, item 2).

Slow studies (minutes, gigabytes at the finest levels) behind
``tests/verification/test_coupling_convergence.py`` and the tables of docs/coupling.md; the closed-form cases
of ``refsim verify`` are in :mod:`refsim.verification.coupling`, whose needles, material and entry positions
these use.
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.sparse as sp

from refsim.constraints import TISSUE
from refsim.fem.tissue import TissueModel
from refsim.geometry.search import TetLocator
from refsim.materials import HookeMaterial
from refsim.mesh.generators import box_mesh
from refsim.verification.coupling_problems import NEEDLE_PAPER, NEEDLE_THIN, PAPER_TISSUE
from refsim.verification.coupling_surface import SURFACE_POSITIONS

__all__ = [
    "BOX_CELLS",
    "BOX_DEPTH",
    "BOX_SIZE",
    "CUBE_DEPTH",
    "box_surface_study",
    "cube_needle_stiffness",
]


# ------------------------------------------------------------------------- the cube, 3-D, under refinement
CUBE_DEPTH = 0.04  # [m], inserted length (the rows every d_i = 0.5 mm from the top face down)


@functools.lru_cache(maxsize=2)
def _cube_system(cells: int, size: float, clamp_sides: bool, material: HookeMaterial):
    """(rest positions, tets, free DoFs, factorised K_ff, locator) of a Kuhn cube, bottom (sides) clamped."""
    from refsim.fem.linear import make_linear_solver

    mesh = box_mesh(size=(size, size, size), cells=(cells, cells, cells), origin=(-size / 2, -size / 2, 0.0))
    rest, tets = np.asarray(mesh.rest_positions), np.asarray(mesh.tets)
    tol = 1e-9 * size
    clamped = rest[:, 2] < tol
    if clamp_sides:
        side = np.abs(np.abs(rest[:, :2]) - size / 2) < tol
        clamped |= side[:, 0] | side[:, 1]
    model = TissueModel(rest, tets, material, fixed_nodes=np.flatnonzero(clamped))
    stiffness = model.rest_stiffness.tocsr()
    free = np.setdiff1d(np.arange(model.dof_count), model.fixed_dofs)
    solver = make_linear_solver()
    solver.factorise(stiffness[free][:, free])
    return rest, tets, free, solver, TetLocator(rest, tets)


@functools.lru_cache(maxsize=64)
def cube_needle_stiffness(
    cells: int,
    *,
    radii: tuple[float, ...] = (NEEDLE_THIN, NEEDLE_PAPER),
    depth: float = CUBE_DEPTH,
    spacing: float = 0.5e-3,
    entry: tuple[float, float] = (0.00123, 0.00231),
    material: HookeMaterial = PAPER_TISSUE,
    size: float = 0.1,
    clamp_sides: bool = False,
) -> dict[tuple[str, float, str], float]:
    """Static stiffness [N/m] of a rigid vertical needle inserted ``depth`` into a cube (the paper's: 100 mm).

    The cube of edge ``size`` (x, y centred on 0, z from 0 up) has its bottom clamped (and its sides too when
    ``clamp_sides``); the needle enters the top face at ``entry`` (x, y) [m]. The rows of the simulation
    (``ring_insertion_block`` with the sub-grid compliance of the inserted line, 3-D or infinite; or the
    paper's ``insertion_block``), bonded (stuck needle): K = gᵀ (W + C)⁻¹ g for a unit rigid translation,
    lateral (x) with the lateral rows, axial with the axial rows. W = H K⁻¹ Hᵀ on the rest stiffness (one
    factorisation per cube, for all needles, couplings and entries).

    Returns
    -------
    {(coupling, needle radius, "lateral" | "axial"): K}, coupling "ring" (3-D sub-grid compliance of the
    finite line, ``insertion.subgrid_line = "finite"``), "ring-infinite" (the plane-strain and antiplane
    values), "surface" (the ring with no sub-grid compliance on the points coupled on the needle's surface, h
    ≤ r: ``surface_subgrid=False``, infinite values elsewhere) or "paper".
    """
    from refsim.constraints.coupling import RingLayout, insertion_compliance, ring_insertion_block
    from refsim.constraints.insertion import InsertionPath, insertion_block
    from refsim.constraints.needle_geometry import RigidNeedleGeometry
    from refsim.constraints.rows import FRICTION
    from refsim.constraints.step_geometry import StepGeometry

    rest, tets, free, solver, locator = _cube_system(cells, size, clamp_sides, material)
    direction = np.array([0.0, 0.0, -1.0])
    top = np.array([entry[0], entry[1], size])
    count = int(round(depth / spacing))
    arc = 0.2 + (np.arange(count) + 0.5) * spacing  # the needle's base is 0.2 m above the top face
    centres = top + np.outer(arc - 0.2, direction)
    needle = RigidNeedleGeometry(base=top - 0.2 * direction, direction=direction, length=0.2 + depth)
    found, barycentric = locator.locate(centres)
    path = InsertionPath(found, barycentric, np.zeros(count, dtype=np.int64))
    geometry = StepGeometry(
        mesh_tets=tets, tissue_previous=rest, tissue_free=rest, needle_previous=needle, needle_free=needle
    )
    g, nu = material.shear_modulus, material.poisson_ratio
    blocks = {
        ("paper", radius): (insertion_block(path, geometry, friction_coefficient=1.0), None)
        for radius in radii
    }
    for radius in radii:
        rings = RingLayout.around(
            path,
            rest_positions=rest,
            mesh_tets=tets,
            locator=locator,
            tangents=needle.tangents(arc),
            needle_radius=radius,
        )
        block = ring_insertion_block(path, geometry, rings, friction_coefficient=1.0)
        common = dict(
            shear_modulus=g,
            poisson_ratio=nu,
            needle_radius=radius,
            mesh_size=rings.mesh_size,
            spacing=spacing,
        )
        blocks[("ring", radius)] = (block, insertion_compliance(block, **common, arc_lengths=arc))
        blocks[("ring-infinite", radius)] = (block, insertion_compliance(block, **common))
        blocks[("surface", radius)] = (block, insertion_compliance(block, **common, surface_subgrid=False))
    out = {}
    paper_done = None
    mesh_part = {}
    for (coupling, radius), (block, extra) in blocks.items():
        if coupling == "paper" and paper_done is not None:
            out[("paper", radius, "lateral")], out[("paper", radius, "axial")] = paper_done
            continue
        if id(block) not in mesh_part:
            dense = sp.csr_matrix(block.jacobians[TISSUE])[:, free].toarray()
            product = dense @ solver.solve(np.ascontiguousarray(dense.T))
            mesh_part[id(block)] = 0.5 * (product + product.T)
        compliance = mesh_part[id(block)]
        if extra is not None:
            compliance = compliance + np.diag(extra)
        values = []
        for kind, mask, motion in (
            ("lateral", block.kind != FRICTION, np.array([1.0, 0.0, 0.0])),
            ("axial", block.kind == FRICTION, direction),
        ):
            index = np.flatnonzero(mask)
            gap = block.directions[index] @ motion
            matrix = compliance[np.ix_(index, index)]
            force = np.linalg.pinv(matrix, rcond=1e-11, hermitian=True) @ gap
            out[(coupling, radius, kind)] = float(force @ gap)
            values.append(float(force @ gap))
        if coupling == "paper":
            paper_done = tuple(values)
    return out


# ------------------------------------------------ the 8 mm needle in a clamped 3-D box, h ≤ r on every level
BOX_SIZE = 0.04  # [m], edge of the box (bottom and sides clamped), the needle at its centre
BOX_DEPTH = 0.02  # [m], inserted length (rows every 0.5 mm)
BOX_CELLS = (8, 16, 32)  # cells per axis: h = 5, 2.5, 1.25 mm < r = 8 mm


def box_surface_study(
    cells=BOX_CELLS,
    *,
    needle_radius: float = NEEDLE_PAPER,
    size: float = BOX_SIZE,
    depth: float = BOX_DEPTH,
    positions=SURFACE_POSITIONS,
) -> dict[tuple[str, str], np.ndarray]:
    """K [N/m] of a rigid needle inserted ``depth`` at the centre of a box clamped on its bottom and sides,
    per level and entry position (the entry at ``positions`` × h from the box's axis, a grid node).

    Returns
    -------
    {(coupling, kind): K of shape (levels, positions)} for the couplings of :func:`cube_needle_stiffness`
    ("ring-infinite" the default, "ring" the finite line, "surface" the bare surface coupling, "paper").

    Raises
    ------
    ValueError
        When a level has h > r (the ring would not lie on the needle's surface).
    """
    sizes = np.array([size / n for n in cells])
    if np.any(sizes > needle_radius):
        raise ValueError(f"cells = {tuple(cells)}: h = {sizes.tolist()} m must be ≤ r = {needle_radius} m")
    runs = [
        [
            cube_needle_stiffness(
                n,
                radii=(needle_radius,),
                depth=depth,
                size=size,
                clamp_sides=True,
                entry=(o[0] * size / n, o[1] * size / n),
            )
            for o in positions
        ]
        for n in cells
    ]
    _cube_system.cache_clear()  # the finest factor holds ~2.5 GB
    return {
        (coupling, kind): np.array(
            [[run[(coupling, needle_radius, kind)] for run in level] for level in runs]
        )
        for coupling in ("ring-infinite", "ring", "surface", "paper")
        for kind in ("lateral", "axial")
    }
