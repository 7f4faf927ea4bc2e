"""The interactive window: an off-screen picture after a keyed insertion and lateral stroke shows the tissue,
the needle and the cut; under Xvfb the command's real window, driven by a scripted pose stream, saves a
picture
that shows them too."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pyvista")

from refsim.interactive.pacing import Pacer  # noqa: E402
from refsim.interactive.pose import KEYS  # noqa: E402
from refsim.interactive.session import InteractiveSession  # noqa: E402
from refsim.scene import load_scene  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
#: The coarse cube_cut: puncture after about 5 steps at the keyed speed, the cut after the sideways keys.
COARSE = ["mesh.cells=[4, 4, 4]"]


def _image(plotter) -> np.ndarray:
    plotter.render()
    return np.asarray(plotter.screenshot(return_img=True), dtype=np.int16)


def _pixels_of(window, name: str) -> np.ndarray:
    """The pixels the actor ``name`` changes: a picture with it against one without it (so the test does not
    depend on shading or blending), as a boolean mask (height, width)."""
    shown = _image(window.plotter)
    window.actors[name].SetVisibility(False)
    hidden = _image(window.plotter)
    window.actors[name].SetVisibility(True)
    return np.abs(shown - hidden).sum(axis=2) > 30


def _display_box(plotter, points: np.ndarray, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Image (row, column) bounds of ``points`` [m] projected on the screen."""
    import vtk

    coordinate = vtk.vtkCoordinate()
    coordinate.SetCoordinateSystemToWorld()
    projected = []
    for point in points:
        coordinate.SetValue(*point)
        x, y = coordinate.GetComputedDisplayValue(plotter.renderer)
        projected.append((height - 1 - y, x))
    projected = np.array(projected)
    return projected.min(axis=0), projected.max(axis=0)


def _press(window, key: str) -> None:
    """A key press as the window's interactor receives it from the keyboard (VTK's KeyPressEvent)."""
    assert key in KEYS
    interactor = window.plotter.iren.interactor
    interactor.SetKeySym(key)
    interactor.InvokeEvent("KeyPressEvent")


@pytest.fixture(scope="module")
def keyed_window(tmp_path_factory):
    """A keyed session on the coarse cube_cut, drawn off-screen: 19 key presses Up (1 mm each along the
    needle), 45 steps (at 50 mm/s: 0.5 mm per step), 8 presses Right (8 mm sideways), 30 steps."""
    from refsim.interactive.window import InteractiveWindow

    folder = tmp_path_factory.mktemp("window")
    session = InteractiveSession(load_scene("cube_cut", COARSE), folder / "keyed.h5")
    pacer = Pacer(session)
    window = InteractiveWindow(session, pacer, off_screen=True, window_size=(900, 600))
    for _ in range(19):
        _press(window, "Up")
    for _ in range(45):
        session.step()
    for _ in range(8):
        _press(window, "Right")
    for _ in range(30):
        session.step()
    window.update()
    picture = window.save(folder / "keyed.png")
    yield session, window, picture
    pacer.finish()
    window.close()


def test_keys_drive_the_needle_through_puncture_and_cut(keyed_window):
    session, _, _ = keyed_window
    names = [name for _, _, name, _, _ in session.summary.events]
    assert "puncture" in names and "cut_start" in names
    # 19 mm down the needle (-z) and 8 mm along a = x for a needle along -z, both reached
    start = np.array([0.00123, 0.00231, 0.422])
    np.testing.assert_allclose(session.target.applied_base - start, [0.008, 0.0, -0.019], atol=1e-12)


def test_the_picture_shows_tissue_needle_and_cut(keyed_window):
    session, window, picture = keyed_window
    assert picture.is_file() and picture.stat().st_size > 10_000
    height = window.plotter.window_size[1]
    for name in ("tissue", "needle", "cut"):
        mask = _pixels_of(window, name)
        assert mask.sum() > 300, f"the {name} changes only {mask.sum()} pixels"
    # The needle's pixels lie where its nodes project (within a few pixels, the tube's radius aside).
    needle = _pixels_of(window, "needle")
    rows, columns = np.nonzero(needle)
    low, high = _display_box(window.plotter, np.asarray(session.state.needle.positions), height)
    margin = 40  # pixels: the tube's radius on screen is about 10
    assert low[0] - margin <= np.median(rows) <= high[0] + margin
    assert low[1] - margin <= np.median(columns) <= high[1] + margin
    # The cut's pixels lie where the cut surface projects, and the cut makes them redder: its colour
    # (214, 39, 40) takes away far more green than red from what lies behind it (tissue, needle, background).
    cut = session.state.cut.deformed_points(session.state.tissue.positions, window.tets)
    rows, columns = np.nonzero(_pixels_of(window, "cut"))
    low, high = _display_box(window.plotter, cut, height)
    assert low[0] - margin <= np.median(rows) <= high[0] + margin
    assert low[1] - margin <= np.median(columns) <= high[1] + margin
    shown = _image(window.plotter)[rows, columns]
    window.actors["cut"].SetVisibility(False)
    hidden = _image(window.plotter)[rows, columns]
    window.actors["cut"].SetVisibility(True)
    removed = hidden - shown  # per channel
    assert np.median(removed[:, 1] - removed[:, 0]) > 20


