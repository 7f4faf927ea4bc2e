"""One run of a study, as executed on a Dask worker: scene → results file (+ XDMF sidecar) → quantities.

:func:`run_scene` calls the one run driver (:func:`refsim.io.driver.run_scene`) and adds the XDMF sidecar.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import socket
import time
import traceback
from pathlib import Path

import numpy as np

__all__ = [
    "BLAS_ENVIRONMENT",
    "NUMERICS_EXCLUDED",
    "file_key",
    "is_complete",
    "is_current",
    "numerics_digest",
    "numerics_files",
    "run_key",
    "run_one",
    "run_scene",
]

# : Environment that gives each worker one BLAS / OpenMP thread (workers = cores, so threads would
# oversubscribe).
BLAS_ENVIRONMENT = {
    "OPENBLAS_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "NUMBA_NUM_THREADS": "1",
}


def run_scene(scene, output, *, overwrite: bool = False, on_step=None):
    """Run ``scene`` through the one run driver (:func:`refsim.io.driver.run_scene`: results file with the cut
    surface, summary) and write the XDMF sidecar beside the file.

    Parameters
    ----------
    scene : A validated :class:`refsim.scene.Scene`.
    output : The results file (.h5).
    overwrite : Replace an existing file.
    on_step : Called after each step as ``on_step(state, record)``.

    Returns
    -------
    The driver's RunSummary (``status``, ``stop_reason``, ``complete``): a run stopped by a numerical problem
    keeps its completed steps with ``complete = False``.

    Raises
    ------
    refsim.io.driver.RunInputError
        Bad input (scene, models, output path), before any file is written.
    """
    from refsim.io.driver import run_scene as drive
    from refsim.io.xdmf import write_xdmf

    summary = drive(scene, output, overwrite=overwrite, handle_signals=False, on_step=on_step)
    write_xdmf(output)
    return summary


def is_complete(path) -> bool:
    """True when ``path`` is a results file whose run finished (root attribute ``complete``)."""
    import h5py

    path = Path(path)
    if not path.is_file():
        return False
    try:
        with h5py.File(path, "r") as handle:
            return bool(handle.attrs.get("complete", False))
    except OSError:
        return False


#: What the numerics digest (:func:`numerics_digest`) leaves out, relative to the refsim package: the code
#: that does not compute a run's numbers. The command line and the entry point (cli.py, __main__.py), the
#: figures and pages (viz/), the interactive viewer (interactive/), the study machinery that schedules runs
#: and reads their quantities afterwards (sweep/), the reference set that reads them (reference/), the
#: verification problems (verification/: checks of the model, not called by a run), and the readers and
#: exporters of a finished results file (io/reader.py, io/export.py, io/xdmf.py). Everything else under
#: refsim/ is numerics (the scene loader, meshes, elements, constraints, cutting, solvers, the simulation
#: loop, the run driver and the results writer, and the package data a scene names: built-in scenes,
#: meshes, trajectories): a file added anywhere else counts, so a new module errs towards running again,
#: never towards a stale reuse.
NUMERICS_EXCLUDED = (
    "cli.py",
    "__main__.py",
    "viz",
    "interactive",
    "sweep",
    "reference",
    "verification",
    "io/reader.py",
    "io/export.py",
    "io/xdmf.py",
)
#: Suffixes of the files the numerics digest reads (source and the package data a run reads).
NUMERICS_SUFFIXES = (".py", ".toml", ".csv", ".vtu", ".msh")


def _excluded(relative: str) -> bool:
    return any(relative == name or relative.startswith(name + "/") for name in NUMERICS_EXCLUDED)


def numerics_files(package=None) -> list[Path]:
    """The files of the refsim package whose content the numbers of a run depend on (sorted): every file with
    a suffix of :data:`NUMERICS_SUFFIXES` under ``package`` (the installed refsim package's folder by
    default) but those :data:`NUMERICS_EXCLUDED` names, and no ``__pycache__``."""
    root = Path(__file__).resolve().parents[1] if package is None else Path(package)
    files = []
    for path in sorted(root.rglob("*")):
        relative = path.relative_to(root).as_posix()
        if (
            path.is_file()
            and path.suffix in NUMERICS_SUFFIXES
            and "__pycache__" not in path.parts
            and not _excluded(relative)
        ):
            files.append(path)
    return files


def numerics_digest(package=None) -> str:
    """SHA-256 over the relative names and contents of :func:`numerics_files` of ``package`` (the installed
    refsim by default): the code and data that compute a run's numbers. A change to the documentation, the
    tests, the studies, the command line, the figures or the study machinery leaves it unchanged; a change to
    any numerics file changes it."""
    root = Path(__file__).resolve().parents[1] if package is None else Path(package)
    digest = hashlib.sha256()
    for path in numerics_files(root):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0")
        digest.update(hashlib.sha256(path.read_bytes()).digest())
    return digest.hexdigest()


@functools.lru_cache(maxsize=1)
def _code_version() -> tuple[str, str]:
    from refsim import __version__

    return __version__, numerics_digest()


#: Scene sections whose ``file`` key names a file the run reads (relative to the scene file's folder).
SCENE_FILE_SECTIONS = ("mesh", "trajectory", "boundary")


def _named_files(scene) -> dict:
    """{section: SHA-256 of the file the scene's section names} for the files a run reads (a mesh, a
    trajectory, a boundary motion); "missing" for one that is not there (the run then fails on its own)."""
    data = scene.to_dict()
    folder = Path(scene.source).parent if scene.source else Path.cwd()
    digests = {}
    for section in SCENE_FILE_SECTIONS:
        name = (data.get(section) or {}).get("file")
        if not name:
            continue
        path = Path(name) if Path(name).is_absolute() else folder / name
        digests[section] = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else "missing"
    return digests


def run_key(scene) -> str:
    """The content key of a run: SHA-256 of what its numbers depend on, the resolved scene (its content with
    the overrides applied, ``Scene.to_dict``; not the path of the scene file), the content of the files it
    names (mesh, trajectory, boundary motion), the refsim version and the numerics digest of the code that
    runs it (:func:`numerics_digest`). Not the git commit: a commit that changes only documentation, tests or
    the study machinery reuses every run (the commit stays in the results file as provenance).

    A study reuses a results file only when the key it records (root attribute ``run_key``, written by
    :func:`run_one` once the run is complete) is this one (:func:`is_current`): an edited scene file or mesh,
    another ``--set`` or a change to the numerics makes the run again, whatever the file's name.
    """
    from refsim.scene import scene_to_json

    scene_json = json.loads(scene_to_json(scene))
    scene_json.pop("source", None)
    version, numerics = _code_version()
    text = json.dumps(
        {"scene": scene_json, "files": _named_files(scene), "refsim_version": version, "numerics": numerics},
        sort_keys=True,
    )
    return hashlib.sha256(text.encode()).hexdigest()


def file_key(path) -> str | None:
    """The content key a complete results file records (root attribute ``run_key``, :func:`run_key` of the
    run that wrote it); None when the file is missing, unreadable, not complete or has no key (a file written
    outside a study)."""
    import h5py

    if not is_complete(path):
        return None
    try:
        with h5py.File(path, "r") as handle:
            key = handle.attrs.get("run_key")
    except OSError:
        return None
    if key is None:
        return None
    return key.decode() if isinstance(key, bytes) else str(key)


def _stamp(path, key: str) -> None:
    """Record a complete run's content key and numerics digest in its results file (root attributes
    ``run_key``, ``numerics_digest``)."""
    import h5py

    with h5py.File(path, "a") as handle:
        handle.attrs["run_key"] = key
        handle.attrs["numerics_digest"] = _code_version()[1]


def is_current(path, key: str | None) -> bool:
    """True when ``path`` is a complete results file of the run whose content key is ``key``
    (:func:`run_key`); False for a missing, incomplete or stale file, and when ``key`` is None."""
    return key is not None and file_key(path) == key


def _ms_per_step(results) -> float:
    if results.step_count == 0:
        return float("nan")
    total = sum(np.asarray(seconds, dtype=float) for seconds in results.stage_seconds.values())
    return float(1e3 * np.nanmean(total))


def describe(path, quantities) -> dict:
    """Quantities, ms per step and step count of a results file."""
    from refsim.io import read_results
    from refsim.sweep.quantities import quantity

    results = read_results(path)
    row = {"steps": results.step_count, "ms_per_step": _ms_per_step(results), "quantities": {}}
    for name in quantities:
        try:
            row["quantities"][name] = quantity(results, name)
        except (ValueError, LookupError):
            row["quantities"][name] = float("nan")
    row["complete"] = results.complete
    return row


_WARMED_UP = False


def _warm_up() -> None:
    """Compile the numba kernels and load the lazy modules of this process once, on a small cutting run
    (cube_cut on 4³ cells, about 5 s), so that the first timed run of a worker does not pay for them."""
    global _WARMED_UP
    if _WARMED_UP:
        return
    import tempfile

    from refsim.scene import load_scene

    with tempfile.TemporaryDirectory() as folder:
        scene = load_scene("cube_cut", ["mesh.cells=[4, 4, 4]", "output.tissue_every=1000"])
        run_scene(scene, Path(folder) / "warm_up.h5", overwrite=True)
    _WARMED_UP = True


def run_one(scene: str, overrides: tuple, output: str, quantities: tuple, warm_up: bool = False) -> dict:
    """Run one study point on this process (a Dask task) unless its results file is complete and current
    (:func:`is_current`: the same resolved scene and code).

    Parameters
    ----------
    scene : Built-in scene name or scene file path (absolute on a cluster).
    overrides : ``section.key=value`` strings.
    output : Results file path (on the shared filesystem for a cluster).
    quantities : Names of the quantities of interest (refsim.sweep.quantities).
    warm_up : Before the first run of this process, run a small cutting scene untimed (compiles the kernels).

    Returns
    -------
    dict with status ("complete", "failed"), error (message, "" when none), seconds (wall time, NaN when the
    file was reused), worker (host and pid), steps, ms_per_step (mean wall time of a step, from the file),
    cpu_ms_per_step (process CPU time per step between the first and the last step; NaN when reused) and
    quantities {name: value}. Never raises for a
    failing run: the failure is the row's status.
    """
    from threadpoolctl import threadpool_limits

    for name, value in BLAS_ENVIRONMENT.items():
        os.environ.setdefault(name, value)
    row = {
        "status": "failed",
        "error": "",
        "seconds": float("nan"),
        "worker": f"{socket.gethostname()}:{os.getpid()}",
        "steps": 0,
        "ms_per_step": float("nan"),
        "cpu_ms_per_step": float("nan"),
        "quantities": {name: float("nan") for name in quantities},
    }
    output = Path(output)
    try:
        from refsim.scene import load_scene

        scene_spec = load_scene(scene, list(overrides))
        key = run_key(scene_spec)
        if not is_current(output, key):
            if warm_up:
                _warm_up()
            start = time.perf_counter()
            cpu = []  # process CPU time at each step: robust to other processes sharing the cores

            def on_step(state, record) -> None:
                cpu.append(time.process_time())

            with threadpool_limits(limits=1):
                summary = run_scene(scene_spec, output, overwrite=True, on_step=on_step)
            row["seconds"] = time.perf_counter() - start
            if len(cpu) > 1:
                row["cpu_ms_per_step"] = 1e3 * (cpu[-1] - cpu[0]) / (len(cpu) - 1)
            if not summary.complete:
                row["error"] = f"{summary.status}: {summary.stop_reason}"
            else:
                _stamp(output, key)
        row.update(describe(output, quantities))
        complete = row.pop("complete")
        row["status"] = "complete" if complete else ("failed" if row["error"] else "incomplete")
    except Exception as error:  # a failing run is a result of the study, not a crash of it
        row["error"] = f"{type(error).__name__}: {error}"
        row["traceback"] = traceback.format_exc(limit=5)
        if output.is_file():
            try:
                row.update(describe(output, quantities))
                row.pop("complete", None)
            except Exception:  # noqa: BLE001 - a damaged partial file: keep the error of the run
                pass
    return row
