"""A picture of a tissue mesh alone (e.g. the liver phantom): three views, optional highlighted nodes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from refsim.viz.render import TISSUE_COLOR, prepare_offscreen, triangle_cells

__all__ = ["render_phantom"]

FIXED_COLOR = "#2a6f3f"


def render_phantom(mesh, output_png, *, highlight=None, window_size: tuple[int, int] = (1800, 600)) -> Path:
    """Draw a tetrahedral mesh's surface from three sides (oblique from below, front, side), off-screen.

    Parameters
    ----------
    mesh : :class:`refsim.mesh.TetMesh`.
    output_png : PNG to write (parent folders are created).
    highlight : Node indices drawn as green spheres (e.g. a fixed surface patch), shape (c,), or None.
    window_size : Picture size in pixels (width, height).

    Returns
    -------
    The PNG's path.
    """
    prepare_offscreen()
    import pyvista as pv

    surface = pv.PolyData(np.asarray(mesh.rest_positions), triangle_cells(mesh.boundary_faces))
    extent = np.ptp(mesh.rest_positions, axis=0)
    views = [("oblique, visceral face", "iso", -55.0), ("front (x-z)", "xz", 0.0), ("side (y-z)", "yz", 0.0)]
    plotter = pv.Plotter(off_screen=True, shape=(1, 3), window_size=list(window_size))
    try:
        plotter.set_background("white")
        for column, (title, camera, elevation) in enumerate(views):
            plotter.subplot(0, column)
            plotter.add_mesh(
                surface, color=TISSUE_COLOR, show_edges=True, edge_color="#6b3b30", line_width=0.4
            )
            if highlight is not None and len(highlight):
                plotter.add_mesh(
                    pv.PolyData(np.asarray(mesh.rest_positions)[np.asarray(highlight)]),
                    color=FIXED_COLOR,
                    point_size=9,
                    render_points_as_spheres=True,
                )
            plotter.camera_position = camera
            if elevation:
                plotter.camera.elevation = elevation
            plotter.add_text(title, font_size=10, color="black")
        plotter.add_text(
            f"{mesh.node_count} nodes, {mesh.tet_count} tets, "
            f"{100 * extent[0]:.1f} x {100 * extent[1]:.1f} x {100 * extent[2]:.1f} cm",
            position="lower_right",
            font_size=9,
            color="black",
        )
        output_png = Path(output_png)
        output_png.parent.mkdir(parents=True, exist_ok=True)
        plotter.screenshot(str(output_png))
    finally:
        plotter.close()
    return output_png
