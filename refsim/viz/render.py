"""Off-screen pictures of a run with pyvista: deformed tissue, needle, insertion points, fixed nodes, boundary
motion and cut surface, framed on the needle and the cut.

Off-screen rendering needs no display: without ``DISPLAY`` (a headless Linux machine) VTK is asked for its EGL
render window (environment variable ``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow``), which renders through
Mesa's EGL (Debian packages libegl1, libegl-mesa0, libgl1-mesa-dri, libgbm1) without X and without Xvfb.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "CameraView",
    "compose_picture",
    "cut_surface_positions",
    "frame_camera",
    "parse_vector",
    "prepare_offscreen",
    "render_result",
]

logger = logging.getLogger(__name__)

TISSUE_COLOR = "#d9a38f"
NEEDLE_COLOR = "#5a6270"
#: One colour per instrument, in the scene's order (the first is NEEDLE_COLOR; the list repeats past its end),
#: none of them the tissue's, the insertion points', the cut's or the boundary's.
NEEDLE_COLORS = (NEEDLE_COLOR, "#b8860b", "#00707a", "#8b4513", "#222222")
INSERTION_COLOR = "#1f77b4"
CUT_COLOR = "#d62728"
FIXED_COLOR = "#2a6f3f"
MOTION_COLOR = "#8e44ad"

#: Named view directions (from the focus towards the camera) accepted by ``camera=``.
NAMED_VIEWS = {
    "iso": (1.0, 1.0, 1.0),
    "xy": (0.0, 0.0, 1.0),
    "yx": (0.0, 0.0, -1.0),
    "xz": (0.0, -1.0, 0.0),
    "zx": (0.0, 1.0, 0.0),
    "yz": (1.0, 0.0, 0.0),
    "zy": (-1.0, 0.0, 0.0),
}
#: Named focus choices accepted by ``focus=``.
FOCUS_CHOICES = ("auto", "insertion", "needle", "cut", "tissue")
#: Width of the picture's margin (title, legend, scale bar, axes), as a fraction of the picture's width.
MARGIN_FRACTION = 0.27
# Vertical view angle of the camera [degrees] (VTK's default).
_VIEW_ANGLE = 30.0
# Angle of the automatic view above the plane perpendicular to the needle, from its base's side [degrees]:
# enough to see the surface the needle enters.
_ELEVATION = 30.0


def prepare_offscreen() -> None:
    """Make VTK render off-screen without a display: on Linux without ``DISPLAY`` choose the EGL window
    (unless the user chose a window class already). Call before the first plotter is created."""
    if os.name == "posix" and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def cut_surface_positions(results, step: int, tissue_positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cut surface of ``step`` in the deformed tissue.

    Each rest-state point is carried by the tissue through its barycentric coordinates in its tet (the paper's
    equation 4 applied with the current nodal positions). When the file does not hold the coordinates, they
    are reconstructed by locating the rest-state point in the rest mesh: for linear tets the rest-state point
    has the same barycentric coordinates as the deformed one, so this is exact (points off the mesh are
    clamped to its closest point).

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

        tet_indices, barycentric, _ = TetLocator(results.rest_positions, results.tets).locate_nearest(
            rest_points
        )
    corners = tissue_positions[results.tets[tet_indices]]  # (p, 4, 3)
    return np.einsum("pk,pkd->pd", barycentric, corners), triangles


def triangle_cells(triangles: np.ndarray) -> np.ndarray:
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    return np.hstack([np.full((triangles.shape[0], 1), 3, dtype=np.int64), triangles]).ravel()


def parse_vector(text, name: str) -> np.ndarray:
    """Three numbers from a string "x,y,z" (or a sequence), for the camera options.

    Raises
    ------
    ValueError
        Naming the option and the value when it is not three finite numbers.
    """
    values = text.replace(",", " ").split() if isinstance(text, str) else text
    try:
        vector = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} = {text!r}: expected three numbers x,y,z") from None
    if vector.shape != (3,) or not np.all(np.isfinite(vector)):
        raise ValueError(f"{name} = {text!r}: expected three finite numbers x,y,z")
    return vector


@dataclass(frozen=True)
class CameraView:
    """A camera: position and focal point [m], shape (3,) each; unit view-up vector; vertical view angle
    [deg]."""

    position: np.ndarray
    focal_point: np.ndarray
    view_up: np.ndarray
    view_angle: float = _VIEW_ANGLE

    def project(self, points: np.ndarray, aspect: float) -> np.ndarray:
        """Normalised screen coordinates of points [m] (q, 3): (u, v) in [-1, 1]² when in view, shape (q, 2).

        A pinhole projection: u along the screen's right, v along view-up, both divided by the half-extent of
        the view at the point's depth (``aspect`` = width / height scales the horizontal half-extent)."""
        forward = self.focal_point - self.position
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, self.view_up)
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        relative = np.atleast_2d(points) - self.position
        depth = relative @ forward
        half = np.tan(np.radians(self.view_angle) / 2.0) * depth
        return np.column_stack([(relative @ right) / (half * aspect), (relative @ up) / half])


