"""Off-screen pictures of a run with pyvista: deformed tissue, needle, insertion points and cut surface.

Off-screen rendering needs no display: without ``DISPLAY`` (a headless Linux machine) VTK is asked for its EGL
render window (environment variable ``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow``), which renders through
Mesa's EGL (Debian packages libegl1, libegl-mesa0, libgl1-mesa-dri, libgbm1) without X and without Xvfb.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

__all__ = ["render_result", "cut_surface_positions", "prepare_offscreen"]

logger = logging.getLogger(__name__)

TISSUE_COLOR = "#d9a38f"
NEEDLE_COLOR = "#5a6270"
INSERTION_COLOR = "#1f77b4"
CUT_COLOR = "#d62728"


def prepare_offscreen() -> None:
    """Make VTK render off-screen without a display: on Linux without ``DISPLAY`` choose the EGL window
    (unless the user chose a window class already). Call before the first plotter is created."""
    if os.name == "posix" and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def cut_surface_positions(results, step: int, tissue_positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cut surface of ``step`` in the deformed tissue.

    Each rest-state point is carried by the tissue through its barycentric coordinates in its tet (the paper's
    equation 4 applied with the current nodal positions). When the file does not hold the coordinates, they are
    reconstructed by locating the rest-state point in the rest mesh: for linear tets the rest-state point has
    the same barycentric coordinates as the deformed one, so this is exact (points off the mesh are clamped to
    its closest point).

    Parameters
    ----------
    results : :class:`refsim.io.Results` with a cut history.
    step : The step whose cut surface is wanted (points and triangles created up to that step).
    tissue_positions : Tissue node positions [m] to map to, shape (n, 3).

    Returns
    -------
    points : Deformed cut points [m], shape (p, 3).
    triangles : Triangles (point indices), shape (t, 3).
    """
    cut = results.cut
    if cut is None:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    rest_points, triangles = cut.at(step)
    count = rest_points.shape[0]
    if count == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    if cut.tet_indices is not None and cut.barycentric is not None:
        tet_indices, barycentric = cut.tet_indices[:count], cut.barycentric[:count]
    else:
        from refsim.geometry import TetLocator

        tet_indices, barycentric, _ = TetLocator(results.rest_positions, results.tets).locate_nearest(rest_points)
    corners = tissue_positions[results.tets[tet_indices]]  # (p, 4, 3)
    return np.einsum("pk,pkd->pd", barycentric, corners), triangles


def triangle_cells(triangles: np.ndarray) -> np.ndarray:
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    return np.hstack([np.full((triangles.shape[0], 1), 3, dtype=np.int64), triangles]).ravel()


def render_result(
    path,
    output_png,
    *,
    step: int | None = None,
    window_size: tuple[int, int] = (1200, 900),
    tissue_opacity: float = 0.35,
) -> Path:
    """Render one step of a results file to a PNG, off-screen.

    Shows the deformed tissue surface (semi-transparent; the recorded tissue state nearest to ``step``), the
    needle as a tube along its nodes (radius from the scene), the insertion points (tissue-side points of the
    insertion rows) as spheres and, when the file holds one, the cut surface in red in the deformed tissue.

    Parameters
    ----------
    path : Results file.
    output_png : PNG to write (parent folders are created).
    step : Step to show (a step number as in ``Results.step``); the last step by default.
    window_size : Picture size in pixels (width, height).
    tissue_opacity : Opacity of the tissue surface, in (0, 1].

    Returns
    -------
    The PNG's path.

    Raises
    ------
    refsim.io.ResultsError (a ValueError)
        When the file holds no such step.
    ValueError
        When the file holds no step at all, or an argument is out of range.
    """
    from refsim.io import read_results

    if not 0.0 < tissue_opacity <= 1.0:
        raise ValueError(f"tissue_opacity = {tissue_opacity}: expected a value in (0, 1]")
    results = read_results(path)
    if results.step_count == 0:
        raise ValueError(f"{results.path}: the file holds no step to render")
    step = int(results.step[-1]) if step is None else int(step)
    index = results.index_of(step)

    prepare_offscreen()
    import pyvista as pv

    tissue_step = results.nearest_tissue_step(step) if results.tissue_steps.size else 0
    tissue_positions = results.tissue_positions_at(step)
    radius = float(results.scene.get("needle", {}).get("radius", 0.0)) or 1e-3 * float(
        np.ptp(results.rest_positions, axis=0).max()
    )

    plotter = pv.Plotter(off_screen=True, window_size=list(window_size))
    try:
        plotter.set_background("white")
        surface = pv.PolyData(tissue_positions, triangle_cells(results.faces))
        plotter.add_mesh(surface, color=TISSUE_COLOR, opacity=tissue_opacity, show_edges=True,
                         edge_color="#8c6d62", line_width=0.5, smooth_shading=False)

        needle_nodes = results.needle_positions[index]
        needle = pv.lines_from_points(needle_nodes).tube(radius=radius, n_sides=24)
        # Translucent: the paper's needle (r = 8 mm) is wider than its cut, which it would hide otherwise.
        plotter.add_mesh(needle, color=NEEDLE_COLOR, smooth_shading=True, opacity=0.35)

        rows = results.constraints_at(step)
        if "insertion" in results.source_names:
            insertion = rows.points[rows.source == results.source_names.index("insertion")]
            insertion = np.unique(insertion, axis=0)
            if insertion.size:
                spheres = pv.PolyData(insertion).glyph(geom=pv.Sphere(radius=0.35 * radius), scale=False,
                                                       orient=False)
                plotter.add_mesh(spheres, color=INSERTION_COLOR, smooth_shading=True)

        cut_points, cut_triangles = cut_surface_positions(results, step, tissue_positions)
        if cut_triangles.size:
            cut = pv.PolyData(cut_points, triangle_cells(cut_triangles))
            plotter.add_mesh(cut, color=CUT_COLOR, opacity=1.0, show_edges=True, edge_color="#7f1010")
        elif cut_points.size:
            plotter.add_mesh(pv.PolyData(cut_points), color=CUT_COLOR, point_size=6,
                             render_points_as_spheres=True)

        phase = results.phase_names[results.phase[index]]
        tissue_note = "" if tissue_step == step else f" (tissue of step {tissue_step})"
        plotter.add_text(
            f"{results.scene_name}  step {step}  t = {results.time[index]:.3f} s  {phase}{tissue_note}",
            position="upper_left", font_size=10, color="black",
        )
        # Frame the tissue (padded), not the whole needle: the needle may be several times longer than the organ;
        # with a cut, frame the cut and its surroundings (three times its size), where the action is.
        lower, upper = tissue_positions.min(axis=0), tissue_positions.max(axis=0)
        pad = 0.25 * (upper - lower).max()
        if cut_triangles.size:
            lower, upper = cut_points.min(axis=0), cut_points.max(axis=0)
            pad = (upper - lower).max()
        plotter.camera_position = "iso"
        plotter.camera.azimuth = 20.0
        plotter.reset_camera(bounds=np.column_stack([lower - pad, upper + pad]).ravel().tolist())
        output_png = Path(output_png)
        output_png.parent.mkdir(parents=True, exist_ok=True)
        plotter.screenshot(str(output_png))
    finally:
        plotter.close()
    logger.info("rendered step %d of %s to %s", step, results.path, output_png)
    return output_png
