"""numba, with refsim's compiled kernels cached per version of refsim's sources.

Every module that defines a kernel takes numba from here (``from refsim.kernel_cache import numba``), so the
cache is set up on the first import of such a module, once per process, and ``import refsim`` alone imports
neither numba nor reads a source file.

Why a directory per version: numba invalidates a cached function only when its own file changes, not when a
function it calls from another file does ("Cache limitations", numba's caching notes). After an edit of
``refsim/solvers/laws.py`` a kernel of ``refsim/solvers/gauss_seidel.py`` would otherwise keep running the old
code. The directory is ``$XDG_CACHE_HOME/refsim/numba/<digest of refsim's sources>`` (``~/.cache`` without
XDG_CACHE_HOME); setting ``NUMBA_CACHE_DIR`` keeps numba's own behaviour in that directory.

Kernels are compiled on their first call (no kernel has an explicit signature), so a run compiles, or loads
from the cache, only the kernels it calls.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numba
import numpy as np

__all__ = ["numba", "numba_cache_directory", "readonly", "source_digest"]

_PACKAGE = Path(__file__).resolve().parent


def source_digest(root: Path | None = None) -> str:
    """SHA-256 (first 16 hex digits) of every ``*.py`` file under ``root`` (refsim's package folder by
    default), names and contents, in sorted order."""
    root = _PACKAGE if root is None else Path(root)
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(b"\0")
        digest.update(path.read_bytes())
        digest.update(b"\0")
    return digest.hexdigest()[:16]


def numba_cache_directory() -> Path:
    """Where refsim's compiled kernels are cached: ``$XDG_CACHE_HOME/refsim/numba/<source digest>``
    (``~/.cache`` without XDG_CACHE_HOME). A new digest, i.e. any change of refsim's sources, starts an empty
    cache; old ones can be deleted at any time no refsim process runs."""
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "refsim" / "numba" / source_digest()


def readonly(array: np.ndarray) -> np.ndarray:
    """A read-only view of ``array`` (no copy). numba compiles a kernel once per argument type, and a
    read-only array is another type than a writable one: an input that callers pass either way (the rest
    positions are read-only, a deformed configuration is not) goes through this, so that the kernel is
    compiled once, not twice."""
    view = array.view()
    view.flags.writeable = False
    return view


def _configure() -> None:
    """Point numba's cache at :func:`numba_cache_directory` before any refsim kernel is defined (numba reads
    ``numba.config.CACHE_DIR`` when a ``cache=True`` function is decorated), unless NUMBA_CACHE_DIR is set or
    the directory cannot be created (then numba's default: next to the sources)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    try:
        directory = numba_cache_directory()
        directory.mkdir(parents=True, exist_ok=True)
    except OSError:
        return
    numba.config.CACHE_DIR = str(directory)


_configure()  # runs once: Python imports a module once per process
