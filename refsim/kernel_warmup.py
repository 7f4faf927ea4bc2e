"""The main job's kernels compiled on a second core while its first run compiles them on the first.

A run compiles each numba kernel at its first call and caches it (:mod:`refsim.kernel_cache`), one kernel
after the other on one core: after a fresh install the first run of the main job (the cube) spends most of its
time compiling. ``kernels.json`` beside this module lists the kernels that run calls from Python, each with
the argument types of its call, in the order of their first calls (callees are compiled with their callers
and are not listed). While the kernel cache has not been filled from that list,
:func:`start_background_compilation` starts one process, ``python -m refsim.kernel_warmup``, that
compiles the list **from its end** into the same cache while the run compiles it from its start; where the
run reaches a kernel the other process has cached, numba loads it from the cache instead of compiling it
(numba looks the cache up before it compiles a new signature, and writes its index by an atomic rename). The
two meet about where half the compile time is spent. ``refsim run`` and ``refsim interactive`` start it. The
process stops with the run that started it (whatever it cached is kept), and once it has gone through the
whole list it leaves ``kernels-compiled`` in the cache folder, after which no run starts one.

The list only makes the first run faster: a kernel missing from it is compiled by the run as before, and an
entry that no longer resolves (a renamed kernel, changed argument types) is skipped. Regenerate it after
changing the main job's kernels (the slow test ``tests/package/test_kernel_warmup.py`` compares it with a
fresh recording)::

    NUMBA_CACHE_DIR=$(mktemp -d) python -m refsim.kernel_warmup --record cube

Switches: ``REFSIM_BACKGROUND_COMPILE=0`` starts no process (the test suite sets it: its workers already use
the cores); no process either on a single core, with ``NUMBA_DISABLE_JIT=1``, when the list is empty, or
when the cache folder cannot be written.
"""

from __future__ import annotations

import argparse
import atexit
import json
import os
import subprocess
import sys
import time
from pathlib import Path

__all__ = [
    "MANIFEST",
    "compile_entries",
    "load_manifest",
    "record_manifest",
    "resolve",
    "start_background_compilation",
]

#: The main job's kernels, in the order of their first calls.
MANIFEST = Path(__file__).resolve().with_name("kernels.json")
#: Left in the kernel cache folder once a background process has gone through the whole list.
DONE_MARKER = "kernels-compiled"
ENVIRONMENT_VARIABLE = "REFSIM_BACKGROUND_COMPILE"


