"""The interactive window (pyvista): the tissue's deformed surface, the needle, the cut surface, a live plot
of the needle force and a text line with the phase, the force and the real-time factor; keys move the needle
base (:data:`refsim.interactive.pose.KEYS`, space holds, q closes).

The window steps the session from a repeating timer (every 15 ms: the due steps, for at most 50 ms or the
last render's time, then one render), so keys, the pose stream and the steps share the main thread: VTK
renders only there.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from refsim.interactive.pose import KEYS

__all__ = ["InteractiveWindow"]

#: Simulated seconds shown by the live force plot.
PLOT_SECONDS = 5.0
#: Timer period of the window [ms] and the wall time of steps taken per tick [s].
TICK_MS = 15
TICK_BUDGET = 0.05


def _faces(triangles: np.ndarray) -> np.ndarray:
    triangles = np.asarray(triangles, dtype=np.int64)
    return np.column_stack([np.full(len(triangles), 3, dtype=np.int64), triangles]).ravel()


class InteractiveWindow:
    """A pyvista window on an interactive session.

    Parameters
    ----------
    session : The :class:`~refsim.interactive.session.InteractiveSession`.
    pacer : The :class:`~refsim.interactive.pacing.Pacer` that takes its steps.
    key_step : Base travel per key press [m].
    key_angle : Tilt per key press [rad].
    off_screen : Render without a window (pictures, tests).
    window_size : [pixels] (width, height).
    """

    def __init__(
        self,
        session,
        pacer,
        *,
        key_step: float = 1e-3,
        key_angle: float = np.radians(2.0),
        off_screen: bool = False,
        window_size: tuple[int, int] = (1200, 800),
    ) -> None:
        import pyvista as pv

        from refsim.viz.render import CUT_COLOR, NEEDLE_COLOR, TISSUE_COLOR, prepare_offscreen

        if off_screen:
            prepare_offscreen()
        self.session = session
        self.pacer = pacer
        self.key_step = float(key_step)
        self.key_angle = float(key_angle)
        self.colors = {"tissue": TISSUE_COLOR, "needle": NEEDLE_COLOR, "cut": CUT_COLOR}
        self._cut_version = None
        self._render_seconds = 0.0  # the last render's wall time [s]
        self.error: Exception | None = None  # what stopped the window's timer, if a step failed
        scene = session.scene
        self.radius = float(scene.needle.radius)
        mesh = session.models.mesh
        self.tets = np.asarray(mesh.tets)
        self.plotter = pv.Plotter(
            off_screen=off_screen, window_size=list(window_size), title="refsim interactive"
        )
        self.plotter.set_background("white")
        positions = np.asarray(session.state.tissue.positions, dtype=float)
        self.surface = pv.PolyData(positions.copy(), _faces(mesh.boundary_faces))
        # Translucent tissue, to see the needle and the cut inside it; a translucent needle, which is drawn at
        # its real radius and may be wider than the cut it would hide (as refsim render draws it).
        self.actors = {
            "tissue": self.plotter.add_mesh(
                self.surface,
                color=TISSUE_COLOR,
                opacity=0.35,
                show_edges=True,
                edge_color="#8c6d62",
                line_width=0.5,
            )
        }
        self._draw_needle()
        self.status = self.plotter.add_text("", position="upper_left", font_size=10, color="black")
        help_text = "\n".join(
            [f"{key}: {action.label}" for key, action in KEYS.items()]
            + ["space: hold", "q: quit (the run is saved)"]
        )
        self.plotter.add_text(help_text, position="lower_left", font_size=7, color="#333333")
        self.chart = pv.Chart2D(size=(0.32, 0.28), loc=(0.66, 0.70), x_label="t [s]", y_label="|F| [N]")
        self.chart.background_color = (1.0, 1.0, 1.0, 0.6)
        self.force_line = self.chart.line([0.0, 1e-9], [0.0, 0.0], color="#1f77b4", width=2.0)
        self.plotter.add_chart(self.chart)
        for key, action in KEYS.items():
            self.plotter.add_key_event(key, lambda action=action: self.key(action))
        self.plotter.add_key_event("space", self.session.target.hold)
        self._focus()
        self.update()

    # ------------------------------------------------------------------ drawing

    def _draw_needle(self) -> None:
        import pyvista as pv

        nodes = np.asarray(self.session.state.needle.positions, dtype=float)
        tube = pv.lines_from_points(nodes).tube(radius=self.radius, n_sides=24, capping=True)
        self.actors["needle"] = self.plotter.add_mesh(
            tube, color=self.colors["needle"], smooth_shading=True, opacity=0.6, name="needle", render=False
        )

    def _focus(self) -> None:
        """Look at the needle's starting tip (where the needle meets the tissue) from above the side, from a
        distance of about the tissue's size."""
        rest = np.asarray(self.session.models.mesh.rest_positions)
        size = float(np.linalg.norm(rest.max(axis=0) - rest.min(axis=0)))
        tip = np.asarray(self.session.state.needle.positions, dtype=float)[-1]
        self.plotter.camera.focal_point = tip
        self.plotter.camera.position = tip + size * np.array([0.55, -0.7, 0.35])
        self.plotter.camera.up = (0.0, 0.0, 1.0)

    def update(self) -> None:
        """Redraw from the session's current state (no render)."""
        state = self.session.state
        self.surface.points = np.asarray(state.tissue.positions, dtype=float)
        self._draw_needle()
        cut = state.cut
        if cut is not None and cut.triangle_count and cut is not self._cut_version:
            import pyvista as pv

            points = cut.deformed_points(np.asarray(state.tissue.positions), self.tets)
            mesh = pv.PolyData(np.asarray(points, dtype=float), _faces(cut.triangles))
            self.actors["cut"] = self.plotter.add_mesh(
                mesh,
                color=self.colors["cut"],
                show_edges=True,
                edge_color="#7f1010",
                name="cut",
                render=False,
            )
            self._cut_version = cut
        record = self.session.last_record
        force = np.zeros(3) if record is None else np.asarray(record.needle_force, dtype=float)
        events = [f"{name} (step {step})" for step, _, name, _, _ in self.session.summary.events[-3:]]
        rate = self.session.real_time_factor
        rate_text = "-" if not np.isfinite(rate) else f"{rate:.2f}"
        self.status.SetText(
            2,
            f"t = {state.time:.3f} s   step {state.step}   {state.phase}\n"
            f"force on the needle {np.linalg.norm(force):.3f} N  "
            f"[{force[0]:+.3f}, {force[1]:+.3f}, {force[2]:+.3f}]\n"
            f"real-time factor {rate_text}\n" + ("events: " + ", ".join(events) if events else ""),
        )
        self._plot_force()

    def _plot_force(self) -> None:
        history = self.session.force_history
        if len(history) < 2:
            return
        times, values = np.array(history).T
        shown = times >= times[-1] - PLOT_SECONDS
        times, values = times[shown], values[shown]
        if times.size < 2:
            return
        self.force_line.update(times, values)
        self.chart.x_range = [float(times[0]), float(times[-1])]
        self.chart.y_range = [0.0, max(1.1 * float(values.max()), 0.1)]

    # ------------------------------------------------------------------ input

    def key(self, action) -> None:
        """One key press (the window's key events call this)."""
        self.session.target.key(action, distance=self.key_step, angle=self.key_angle)

    def tick(self) -> None:
        """The timer's work: the due steps, then one render. The steps may take as long as the last render
        did (at least :data:`TICK_BUDGET`), so a slow display (software OpenGL: 0.5 s per render measured
        under Xvfb on a loaded machine) does not starve the simulation."""
        if self.pacer.pump(budget=max(TICK_BUDGET, self._render_seconds)):  # may raise: see show()
            self.update()
            started = time.perf_counter()
            self.plotter.render()
            self._render_seconds = time.perf_counter() - started

    def show(self, should_stop) -> None:
        """Open the window and step from its timer until it is closed, ``should_stop()`` or the pacer is
        done; a step that raised stops it too, the error kept in :attr:`error`."""
        plotter = self.plotter

        def on_timer(*_) -> None:
            if should_stop() or self.pacer.done:
                plotter.iren.terminate_app()
                return
            try:
                self.tick()
            except Exception as error:  # noqa: BLE001 - VTK would print it and call the timer again
                self.error = error
                plotter.iren.terminate_app()

        plotter.show(interactive_update=True, auto_close=False)
        self.pacer.start_clock()
        plotter.iren.add_observer("TimerEvent", on_timer)
        plotter.iren.create_timer(TICK_MS, repeating=True)
        plotter.iren.start()

    def save(self, path: Path) -> Path:
        """Render and write the window to ``path`` (PNG)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.plotter.render()
        self.plotter.screenshot(str(path))
        return path

    def close(self) -> None:
        self.plotter.close()
