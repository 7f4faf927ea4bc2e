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
    "cut_surface_positions",
    "frame_camera",
    "parse_vector",
    "prepare_offscreen",
    "render_result",
]

logger = logging.getLogger(__name__)

TISSUE_COLOR = "#d9a38f"
NEEDLE_COLOR = "#5a6270"
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
FOCUS_CHOICES = ("auto", "needle", "cut", "tissue")
# Vertical view angle of the camera [degrees] (VTK's default).
_VIEW_ANGLE = 30.0


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

    "auto": the needle's inserted part, its tip, the insertion points and the cut; before the needle reaches
    the tissue, its tip and the closest point of the tissue's bounding box. "needle": the whole needle. "cut":
    the cut (auto when there is none). "tissue": the tissue.
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
    if inserted.shape[0] == 0:
        lower, upper = tissue_positions.min(axis=0), tissue_positions.max(axis=0)
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
    radius = float(np.max(np.linalg.norm(points - centre, axis=1)))
    needle_radius = float(results.scene.get("needle", {}).get("radius", 0.0) or 0.0)
    extent = float(np.ptp(tissue_positions, axis=0).max())
    # Padding: the needle's thickness, and never a view smaller than 5 % of the tissue.
    radius = max(1.3 * radius + 3.0 * needle_radius, 0.05 * extent)

    direction = _view_direction(camera, axis, cut_points, cut_triangles)
    up = -axis if view_up is None else _unit(parse_vector(view_up, "view_up"))
    if np.linalg.norm(np.cross(up, direction)) < 1e-3:
        if view_up is not None:
            raise ValueError(f"view_up = {view_up!r} is parallel to the view direction")
        up = _unit(np.cross(direction, np.cross(np.array([0.0, 0.0, 1.0]) + 0.1, direction)))
    # Hold a sphere of that radius in the narrower of the two view angles.
    half_angle = np.radians(_VIEW_ANGLE) / 2.0
    narrow = min(half_angle, np.arctan(np.tan(half_angle) * aspect))
    distance = radius / np.sin(narrow) / zoom
    if camera is None or (isinstance(camera, str) and camera == "auto"):
        # Of the two sides of the cut (or of the needle), prefer one where the camera is outside the tissue.
        mirrored = _unit(direction - 2.0 * (direction - (direction @ axis) * axis))
        inside = (
            locator.locate(np.array([centre + distance * direction, centre + distance * mirrored]))[0] >= 0
        )
        if inside[0] and not inside[1]:
            direction = mirrored
    return CameraView(centre + distance * direction, centre, up)


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
    return _unit(side - np.tan(np.radians(20.0)) * axis)


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
    show_legend: bool = True