def _drive(stream, target: np.ndarray, direction) -> list[str]:
    """Send the pose ``target`` once (it holds until replaced) and read the step replies until the applied
    base reaches it; return the events seen."""
    stream.write(json.dumps({"base": target.tolist(), "direction": direction}) + "\n")
    stream.flush()
    events = []
    while True:
        reply = json.loads(stream.readline())
        assert "error" not in reply, reply
        events += reply.get("events", [])
        if "base" in reply and np.allclose(reply["base"], target, rtol=0.0, atol=1e-12):
            return events


def _xvfb_skip_reason() -> str | None:
    if shutil.which("Xvfb") is None:
        return "Xvfb is not installed (apt-get install xvfb; .ci/run installs it when it can)"
    return None


@pytest.fixture(scope="module")
def xvfb_display():
    """A virtual X display for the module's window tests."""
    from refsim.interactive.command import x_display_error

    display = f":{90 + os.getpid() % 100}"
    # -noreset: a server whose last client disconnects resets, refusing connections for a moment (a window
    # started then got no display)
    server = subprocess.Popen(
        ["Xvfb", display, "-screen", "0", "1280x1024x24", "-nolisten", "tcp", "-noreset"]
    )
    # Until the server accepts connections (a fixed second was too short on a loaded machine: the window got
    # no display and its session ended after one step).
    deadline = time.monotonic() + 60.0
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("DISPLAY", display)
        while x_display_error() is not None and server.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        reason = x_display_error()
    if reason is not None:
        server.terminate()
        pytest.fail(f"Xvfb {display} did not start within 60 s: {reason}")
    yield display
    server.terminate()
    server.wait(timeout=10)


def _start_window(display: str, tmp_path: Path, picture: Path):
    """`refsim interactive` on the coarse cube_cut with its window on ``display`` and a pose stream (on which
    the test reads the steps and asks to stop); returns the process and the connected stream."""
    env = {**os.environ, "DISPLAY": display, "PYTHONPATH": str(ROOT)}
    env.pop("VTK_DEFAULT_OPENGL_WINDOW", None)
    command = [sys.executable, "-m", "refsim", "interactive", "cube_cut", "--set", COARSE[0]]
    command += ["--socket", "0", "-o", str(tmp_path / "x.h5"), "--screenshot", str(picture)]
    command += ["--max-speed", "0.2"]  # 2 mm per step: few steps on a slow software display
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    line = process.stdout.readline()
    if "pose stream on" not in line:
        process.kill()
        pytest.fail(f"no pose stream: {line}{process.stderr.read()}")
    port = int(line.split(":")[1].split()[0])
    connection = socket.create_connection(("127.0.0.1", port), timeout=120)
    return process, connection


def _finish(process, connection) -> list[dict]:
    """Ask the session to stop; return the replies after it, and wait for the command to exit 0."""
    stream = connection.makefile("rw")
    stream.write('{"stop": true}\n')
    stream.flush()
    replies = [json.loads(line) for line in stream]
    connection.close()
    out, err = process.communicate(timeout=300)
    assert process.returncode == 0, out + err
    assert replies and replies[-1].get("done") and replies[-1]["status"] == "complete", (
        replies[-3:],
        out,
        err,
    )
    return replies


def _until(stream, reached) -> list[str]:
    """Read step replies until ``reached(reply)``; return the events seen."""
    events = []
    while True:
        line = stream.readline()
        if not line:
            raise EOFError("the session closed the pose stream")
        reply = json.loads(line)
        assert "error" not in reply, reply
        events += reply.get("events", [])
        if "base" in reply and reached(reply):
            return events


