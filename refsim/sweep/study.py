"""Running a study on Dask and its HDF5 index (the study file).

The study file ``STUDY.h5`` indexes the runs, whose results files sit in the folder ``STUDY_runs/`` beside it
(one ``<run id>.h5`` each, the id a hash of the scene and the run's overrides). It is rewritten (atomically)
each time a run finishes, so an interrupted study keeps what it did; started again, it runs only the runs
whose results file is missing, not ``complete``, or stale: a file is reused only when its content key
(:func:`refsim.sweep.worker.run_key`: the resolved scene, the files it names, the refsim version and the
digest of the numerics source, :func:`refsim.sweep.worker.numerics_digest`) is the run's now, so an edited
scene file or mesh, another ``--set`` or changed numerics run it again, and a commit that changes only
documentation, tests or the study machinery reruns nothing. Layout (also in
``docs/studies.md``):

- path: root attributes; meaning: ``format`` = "refsim-study", ``schema_version``, ``name``, ``scene``,
  ``combine``, ``study`` (the study as JSON), ``created``, ``refsim_version``, ``git_commit``, ``run_folder``,
  ``runs_total``, ``runs_complete``, ``runs_failed``
- path: ``runs/id``, ``runs/label``, ``runs/file``; shape: (R,) str; meaning: run id, label, results file
  (relative to the study file)
- path: ``runs/status``, ``runs/error``; shape: (R,) str; meaning: complete, incomplete, failed, pending; the
  error message
- path: ``runs/ms_per_step``, ``runs/cpu_ms_per_step`` [ms], ``runs/seconds`` [s], ``runs/steps``; shape:
  (R,); meaning: mean wall time per step, process CPU time per step (NaN when reused), wall time of the run
  (NaN when reused), steps done
- path: ``runs/worker``; shape: (R,) str; meaning: host:pid of the worker that ran it
- path: ``runs/values/<key>``; shape: (R,); meaning: swept value (float, or JSON text for lists; NaN / "" for
  a case)
- path: ``runs/spacing/<key>``; shape: (R,) f8; meaning: refinement measure h of that value
- path: ``runs/quantities/<name>``; shape: (R,) f8; meaning: quantity of interest (unit attribute)
- path: ``runs/errors/<name>``; shape: (R,) f8; meaning: relative error against the reference run;
  ``force_history``: ‖F − F_ref‖/‖F_ref‖
- path: ``reference/``; meaning: attributes ``label``, ``id``, ``file``, ``status``; ``quantities/<name>``
  scalars
- path: ``convergence/<column>``; shape: (C,); meaning: one row per (key, quantity, group of fixed values):
  ``key``, ``quantity``, ``group``, ``kind``, ``order``, ``extrapolated``, ``gci``, ``uncertainty``,
  ``ratio_fine``, ``ratio_coarse``, ``h`` (C, 3), ``f`` (C, 3), ``fitted_order``, ``levels``, ``noise`` (the
  round-off floor δ below which a difference is not an observation)
"""

from __future__ import annotations

import datetime
import json
import logging
import math
import os
import shutil
import sys
import tempfile
import weakref
from pathlib import Path

import numpy as np

from refsim.sweep.convergence import convergence, fitted_order
from refsim.sweep.quantities import UNITS
from refsim.sweep.spec import RunSpec, StudySpec
from refsim.sweep.worker import BLAS_ENVIRONMENT, is_current, run_key, run_one

__all__ = [
    "LOOPBACK",
    "STUDY_FORMAT",
    "STUDY_SCHEMA_VERSION",
    "check_study_output",
    "read_study",
    "run_study",
    "run_folder",
    "start_client",
    "stop_client",
]

logger = logging.getLogger(__name__)

STUDY_FORMAT = "refsim-study"
STUDY_SCHEMA_VERSION = 1
#: The address a LocalCluster's scheduler, workers and dashboard listen on: this machine only.
LOOPBACK = "127.0.0.1"
#: Seconds to wait for a --scheduler to answer before the study gives up.
SCHEDULER_TIMEOUT = 10


def run_folder(output) -> Path:
    """Folder holding the runs' results files of the study file ``output``."""
    output = Path(output)
    return output.with_name(output.stem + "_runs")


def _pending(run: RunSpec) -> dict:
    return {
        "status": "pending",
        "error": "",
        "seconds": float("nan"),
        "worker": "",
        "steps": 0,
        "ms_per_step": float("nan"),
        "cpu_ms_per_step": float("nan"),
        "quantities": {},
    }


