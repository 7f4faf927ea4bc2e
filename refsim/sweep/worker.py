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

__all__ = ["BLAS_ENVIRONMENT", "is_complete", "is_current", "run_key", "run_one", "run_scene"]

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


def _key(scene_json: str, version: str, commit: str) -> str:
    text = json.dumps({"scene": scene_json, "refsim_version": version, "git_commit": commit}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


@functools.lru_cache(maxsize=1)
def _code_version() -> tuple[str, str]:
    from refsim import __version__
    from refsim.io import git_commit

    return __version__, git_commit()


def run_key(scene) -> str:
    """The content key of a run: SHA-256 of what its results depend on and its results file records, the
    resolved scene (``refsim.scene.scene_to_json``: the scene file's content with the overrides applied) and
    the code that runs it (refsim version and git commit of this process).

    A study reuses a results file only when its key is this one (:func:`is_current`): an edited scene file,
    another ``--set`` or another refsim makes the run again, whatever the file's name.
    """
    from refsim.scene import scene_to_json

    return _key(scene_to_json(scene), *_code_version())


def file_key(path) -> str | None:
    """The content key of a complete results file from the attributes it records (scene, refsim_version,
    git_commit); None when the file is missing, unreadable or not complete."""
    import h5py

    if not is_complete(path):
        return None
    try:
        with h5py.File(path, "r") as handle:
            attributes = handle.attrs
            texts = [attributes.get(name, "") for name in ("scene", "refsim_version", "git_commit")]
    except OSError:
        return None
    texts = [t.decode() if isinstance(t, bytes) else str(t) for t in texts]
    return _key(*texts)


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
        if not is_current(output, run_key(scene_spec)):
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