def needle_radius(scene: dict, name: str) -> float:
    """The radius [m] of instrument ``name``'s needle in a stored scene (its [[instruments]] override, else
    [needle]'s; 0 when absent)."""
    radius = scene.get("needle", {}).get("radius", 0.0)
    for instrument in scene.get("instruments", ()):
        if instrument.get("name") == name:
            radius = instrument.get("radius", radius)
    return float(radius or 0.0)


def _unit(vector: np.ndarray) -> np.ndarray:
    return vector / np.linalg.norm(vector)


def _inserted_needle_nodes(results, index: int, locator) -> np.ndarray:
    """Needle nodes inside the tissue at rest (a cheap test good enough for framing), shape (q, 3)."""
    nodes = results.needle_positions[index]
    tets, _ = locator.locate(nodes, tolerance=1e-9)
    return nodes[tets >= 0]


def focus_points(
    results, step: int, tissue_positions: np.ndarray, cut_points: np.ndarray, focus="auto", locator=None
) -> np.ndarray:
    """Points the picture must hold, shape (q, 3) [m].

    "auto": the tissue with the needle's inserted part, its tip, the insertion points and the cut, and the
    needle's nodes within a quarter of the tissue's extent of its bounding box (the needle seen entering).
    "insertion": the needle's inserted part, its tip, the insertion points and the cut; before the needle
    reaches the tissue, its tip and the closest point of the tissue's bounding box. "needle": the whole
    needle. "cut": the cut (insertion when there is none). "tissue": the tissue.
    """
    index = results.index_of(step)
    needle = results.needle_positions[index]
    if focus == "tissue":
        return tissue_positions
    if focus == "needle":
        return needle
    if focus == "cut" and cut_points.shape[0]:
        return cut_points
    if locator is None:
        from refsim.geometry import TetLocator

        locator = TetLocator(results.rest_positions, results.tets)
    inserted = _inserted_needle_nodes(results, index, locator)
    rows = results.constraints_at(step)
    points = [needle[-1:], inserted, cut_points, rows.points]
    lower, upper = tissue_positions.min(axis=0), tissue_positions.max(axis=0)
    if focus == "auto":
        reach = 0.25 * float(np.max(upper - lower))
        outside = np.linalg.norm(np.maximum(np.maximum(lower - needle, needle - upper), 0.0), axis=1)
        points += [tissue_positions, needle[outside <= reach]]
    elif inserted.shape[0] == 0:
        points.append(np.clip(needle[-1], lower, upper)[None, :])
    return np.concatenate([p.reshape(-1, 3) for p in points])