def _check_workers(workers) -> int:
    """The LocalCluster's worker count: an integer in [1, 4 × cores] (each worker runs one single-threaded
    run, so more workers than that only share the cores and the memory)."""
    cores = os.cpu_count() or 1
    if workers is None:
        return cores
    if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= 4 * cores:
        raise ValueError(
            f"--workers = {workers!r}: expected an integer in [1, {4 * cores}] (worker processes, each "
            f"running one single-threaded run; this machine has {cores} cores)"
        )
    return workers


def _ignore_sigpipe() -> None:
    """Ignore SIGPIPE at the C level, as Python does at start-up: a library may have reset it (gmsh's
    initialize does), and then a write to a socket a worker closed kills this process (exit 141) instead of
    raising BrokenPipeError. Only the main thread can set a handler."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)


def start_client(scheduler: str | None = None, workers: int | None = None):
    """A Dask client on ``scheduler``, or on a new LocalCluster of ``workers`` processes (the cores by
    default), one thread and one BLAS thread each. Returns (client, cluster); cluster is None for a scheduler.
    Close both with :func:`stop_client`.

    The LocalCluster listens on the loopback interface only (scheduler, workers and dashboard on
    ``127.0.0.1``), authenticates its processes with TLS certificates made for it (``security=True``: a Dask
    client of another user of the machine cannot submit tasks, which are pickled code; without the package
    ``cryptography`` it warns and runs without TLS), and keeps its scratch
    space in a private temporary folder (mode 0700, removed with the cluster). A ``scheduler`` is trusted
    completely: it and its workers run the study's code and read and write its files; give only the address
    of a scheduler you started (docs/studies.md, "Security").

    Raises
    ------
    ValueError
        When ``workers`` is out of range or ``scheduler`` cannot be reached within SCHEDULER_TIMEOUT seconds
        (naming the address).
    """
    from distributed import Client, LocalCluster

    if scheduler:
        _ignore_sigpipe()
        try:
            return Client(scheduler, timeout=SCHEDULER_TIMEOUT), None
        except (OSError, TimeoutError, ValueError, TypeError) as error:
            raise ValueError(
                f"--scheduler {scheduler}: cannot reach a Dask scheduler there within {SCHEDULER_TIMEOUT} s "
                f"({type(error).__name__}: {error}); start one (dask scheduler) and give its address, e.g. "
                "tcp://127.0.0.1:8786, or omit --scheduler for a local cluster"
            ) from None
    count = _check_workers(workers)
    _ignore_sigpipe()
    for name, value in BLAS_ENVIRONMENT.items():
        os.environ.setdefault(name, value)  # inherited by the worker processes
    scratch = tempfile.mkdtemp(prefix="refsim-dask-")  # mode 0700: this user only
    try:
        import cryptography  # noqa: F401 - Dask makes the cluster's TLS certificates with it

        tls = True
    except ImportError:
        tls = False
        logger.warning(
            "the Python package 'cryptography' is not installed: the LocalCluster listens on %s without TLS, "
            "so another user of this machine could submit tasks to it (pip install cryptography)",
            LOOPBACK,
        )
    try:
        cluster = LocalCluster(
            n_workers=count,
            threads_per_worker=1,
            processes=True,
            host=LOOPBACK,
            dashboard_address=f"{LOOPBACK}:0",
            security=tls,
            local_directory=scratch,
            env=dict(BLAS_ENVIRONMENT),
            silence_logs=logging.ERROR,
        )
    except BaseException:
        shutil.rmtree(scratch, ignore_errors=True)
        raise
    cluster.refsim_scratch = scratch
    weakref.finalize(cluster, shutil.rmtree, scratch, ignore_errors=True)  # also if a caller forgets
    return Client(cluster), cluster


def stop_client(client, cluster) -> None:
    """Close what :func:`start_client` opened: the client, the LocalCluster and its private scratch folder."""
    client.close()
    if cluster is not None:
        cluster.close()
        scratch = getattr(cluster, "refsim_scratch", None)
        if scratch:
            shutil.rmtree(scratch, ignore_errors=True)


def check_study_output(spec: StudySpec, output, *, overwrite: bool = False) -> Path:
    """Check the study file's path before anything runs.

    An existing study file of the same study (same name, and the same scene: the same path, or a scene file
    with the same bytes at another path, as in a checkout of the same commit elsewhere) is resumed: its
    complete runs are kept. (A run's file is named by the scene's path and its overrides,
    :class:`refsim.sweep.spec.RunSpec`, so the runs of a scene at another path are made again, into the same
    study file.)
    Any other existing file (another study's, a run's results file, anything) is replaced only with
    ``overwrite``.

    Raises
    ------
    ValueError
        Naming the path and what it holds.
    """
    output = Path(output)
    if output.is_dir():
        raise ValueError(f"{output}: is a directory; expected the path of the study file (.h5)")
    for what, name in (("the study's scene file", spec.scene), ("the study file (.toml)", spec.source)):
        if output.exists() and Path(name).is_file() and output.resolve() == Path(name).resolve():
            raise ValueError(f"{output}: is {what}; give another path for the study file (.h5)")
    if not output.exists() or overwrite:
        return output
    try:
        attributes = read_study(output)["attributes"]
    except (OSError, ValueError, KeyError) as error:
        raise ValueError(
            f"{output}: exists and is not a refsim study file ({error}); pass --overwrite to replace it"
        ) from None
    if attributes.get("name") != spec.name or not _same_scene(attributes, spec.scene):
        raise ValueError(
            f"{output}: holds another study (name {attributes.get('name')!r}, scene "
            f"{attributes.get('scene')!r}; this one: {spec.name!r}, {spec.scene!r}); pass --overwrite to "
            "replace it, or choose another -o"
        )
    return output


def _scene_digest(path) -> str:
    """SHA-256 of a scene file's bytes ("" when it cannot be read)."""
    import hashlib

    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return ""


