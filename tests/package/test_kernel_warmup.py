"""The main job's kernels compiled on a second core (refsim.kernel_warmup).

What the mechanism relies on: the kernel list names kernels that still exist with argument types that still
parse (a stale entry only costs speed, and is skipped), the background process compiles its list into the
kernel cache and marks the cache done, after which no run starts another, and the list is what the main job's
run compiles from Python (slow: a recording with an empty cache, compared as a set).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from refsim import kernel_warmup
from refsim.kernel_warmup import DONE_MARKER, compile_entries, load_manifest, resolve

_ALL_FINITE = {
    "module": "refsim.solvers.array_checks",
    "name": "all_finite",
    "signature": "(Array(float64, 1, 'C', False, aligned=True),)",
}


def test_every_listed_kernel_resolves_to_a_kernel_and_its_argument_types():
    entries = load_manifest()
    assert entries, f"{kernel_warmup.MANIFEST}: no kernel listed"
    assert json.loads(kernel_warmup.MANIFEST.read_text())["scene"] == "cube"  # the main job's scene
    for entry in entries:
        resolved = resolve(entry)
        assert resolved is not None, f"stale entry {entry['module']}.{entry['name']} {entry['signature']}"
        dispatcher, signature = resolved
        assert dispatcher.py_func.__module__ == entry["module"] and len(signature) >= 1
    keys = [(entry["module"], entry["name"], entry["signature"]) for entry in entries]
    assert len(set(keys)) == len(keys)


def test_a_stale_entry_is_skipped_and_the_others_compile():
    stale = [
        {**_ALL_FINITE, "module": "refsim.no_such_module"},
        {**_ALL_FINITE, "name": "no_such_kernel"},
        {**_ALL_FINITE, "signature": "(NoSuchType(1),)"},
        {**_ALL_FINITE, "signature": "(float64,)"},  # resolves, fails to type
    ]
    assert all(resolve(entry) is None for entry in stale[:3])
    assert compile_entries([*stale, _ALL_FINITE]) == 1


def test_the_background_process_fills_the_cache_and_marks_it_done(tmp_path):
    manifest = tmp_path / "kernels.json"
    manifest.write_text(json.dumps({"scene": "test", "kernels": [_ALL_FINITE]}))
    cache = tmp_path / "cache"
    environment = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    done = subprocess.run(
        [sys.executable, "-m", "refsim.kernel_warmup", "--manifest", str(manifest)],
        env=environment,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    assert (cache / DONE_MARKER).is_file()
    assert [path.name for path in cache.rglob("*.nbi") if "all_finite" in path.name]


def test_no_process_when_the_cache_is_marked_done_or_the_switch_is_off(tmp_path, monkeypatch):
    monkeypatch.setattr(kernel_warmup, "_started", None)
    monkeypatch.setattr(kernel_warmup, "_cache_folder", lambda: tmp_path)
    monkeypatch.setattr(kernel_warmup, "_cores", lambda: 2)
    monkeypatch.setenv("REFSIM_BACKGROUND_COMPILE", "0")
    assert kernel_warmup.start_background_compilation() is None
    monkeypatch.setenv("REFSIM_BACKGROUND_COMPILE", "1")
    (tmp_path / DONE_MARKER).touch()
    assert kernel_warmup.start_background_compilation() is None
    (tmp_path / DONE_MARKER).unlink()
    monkeypatch.setattr(kernel_warmup, "_cores", lambda: 1)
    assert kernel_warmup.start_background_compilation() is None
    monkeypatch.setattr(kernel_warmup, "_cores", lambda: 2)
    monkeypatch.setattr(kernel_warmup, "_cache_folder", lambda: tmp_path / "missing")  # cannot be written
    assert kernel_warmup.start_background_compilation() is None
    assert kernel_warmup._started is None


@pytest.mark.slow
def test_the_list_is_what_the_main_jobs_run_compiles(tmp_path, monkeypatch):
    """A recording of the cube's run with an empty kernel cache lists the same kernels and argument types
    (about a minute: everything compiles)."""
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    code = (
        "import json, refsim.kernel_warmup as k; "
        "print(json.dumps([[e['module'], e['name'], e['signature']] for e in k.record_manifest('cube')]))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr
    recorded = {tuple(entry) for entry in json.loads(done.stdout.strip().splitlines()[-1])}
    listed = {(entry["module"], entry["name"], entry["signature"]) for entry in load_manifest()}
    assert recorded == listed


def test_a_run_on_an_empty_cache_starts_one_process_that_marks_the_cache(tmp_path, monkeypatch):
    manifest = tmp_path / "kernels.json"
    manifest.write_text(json.dumps({"scene": "test", "kernels": [_ALL_FINITE]}))
    cache = tmp_path / "cache"
    cache.mkdir()
    monkeypatch.setattr(kernel_warmup, "_started", None)
    monkeypatch.setattr(kernel_warmup, "_cache_folder", lambda: cache)
    monkeypatch.setattr(kernel_warmup, "_cores", lambda: 2)
    monkeypatch.setenv("REFSIM_BACKGROUND_COMPILE", "1")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))  # the process's cache: the same folder
    process = kernel_warmup.start_background_compilation(manifest)
    assert process is not None
    assert kernel_warmup.start_background_compilation(manifest) is None  # at most one per process
    assert process.wait(timeout=600) == 0
    assert (cache / DONE_MARKER).is_file()