def _draw_step(
    plotter, results, step: int, tissue_positions, cut_points, cut_triangles, view_size: float, style: _Style
) -> None:
    """Add the actors of one step to a plotter (see :func:`render_result`), without rendering (each render
    through Mesa takes ~0.2 s; the screenshot renders once)."""
    import pyvista as pv

    index = results.index_of(step)
    legend = []
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
    legend.append(["tissue", "#8c5a48"])

    radius = float(results.scene.get("needle", {}).get("radius", 0.0) or 0.0)
    needle_nodes = results.needle_positions[index]
    drawn_radius = radius if radius > 0 else 1e-3 * float(np.ptp(results.rest_positions, axis=0).max())
    needle = pv.lines_from_points(needle_nodes).tube(radius=drawn_radius, n_sides=32, capping=True)
    # Translucent: the needle is drawn at its real radius and may be wider than the cut it would hide.
    plotter.add_mesh(needle, color=NEEDLE_COLOR, smooth_shading=True, opacity=0.45, render=False)
    legend.append([f"needle, r = {1e3 * radius:.2f} mm" if radius > 0 else "needle", NEEDLE_COLOR])

    mark = max(0.35 * drawn_radius, 0.012 * view_size)
    rows = results.constraints_at(step)
    if "insertion" in results.source_names:
        insertion = np.unique(rows.points[rows.source == results.source_names.index("insertion")], axis=0)
        if insertion.size:
            spheres = pv.PolyData(insertion).glyph(geom=pv.Sphere(radius=mark), scale=False, orient=False)
            plotter.add_mesh(spheres, color=INSERTION_COLOR, smooth_shading=True, render=False)
            legend.append([f"insertion points ({insertion.shape[0]})", INSERTION_COLOR])

    fixed = np.asarray(results.fixed_nodes, dtype=np.int64)
    if style.show_fixed and fixed.size:
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
            scale = 0.12 * float(np.ptp(tissue_positions, axis=0).max()) / largest
            shown = np.linspace(0, fixed.size - 1, min(fixed.size, 150)).astype(np.int64)
            arrows = pv.PolyData(tissue_positions[fixed[shown]])
            arrows["motion"] = motion[shown] * scale
            plotter.add_mesh(
                arrows.glyph(orient="motion", scale="motion", factor=1.0, geom=pv.Arrow()),
                color=MOTION_COLOR,
                render=False,
            )
            legend.append([f"boundary motion (max {1e3 * largest:.2f} mm, x{scale:.3g})", MOTION_COLOR])

    if cut_triangles.size:
        cut = pv.PolyData(cut_points, triangle_cells(cut_triangles))
        plotter.add_mesh(
            cut, color=CUT_COLOR, opacity=1.0, show_edges=True, edge_color="#7f1010", render=False
        )
        legend.append(
            [f"cut surface ({cut_points.shape[0]} points, {cut_triangles.shape[0]} triangles)", CUT_COLOR]
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

    phase = results.phase_names[results.phase[index]]
    tissue_step = results.nearest_tissue_step(step) if results.tissue_steps.size else 0
    tissue_note = "" if tissue_step == step else f" (tissue of step {tissue_step})"
    plotter.add_text(
        f"{results.scene_name}  step {step}  t = {results.time[index]:.3f} s  {phase}{tissue_note}",
        position="upper_left",
        font_size=10,
        color="black",
        render=False,
    )
    if style.show_legend:
        # A legend of coloured text lines at the upper right, usually over the background above the tissue
        # (pyvista's legend box clips long labels).
        width, height = plotter.window_size
        line = max(14, int(0.03 * height))
        for row, (label, color) in enumerate(legend):
            plotter.add_text(
                label,
                position=(int(0.6 * width), height - int(0.02 * height) - (row + 1) * line),
                font_size=max(7, int(0.42 * line * 72 / 96)),
                color=color,
                render=False,
            )


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
    """Render one step of a results file to a PNG, off-screen, framed on the needle and the cut.

    Shows the deformed tissue surface (semi-transparent; the recorded tissue state nearest to ``step``), the
    needle as a tube at its real radius (``needle.radius`` of the scene), the insertion points (tissue-side
    points of the insertion rows) as blue spheres, the fixed nodes as green cubes with, when they move, arrows
    of their prescribed displacement (scaled, the scale in the legend), and the cut surface in red.

    Parameters
    ----------
    path : Results file.
    output_png : PNG to write (parent folders are created).
    step : Step to show (a step number as in ``Results.step``); the last step by default.
    window_size : Picture size in pixels (width, height), each >= 64.
    tissue_opacity : Opacity of the tissue surface, in (0, 1].
    camera, view_up, zoom, focus : The framing (see :func:`frame_camera`): by default aimed at the needle's
        inserted part and the cut, looking at the cut face-on, the needle's base up.

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
    view = frame_camera(
        results,
        step,
        tissue_positions,
        cut_points,
        cut_triangles,
        camera=camera,
        view_up=view_up,
        zoom=zoom,
        focus=focus,
        aspect=width / height,
    )

    prepare_offscreen()
    import pyvista as pv

    view_size = float(np.linalg.norm(view.position - view.focal_point)) * np.tan(np.radians(_VIEW_ANGLE) / 2)
    plotter = pv.Plotter(off_screen=True, window_size=[width, height])
    try:
        plotter.set_background("white")
        _draw_step(
            plotter,
            results,
            step,
            tissue_positions,
            cut_points,
            cut_triangles,
            view_size,
            _Style(tissue_opacity),
        )
        _apply_camera(plotter, view)
        plotter.render()
        output_png = Path(output_png)
        output_png.parent.mkdir(parents=True, exist_ok=True)
        plotter.screenshot(str(output_png))
    finally:
        plotter.close()
    logger.info("rendered step %d of %s to %s", step, results.path, output_png)
    return output_png