def _same_scene(attributes: dict, scene: str) -> bool:
    """Whether a study file's scene is ``scene``: the same path, or the same bytes (the digest the file
    records, or, in a file from before it recorded one, the bytes of the file at its recorded path)."""
    if attributes.get("scene") == scene:
        return True
    mine = _scene_digest(scene)
    recorded = attributes.get("scene_sha256") or _scene_digest(attributes.get("scene", ""))
    return bool(mine) and recorded == mine


def _run_keys(spec: StudySpec, runs) -> dict:
    """{run id: content key (:func:`refsim.sweep.worker.run_key`)}; None for a run whose scene does not load
    (it is run, and its row says why it failed)."""
    from refsim.scene import load_scene

    keys = {}
    for run in runs:
        try:
            keys[run.id] = run_key(load_scene(spec.scene, list(run.overrides)))
        except (ValueError, OSError):
            keys[run.id] = None
    return keys


def _check_shared_scene(spec: StudySpec, keys: dict) -> None:
    """Refuse a study whose scene, with the overrides every run shares, does not load while none of its runs
    does either (a scene that does not exist, a shared override that is refused): bad input, before anything
    is written or started. A study whose runs fail on their own values runs (the others); their rows say why.

    Raises
    ------
    ValueError
        Naming the study's source and the scene's load error.
    """
    from refsim.scene import load_scene

    if not keys or any(key is not None for key in keys.values()):
        return
    try:
        load_scene(spec.scene, list(spec.overrides))
    except (ValueError, OSError) as error:
        raise ValueError(
            f"{spec.source}: the scene of study {spec.name!r} does not load (no run can): {error}"
        ) from None


def run_study(
    spec: StudySpec,
    output,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool = True,
    client=None,
    warm_up: bool = True,
    overwrite: bool = False,
) -> dict:
    """Run every missing run of a study on Dask and write the study file.

    Parameters
    ----------
    spec : The study.
    output : The study file (.h5); the runs go to :func:`run_folder` (output).
    scheduler : Address of a running Dask scheduler (``tcp://host:8786``); a LocalCluster when None.
    workers : Worker processes of the LocalCluster (one thread and one BLAS thread each); the cores by
    default.
    progress : Show a progress bar (tqdm, on stderr).
    client : An existing ``distributed.Client`` to use (and leave open), e.g. one for several studies;
        ``scheduler`` and ``workers`` are then ignored.
    warm_up : Each worker first runs a small cutting scene untimed, so that compiling the kernels does not
        count in the first run's time per step (about 5 s per worker).
    overwrite : Replace an existing file that is not this study's (:func:`check_study_output`).

    Returns
    -------
    The study as read back by :func:`read_study`.

    Raises
    ------
    ValueError
        An existing output that is not this study's (without ``overwrite``), ``workers`` out of range, an
        unreachable ``scheduler``, a scene that does not load with the shared overrides (and no run's does);
        before anything runs.
    """
    output = check_study_output(spec, Path(output).resolve(), overwrite=overwrite)
    if client is None and not scheduler:
        _check_workers(workers)
    runs = spec.runs()
    reference = spec.reference_run()
    every = runs + ([reference] if reference is not None and reference.id not in {r.id for r in runs} else [])
    keys = _run_keys(spec, every)
    _check_shared_scene(spec, keys)
    folder = run_folder(output)
    folder.mkdir(parents=True, exist_ok=True)
    rows = {run.id: _pending(run) for run in every}
    missing = [run for run in every if not is_current(folder / run.file_name, keys[run.id])]
    done = [run for run in every if run not in missing]
    previous = _previous_timing(output)
    # reused: quantities read here, nothing is run again; timings kept from the last study file
    for run in done:
        rows[run.id] = run_one(spec.scene, run.overrides, str(folder / run.file_name), spec.quantities)
        rows[run.id].update(previous.get(run.id, {}))
    _write(spec, output, runs, reference, rows)
    if missing:
        _run_missing(
            spec,
            output,
            runs,
            reference,
            missing,
            rows,
            client=client,
            scheduler=scheduler,
            workers=workers,
            progress=progress,
            warm_up=warm_up,
        )
    _write(spec, output, runs, reference, rows, final=True)
    return read_study(output)


