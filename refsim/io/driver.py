"""The one run driver: scene → simulation → results file → summary (used by `refsim run`, the studies and
sweeps).

:func:`run_scene` is a plain function without global state, so a Dask task can call it. It checks the output
path before anything is built, builds the simulation (every input error surfaces there, before a file exists),
then runs it, writing each step (buffered in blocks, see :mod:`refsim.io.writer`) and the cut surface as it
grows, and feeding a :class:`~refsim.simulation.summary.RunSummary`. Whatever stops the run, the file is
closed with every completed step readable, ``complete`` false and the reason in the root attribute
``stop_reason``:

============================================  ====================  =========
what stopped the run                           ``summary.status``    exit code
============================================  ====================  =========
nothing (finished)                             "complete"            0
non-finite or overflowing values, singular     "numerical"           3
factorisation, diverging constraint solver
a failed write (full disk)                     "write_failed"        3
SIGINT (Ctrl-C)                                "interrupted"         130
SIGHUP (a closed terminal, a dropped ssh)      "hangup"              129
SIGTERM                                        "terminated"          143
============================================  ====================  =========

The table is :data:`refsim.simulation.summary.RUN_STATUSES`, the one definition the code reads.

Bad input raises :class:`RunInputError` (exit code 2) before any file is written; so does a results file that
another run is writing (its lock is held). A file that cannot be created because the disk is full raises
:class:`RunWriteError` (exit code 3), with nothing written and an existing file untouched.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

__all__ = [
    "RunInputError",
    "RunWriteError",
    "StepSink",
    "check_output_path",
    "check_record",
    "run_scene",
]

logger = logging.getLogger(__name__)

# : A tissue displacement beyond this many times the tissue's bounding-box diagonal is a diverging run: a
# tissue : with fixed nodes cannot move that far (measured: an overflow moved it by 1e144 m with finite
# numbers).
DIVERGENCE_FACTOR = 10.0
#: Largest magnitude of a force [N] or position [m] that is still a number to compute with (beyond it squares
#: overflow float64 and the next step gives inf).
OVERFLOW = 1e150


class RunInputError(ValueError):
    """Bad input found before the run (scene, mesh, output path); nothing was written. Exit code 2."""


class RunWriteError(OSError):
    """The results file could not be created (a full disk before the first step); nothing was written and an
    existing file is untouched. Exit code 3."""

    def __str__(self) -> str:
        return str(self.strerror)


class _Terminated(BaseException):
    """Raised in the main thread by the SIGTERM and SIGHUP handlers (a BaseException, like
    KeyboardInterrupt); ``signum`` says which."""

    def __init__(self, signum: int = signal.SIGTERM) -> None:
        super().__init__(signum)
        self.signum = signum


class _NumericalProblem(Exception):
    """A detected numerical problem (the message names the step and the value)."""


def check_output_path(path: str | Path, *, overwrite: bool, what: str = "results file") -> Path:
    """Check that ``path`` can be created, before anything runs.

    Parameters
    ----------
    path : The file to write.
    overwrite : Whether an existing file may be replaced.
    what : What the file is, for messages ("results file", "figure").

    Raises
    ------
    RunInputError
        When the path is a directory, exists (without ``overwrite``), has a parent that is a file, or lies in
        a folder that cannot be created or written to; the message names the path and the cause.
    """
    path = Path(path)
    if path.is_dir():
        raise RunInputError(f"{path}: is a directory; expected the path of the {what}")
    if path.exists() and not overwrite:
        raise RunInputError(f"{path}: the {what} exists; pass --overwrite to replace it")
    ancestor = path.parent
    while not ancestor.exists():
        if ancestor == ancestor.parent:
            break
        ancestor = ancestor.parent
    if ancestor.exists() and not ancestor.is_dir():
        raise RunInputError(f"{path}: cannot create the {what}: {ancestor} is a file, not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise RunInputError(f"{path}: cannot create the {what}: the folder {ancestor} is not writable")
    return path


#: The suffixes of a results file (HDF5); its XDMF sidecar is the same path with ``.xdmf``.
RESULTS_SUFFIXES = (".h5", ".hdf5")


def check_results_path(path: str | Path, *, overwrite: bool, scene=None) -> Path:
    """Check the path of a run's results file before anything runs: :func:`check_output_path`, not one of
    ``scene``'s input files (when given), and an HDF5 suffix (another one would be overwritten by the
    ParaView sidecar written beside it with ``.xdmf``, or mistaken for another format).

    Raises
    ------
    RunInputError
        Naming the path and what is wrong with it.
    """
    path = check_output_path(path, overwrite=overwrite)
    if scene is not None:
        _check_not_an_input(path, scene)
    if path.suffix.lower() not in RESULTS_SUFFIXES:
        raise RunInputError(
            f"{path}: a results file is HDF5 and must end in {' or '.join(RESULTS_SUFFIXES)} (its ParaView "
            f"sidecar is written beside it with .xdmf)"
        )
    return path


def _check_not_an_input(output: Path, scene) -> None:
    """Refuse a results path that is one of the run's input files (the scene file, mesh.file, a trajectory
    file, boundary.file): with --overwrite it was replaced by the results.

    Raises
    ------
    RunInputError
        Naming the path and the input it is.
    """
    base = Path(scene.base_directory)
    files = [("mesh.file", scene.mesh.file), ("boundary.file", getattr(scene.boundary, "file", None))]
    files += [
        (f"trajectory.file of instrument {spec.name!r}", spec.trajectory.file)
        for spec in scene.instrument_specs
    ]
    inputs = [(what, base / name) for what, name in files if name is not None]  # relative to the scene file
    if scene.source != "<memory>":
        inputs.append(("the scene file", Path(scene.source)))
    target = output.resolve()
    for what, path in inputs:
        if path.resolve() == target:
            raise RunInputError(
                f"{output}: is {what} of this run ({path}); give another path for the results file"
            )


def check_record(state, record, *, size: float, rest_positions: np.ndarray) -> None:
    """Stop on a numerical problem visible in a step: non-finite or overflowing values, a diverging tissue, a
    solver that reports divergence or a non-finite residual.

    Raises
    ------
    _NumericalProblem
        Naming the step, the quantity and its value.
    """
    step = record.step
    checks = (
        ("needle positions [m]", record.needle_positions),
        ("needle frames", record.needle_frames),
        ("constraint forces [N]", record.row_forces),
        ("force on the needle [N]", record.needle_force),
        ("tissue positions [m]", state.tissue.positions),
        ("tissue velocities [m/s]", state.tissue.velocities),
        *(
            check
            for part in tuple(getattr(record, "instruments", ()))[1:]
            for check in (
                (f"{part.name}'s needle positions [m]", part.needle_positions),
                (f"force on {part.name}'s needle [N]", part.needle_force),
            )
        ),
    )
    for name, values in checks:
        values = np.asarray(values, dtype=float)
        if values.size == 0:
            continue
        finite = np.isfinite(values)
        if not np.all(finite):
            raise _NumericalProblem(
                f"step {step}: non-finite {name} ({int(np.count_nonzero(~finite))} values)"
            )
        largest = float(np.abs(values).max())
        if largest > OVERFLOW:
            raise _NumericalProblem(f"step {step}: overflowing {name}: |value| up to {largest:.3g}")
    moved = float(np.linalg.norm(np.asarray(state.tissue.positions) - rest_positions, axis=1).max())
    if moved > DIVERGENCE_FACTOR * size:
        raise _NumericalProblem(
            f"step {step}: the tissue diverges: a node moved {moved:.3g} m, more than {DIVERGENCE_FACTOR:g} "
            f"times "
            f"the tissue's size ({size:.3g} m); check the material (E, density) and dt"
        )
    report = record.solver
    if report is not None:
        if getattr(report, "diverged", False):
            raise _NumericalProblem(
                f"step {step}: the constraint solver diverged ({getattr(report, 'message', '')})"
            )
        residual = float(getattr(report, "residual", 0.0))
        if not np.isfinite(residual) and np.asarray(record.row_forces).size:
            raise _NumericalProblem(f"step {step}: the constraint solver's residual is {residual}")


def _numerical_message(error: BaseException, step: int) -> str | None:
    """A clear message for the numerical errors the libraries raise, or None when ``error`` is not one."""
    from refsim.simulation import SimulationError

    text = str(error)
    if isinstance(error, (_NumericalProblem, SimulationError)):
        return text
    if isinstance(error, RuntimeError) and "singular" in text.lower():
        return (
            f"step {step}: the system matrix is singular (the sparse factorisation said: {text}); the "
            "material or dt leave it without a usable inverse (e.g. a Young's modulus so large that the mass "
            "is lost in round-off)"
        )
    if isinstance(error, np.linalg.LinAlgError):
        return f"step {step}: linear algebra failed ({text})"
    if isinstance(error, (FloatingPointError, OverflowError, ZeroDivisionError)):
        return f"step {step}: arithmetic failed ({type(error).__name__}: {text})"
    return None


class _Signals:
    """SIGINT raises KeyboardInterrupt, SIGTERM and SIGHUP raise _Terminated in the main thread, for one run;
    the previous handlers come back afterwards. A SIGHUP that is ignored (``nohup refsim run``) stays ignored.
    In another thread (a Dask worker) nothing is installed."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled and threading.current_thread() is threading.main_thread()
        self.previous: dict = {}
        self.received: int | None = None  # the terminating signal, once one has arrived
        self._unraisable_hook = None

    def _unraisable(self, unraisable) -> None:
        """``sys.unraisablehook`` during the run: the signal's own exception, raised by its handler inside a
        weakref callback or a finaliser and dropped there, is not printed as an "ignored" traceback (the
        signal is recorded, and :meth:`check` raises it again in the run's loop); anything else goes to the
        previous hook."""
        own = isinstance(unraisable.exc_value, (_Terminated, KeyboardInterrupt)) and self.received is not None
        if not own:
            self._unraisable_hook(unraisable)

    def __enter__(self) -> _Signals:
        if self.enabled:
            self._unraisable_hook, sys.unraisablehook = sys.unraisablehook, self._unraisable
            self.previous[signal.SIGINT] = signal.signal(signal.SIGINT, self._interrupt)
            self.previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, self._terminate)
            if signal.getsignal(signal.SIGHUP) is not signal.SIG_IGN:  # `nohup refsim run`: keep running
                self.previous[signal.SIGHUP] = signal.signal(signal.SIGHUP, self._terminate)
        return self

    def _interrupt(self, signum, frame) -> None:
        if self.received is not None:  # the run is already stopping (see _terminate)
            return
        self.received = signum
        raise KeyboardInterrupt

    def _terminate(self, signum, frame) -> None:
        # A second signal (an impatient second Ctrl-C) is ignored once the run is stopping: raised while the
        # writer closes the file, it would abort the close and lose the buffered steps and the stop reason.
        if self.received is not None:
            return
        self.received = signum
        raise _Terminated(signum)

    def check(self) -> None:
        """Raise the terminating signal again if one arrived and its exception was swallowed: Python runs a
        signal handler between any two bytecodes, also inside a weakref callback or a finaliser, where an
        exception is printed as "ignored" and dropped (the run would then go on to its end)."""
        if self.received == signal.SIGINT:
            raise KeyboardInterrupt
        if self.received is not None:
            raise _Terminated(self.received)

    def __exit__(self, *exc) -> None:
        for number, handler in self.previous.items():
            signal.signal(number, handler)
        if self._unraisable_hook is not None:
            sys.unraisablehook, self._unraisable_hook = self._unraisable_hook, None


