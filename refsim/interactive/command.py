"""``refsim interactive SCENE``: its options (:func:`add_parser`, imported by ``refsim --help``: argparse
only) and its handler (imports the simulation when it runs)."""

from __future__ import annotations

import argparse
import math

__all__ = ["REACH", "add_parser", "run_interactive", "x_display_error"]

#: Largest accepted distance of a base position from the origin [m] (the bound of trajectory waypoints).
REACH = 1e3


def add_parser(commands) -> None:
    """Register the ``interactive`` subcommand on the command line's subparsers."""
    parser = commands.add_parser(
        "interactive",
        help="drive the needle live: a window (keys) and/or a pose stream on a loopback socket",
        description="Drive the needle base live, by keyboard in a window or by a pose stream "
        "(newline-delimited JSON on a loopback TCP socket, the force sent back every step), recorded to HDF5 "
        "with a replay scene beside it (docs/interactive.md).",
    )
    parser.add_argument(
        "scene", help="scene file (.toml) or built-in scene name; its trajectory gives the start pose"
    )
    parser.add_argument(
        "-o", "--output", default="interactive.h5", help="results file (.h5), default interactive.h5"
    )
    parser.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override a scene value")
    parser.add_argument(
        "--socket", type=int, metavar="PORT", help="serve the pose stream on this TCP port (0: any)"
    )
    parser.add_argument("--host", default="127.0.0.1", help="loopback address to bind (127.0.0.1 or ::1)")
    parser.add_argument("--no-window", action="store_true", help="headless: the pose stream only")
    parser.add_argument(
        "--lockstep", action="store_true", help="one step per received pose instead of the wall clock"
    )
    parser.add_argument("--duration", type=float, metavar="S", help="end after this simulated time [s]")
    parser.add_argument(
        "--max-speed", type=float, default=0.05, metavar="M/S", help="largest base speed [m/s] (default 0.05)"
    )
    parser.add_argument(
        "--max-turn",
        type=float,
        default=30.0,
        metavar="DEG/S",
        help="largest turning rate [deg/s] (default 30)",
    )
    parser.add_argument("--key-step", type=float, default=1.0, metavar="MM", help="travel per key press [mm]")
    parser.add_argument(
        "--key-angle", type=float, default=2.0, metavar="DEG", help="tilt per key press [deg]"
    )
    parser.add_argument(
        "--screenshot", metavar="PNG", help="save the window as a picture when the session ends"
    )
    parser.add_argument("--overwrite", action="store_true", help="replace existing output files")
    parser.set_defaults(handler=run_interactive)


def _positive(value: float | None, option: str, unit: str) -> None:
    if value is not None and not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"{option} {value!r}: expected a positive number [{unit}]")


def run_interactive(args: argparse.Namespace) -> int:
    """The handler of ``refsim interactive``; returns the exit code: the options checked, the pose server
    bound, the session opened, driven (window or headless) until a stop, closed, and reported."""
    import threading
    from pathlib import Path

    from refsim.interactive.pacing import Pacer
    from refsim.interactive.server import PoseServer
    from refsim.interactive.session import InteractiveSession
    from refsim.kernel_warmup import start_background_compilation
    from refsim.scene import load_scene

    _check_options(args)
    # After a fresh install, the kernels on the second core too (refsim.kernel_warmup), from before the
    # scene's loading, as `refsim run` does; stopped at exit, bad input included.
    start_background_compilation()
    scene = load_scene(args.scene, args.set or ())
    max_steps = None if args.duration is None else max(1, round(args.duration / scene.time.dt))
    server = None
    if args.socket is not None:  # bound before anything is written: a port in use is bad input
        server = PoseServer(args.socket, host=args.host, reach=REACH, hello={}, on_pose=None)
    try:
        session = InteractiveSession(
            scene,
            Path(args.output),
            overwrite=args.overwrite,
            max_speed=args.max_speed,
            max_turn=math.radians(args.max_turn),
        )
    except BaseException:
        if server is not None:
            server.close()
        raise
    stop = threading.Event()
    try:
        if server is not None:
            _serve(args, scene, session, server)
        pacer = Pacer(session, server, lockstep=args.lockstep, max_steps=max_steps)
        _drive(args, session, pacer, server, stop)
    except Exception as error:  # noqa: BLE001 - a failed step: the file is closed, the reason stored
        if session.finished:
            raise
        session.fail(error)
    finally:
        if not session.finished:
            session.fail(RuntimeError("stopped"))
        if server is not None:
            server.close(
                {
                    "done": True,
                    "status": session.status,
                    "steps": session.state.step,
                    "output": str(session.output),
                    "replay": str(session.replay_path),
                    "reason": session.stop_reason,
                }
            )
    return _report(scene, session)