def frame_camera(
    results,
    step: int,
    tissue_positions: np.ndarray,
    cut_points: np.ndarray,
    cut_triangles: np.ndarray,
    *,
    camera=None,
    view_up=None,
    zoom: float = 1.0,
    focus="auto",
    aspect: float = 4.0 / 3.0,
    locator=None,
    include=None,
) -> CameraView:
    """The camera of a picture: aimed at the focus, far enough to hold it, from a direction that shows the
    cut.

    Parameters
    ----------
    results : :class:`refsim.io.Results`.
    step : The step shown.
    tissue_positions : Tissue node positions [m], shape (n, 3).
    cut_points, cut_triangles : The deformed cut surface (see :func:`cut_surface_positions`).
    camera : None or "auto": looking at the cut face-on (its mean normal, perpendicular to the needle), or
        without a cut from the side of the needle, 30° around it and 20° from its base, from the side where
        the camera is outside the tissue when only one is; a name of
        ``NAMED_VIEWS``; or a direction from the focus towards the camera, shape (3,).
    view_up : Up direction of the picture, shape (3,); by default the needle's base is up.
    zoom : Magnification (> 0) applied after the framing; 2 shows half the size.
    focus : One of ``FOCUS_CHOICES`` (see :func:`focus_points`) or a point [m], shape (3,), to centre on (the
        framing then holds the automatic focus too).
    aspect : Width / height of the picture.
    locator : A :class:`refsim.geometry.TetLocator` of the rest mesh, to reuse.
    include : More points [m] the view must hold, shape (q, 3) (e.g. the focus of other frames), or None.

    Raises
    ------
    ValueError
        For an unknown camera name or focus, a zoom <= 0, or a view-up parallel to the view direction.
    """
    if not (np.isfinite(zoom) and zoom > 0):
        raise ValueError(f"zoom = {zoom}: expected a number > 0")
    index = results.index_of(step)
    axis = _unit(results.needle_positions[index, -1] - results.needle_positions[index, 0])
    if locator is None:
        from refsim.geometry import TetLocator

        locator = TetLocator(results.rest_positions, results.tets)
    if isinstance(focus, str) and ("," in focus or " " in focus.strip()):
        focus = parse_vector(focus, "focus")
    if isinstance(focus, str):
        if focus not in FOCUS_CHOICES:
            raise ValueError(
                f"focus = {focus!r}: expected one of {', '.join(FOCUS_CHOICES)} or a point x,y,z"
            )
        points = focus_points(results, step, tissue_positions, cut_points, focus, locator)
        if include is not None:
            points = np.concatenate([points, np.asarray(include, dtype=float).reshape(-1, 3)])
        lower, upper = points.min(axis=0), points.max(axis=0)
        centre = 0.5 * (lower + upper)
    else:
        centre = parse_vector(focus, "focus")
        points = focus_points(results, step, tissue_positions, cut_points, "auto", locator)
        points = np.concatenate(
            [points, centre[None, :]]
            + ([] if include is None else [np.asarray(include, dtype=float).reshape(-1, 3)])
        )
    needle_radius = float(results.scene.get("needle", {}).get("radius", 0.0) or 0.0)
    extent = float(np.ptp(tissue_positions, axis=0).max())

    direction = _view_direction(camera, axis, cut_points, cut_triangles)
    up = -axis if view_up is None else _unit(parse_vector(view_up, "view_up"))
    if np.linalg.norm(np.cross(up, direction)) < 1e-3:
        if view_up is not None:
            raise ValueError(f"view_up = {view_up!r} is parallel to the view direction")
        up = _unit(np.cross(direction, np.cross(np.array([0.0, 0.0, 1.0]) + 0.1, direction)))
    distance = _fitting_distance(points, centre, direction, up, aspect, needle_radius, extent) / zoom
    if camera is None or (isinstance(camera, str) and camera == "auto"):
        # Of the two sides of the cut (or of the needle), prefer one where the camera is outside the tissue.
        mirrored = _unit(direction - 2.0 * (direction - (direction @ axis) * axis))
        inside = (
            locator.locate(np.array([centre + distance * direction, centre + distance * mirrored]))[0] >= 0
        )
        if inside[0] and not inside[1]:
            direction = mirrored
    return CameraView(centre + distance * direction, centre, up)


