"""Figures of a run (layer 6): an off-screen pyvista picture, an animation and matplotlib plots, read from
the results file; a picture of a mesh alone.

pyvista and matplotlib are imported inside the functions that draw, so importing refsim.viz is light.
"""

from refsim.viz.animation import animate_result, animation_steps
from refsim.viz.phantom import render_phantom
from refsim.viz.plots import plot_result
from refsim.viz.render import (
    CameraView,
    cut_surface_positions,
    frame_camera,
    prepare_offscreen,
    render_result,
)

__all__ = [
    "CameraView",
    "animate_result",
    "animation_steps",
    "cut_surface_positions",
    "frame_camera",
    "plot_result",
    "prepare_offscreen",
    "render_phantom",
    "render_result",
]