def _check_options(args: argparse.Namespace) -> None:
    """Bad options and a missing window (pyvista, a display) as errors naming the option, before anything
    is opened."""
    import os

    from refsim.interactive.server import check_loopback

    for value, option, unit in (
        (args.duration, "--duration", "s"),
        (args.max_speed, "--max-speed", "m/s"),
        (args.max_turn, "--max-turn", "deg/s"),
        (args.key_step, "--key-step", "mm"),
        (args.key_angle, "--key-angle", "deg"),
    ):
        _positive(value, option, unit)
    if args.no_window and args.socket is None:
        raise ValueError("--no-window needs the pose stream: give --socket PORT")
    if args.lockstep and args.socket is None:
        raise ValueError("--lockstep needs the pose stream: give --socket PORT")
    if args.screenshot and args.no_window:
        raise ValueError("--screenshot needs the window (drop --no-window)")
    check_loopback(args.host)
    if not args.no_window:
        import importlib.util

        if importlib.util.find_spec("pyvista") is None:  # the command line names the extra to install
            raise ModuleNotFoundError("the interactive window needs pyvista", name="pyvista")
        if os.name == "posix" and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            raise ValueError(
                "the interactive window needs a display (DISPLAY is not set): run headless with --no-window "
                "--socket PORT, or under a virtual display (xvfb-run refsim interactive ...)"
            )
        unreachable = x_display_error()
        if unreachable is not None:  # VTK would only warn, and the window's event loop end at once
            raise ValueError(
                f"the interactive window needs a display: {unreachable}; run headless with --no-window "
                "--socket PORT, or under a virtual display (xvfb-run refsim interactive ...)"
            )


_X_CONNECTIONS: dict = {}  # DISPLAY -> the open probe connection, kept for the process's life


def x_display_error() -> str | None:
    """Why the X server named by ``$DISPLAY`` cannot be reached (``XOpenDisplay`` of libX11 fails), or None:
    reached, or not checkable here (no DISPLAY, no libX11: another platform, a Wayland-only session).

    A connection that succeeds is kept open until the process exits: closing it would leave a server without
    other clients (a bare Xvfb) to reset, refusing connections for a moment, the window's own among them."""
    import ctypes
    import ctypes.util
    import os

    display = os.environ.get("DISPLAY")
    if display in _X_CONNECTIONS:
        return None
    name = ctypes.util.find_library("X11") if display else None
    if name is None:
        return None
    try:
        library = ctypes.CDLL(name)
    except OSError:
        return None
    library.XOpenDisplay.restype = ctypes.c_void_p
    library.XOpenDisplay.argtypes = [ctypes.c_char_p]
    handle = library.XOpenDisplay(display.encode())
    if not handle:
        return f"cannot connect to the X server of DISPLAY={display}"
    _X_CONNECTIONS[display] = handle
    return None


def _serve(args: argparse.Namespace, scene, session, server) -> None:
    """Start the pose stream: poses to the session's target (or queued, lockstep), the hello message."""
    server.on_pose = None if args.lockstep else session.target.set
    server.queue_poses = args.lockstep
    server.hello.update(
        {
            "scene": scene.name,
            "dt": session.dt,
            "mode": "lockstep" if args.lockstep else "realtime",
            "needle_length": scene.needle.length,
            "base": session.target.applied_base.tolist(),
            "direction": session.target.applied_direction.tolist(),
            "max_speed": args.max_speed,
        }
    )
    server.start()
    print(
        f"pose stream on {server.host}:{server.port} (newline-delimited JSON, docs/interactive.md)",
        flush=True,
    )


def _drive(args: argparse.Namespace, session, pacer, server, stop) -> None:
    """Step the session in the window or headless until a stop (Ctrl-C and SIGTERM set ``stop`` meanwhile),
    then finish it; the window's screenshot when asked."""
    import signal
    import threading
    import time as clock
    from pathlib import Path

    previous = {}

    def request_stop(signum, frame) -> None:
        stop.set()

    if threading.current_thread() is threading.main_thread():  # Ctrl-C, SIGTERM: a clean end
        for number in (signal.SIGINT, signal.SIGTERM):
            previous[number] = signal.signal(number, request_stop)
    try:
        if args.no_window:
            _headless(pacer, server, stop, clock)
        else:
            from refsim.interactive.window import InteractiveWindow

            window = InteractiveWindow(
                session,
                pacer,
                key_step=args.key_step * 1e-3,
                key_angle=math.radians(args.key_angle),
            )
            window.show(
                should_stop=lambda: stop.is_set() or (server is not None and server.stop_requested.is_set())
            )
            if window.error is not None:  # a step failed inside the window's timer
                raise window.error
        pacer.finish()
        if not args.no_window:
            if args.screenshot:
                window.update()
                print(f"wrote {window.save(Path(args.screenshot))}")
            window.close()
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def _report(scene, session) -> int:
    """Print where the session went (results, ParaView sidecar, trajectory, replay) and its summary; the
    exit code."""
    summary = session.summary
    print(f"scene {scene.name} ({scene.source}) -> {session.output}")
    if session.status != "write_failed":  # the ParaView sidecar, as `refsim run` writes it
        from refsim.io.xdmf import write_xdmf

        try:
            print(f"ParaView: {write_xdmf(session.output)}")
        except (OSError, ValueError, RuntimeError) as error:
            print(f"refsim: no XDMF sidecar for {session.output}: {error}")
    if session.status != "complete":
        print(f"refsim interactive: error: {session.stop_reason}", flush=True)
    print(f"trajectory: {session.trajectory_path}")
    print(f"replay: refsim run {session.replay_path} -o REPLAY.h5")
    print(summary.format())
    return summary.exit_code


def _headless(pacer, server, stop, clock) -> None:
    """Step until a stop (signal, {"stop": true}, --duration, or the last client leaving); real time starts
    when the first client connects."""
    while not (stop.is_set() or server.stop_requested.is_set() or server.connected.is_set()):
        server.connected.wait(0.05)
    pacer.start_clock()
    while not (stop.is_set() or server.stop_requested.is_set() or pacer.done):
        if server.disconnected.is_set() and (not pacer.lockstep or server.poses.empty()):
            break
        if pacer.pump(budget=0.05) == 0:
            clock.sleep(min(pacer.wait_time(), 0.01))