def _fitting_distance(
    points: np.ndarray,
    centre: np.ndarray,
    direction: np.ndarray,
    up: np.ndarray,
    aspect: float,
    needle_radius: float,
    extent: float,
) -> float:
    """Camera distance from ``centre`` along ``direction`` [m] at which every point projects inside 90 % of
    the picture (pinhole model of :class:`CameraView`), each point padded by three needle radii; never
    closer than a view 5 % of the tissue's extent ``extent`` [m] across.

    A point at depth z towards the camera and lateral offsets (x, y) along the screen's right and up stays in
    view when D − z ≥ |y| / tan(θ/2) and D − z ≥ |x| / (aspect tan(θ/2)), θ the vertical view angle."""
    right = _unit(np.cross(-direction, up))
    screen_up = np.cross(right, -direction)
    relative = points - centre
    depth = relative @ direction
    pad = 3.0 * needle_radius
    half = 0.9 * np.tan(np.radians(_VIEW_ANGLE) / 2.0)
    needed = depth + np.maximum(
        (np.abs(relative @ screen_up) + pad) / half, (np.abs(relative @ right) + pad) / (half * aspect)
    )
    narrow = min(half, half * aspect)
    return float(max(needed.max(), 0.05 * extent / narrow + depth.max()))


def _view_direction(
    camera, axis: np.ndarray, cut_points: np.ndarray, cut_triangles: np.ndarray
) -> np.ndarray:
    if isinstance(camera, str) and camera in NAMED_VIEWS:
        return _unit(np.array(NAMED_VIEWS[camera]))
    if camera is not None and camera != "auto":
        if isinstance(camera, str) and "," not in camera and " " not in camera.strip():
            raise ValueError(
                f"camera = {camera!r}: expected auto, one of {', '.join(NAMED_VIEWS)} or a direction x,y,z"
            )
        direction = parse_vector(camera, "camera")
        if np.linalg.norm(direction) == 0:
            raise ValueError("camera direction is zero")
        return _unit(direction)
    # Automatic: face the cut (its area-weighted mean normal, made perpendicular to the needle).
    side = None
    if cut_triangles.shape[0]:
        corners = cut_points[cut_triangles]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        # Triangle orientations may be mixed: align them with the dominant one before averaging.
        dominant = normals[np.argmax(np.linalg.norm(normals, axis=1))]
        normals *= np.where(normals @ dominant < 0, -1.0, 1.0)[:, None]
        mean = normals.sum(axis=0)
        mean -= (mean @ axis) * axis
        if np.linalg.norm(mean) > 1e-12:
            side = _unit(mean)
    if side is None:
        reference = np.eye(3)[np.argmin(np.abs(axis))]
        side = _unit(np.cross(axis, reference))
        side = _unit(np.cos(np.radians(30.0)) * side + np.sin(np.radians(30.0)) * np.cross(axis, side))
    if side @ np.array([0.3, -1.0, 0.2]) < 0:  # of the two faces, prefer the one seen from -y (front views)
        side = -side
    return _unit(side - np.tan(np.radians(_ELEVATION)) * axis)


def _fixed_motion(results, tissue_positions: np.ndarray) -> np.ndarray:
    """Displacement of the fixed nodes from rest [m], shape (c, 3): the prescribed boundary motion when there
    is one (zero for clamped nodes). Taken from the recorded tissue positions, where fixed nodes sit exactly
    at their prescribed positions, so it needs no boundary-motion dataset in the file."""
    fixed = np.asarray(results.fixed_nodes, dtype=np.int64)
    return tissue_positions[fixed] - results.rest_positions[fixed]


@dataclass(frozen=True)
class _Style:
    tissue_opacity: float
    show_fixed: bool = True
    show_motion: bool = True


def _draw_step(
    plotter, results, step: int, tissue_positions, cut_points, cut_triangles, view_size: float, style: _Style
) -> tuple[list, str]:
    """Add the actors of one step to a plotter (see :func:`render_result`), without rendering (the screenshot
    renders once). Returns the legend ([label, colour] rows) and the title of the picture's margin."""
    index = results.index_of(step)
    legend: list = []
    _draw_tissue(plotter, results, tissue_positions, style, legend)
    drawn_radius = _draw_needles(plotter, results, index, legend)
    mark = max(0.35 * drawn_radius, 0.012 * view_size)
    _draw_insertion_points(plotter, results, step, mark, legend)
    if style.show_fixed:
        _draw_fixed_nodes(plotter, results, tissue_positions, mark, style, legend)
    _draw_cut(plotter, cut_points, cut_triangles, legend)
    return legend, _title(results, step, index)


