"""Figures of a run (layer 6): an off-screen pyvista picture and matplotlib plots, read from the results file.

pyvista and matplotlib are imported inside the functions that draw, so importing refsim.viz is light.
"""

from refsim.viz.plots import plot_result
from refsim.viz.render import cut_surface_positions, prepare_offscreen, render_result

__all__ = ["cut_surface_positions", "plot_result", "prepare_offscreen", "render_result"]
