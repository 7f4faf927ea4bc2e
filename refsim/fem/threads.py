"""BLAS and OpenMP threads inside refsim's hot path (layer 2).

The step's dense and sparse kernels are small (a few thousand DoFs, tens of columns): on a shared 2-core
machine two OpenBLAS threads made one W computation 26 times slower than one thread (196 against 7.4 ms, issue
12). Inside the step refsim therefore pins every BLAS / OpenMP pool (OpenBLAS, MKL, the OpenMP runtime) to one
thread with threadpoolctl, *as a context manager*: the user's global setting is restored on exit, so NumPy
code around refsim keeps its threads.
"""

from __future__ import annotations

import contextlib
import threading
from functools import lru_cache

__all__ = ["hot_path_threads", "thread_settings"]


@lru_cache(maxsize=1)
def _controller():
    from threadpoolctl import ThreadpoolController

    from refsim.fem.linear import available_linear_solvers

    available_linear_solvers()  # load oneMKL first (when it is there) so that its pool is controlled too
    return ThreadpoolController()


_active = threading.local()  # the limit set by the innermost enclosing block of this thread, if any


#: The block of a nested call that finds its limit set: it does nothing (reusable and reentrant).
_NESTED = contextlib.nullcontext()


def hot_path_threads(threads: int = 1):
    """Limit every BLAS / OpenMP thread pool to ``threads`` inside the block (restored on exit).

    Setting the limit costs tens of µs (threadpoolctl visits every pool twice); a block nested in one that
    already set the same limit (a body's stage inside ``Simulation.step``) does nothing (an empty context
    manager, without the generator of a limiting block)."""
    if not isinstance(threads, int) or threads < 1:
        raise ValueError(f"threads must be an integer >= 1, got {threads!r}")
    if getattr(_active, "threads", None) == threads:
        return _NESTED
    return _limited(threads)


@contextlib.contextmanager
def _limited(threads: int):
    """The block of :func:`hot_path_threads` that sets the limit (and restores the enclosing one on exit)."""
    outer = getattr(_active, "threads", None)
    _active.threads = threads
    try:
        with _controller().limit(limits=threads):
            yield
    finally:
        _active.threads = outer


def thread_settings() -> list[dict]:
    """The thread pools as they are now (outside the hot path): library, API, version and thread count."""
    return [
        {
            "library": info.get("prefix"),
            "api": info.get("internal_api"),
            "version": info.get("version"),
            "threads": info.get("num_threads"),
        }
        for info in _controller().info()
    ]