def _draw_tissue(plotter, results, tissue_positions, style: _Style, legend: list) -> None:
    """The deformed tissue surface, translucent with its edges."""
    import pyvista as pv

    surface = pv.PolyData(tissue_positions, triangle_cells(results.faces))
    plotter.add_mesh(
        surface,
        color=TISSUE_COLOR,
        opacity=style.tissue_opacity,
        show_edges=True,
        edge_color="#8c6d62",
        line_width=0.5,
        smooth_shading=False,
        render=False,
    )
    legend.append(["tissue (deformed surface)", TISSUE_COLOR])


def _instrument_views(results) -> tuple[tuple, tuple]:
    """The instruments' names and their views of the results (the results themselves for one needle)."""
    names = tuple(getattr(results, "instrument_names", ("needle",)))
    return names, (results.instruments if len(names) > 1 else (results,))


def _draw_needles(plotter, results, index: int, legend: list) -> float:
    """Every instrument's needle at step ``index`` as a translucent tube at its real radius, one colour each;
    returns the last one's drawn radius [m] (the markers' scale)."""
    import pyvista as pv

    names, views = _instrument_views(results)
    drawn_radius = 0.0
    for number, (name, view) in enumerate(zip(names, views, strict=True)):
        color = NEEDLE_COLORS[number % len(NEEDLE_COLORS)]
        radius = needle_radius(results.scene, name)
        needle_nodes = view.needle_positions[index]
        drawn_radius = radius if radius > 0 else 1e-3 * float(np.ptp(results.rest_positions, axis=0).max())
        needle = pv.lines_from_points(needle_nodes).tube(radius=drawn_radius, n_sides=32, capping=True)
        # Translucent: the needle is drawn at its real radius and may be wider than the cut it would hide.
        plotter.add_mesh(needle, color=color, smooth_shading=True, opacity=0.45, render=False)
        label = "needle" if len(names) == 1 else f"needle {name}"
        legend.append([f"{label}, r = {1e3 * radius:.2f} mm" if radius > 0 else label, color])
    return drawn_radius


def _draw_insertion_points(plotter, results, step: int, mark: float, legend: list) -> None:
    """The tissue-side points of the step's insertion rows as spheres of radius ``mark``."""
    import pyvista as pv

    rows = results.constraints_at(step)
    if "insertion" not in results.source_names:
        return
    insertion = np.unique(rows.points[rows.source == results.source_names.index("insertion")], axis=0)
    if insertion.size:
        spheres = pv.PolyData(insertion).glyph(geom=pv.Sphere(radius=mark), scale=False, orient=False)
        plotter.add_mesh(spheres, color=INSERTION_COLOR, smooth_shading=True, render=False)
        legend.append([f"insertion points ({insertion.shape[0]})", INSERTION_COLOR])


def _draw_fixed_nodes(plotter, results, tissue_positions, mark: float, style: _Style, legend: list) -> None:
    """The fixed nodes as cubes and, when they move, a few arrows of their prescribed displacement (scaled,
    the scale in the legend)."""
    import pyvista as pv

    fixed = np.asarray(results.fixed_nodes, dtype=np.int64)
    if not fixed.size:
        return
    cubes = pv.PolyData(tissue_positions[fixed]).glyph(
        geom=pv.Cube(x_length=1.4 * mark, y_length=1.4 * mark, z_length=1.4 * mark),
        scale=False,
        orient=False,
    )
    plotter.add_mesh(cubes, color=FIXED_COLOR, render=False)
    legend.append([f"fixed nodes ({fixed.size})", FIXED_COLOR])
    motion = _fixed_motion(results, tissue_positions)
    largest = float(np.linalg.norm(motion, axis=1).max())
    if style.show_motion and largest > 1e-9:
        # Small and few, so that they show the motion without hiding the tissue or the cut.
        scale = 0.06 * float(np.ptp(tissue_positions, axis=0).max()) / largest
        shown = np.linspace(0, fixed.size - 1, min(fixed.size, 16)).astype(np.int64)
        arrows = pv.PolyData(tissue_positions[fixed[shown]])
        arrows["motion"] = motion[shown] * scale
        plotter.add_mesh(
            arrows.glyph(orient="motion", scale="motion", factor=1.0, geom=pv.Arrow()),
            color=MOTION_COLOR,
            opacity=0.6,
            render=False,
        )
        legend.append([f"boundary motion\n(max {1e3 * largest:.2f} mm, drawn x{scale:.3g})", MOTION_COLOR])


