"""refsim's compiled kernels are cached per version of its sources (refsim.numba_cache_directory).

Reference: numba's caching notes, "Cache limitations": a cached function is invalidated only when its own
source file changes, not when a function it calls from another file does. The tests check the digest that
names the directory (it must change with any source file) and that importing refsim points numba at it, or
leaves an explicit NUMBA_CACHE_DIR alone.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import refsim
from refsim import source_digest

PACKAGE = Path(refsim.__file__).resolve().parent


def _copy(tmp_path: Path) -> Path:
    copy = tmp_path / "tree"
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc"))
    return copy


def test_digest_changes_with_any_source_file(tmp_path):
    copy = _copy(tmp_path)
    first = source_digest(copy)
    assert first == source_digest(PACKAGE) and len(first) == 16
    callee = copy / "solvers" / "laws.py"  # a file whose functions others call from their own files
    callee.write_text(callee.read_text() + "\n# edited\n")
    second = source_digest(copy)
    assert second != first
    (copy / "solvers" / "new_module.py").write_text("")  # an added file counts too
    assert source_digest(copy) not in (first, second)


def test_digest_ignores_compiled_caches(tmp_path):
    copy = _copy(tmp_path)
    before = source_digest(copy)
    (copy / "solvers" / "__pycache__").mkdir(exist_ok=True)
    (copy / "solvers" / "__pycache__" / "x.nbi").write_bytes(b"cache")
    assert source_digest(copy) == before


def _cache_dir_in_subprocess(environment: dict[str, str]) -> str:
    code = "import refsim, numba; print(numba.config.CACHE_DIR)"
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=environment, check=True
    )
    return done.stdout.strip()


def test_import_points_numba_at_the_digest_directory(tmp_path):
    environment = {key: value for key, value in os.environ.items() if key != "NUMBA_CACHE_DIR"}
    environment["XDG_CACHE_HOME"] = str(tmp_path)
    expected = tmp_path / "refsim" / "numba" / source_digest()
    assert Path(_cache_dir_in_subprocess(environment)) == expected
    assert expected.is_dir()


def test_an_explicit_numba_cache_dir_is_kept(tmp_path):
    environment = dict(
        os.environ, NUMBA_CACHE_DIR=str(tmp_path / "mine"), XDG_CACHE_HOME=str(tmp_path / "xdg")
    )
    assert _cache_dir_in_subprocess(environment) == str(tmp_path / "mine")
    assert not (tmp_path / "xdg").exists()
