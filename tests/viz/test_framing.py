"""Pictures that serve an organ: size, not blank, the needle in view, camera options, fixed nodes, boundary
motion arrows, animation frames, and force plots with a label per tear and a lateral-stroke panel."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from refsim.io import RecordedEvent, read_results
from refsim.viz import animate_result, animation_steps, frame_camera, plot_result, render_result
from refsim.viz.plots import LATERAL_STROKE_MIN, event_rows, force_figure, lateral_stroke
from refsim.viz.render import (
    _scale_length,
    compose_picture,
    cut_surface_positions,
    parse_vector,
    view_width_of,
)


def _read_png(path):
    import matplotlib.image

    return matplotlib.image.imread(str(path))[:, :, :3]


def _mask(image, condition):
    """Pixels where condition(r, g, b) holds (0-255) in the 3-D view, not in the margin (title, legend with
    the colours of what it names, scale bar, axes)."""
    r, g, b = (255 * image[:, :, i] for i in range(3))
    mask = condition(r, g, b)
    mask[:, view_width_of(mask.shape[1]) :] = False
    return mask


def _camera(results, step=None, **options):
    step = int(results.step[-1]) if step is None else step
    tissue = results.tissue_positions_at(step)
    points, triangles = cut_surface_positions(results, step, tissue)
    return frame_camera(results, step, tissue, points, triangles, **options)


def test_render_has_the_asked_size_and_is_not_blank(insertion_file, tmp_path):
    output = render_result(insertion_file, tmp_path / "r.png", window_size=(640, 480))
    image = _read_png(output)
    assert image.shape == (480, 640, 3)
    background = np.all(image > 0.98, axis=2)
    assert 0.05 < 1.0 - background.mean() < 0.98  # something drawn, not all of it
    assert len(np.unique(image.reshape(-1, 3).round(2), axis=0)) > 20


@pytest.mark.parametrize(
    "options",
    [
        {},
        {"camera": "iso"},
        {"camera": "xz", "zoom": 2.0},
        {"camera": (1.0, -0.5, 0.2), "view_up": (0, 0, 1)},
        {"focus": "needle"},
    ],
)
def test_framing_puts_the_needle_tip_and_inserted_part_in_view(insertion_file, options):
    results = read_results(insertion_file)
    view = _camera(results, **options)
    needle = results.needle_positions[-1]
    inserted = needle[needle[:, 2] < results.rest_positions[:, 2].max()]
    uv = view.project(np.vstack([needle[-1:], inserted]), aspect=4 / 3)
    assert np.all(np.abs(uv) < 1.0), uv


def test_framing_before_the_needle_reaches_the_tissue_holds_the_tip_and_the_surface(insertion_file):
    results = read_results(insertion_file)
    view = _camera(results, step=1)
    tip = results.needle_positions[0, -1]
    assert tip[2] > results.rest_positions[:, 2].max()  # still in the air
    below = np.array([tip[0], tip[1], results.rest_positions[:, 2].max()])  # the surface point under it
    assert np.all(np.abs(view.project(np.vstack([tip, below]), aspect=4 / 3)) < 1.0)


def test_projection_agrees_with_vtk(insertion_file):
    # CameraView.project is the pinhole model; VTK's world-to-display transform of the same camera must give
    # the same pixel (to a pixel's rounding) for the needle tip, so the framing test tests what is drawn.
    from refsim.viz.render import _apply_camera, prepare_offscreen

    results = read_results(insertion_file)
    view = _camera(results, camera="iso")
    prepare_offscreen()
    import pyvista as pv

    width, height = 800, 600
    plotter = pv.Plotter(off_screen=True, window_size=[width, height])
    try:
        plotter.add_mesh(pv.Sphere(radius=0.01))
        _apply_camera(plotter, view)
        plotter.render()
        tip = results.needle_positions[-1, -1]
        renderer = plotter.renderer
        renderer.SetWorldPoint(*tip, 1.0)
        renderer.WorldToDisplay()
        display = np.array(renderer.GetDisplayPoint()[:2])
    finally:
        plotter.close()
    u, v = view.project(tip[None, :], aspect=width / height)[0]
    expected = np.array([(u + 1) * width / 2, (v + 1) * height / 2])
    np.testing.assert_allclose(display, expected, atol=1.0)


def test_zoom_brings_the_camera_closer(insertion_file):
    results = read_results(insertion_file)
    near, far = _camera(results, zoom=2.0), _camera(results, zoom=1.0)
    ratio = np.linalg.norm(far.position - far.focal_point) / np.linalg.norm(near.position - near.focal_point)
    assert ratio == pytest.approx(2.0, rel=1e-12)


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"camera": "top"}, "camera = 'top'"),
        ({"camera": "1,2"}, "camera"),
        ({"focus": "organ"}, "focus = 'organ'"),
        ({"zoom": 0.0}, "zoom = 0"),
        ({"camera": "xy", "view_up": (0, 0, 1)}, "parallel"),
    ],
)
def test_bad_camera_options_are_named(insertion_file, options, message):
    with pytest.raises(ValueError, match=message):
        _camera(read_results(insertion_file), **options)


def test_parse_vector():
    np.testing.assert_array_equal(parse_vector("1, -2,3e-3", "x"), [1, -2, 3e-3])
    with pytest.raises(ValueError, match="focus = 'a,b,c'"):
        parse_vector("a,b,c", "focus")


def _count_green(image):
    return int(np.count_nonzero(_mask(image, lambda r, g, b: (g > r + 25) & (g > b + 10))))


def _count_purple(image):
    """Purple (boundary-motion arrow) pixels."""
    return int(np.count_nonzero(_mask(image, lambda r, g, b: (b > g + 40) & (r > g + 30))))


def test_fixed_nodes_are_drawn(insertion_file, tmp_path):
    # The clamped bottom face (25 nodes on 4² cells) drawn as green cubes when the camera sees it.
    output = render_result(
        insertion_file,
        tmp_path / "fixed.png",
        focus="tissue",
        camera=(0.4, -1.0, -0.6),
        view_up=(0, 0, 1),
        window_size=(640, 480),
    )
    assert _count_green(_read_png(output)) > 100
    assert read_results(insertion_file).fixed_nodes.size == 25


def test_boundary_motion_arrows_appear_only_when_the_fixed_nodes_move(insertion_file, tmp_path):
    import h5py

    moved = tmp_path / "moved.h5"
    shutil.copy(insertion_file, moved)
    with h5py.File(moved, "r+") as handle:
        fixed = handle["scene/tissue/fixed_nodes"][:]
        positions = handle["tissue/positions"][:]
        positions[:, fixed, 0] += 0.005  # a prescribed 5 mm motion along x of the clamped face
        handle["tissue/positions"][:] = positions
    options = {
        "focus": "tissue",
        "camera": (0.4, -1.0, -0.6),
        "view_up": (0, 0, 1),
        "window_size": (640, 480),
    }
    still = _read_png(render_result(insertion_file, tmp_path / "still.png", **options))
    moving = _read_png(render_result(moved, tmp_path / "moving.png", **options))
    assert _count_purple(still) == 0
    # At most 16 arrows of 6 % of the tissue, translucent (so that they do not hide the cut).
    assert _count_purple(moving) > 50, _count_purple(moving)


@pytest.mark.parametrize(("every", "frames"), [(10, 5), (7, 8), (50, 1), (1, 50)])
def test_animation_steps_are_every_kth_and_the_last(every, frames):
    steps = np.arange(1, 51)
    chosen = animation_steps(steps, every)
    assert chosen.shape == (frames,) == (int(np.ceil(50 / every)),)
    assert chosen[-1] == 50 and np.all(np.diff(chosen) > 0)
    with pytest.raises(ValueError, match="every = 0"):
        animation_steps(steps, 0)


def test_gif_animation_has_steps_over_k_frames(insertion_file, tmp_path):
    import imageio.v3 as iio

    results = read_results(insertion_file)
    output = animate_result(insertion_file, tmp_path / "run.gif", every=10, window_size=(320, 240))
    frames = iio.imread(output, index=None)
    assert frames.shape[0] == results.step_count // 10 == 5
    assert frames.shape[1:3] == (240, 320)
    assert not np.array_equal(frames[0], frames[-1])  # the needle moved (and the step text changed)


def test_mp4_animation_has_steps_over_k_frames(insertion_file, tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    import imageio.v2 as imageio

    output = animate_result(insertion_file, tmp_path / "run.mp4", every=25, window_size=(320, 240))
    reader = imageio.get_reader(output)
    try:
        assert reader.count_frames() == 2
    finally:
        reader.close()


def test_an_interrupted_animation_leaves_no_file(insertion_file, tmp_path, monkeypatch):
    """The frames go to a temporary name renamed once every frame is in: Ctrl-C after the second frame leaves
    nothing (before: a GIF of two frames at the path)."""
    import refsim.viz.animation as animation

    compose = animation.compose_picture
    calls = []

    def interrupted(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return compose(*args, **kwargs)

    monkeypatch.setattr(animation, "compose_picture", interrupted)
    with pytest.raises(KeyboardInterrupt):
        animate_result(insertion_file, tmp_path / "run.gif", every=10, window_size=(320, 240))
    assert list(tmp_path.iterdir()) == []


def test_animation_rejects_an_unknown_format(insertion_file, tmp_path):
    with pytest.raises(ValueError, match="avi"):
        animate_result(insertion_file, tmp_path / "run.avi")


def _overlaps(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


def test_one_label_per_event_kind_with_its_unit_and_the_legend_off_the_data(insertion_file):
    results = read_results(insertion_file)
    added = (
        RecordedEvent(25, float(results.time[24]), "cut_start", 207.91, "N/m"),
        RecordedEvent(30, float(results.time[29]), "tear", 2.27),
        RecordedEvent(40, float(results.time[39]), "tear", 13.77),
    )
    results = dataclasses.replace(results, events=results.events + added)
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    figure = force_figure(results)
    canvas = FigureCanvasAgg(figure)
    canvas.draw()
    panels = [axis for axis in figure.axes if axis.axison]
    assert len(panels) == 2  # no lateral motion: depth and time only
    assert not [text.get_text() for axis in panels for text in axis.texts]  # nothing written over the data
    (legend,) = figure.legends
    labels = [text.get_text() for text in legend.get_texts()]
    assert labels.count("tear (2)") == 1 and labels.count("cut_start (1)") == 1
    assert sum(label.startswith("tear") for label in labels) == 1
    renderer = canvas.get_renderer()
    box = legend.get_window_extent(renderer)
    assert not any(_overlaps(box, axis.get_window_extent(renderer)) for axis in panels)
    table = [axis for axis in figure.axes if not axis.axison][0].tables[0]
    cells = {(row, col): cell.get_text().get_text() for (row, col), cell in table.get_celld().items()}
    rows = {
        cells[(r, 0)]: [cells[(r, c)] for c in range(1, 4)] for r in range(1, 1 + len(event_rows(results)))
    }
    assert rows["tear"] == ["2", "30 - 40", "2.27 - 13.77 N"]
    assert rows["cut_start"] == ["1", "25", "207.9 N/m"]  # a force per unit length (energy law)


def test_lateral_motion_gets_a_stroke_panel(lateral_file, tmp_path):
    results = read_results(lateral_file)
    stroke = lateral_stroke(results)
    # The base moves 3 mm along x, perpendicular to the needle axis (−z), after a purely axial insertion.
    assert stroke.max() == pytest.approx(0.003, abs=1e-12)
    assert np.all(stroke[results.time <= 0.25 + 1e-9] < 1e-12)
    assert stroke.max() > LATERAL_STROKE_MIN
    figure = force_figure(results)
    panels = [axis for axis in figure.axes if axis.axison]
    # A lateral stroke: against time and the stroke; no depth panel (the depth stays still while it moves).
    assert [axis.get_title() for axis in panels] == ["against time", "against the lateral stroke"]
    assert "lateral stroke" in panels[1].get_xlabel()
    output = plot_result(lateral_file, tmp_path / "forces.png")
    assert _read_png(output).shape[1] > 1.4 * _read_png(output).shape[0]


def _count_blue(image):
    return int(np.count_nonzero(_mask(image, lambda r, g, b: (b > r + 50) & (b > g + 20))))


def test_organ_picture_shows_insertion_points_and_fixed_nodes(organ_file, tmp_path):
    results = read_results(organ_file)
    assert results.insertion_point_count[-1] > 0 and results.fixed_nodes.size > 0
    # Framing on the inserted needle: the insertion points (blue) are visible at organ scale.
    needle = _read_png(
        render_result(organ_file, tmp_path / "needle.png", window_size=(640, 480), focus="insertion")
    )
    assert _count_blue(needle) > 30
    # The whole organ from behind-above: the fixed posterior edge (green cubes) is visible.
    organ = _read_png(
        render_result(
            organ_file,
            tmp_path / "organ.png",
            focus="tissue",
            camera=(0.3, -1.0, 0.8),
            window_size=(640, 480),
        )
    )
    assert _count_green(organ) > 30


def test_default_framing_holds_the_whole_tissue_the_tip_and_the_cut(organ_file, insertion_file):
    for path in (organ_file, insertion_file):
        results = read_results(path)
        step = int(results.step[-1])
        tissue = results.tissue_positions_at(step)
        view = _camera(results, aspect=view_width_of(1200) / 900)
        uv = view.project(
            np.vstack([tissue, results.needle_positions[-1, -1:]]), aspect=view_width_of(1200) / 900
        )
        assert np.all(np.abs(uv) < 0.95)
        assert np.abs(uv).max() > 0.6  # and fills the view: not a small object in white space


def test_the_margin_holds_title_legend_scale_bar_and_axes_and_nothing_covers_the_view():
    from refsim.viz.render import CameraView

    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, size=(480, view_width_of(640), 3), dtype=np.uint8)
    view = CameraView(np.array([0.0, -0.5, 0.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
    legend = [["tissue", "#d9a38f"], ["cut surface", "#d62728"]]
    picture = compose_picture(image, legend, "cube\nstep 3", view, (640, 480))
    assert picture.shape == (480, 640, 3)
    # The view is the rendered image, pixel for pixel: no legend, label or bar drawn over it.
    assert np.mean(np.all(picture[:, : image.shape[1]] == image, axis=2)) > 0.995
    margin = picture[:, image.shape[1] :]
    assert np.any(np.all(margin == (214, 39, 40), axis=2))  # the cut's legend patch
    # Scale bar: at 0.5 m the view is 2 x 0.5 tan(15 deg) = 0.268 m high (480 px); the bar is a round length
    # near a quarter of the view's width, drawn at its length in pixels.
    span = 2 * 0.5 * np.tan(np.radians(15.0))
    length = _scale_length(span * image.shape[1] / image.shape[0])
    assert length == 0.05
    dark = np.all(margin < 40, axis=2)
    widest = max(np.count_nonzero(row) for row in dark)
    assert widest == pytest.approx(length / span * 480, abs=3)