def _draw_cut(plotter, cut_points, cut_triangles, legend: list) -> None:
    """The cut surface (its triangles, or its points before any triangle)."""
    import pyvista as pv

    if cut_triangles.size:
        cut = pv.PolyData(cut_points, triangle_cells(cut_triangles))
        plotter.add_mesh(
            cut, color=CUT_COLOR, opacity=1.0, show_edges=True, edge_color="#7f1010", render=False
        )
        legend.append(
            [f"cut surface\n({cut_points.shape[0]} points, {cut_triangles.shape[0]} triangles)", CUT_COLOR]
        )
    elif cut_points.size:
        plotter.add_mesh(
            pv.PolyData(cut_points),
            color=CUT_COLOR,
            point_size=8,
            render_points_as_spheres=True,
            render=False,
        )
        legend.append([f"cut points ({cut_points.shape[0]})", CUT_COLOR])


def _title(results, step: int, index: int) -> str:
    """The picture's title: scene, step and time, each instrument's phase, the tissue step shown."""
    names, views = _instrument_views(results)
    phase = f"{results.phase_names[results.phase[index]]} phase"
    if len(views) > 1:  # each instrument's phase
        phase = "\n".join(
            f"{name}: {view.phase_names[view.phase[index]]}" for name, view in zip(names, views, strict=True)
        )
    tissue_step = results.nearest_tissue_step(step) if results.tissue_steps.size else 0
    tissue_note = "" if tissue_step == step else f"\n(tissue of step {tissue_step})"
    return f"{results.scene_name}\nstep {step}, t = {results.time[index]:.3f} s\n{phase}{tissue_note}"