def run_scene(
    scene,
    output_path: str | Path,
    *,
    overwrite: bool = False,
    progress: Callable[[int, int, str], None] | None = None,
    on_step: Callable | None = None,
    steps: int | None = None,
    buffer_steps: int | None = None,
    handle_signals: bool = True,
):
    """Run a scene and write its results file; return the run's summary.

    Parameters
    ----------
    scene : A validated :class:`refsim.scene.Scene` (``refsim.scene.load_scene``).
    output_path : The results file (.h5) to create.
    overwrite : Replace an existing file (otherwise an existing file is bad input).
    progress : Called after each step as ``progress(done, total, phase)``.
    on_step : Called after each step as ``on_step(state, record)`` (after it was checked and buffered).
    steps : Steps to run (the scene's duration by default).
    buffer_steps : Steps per written block (`refsim.io.writer.DEFAULT_BUFFER_STEPS` by default).
    handle_signals : In the main thread, turn SIGTERM and SIGHUP into a clean stop (exit codes 143 and 129)
        for the run's duration and make SIGINT raise KeyboardInterrupt (130); the previous handlers are
        restored afterwards. The signal ends this run and is reported in the summary, not re-raised: a caller
        that runs several scenes in a loop must stop when ``summary.stopped_by_signal`` (the resolution
        study stops on any incomplete run).

    Returns
    -------
    RunSummary
        Events, forces, solver health and timing, plus ``status`` and ``exit_code`` (a key of
        :data:`~refsim.simulation.summary.RUN_STATUSES` and its code, the module's table), ``stop_reason`` (""
        when complete), ``complete`` and ``output``.
        The results file holds every completed step in every case.

    Raises
    ------
    RunInputError
        Bad input (the scene's models, the mesh, the output path, a file another run is writing), before any
        file is written.
    RunWriteError
        The results file cannot be created (a full disk); nothing is written.
    """
    from refsim.simulation import Simulation
    from refsim.simulation.summary import RunSummary

    output = check_results_path(output_path, overwrite=overwrite, scene=scene)
    try:
        simulation = Simulation(scene)  # every input error surfaces here, before any file is written
    except (ValueError, OSError) as error:
        raise RunInputError(str(error)) from None
    total = scene.time.step_count if steps is None else int(steps)
    summary = RunSummary(total_steps=total, output=str(output))
    writer = _open_writer(output, scene, simulation.models, overwrite=overwrite, buffer_steps=buffer_steps)
    step_done = StepSink(
        writer, summary, simulation.models.mesh.rest_positions, total, on_step=on_step, progress=progress
    )
    with _Signals(handle_signals) as signals:

        def step_checked(state, record) -> None:
            step_done(state, record)
            signals.check()

        status, reason = _run_steps(simulation, total, step_checked, summary, writer, signals=signals)
    if writer.failure is not None and status != "write_failed":
        status = "write_failed"
        reason = f"{reason}; {writer.failure}" if reason else writer.failure
    summary.tissue_linear_counts = simulation.tissue_compliance.linear_counts()
    summary.finish(status=status, stop_reason=reason, steps_written=writer.steps_completed)
    return summary