def _hues(picture: Path) -> tuple[int, int, int]:
    """Pixels of the cut's, the needle's and the tissue's hue in the picture.

    Hues tell the three apart (the picture blends them: the cut lies behind the translucent tissue and
    needle): the needle's grey-blue #5a6270 has blue above red, the tissue's #d9a38f red above blue with R - G
    about 20 after blending with white, the cut's #d62728 R - G above 30 (measured 36 through both)."""
    import imageio.v3 as iio

    image = np.asarray(iio.imread(picture), dtype=np.int16)[..., :3]
    red, green, blue = image[..., 0], image[..., 1], image[..., 2]
    cut = red - green >= 30
    return int(cut.sum()), int((blue - red >= 5).sum()), int(((red - blue >= 15) & ~cut).sum())


@pytest.mark.skipif(_xvfb_skip_reason() is not None, reason=str(_xvfb_skip_reason()))
def test_the_window_under_xvfb_driven_by_a_scripted_pose_stream(xvfb_display, tmp_path):
    """The real window on an X server (Xvfb), a pose stream in real time: the scripted client inserts the
    needle and moves it sideways (each pose held until reached), asks to stop; the window's picture shows the
    tissue's, the needle's and the cut's colours."""
    picture = tmp_path / "window.png"
    process, connection = _start_window(xvfb_display, tmp_path, picture)
    try:
        stream = connection.makefile("rw")
        hello = json.loads(stream.readline())
        base, direction = np.array(hello["base"]), hello["direction"]
        events = []
        for target in (base + [0.0, 0.0, -0.019], base + [0.008, 0.0, -0.019]):
            stream.write(json.dumps({"base": target.tolist(), "direction": direction}) + "\n")
            stream.flush()
            events += _until(
                stream, lambda reply, t=target: np.allclose(reply["base"], t, rtol=0.0, atol=1e-12)
            )
        _finish(process, connection)
    except EOFError as error:
        process.kill()
        out, err = process.communicate(timeout=60)
        pytest.fail(f"{error} before the poses were reached:\n{out[-3000:]}\n{err[-3000:]}")
    finally:
        if process.poll() is None:
            process.kill()
    assert "puncture" in events and "cut_start" in events
    cut, needle, tissue = _hues(picture)
    assert cut > 500 and needle > 5_000 and tissue > 50_000


@pytest.mark.skipif(_xvfb_skip_reason() is not None, reason=str(_xvfb_skip_reason()))
@pytest.mark.skipif(
    shutil.which("xdotool") is None, reason="xdotool is not installed (apt-get install xdotool)"
)
@pytest.mark.slow  # 75 s on a loaded 2-core machine: the software display renders a frame in about 0.5 s
def test_the_window_under_xvfb_driven_by_scripted_keys(xvfb_display, tmp_path):
    """Real key presses (xdotool, through the X server) on the real window: 19 x Up and 8 x Right insert the
    needle 19 mm and move it 8 mm sideways (a = +x for the cube's needle); the steps read on the stream show
    the puncture and the cut, and the picture shows them."""
    picture = tmp_path / "keys.png"
    process, connection = _start_window(xvfb_display, tmp_path, picture)
    env = {**os.environ, "DISPLAY": xvfb_display}
    try:
        stream = connection.makefile("rw")
        base = np.array(json.loads(stream.readline())["base"])
        window = ""
        for _ in range(600):  # the window opens once the session is built (seconds on a loaded machine)
            found = subprocess.run(
                ["xdotool", "search", "--name", "refsim interactive"], capture_output=True, text=True, env=env
            )
            window = found.stdout.split()[0] if found.stdout.split() else ""
            if window:
                break
            time.sleep(0.2)
        assert window, "the window did not open"
        subprocess.run(["xdotool", "windowfocus", "--sync", window], check=True, env=env)
        events = []
        for key, presses, target in (
            ("Up", 19, base + [0.0, 0.0, -0.019]),
            ("Right", 8, base + [0.008, 0.0, -0.019]),
        ):
            subprocess.run(
                ["xdotool", "key", "--delay", "30", "--repeat", str(presses), key], check=True, env=env
            )
            events += _until(
                stream, lambda reply, t=target: np.allclose(reply["base"], t, rtol=0.0, atol=1e-9)
            )
        _finish(process, connection)
    finally:
        if process.poll() is None:
            process.kill()
    assert "puncture" in events and "cut_start" in events
    cut, needle, tissue = _hues(picture)
    assert cut > 500 and needle > 5_000 and tissue > 50_000