def _distance_to_segment(point: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Distance from a 2-D point to the segment ab (same units)."""
    ab = b - a
    t = float(np.clip((point - a) @ ab / max(ab @ ab, 1e-30), 0.0, 1.0))
    return float(np.linalg.norm(point - (a + t * ab)))


def _scale_length(span: float) -> float:
    """A round length (1, 2 or 5 times a power of ten) [m] near a quarter of ``span`` [m]."""
    target = 0.25 * span
    power = 10.0 ** np.floor(np.log10(target))
    return float(max(m * power for m in (1.0, 2.0, 5.0) if m * power <= target))


def _length_text(length: float) -> str:
    return f"{1e3 * length:g} mm" if length < 1.0 else f"{length:g} m"


def compose_picture(image: np.ndarray, legend: list, title: str, view: CameraView, size: tuple[int, int]):
    """The picture: the 3-D view ``image`` (h, w3, 3) at the left, and in the margin at the right the
    ``title``, the ``legend`` ([label, colour] rows), a scale bar and the axes' directions, all outside the
    view. Returns the RGB array (h, w, 3) of ``size`` = (w, h) pixels.

    The scale bar is the length of a segment at the focal point's depth, perpendicular to the view (the
    camera has perspective: nearer things look larger); the axes are the world x, y, z as the camera sees
    them."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    width, height = size
    dpi = 100.0
    figure = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(figure)
    left = image.shape[1] / width
    view_axis = figure.add_axes((0.0, 0.0, left, 1.0))
    view_axis.imshow(image, interpolation="nearest")
    view_axis.set_axis_off()
    margin = figure.add_axes((left, 0.0, 1.0 - left, 1.0))
    margin.set_xlim(0.0, 1.0)
    margin.set_ylim(0.0, 1.0)
    margin.set_axis_off()
    font = float(np.clip(height / 75.0, 6.0, 12.0))
    line = 1.9 * font / (height * 72.0 / dpi)  # a text line, in margin coordinates
    margin.text(0.06, 0.97, title, va="top", ha="left", fontsize=font * 1.1, color="black")
    y = 0.97 - (title.count("\n") + 2) * line * 1.1
    for label, color in legend:
        margin.add_patch(Rectangle((0.06, y - 0.55 * line), 0.06, 0.7 * line, color=color, clip_on=False))
        margin.text(0.16, y, label, va="center", ha="left", fontsize=font * 0.85, color="black", wrap=True)
        y -= 1.25 * line * (1 + label.count("\n"))
    # Scale bar: metres per pixel at the focal point's depth.
    distance = float(np.linalg.norm(view.position - view.focal_point))
    span = 2.0 * distance * np.tan(np.radians(view.view_angle) / 2.0)  # view height [m] at that depth
    length = _scale_length(span * image.shape[1] / image.shape[0])
    fraction = length / span * image.shape[0] / (width - image.shape[1])  # of the margin's width
    bar_y = 0.27
    margin.plot([0.06, 0.06 + fraction], [bar_y, bar_y], color="black", linewidth=3, solid_capstyle="butt")
    margin.text(
        0.06, bar_y + 0.6 * line, f"{_length_text(length)} (at the focal point)", fontsize=font * 0.85
    )
    # Axes: the world axes projected on the screen, arrows of equal length in pixels for equal projections.
    forward = _unit(view.focal_point - view.position)
    right = _unit(np.cross(forward, view.view_up))
    up = np.cross(right, forward)
    margin.text(0.06, 0.19, "axes", fontsize=font * 0.85)
    centre = np.array([0.3, 0.09])
    scale = 0.2
    ratio = (width - image.shape[1]) / height  # margin width over height
    colors = ("#c0392b", "#27ae60", "#2c3e50")
    tips = [np.array([v @ right, (v @ up) * ratio]) * scale for v in np.eye(3)]
    pixels = np.array([width - image.shape[1], height], dtype=float)  # margin units to pixels
    for index, (axis_vector, name, color, tip) in enumerate(zip(np.eye(3), "xyz", colors, tips, strict=True)):
        if np.hypot(*(tip * pixels)) < 0.3 * scale * pixels[0]:  # along the view: no arrow, words instead
            margin.text(
                0.55,
                0.13 - 0.04 * index,
                f"{name} {'out of' if axis_vector @ forward < 0 else 'into'} the picture",
                color=color,
                fontsize=font * 0.8,
                va="center",
            )
            continue
        margin.annotate(
            "",
            xy=centre + tip,
            xytext=centre,
            arrowprops={"arrowstyle": "-|>", "color": color, "linewidth": 1.5},
        )
        label = centre + 1.3 * tip
        if any(_distance_to_segment(label * pixels, (centre + other) * pixels, centre * pixels) < 0.6 * font
               for j, other in enumerate(tips) if j != index):  # fmt: skip
            label = centre + tip + (0.06, 0.0)  # on another arrow: the name beside its own tip
        margin.text(*label, name, color=color, fontsize=font, ha="center", va="center")
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[:, :, :3].copy()


def view_width_of(width: int) -> int:
    """Width [pixels] of the 3-D view in a picture ``width`` pixels wide (the rest is the margin), even."""
    return 2 * int(round(0.5 * (1.0 - MARGIN_FRACTION) * width))


def _apply_camera(plotter, view: CameraView) -> None:
    plotter.camera.position = tuple(view.position)
    plotter.camera.focal_point = tuple(view.focal_point)
    plotter.camera.up = tuple(view.view_up)
    plotter.camera.view_angle = view.view_angle
    plotter.reset_camera_clipping_range()


def _validate_window(window_size) -> tuple[int, int]:
    width, height = (int(v) for v in window_size)
    if width < 64 or height < 64:
        raise ValueError(f"window_size = {window_size}: expected at least 64 x 64 pixels")
    return width, height