def _run_missing(
    spec, output, runs, reference, missing, rows, *, client, scheduler, workers, progress, warm_up
) -> None:
    """Run ``missing`` on Dask (``client``, or a cluster started here and stopped after), filling ``rows`` and
    rewriting the study file as each run finishes; a worker that dies makes its run's row "failed"."""
    from tqdm import tqdm

    folder, total = run_folder(output), len(rows)

    own = client is None
    if own:
        client, cluster = start_client(scheduler, workers)
    bar = tqdm(
        total=total,
        initial=total - len(missing),
        desc=f"study {spec.name}",
        unit="run",
        disable=not progress,
        file=sys.stderr,
    )
    try:
        from distributed import as_completed

        futures = {
            client.submit(
                run_one,
                spec.scene,
                run.overrides,
                str(folder / run.file_name),
                spec.quantities,
                warm_up,
                key=f"run-{spec.name}-{run.id}",
                pure=False,
            ): run
            for run in missing
        }
        for future in as_completed(futures):
            run = futures[future]
            try:
                rows[run.id] = future.result()
            except Exception as error:  # the worker died (killed, out of memory)
                rows[run.id] = {
                    **_pending(run),
                    "status": "failed",
                    "error": f"{type(error).__name__}: {error}",
                }
            bar.update(1)
            if rows[run.id]["status"] != "complete":
                bar.write(f"run {run.id} ({run.label}): {rows[run.id]['status']} {rows[run.id]['error']}")
            _write(spec, output, runs, reference, rows)
    finally:
        bar.close()
        if own:
            stop_client(client, cluster)


# ---------------------------------------------------------------------- the study file


def _previous_timing(output: Path) -> dict:
    """{run id: {seconds, cpu_ms_per_step, worker}} from an existing study file (runs reused keep them)."""
    if not output.is_file():
        return {}
    try:
        runs = read_study(output)["runs"]
    except (OSError, ValueError, KeyError):
        return {}
    keep = {}
    for index, run_id in enumerate(runs.get("id", [])):
        keep[run_id] = {
            name: runs[name][index] for name in ("seconds", "cpu_ms_per_step", "worker") if name in runs
        }
    return keep


def _errors(spec, folder, runs, reference, rows) -> dict:
    if reference is None or rows[reference.id]["status"] != "complete":
        return {}
    from refsim.io import read_results
    from refsim.sweep.quantities import force_history_error

    reference_values = rows[reference.id]["quantities"]
    errors = {name: np.full(len(runs), np.nan) for name in (*spec.quantities, "force_history")}
    reference_results = read_results(folder / reference.file_name)
    for index, run in enumerate(runs):
        if rows[run.id]["status"] != "complete":
            continue
        for name in spec.quantities:
            value, exact = rows[run.id]["quantities"].get(name, np.nan), reference_values.get(name, np.nan)
            if np.isfinite(value) and np.isfinite(exact) and exact != 0.0:
                errors[name][index] = abs(value - exact) / abs(exact)
        errors["force_history"][index] = force_history_error(
            read_results(folder / run.file_name), reference_results
        )
    return errors