def _open_writer(output: Path, scene, models, *, overwrite: bool, buffer_steps: int | None):
    """The run's :class:`~refsim.io.writer.ResultWriter`, its folder created.

    Raises
    ------
    RunInputError
        Another run is writing the file (its lock is held: it is left alone), or the path cannot be created.
    RunWriteError
        A full disk: nothing written, an existing file untouched.
    """
    from refsim.io.filelock import WriterLockedError
    from refsim.io.writer import DEFAULT_BUFFER_STEPS, ResultWriter

    try:
        output.parent.mkdir(parents=True, exist_ok=True)
        return ResultWriter(
            output,
            scene,
            models,
            overwrite=overwrite,
            buffer_steps=DEFAULT_BUFFER_STEPS if buffer_steps is None else buffer_steps,
        )
    except WriterLockedError as error:  # another run is writing the file: it is left alone
        raise RunInputError(str(error)) from None
    except (FileExistsError, IsADirectoryError, NotADirectoryError, PermissionError, ValueError) as error:
        raise RunInputError(f"{output}: cannot create the results file: {error}") from None
    except OSError as error:  # a full disk: nothing written, an existing file untouched
        raise RunWriteError(error.errno, error.strerror or str(error)) from None


class StepSink:
    """What happens after each step of a run that writes a results file: the numerical checks, the buffered
    write (and the cut surface when it changed), the summary, then the caller's ``on_step`` and ``progress``.
    Used by :func:`run_scene` and by any other driver of the steps (``refsim interactive``)."""

    def __init__(self, writer, summary, rest_positions, total: int, *, on_step=None, progress=None) -> None:
        self.writer, self.summary, self.total = writer, summary, total
        self.on_step, self.progress = on_step, progress
        self.rest = np.asarray(rest_positions)
        self.size = float(np.linalg.norm(self.rest.max(axis=0) - self.rest.min(axis=0)))
        self.written_cut, self.recorded = None, None

    def __call__(self, state, record) -> None:
        check_record(state, record, size=self.size, rest_positions=self.rest)
        # The cut as far as the model has cut: the laid layers and the crack tip (recorded_surface), in the
        # file's surface and in the step's counts alike.
        strips = tuple(own.cut_strip for own in state.instruments if own.cut_strip is not None)
        changed = state.cut is not None and (
            self.written_cut is None
            or state.cut is not self.written_cut[0]
            or len(strips) != len(self.written_cut[1])
            or any(a is not b for a, b in zip(strips, self.written_cut[1], strict=False))
        )
        if changed:
            from refsim.cutting.strip import recorded_surface

            self.recorded = state.cut
            for strip in strips:  # to each cutting instrument's crack tip
                self.recorded = recorded_surface(self.recorded, strip, record.step)
        cut = self.recorded if state.cut is not None else None
        if cut is not None and cut is not state.cut:
            record = replace(record, cut_point_count=cut.point_count, cut_triangle_count=cut.triangle_count)
        self.writer.append(record)
        if changed:
            self.writer.write_cut_surface(
                cut.rest_points,
                cut.created_step,
                cut.triangles,
                cut.triangle_created_step,
                tet_indices=cut.tet_indices,
                barycentric=cut.barycentric,
            )
            self.written_cut = (state.cut, strips)
        self.summary.add(record)
        if self.on_step is not None:
            self.on_step(state, record)
        if self.progress is not None:
            parts = tuple(getattr(record, "instruments", ()))
            phase = ", ".join(f"{p.name} {p.phase}" for p in parts) if len(parts) > 1 else record.phase
            self.progress(record.step, self.total, phase)