def render_result(
    path,
    output_png,
    *,
    step: int | None = None,
    window_size: tuple[int, int] = (1200, 900),
    tissue_opacity: float = 0.35,
    camera=None,
    view_up=None,
    zoom: float = 1.0,
    focus="auto",
) -> Path:
    """Render one step of a results file to a PNG, off-screen, framed on the tissue, the needle and the cut.

    Shows the deformed tissue surface (semi-transparent; the recorded tissue state nearest to ``step``), the
    needle as a tube at its real radius (``needle.radius`` of the scene), the insertion points (tissue-side
    points of the insertion rows) as blue spheres, the fixed nodes as green cubes with, when they move, arrows
    of their prescribed displacement (scaled, the scale in the legend), and the cut surface in red. The
    title, the legend, a scale bar and the axes are in a margin at the right (:func:`compose_picture`),
    never over the view.

    Parameters
    ----------
    path : Results file.
    output_png : PNG to write (parent folders are created).
    step : Step to show (a step number as in ``Results.step``); the last step by default.
    window_size : Picture size in pixels (width, height), each >= 64.
    tissue_opacity : Opacity of the tissue surface, in (0, 1].
    camera, view_up, zoom, focus : The framing (see :func:`frame_camera`): by default the tissue with the
        needle's inserted part and the cut, looking at the cut face-on from 30° on the needle's base side, the
        base up.

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
    width, height = _validate_window(window_size)
    results = read_results(path)
    if results.step_count == 0:
        raise ValueError(f"{results.path}: the file holds no step to render")
    step = int(results.step[-1]) if step is None else int(step)
    results.index_of(step)
    tissue_positions = results.tissue_positions_at(step)
    cut_points, cut_triangles = cut_surface_positions(results, step, tissue_positions)
    view_width = view_width_of(width)
    view = _frame_every_needle(
        results,
        step,
        tissue_positions,
        cut_points,
        cut_triangles,
        camera=camera,
        view_up=view_up,
        zoom=zoom,
        focus=focus,
        aspect=view_width / height,
    )
    image, legend, title = _screenshot(
        results,
        step,
        tissue_positions,
        cut_points,
        cut_triangles,
        view,
        (view_width, height),
        _Style(tissue_opacity),
    )
    import imageio.v3 as iio

    output_png = Path(output_png)
    output_png.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(output_png, compose_picture(image, legend, title, view, (width, height)))
    logger.info("rendered step %d of %s to %s", step, results.path, output_png)
    return output_png


def _frame_every_needle(results, step: int, tissue_positions, cut_points, cut_triangles, *, focus, **framing):
    """:func:`frame_camera` with every instrument's needle in the picture (the further instruments' focus
    points included, unless the focus is the tissue or given as a point)."""
    others = None
    if len(getattr(results, "instrument_names", ())) > 1 and isinstance(focus, str) and focus != "tissue":
        others = np.concatenate(
            [
                focus_points(other, step, tissue_positions, cut_points, focus)
                for other in results.instruments[1:]
            ]
        )
    return frame_camera(
        results, step, tissue_positions, cut_points, cut_triangles, focus=focus, include=others, **framing
    )


def _screenshot(results, step, tissue_positions, cut_points, cut_triangles, view, size, style: _Style):
    """The step drawn off-screen through ``view`` in a window of ``size`` (width, height): the image, the
    legend and the title (:func:`_draw_step`)."""
    prepare_offscreen()
    import pyvista as pv

    view_size = float(np.linalg.norm(view.position - view.focal_point)) * np.tan(np.radians(_VIEW_ANGLE) / 2)
    plotter = pv.Plotter(off_screen=True, window_size=list(size))
    try:
        plotter.set_background("white")
        legend, title = _draw_step(
            plotter, results, step, tissue_positions, cut_points, cut_triangles, view_size, style
        )
        _apply_camera(plotter, view)
        plotter.render()
        image = plotter.screenshot(return_img=True)
    finally:
        plotter.close()
    return image, legend, title