def convergence_rows(spec: StudySpec, runs, rows) -> list[dict]:
    """Convergence of every quantity along every swept key with a refinement measure (three finest levels),
    within each group of runs sharing the values of the other keys."""
    table = []
    swept = [run for run in runs if run.values]
    for sweep in spec.sweeps:
        if sweep.measure == "none":
            continue
        others = [s.key for s in spec.sweeps if s.key != sweep.key] if spec.combine == "product" else []
        groups: dict = {}
        for run in swept:
            group = json.dumps({key: run.values[key] for key in others}, sort_keys=True)
            groups.setdefault(group, []).append(run)
        for group, members in groups.items():
            members = [m for m in members if rows[m.id]["status"] == "complete"]
            h = np.array([sweep.spacing(m.values[sweep.key]) for m in members])
            if np.count_nonzero(np.isfinite(h)) < 3 or np.unique(h).size < 3:
                continue
            for name in spec.quantities:
                f = np.array([rows[m.id]["quantities"].get(name, np.nan) for m in members])
                keep = np.isfinite(h) & np.isfinite(f)
                if np.count_nonzero(keep) < 3 or np.unique(h[keep]).size < 3:
                    continue
                result = convergence(h[keep], f[keep])
                slope = (
                    fitted_order(h[keep], f[keep], result.extrapolated)[0]
                    if math.isfinite(result.extrapolated) and result.kind == "monotone"
                    else float("nan")
                )
                table.append(
                    {
                        "key": sweep.key,
                        "quantity": name,
                        "group": group,
                        "fitted_order": slope,
                        "levels": int(np.count_nonzero(keep)),
                        **result.as_dict(),
                    }
                )
    return table


def _strings(handle, path, values) -> None:
    import h5py

    handle.create_dataset(
        path, data=np.array([str(v) for v in values], dtype=object), dtype=h5py.string_dtype()
    )


def _write(spec, output: Path, runs, reference, rows, *, final: bool = False) -> None:
    import h5py

    from refsim import __version__
    from refsim.io import git_commit

    folder = run_folder(output)
    temporary = output.with_name(output.name + ".tmp")
    created = None
    if output.exists():
        try:
            with h5py.File(output, "r") as old:
                created = old.attrs.get("created")
        except OSError:
            created = None
    now = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    statuses = [rows[run.id]["status"] for run in runs]
    with h5py.File(temporary, "w") as handle:
        attributes = handle.attrs
        attributes.update(
            {
                "format": STUDY_FORMAT,
                "schema_version": STUDY_SCHEMA_VERSION,
                "name": spec.name,
                "scene": spec.scene,
                "scene_sha256": _scene_digest(spec.scene),
                "combine": spec.combine,
                "study": spec.to_json(),
                "created": created or now,
                "updated": now,
                "refsim_version": __version__,
                "git_commit": git_commit(),
                "run_folder": folder.name,
                "runs_total": len(runs),
                "runs_complete": statuses.count("complete"),
                "runs_failed": statuses.count("failed"),
                "final": bool(final),
            }
        )
        _write_runs(handle.create_group("runs"), spec, folder, runs, rows, statuses)
        if final:
            for name, values in _errors(spec, folder, runs, reference, rows).items():
                handle.create_dataset(f"runs/errors/{name}", data=values).attrs["units"] = "1"
        if reference is not None:
            _write_reference(handle.create_group("reference"), spec, folder, reference, rows)
        table = convergence_rows(spec, runs, rows)
        if table:
            _write_convergence(handle.create_group("convergence"), table)
    os.replace(temporary, output)


def _write_runs(group, spec, folder: Path, runs, rows, statuses) -> None:
    """The study file's ``runs`` group: one entry per run (ids, labels, files, status, timings, swept values
    with their spacing, quantities)."""
    _strings(group, "id", [run.id for run in runs])
    _strings(group, "label", [run.label for run in runs])
    _strings(group, "file", [f"{folder.name}/{run.file_name}" for run in runs])
    _strings(group, "overrides", ["\n".join(run.overrides) for run in runs])
    _strings(group, "status", statuses)
    _strings(group, "error", [rows[run.id]["error"] for run in runs])
    _strings(group, "worker", [rows[run.id]["worker"] for run in runs])
    for name, unit in (("ms_per_step", "ms"), ("cpu_ms_per_step", "ms"), ("seconds", "s")):
        group.create_dataset(
            name, data=np.array([rows[run.id].get(name, np.nan) for run in runs], dtype=float)
        )
        group[name].attrs["units"] = unit
    group.create_dataset("steps", data=np.array([rows[run.id]["steps"] for run in runs], dtype=np.int64))
    for sweep in spec.sweeps:
        values = [run.values.get(sweep.key) for run in runs]
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) or v is None for v in values):
            group.create_dataset(
                f"values/{sweep.key}",
                data=np.array([np.nan if v is None else v for v in values], dtype=float),
            )
        else:
            _strings(group, f"values/{sweep.key}", ["" if v is None else json.dumps(v) for v in values])
        group.create_dataset(
            f"spacing/{sweep.key}",
            data=np.array([np.nan if v is None else sweep.spacing(v) for v in values], dtype=float),
        )
        group[f"spacing/{sweep.key}"].attrs["measure"] = sweep.measure
    for name in spec.quantities:
        dataset = group.create_dataset(
            f"quantities/{name}",
            data=np.array([rows[run.id]["quantities"].get(name, np.nan) for run in runs], dtype=float),
        )
        dataset.attrs["units"] = UNITS.get(name.partition("@")[0], "")


