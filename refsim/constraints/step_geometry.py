"""The geometry of one step as every constraint builder sees it.

A builder needs the positions of both bodies at the start of the step and after the free motion (rows are
linearised at the free positions; friction rows measure the relative slip over the step), the needle's
centreline in both configurations, and the tissue's tets (tissue points are material points: a tet and
barycentric coordinates). :class:`StepGeometry` carries exactly that, built once per step by the simulation,
instead of the same six arguments passed to each builder.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from refsim.constraints.needle_geometry import NeedleGeometry

__all__ = ["StepGeometry"]


@dataclass(frozen=True)
class StepGeometry:
    """Positions of both bodies at the start of the step and after free motion.

    Attributes
    ----------
    mesh_tets : Tissue tets, shape (tet_count, 4).
    tissue_previous : Tissue positions at the start of the step [m], shape (node_count, 3).
    tissue_free : Tissue positions after the free motion [m], shape (node_count, 3).
    needle_previous : The needle's centreline at the start of the step.
    needle_free : The needle's centreline after the free motion.
    """

    mesh_tets: np.ndarray
    tissue_previous: np.ndarray
    tissue_free: np.ndarray
    needle_previous: NeedleGeometry
    needle_free: NeedleGeometry

    @property
    def tissue_dof_count(self) -> int:
        """3 · tissue node count."""
        return 3 * int(self.tissue_free.shape[0])

    def tissue_points(self, nodes: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Material points Σ_k w_k x_k in the previous and free configurations [m], each shape (q, 3).

        Parameters
        ----------
        nodes : Nodes of each point, shape (q, p).
        weights : Their weights (barycentric coordinates), shape (q, p).
        """
        from refsim.constraints.kernels import interpolated_points  # numba: imported on first use
        from refsim.kernel_cache import readonly

        # np.einsum("qk,qkj->qj", weights, positions[nodes])'s bits, compiled
        weights = np.asarray(weights, dtype=float)
        nodes = np.asarray(nodes)
        return (
            interpolated_points(weights, readonly(self.tissue_previous), nodes),
            interpolated_points(weights, readonly(self.tissue_free), nodes),
        )