_SIGNAL_STOPS = {
    signal.SIGINT: ("interrupted", "interrupted by SIGINT"),
    signal.SIGTERM: ("terminated", "interrupted by SIGTERM"),
    signal.SIGHUP: ("hangup", "interrupted by SIGHUP (the terminal closed)"),
}


def _signal_behind(error: BaseException, signals: _Signals | None) -> int | None:
    """The signal that stopped the run when ``error`` is its exception or was raised because of it, else None.

    A signal handler runs between any two bytecodes, also while compiled code calls back into the interpreter
    (a Numba dispatcher typing its arguments): its exception then surfaces as another one (``SystemError: ...
    returned a result with an exception set``) with the signal's exception as its context. The chain of causes
    and contexts is followed, and a signal recorded by the run's handlers counts as well."""
    seen: set[int] = set()
    link: BaseException | None = error
    while link is not None and id(link) not in seen:
        seen.add(id(link))
        if isinstance(link, KeyboardInterrupt):
            return signal.SIGINT
        if isinstance(link, _Terminated):
            return link.signum
        link = link.__cause__ or link.__context__
    return None if signals is None else signals.received


def _run_steps(simulation, total: int, step_done, summary, writer, *, signals=None) -> tuple[str, str]:
    """Run the steps and close the file whatever stops them; return (status, stop reason) (a key of
    RUN_STATUSES; the reason is "" when complete). ``signals`` (the run's :class:`_Signals`) tells a failure
    caused by a signal from any other."""
    status, reason = "complete", ""
    try:
        try:
            simulation.run(steps=total, on_step=step_done)
        except (KeyboardInterrupt, _Terminated) as stop:
            status, reason = _SIGNAL_STOPS[_signal_behind(stop, None)]
        except OSError as error:
            number = _signal_behind(error, signals)
            if number is not None:
                status, reason = _SIGNAL_STOPS[number]
            else:
                status = "write_failed"
                reason = writer.failure or f"writing the results failed: {error}"
        except Exception as error:  # noqa: BLE001 - every failure must close the file and say why
            number = _signal_behind(error, signals)
            if number is not None:
                status, reason = _SIGNAL_STOPS[number]
            else:
                step = summary.steps + 1
                status = "numerical"
                reason = _numerical_message(error, step)
                if reason is None:
                    logger.debug("run stopped by an unexpected error", exc_info=True)
                    reason = f"step {step}: stopped by an internal error ({type(error).__name__}: {error})"
    finally:
        # A signal after the first is ignored (_Signals), so nothing interrupts the close.
        writer.close(complete=status == "complete", reason=reason)
    return status, reason
