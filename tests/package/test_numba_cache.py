"""refsim's compiled kernels are cached per version of its sources (refsim.kernel_cache).

Reference: numba's caching notes, "Cache limitations": a cached function is invalidated only when its own
source file changes, not when a function it calls from another file does. The tests check the digest that
names the directory (it must change with any source file), that importing a module with kernels points numba
at it before its kernels are defined, or leaves an explicit NUMBA_CACHE_DIR alone, and that ``import refsim``
alone neither imports numba nor creates the directory (the set-up happens on first use of a kernel module).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import refsim
from refsim.kernel_cache import source_digest

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


def _cache_dirs_in_subprocess(environment: dict[str, str]) -> tuple[Path, Path]:
    """numba's cache directory, and where a kernel of refsim.solvers.array_checks writes its cache (its
    dispatcher's cache path, fixed when the kernel is decorated), in a fresh interpreter."""
    code = (
        "import numba, refsim.solvers.array_checks as checks; "
        "print(numba.config.CACHE_DIR); print(checks.all_finite._cache._cache_path)"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=environment, check=True
    )
    directory, kernel = done.stdout.strip().splitlines()[-2:]
    return Path(directory), Path(kernel)


def test_a_kernel_module_points_numba_at_the_digest_directory(tmp_path):
    environment = {key: value for key, value in os.environ.items() if key != "NUMBA_CACHE_DIR"}
    environment["XDG_CACHE_HOME"] = str(tmp_path)
    expected = tmp_path / "refsim" / "numba" / source_digest()
    directory, kernel = _cache_dirs_in_subprocess(environment)
    assert directory == expected and kernel.is_relative_to(expected)
    assert expected.is_dir()


def test_an_explicit_numba_cache_dir_is_kept(tmp_path):
    environment = dict(
        os.environ, NUMBA_CACHE_DIR=str(tmp_path / "mine"), XDG_CACHE_HOME=str(tmp_path / "xdg")
    )
    directory, kernel = _cache_dirs_in_subprocess(environment)
    assert directory == tmp_path / "mine" and kernel.is_relative_to(tmp_path / "mine")
    assert not (tmp_path / "xdg").exists()
