"""Timings of the tissue model's stages, for ``refsim bench`` (figures, never asserted)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from refsim.fem.tissue import TissueModel, TissueState
from refsim.materials import HookeMaterial

__all__ = ["bench_tissue"]

logger = logging.getLogger(__name__)

# The paper's cube (DESIGN.md): 0.1 m, E = 500 kPa, ν = 0.4; density 1000 kg/m³ and dt = 0.01 s
# are our choices.
_CUBE_SIZE = 0.1
_MATERIAL = HookeMaterial(youngs_modulus=5.0e5, poisson_ratio=0.4, density=1000.0)
_DT = 0.01


def _best_ms(function: Callable[[], object], repeats: int) -> tuple[float, object]:
    """Smallest wall time over ``repeats`` calls [ms], and the last result."""
    best, result = np.inf, None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        best = min(best, time.perf_counter() - start)
    return 1e3 * best, result


def _cube(cells: int) -> tuple[np.ndarray, np.ndarray]:
    try:
        from refsim.mesh import box_mesh
    except ImportError:  # the package's __init__ may not export it yet
        from refsim.mesh.generators import box_mesh
    mesh = box_mesh(size=(_CUBE_SIZE,) * 3, cells=(cells,) * 3, origin=(0.0, 0.0, 0.0))
    return np.asarray(mesh.rest_positions, dtype=float), np.asarray(mesh.tets)


def bench_tissue(
    cells_per_axis: tuple[int, ...] = (8, 16, 24),
    repeats: int = 3,
    *,
    max_factorisation_seconds: float = 60.0,
) -> list[dict[str, float | int]]:
    """Time the stages of one tissue step on cube meshes of the paper's 0.1 m cube.

    For each size: a cube with ``cells`` hexahedra per axis (6 tets each; 8 is the paper's 3,072 tets), bottom
    face fixed, gravity, a smoothly deformed configuration. Stages, best of ``repeats`` in milliseconds:
    co-rotational update (polar rotations of every tet), assembly (internal forces and the tangent R K Rᵀ on
    the fixed pattern), factorisation (:meth:`TissueModel.step_system`: A = M/dt² + C/dt + K, elimination of
    the fixed DoFs, sparse LU) and one solve (the free motion's right-hand side through the factors).
    Sizes after one whose factorisation took longer than ``max_factorisation_seconds`` are skipped (logged).
    The default stops at 24 cells per axis (the 3× refinement): with SuperLU the 32-cell cube (196,608 tets,
    ~107k free DoFs) took more than 7 minutes to factorise on a 2-core machine.

    Returns
    -------
    One dict per size: ``cells_per_axis``, ``node_count``, ``tet_count``, ``dof_count``, ``setup_ms``
    (building the model: scikit-fem element matrices and the sparsity pattern, once), ``rotations_ms``,
    ``assembly_ms``, ``factorisation_ms``, ``solve_ms``.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats!r}")
    rows: list[dict[str, float | int]] = []
    for cells in cells_per_axis:
        row = _bench_one(int(cells), repeats)
        logger.info("tissue bench: %s", row)
        rows.append(row)
        if row["factorisation_ms"] > 1e3 * max_factorisation_seconds:
            logger.warning(
                "factorisation took %.1f s on %d cells per axis: larger sizes skipped",
                row["factorisation_ms"] / 1e3,
                cells,
            )
            break
    return rows


def _bench_one(cells: int, repeats: int) -> dict[str, float | int]:
    """Timings of one cube size (see :func:`bench_tissue`)."""
    rest, tets = _cube(cells)
    start = time.perf_counter()
    model = TissueModel(
        rest,
        tets,
        _MATERIAL,
        rayleigh_mass=1.0,
        rayleigh_stiffness=0.01,
        fixed_nodes=np.flatnonzero(rest[:, 2] < 1e-9 * _CUBE_SIZE),
        gravity=(0.0, 0.0, -9.81),
    )
    setup_ms = 1e3 * (time.perf_counter() - start)
    positions = rest + 0.01 * _CUBE_SIZE * np.sin(20.0 * rest / _CUBE_SIZE)
    positions[model.fixed_nodes] = rest[model.fixed_nodes]
    state = TissueState(positions=positions, velocities=np.zeros_like(rest))

    rotations_ms, rotations = _best_ms(lambda: model.element_rotations(state.positions), repeats)

    def assemble():
        return model.internal_forces(state.positions, rotations), model.tangent_stiffness(rotations)

    assembly_ms, (internal, _) = _best_ms(assemble, repeats)
    factor_repeats = repeats if cells <= 16 else 1
    factorisation_ms, system = _best_ms(lambda: model.step_system(rotations, _DT), factor_repeats)
    forces = (model.external_forces() - internal).ravel()
    solve_ms, _ = _best_ms(lambda: system.free_displacement(forces, state.velocities.ravel()), repeats)
    return {
        "cells_per_axis": cells,
        "node_count": model.node_count,
        "tet_count": model.tet_count,
        "dof_count": model.dof_count,
        "setup_ms": setup_ms,
        "rotations_ms": rotations_ms,
        "assembly_ms": assembly_ms,
        "factorisation_ms": factorisation_ms,
        "solve_ms": solve_ms,
    }
