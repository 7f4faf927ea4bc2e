"""An animation of a run (GIF or MP4 through imageio), one frame every K steps, with a fixed camera."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from refsim.viz.render import (
    _VIEW_ANGLE,
    _apply_camera,
    _draw_step,
    _Style,
    _validate_window,
    compose_picture,
    cut_surface_positions,
    focus_points,
    frame_camera,
    prepare_offscreen,
    view_width_of,
)

__all__ = ["animate_result", "animation_steps"]

logger = logging.getLogger(__name__)

#: Output formats by file extension.
ANIMATION_FORMATS = (".gif", ".mp4")


def animation_steps(step: np.ndarray, every: int) -> np.ndarray:
    """The steps shown: every ``every``-th step of the file (the K-th, 2K-th, ...) and always the last one.

    Parameters
    ----------
    step : Step numbers of the file, shape (s,).
    every : K >= 1.

    Returns
    -------
    Step numbers, shape (ceil(s / K),).
    """
    if int(every) != every or every < 1:
        raise ValueError(f"every = {every}: expected an integer >= 1")
    every = int(every)
    chosen = np.asarray(step)[every - 1 :: every]
    if chosen.size == 0 or chosen[-1] != step[-1]:
        chosen = np.append(chosen, step[-1])
    return chosen


def animate_result(
    path,
    output,
    *,
    every: int = 1,
    fps: float = 10.0,
    window_size: tuple[int, int] = (960, 720),
    tissue_opacity: float = 0.35,
    camera=None,
    view_up=None,
    zoom: float = 1.0,
    focus="auto",
) -> Path:
    """Write an animation of a results file: one frame per K steps, GIF or MP4 by the output's extension.

    The camera is the same for every frame: framed (see :func:`refsim.viz.render.frame_camera`) on what the
    frames show together (the needle's inserted part, the insertion points and the cut of every shown step).

    Parameters
    ----------
    path : Results file.
    output : .gif or .mp4 file to write (parent folders are created). MP4 needs the imageio-ffmpeg package.
    every : K >= 1: one frame every K steps (frames = ceil(steps / K); the last step is always shown).
    fps : Frames per second, > 0.
    window_size : Frame size in pixels (width, height); MP4 frames are multiples of 16 (960 x 720 is).
    tissue_opacity, camera, view_up, zoom, focus : As for :func:`refsim.viz.render_result`.

    Returns
    -------
    The animation's path.

    Raises
    ------
    ValueError
        For an unknown extension, ``every`` < 1, ``fps`` <= 0, or a file without steps.
    """
    from refsim.io import read_results

    output = Path(output)
    if output.suffix.lower() not in ANIMATION_FORMATS:
        raise ValueError(f"{output}: unknown animation format {output.suffix!r}; expected .gif or .mp4")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps = {fps}: expected a number > 0")
    if not 0.0 < tissue_opacity <= 1.0:
        raise ValueError(f"tissue_opacity = {tissue_opacity}: expected a value in (0, 1]")
    width, height = _validate_window(window_size)
    results = read_results(path)
    if results.step_count == 0:
        raise ValueError(f"{results.path}: the file holds no step to animate")
    states, view = _frames_and_camera(
        results,
        animation_steps(results.step, every),
        camera=camera,
        view_up=view_up,
        zoom=zoom,
        focus=focus,
        aspect=view_width_of(width) / height,
    )
    _write_frames(output, results, states, view, fps=fps, size=(width, height), tissue_opacity=tissue_opacity)
    logger.info("animated %d frames of %s to %s", len(states), results.path, output)
    return output


def _frames_and_camera(results, steps, *, camera, view_up, zoom, focus, aspect):
    """The shown steps' states (step, tissue positions, cut points, cut triangles) and the one camera for all
    frames: the last step's framing, holding what every frame focuses on."""
    from refsim.geometry import TetLocator

    locator = TetLocator(results.rest_positions, results.tets)
    states = []
    for step in steps:
        tissue = results.tissue_positions_at(int(step))
        states.append((int(step), tissue, *cut_surface_positions(results, int(step), tissue)))
    together = np.concatenate([focus_points(results, s, t, c, "auto", locator) for s, t, c, _ in states])
    last, tissue, cut_points, cut_triangles = states[-1]
    view = frame_camera(
        results,
        last,
        tissue,
        cut_points,
        cut_triangles,
        camera=camera,
        view_up=view_up,
        zoom=zoom,
        focus=focus,
        aspect=aspect,
        locator=locator,
        include=together if focus == "auto" else None,
    )
    return states, view


def _write_frames(output: Path, results, states, view, *, fps: float, size, tissue_opacity: float) -> None:
    """Draw each state off screen with the fixed camera and append it to the GIF or MP4 ``output``."""
    import imageio.v2 as imageio

    prepare_offscreen()
    import pyvista as pv

    width, height = size
    view_size = float(np.linalg.norm(view.position - view.focal_point)) * np.tan(np.radians(_VIEW_ANGLE) / 2)
    output.parent.mkdir(parents=True, exist_ok=True)
    # the frames go to a temporary name (same suffix: it picks the format), renamed once every frame is in: an
    # interrupted or failed animation leaves no partial file at ``output``
    temporary = output.with_name(f".{output.stem}.partial{output.suffix}")
    if output.suffix.lower() == ".gif":
        writer = imageio.get_writer(temporary, mode="I", duration=1000.0 / fps, loop=0)
    else:
        writer = imageio.get_writer(temporary, format="FFMPEG", mode="I", fps=fps, macro_block_size=16)
    plotter = pv.Plotter(off_screen=True, window_size=[view_width_of(width), height])
    completed = False
    try:
        plotter.set_background("white")
        for step, tissue, cut_points, cut_triangles in states:
            plotter.clear_actors()
            legend, title = _draw_step(
                plotter, results, step, tissue, cut_points, cut_triangles, view_size, _Style(tissue_opacity)
            )
            _apply_camera(plotter, view)
            plotter.render()  # the actors were added without rendering; the screenshot reuses the last render
            image = plotter.screenshot(return_img=True)
            writer.append_data(compose_picture(image, legend, title, view, (width, height)))
            plotter.clear()
        completed = True
    finally:
        plotter.close()
        writer.close()
        if completed:
            os.replace(temporary, output)
        else:
            temporary.unlink(missing_ok=True)