def load_manifest(path: Path | None = None) -> list[dict]:
    """The entries of the kernel list (``{"module", "name", "signature", "seconds"}``); [] when the file is
    missing or unreadable (it only makes the first run faster)."""
    try:
        data = json.loads(Path(path or MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []
    kernels = data.get("kernels", []) if isinstance(data, dict) else []
    fields = {"module", "name", "signature"}
    return [entry for entry in kernels if isinstance(entry, dict) and fields <= entry.keys()]


def _type_namespace() -> dict:
    from numba.core import types

    return {name: getattr(types, name) for name in dir(types) if not name.startswith("_")}


def resolve(entry: dict, namespace: dict | None = None):
    """``(dispatcher, argument types)`` of a list entry, or None when its module, kernel or types no longer
    resolve."""
    import importlib

    from numba.core.registry import CPUDispatcher

    try:
        module = importlib.import_module(entry["module"])
        dispatcher = getattr(module, entry["name"])
        signature = eval(entry["signature"], {"__builtins__": {}}, namespace or _type_namespace())  # noqa: S307
    except Exception:  # noqa: BLE001 - a stale entry is skipped, whatever it fails with
        return None
    if not isinstance(dispatcher, CPUDispatcher) or not isinstance(signature, tuple):
        return None
    return dispatcher, signature


def compile_entries(entries: list[dict]) -> int:
    """Compile (or load from the cache) each entry, in the given order; returns how many resolved and
    compiled. An entry that fails is skipped."""
    namespace = _type_namespace()
    done = 0
    for entry in entries:
        resolved = resolve(entry, namespace)
        if resolved is None:
            continue
        dispatcher, signature = resolved
        try:
            dispatcher.compile(signature)
        except Exception:  # noqa: BLE001 - the run compiles it itself if it needs it
            continue
        done += 1
    return done


def _cache_folder() -> Path | None:
    """Where the kernels are cached (numba's setting, which :mod:`refsim.kernel_cache` sets on import)."""
    from numba import config

    import refsim.kernel_cache  # noqa: F401 - points numba's cache at refsim's folder

    folder = getattr(config, "CACHE_DIR", "") or ""
    return Path(folder) if folder else None


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


_started: subprocess.Popen | None = None


def start_background_compilation(manifest: Path | None = None) -> subprocess.Popen | None:
    """Start the process that compiles the kernel list from its end, unless it is not needed or wanted
    (module docstring); at most once per process. Returns the process, or None. The process is stopped when
    this one exits."""
    global _started
    if _started is not None:
        return None
    if os.environ.get(ENVIRONMENT_VARIABLE, "").strip() in ("0", "false", "no", "off"):
        return None
    if os.environ.get("NUMBA_DISABLE_JIT", "").strip() not in ("", "0") or _cores() < 2:
        return None
    if not load_manifest(manifest):
        return None
    folder = _cache_folder()
    if folder is None or (folder / DONE_MARKER).exists() or not os.access(folder, os.W_OK):
        return None  # no cache, already filled, or one this user cannot write (nothing would be kept)
    command = [sys.executable, "-m", "refsim.kernel_warmup"]
    if manifest is not None:
        command += ["--manifest", str(manifest)]
    environment = dict(os.environ)
    for variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        environment[variable] = "1"
    try:
        process = subprocess.Popen(
            command,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=environment,
        )
    except OSError:
        return None
    _started = process
    atexit.register(_stop, process)
    return process


def _stop(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:  # pragma: no cover - a compile ignoring SIGTERM
            process.kill()


def record_manifest(scene: str = "cube") -> list[dict]:
    """Run ``scene`` as ``refsim run`` does (``refsim.io.driver.run_scene``, its results into a temporary
    folder) in this process and return the kernels it compiled from Python (not those compiled as callees
    of another), in order, with their compile seconds. Meaningful with an empty kernel cache only
    (``NUMBA_CACHE_DIR=$(mktemp -d)``): a kernel loaded from the cache is not compiled, so not seen."""
    import tempfile

    from numba.core import event

    from refsim.io.driver import run_scene
    from refsim.scene import load_scene

    namespace = _type_namespace()
    entries: list[dict] = []
    depth = [0]

    class _Listener(event.Listener):
        def __init__(self) -> None:
            self.started: list[float] = []

        def on_start(self, ev) -> None:
            depth[0] += 1
            self.started.append(time.perf_counter())

        def on_end(self, ev) -> None:
            depth[0] -= 1
            began = self.started.pop()
            if depth[0] != 0:
                return
            dispatcher = ev.data["dispatcher"]
            function = dispatcher.py_func
            signature = repr(tuple(ev.data["args"]))
            entry = {
                "module": function.__module__,
                "name": function.__qualname__,
                "signature": signature,
                "seconds": round(time.perf_counter() - began, 2),
            }
            resolved = resolve(entry, namespace)
            if resolved is not None and resolved[0] is dispatcher and resolved[1] == tuple(ev.data["args"]):
                entries.append(entry)

    loaded = load_scene(scene)
    with tempfile.TemporaryDirectory() as folder, event.install_listener("numba:compile", _Listener()):
        summary = run_scene(loaded, Path(folder) / "run.h5")
    if not summary.complete:
        raise RuntimeError(f"the run of {scene} did not complete ({summary.stop_reason}): nothing recorded")
    return entries


def _main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m refsim.kernel_warmup", description=__doc__.split("\n", 1)[0]
    )
    parser.add_argument("--manifest", type=Path, default=None, help="the kernel list (default: kernels.json)")
    parser.add_argument("--record", metavar="SCENE", help="record the list from a run of SCENE and write it")
    args = parser.parse_args(argv)
    if args.record:
        entries = record_manifest(args.record)
        text = json.dumps({"scene": args.record, "kernels": entries}, indent=1) + "\n"
        (args.manifest or MANIFEST).write_text(text, encoding="utf-8")
        print(f"{len(entries)} kernels, {sum(e['seconds'] for e in entries):.1f} s of compilation recorded")
        return 0
    entries = load_manifest(args.manifest)
    compile_entries(entries[::-1])
    folder = _cache_folder()
    if folder is not None:
        try:
            (folder / DONE_MARKER).touch()
        except OSError:
            pass
    return 0


if __name__ == "__main__":
    sys.exit(_main())