def _write_reference(group, spec, folder: Path, reference, rows) -> None:
    """The study file's ``reference`` group: the reference run's status, timing and quantities."""
    row = rows[reference.id]
    group.attrs.update(
        {
            "label": reference.label,
            "id": reference.id,
            "file": f"{folder.name}/{reference.file_name}",
            "status": row["status"],
            "error": row["error"],
            "ms_per_step": row["ms_per_step"],
            "cpu_ms_per_step": row.get("cpu_ms_per_step", np.nan),
        }
    )
    for name in spec.quantities:
        group.create_dataset(f"quantities/{name}", data=row["quantities"].get(name, np.nan))


#: Float columns of the study file's ``convergence`` group (fields of
#: :class:`refsim.sweep.convergence.ConvergenceResult`, and the fitted order).
_CONVERGENCE_COLUMNS = (
    "order",
    "extrapolated",
    "gci",
    "uncertainty",
    "ratio_fine",
    "ratio_coarse",
    "fitted_order",
    "noise",
)


def _write_convergence(group, table: list) -> None:
    """The study file's ``convergence`` group: one row per (key, quantity, group of fixed values)."""
    for column in ("key", "quantity", "group", "kind"):
        _strings(group, column, [row[column] for row in table])
    for column in _CONVERGENCE_COLUMNS:
        group.create_dataset(column, data=np.array([row[column] for row in table], dtype=float))
    group.create_dataset("levels", data=np.array([row["levels"] for row in table], dtype=np.int64))
    group.create_dataset("h", data=np.array([row["spacings"] for row in table], dtype=float))
    group.create_dataset("f", data=np.array([row["values"] for row in table], dtype=float))


def read_study(path) -> dict:
    """A study file as plain data: ``attributes``, ``runs`` (a dict of columns, with ``values``, ``spacing``,
    ``quantities`` and ``errors`` as dicts of columns), ``reference`` and ``convergence`` (a list of rows).

    Raises
    ------
    ValueError
        When the file is not a refsim study file.
    """
    import h5py

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such study file")

    def plain(value):
        if isinstance(value, bytes):
            return value.decode()
        if isinstance(value, np.ndarray) and value.dtype.kind == "O":
            return [v.decode() if isinstance(v, bytes) else v for v in value.tolist()]
        if isinstance(value, np.generic):
            return value.item()
        return value

    with h5py.File(path, "r") as handle:
        if plain(handle.attrs.get("format")) != STUDY_FORMAT:
            raise ValueError(
                f"{path}: not a refsim study file (root attribute 'format' is "
                f"{plain(handle.attrs.get('format'))!r}, expected {STUDY_FORMAT!r})"
            )
        attributes = {key: plain(value) for key, value in handle.attrs.items()}
        runs: dict = {}
        for name, item in handle["runs"].items():
            if isinstance(item, h5py.Group):
                runs[name] = {key: plain(item[key][()]) for key in item}
            else:
                runs[name] = plain(item[()])
        reference = None
        if "reference" in handle:
            reference = {key: plain(value) for key, value in handle["reference"].attrs.items()}
            reference["quantities"] = {k: float(v[()]) for k, v in handle["reference/quantities"].items()}
        table = []
        if "convergence" in handle:
            columns = {key: plain(handle["convergence"][key][()]) for key in handle["convergence"]}
            count = len(columns["key"])
            table = [
                {
                    key: (value[i].tolist() if isinstance(value, np.ndarray) else value[i])
                    for key, value in columns.items()
                }
                for i in range(count)
            ]
    return {
        "attributes": attributes,
        "runs": runs,
        "reference": reference,
        "convergence": table,
        "path": path,
    }
