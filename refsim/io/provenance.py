"""Provenance of a result: the git commit refsim runs from (:func:`git_commit`)."""

from __future__ import annotations

import subprocess
from pathlib import Path

__all__ = ["git_commit"]


def git_commit(directory: str | Path | None = None) -> str:
    """The commit checked out where refsim lives (``git rev-parse HEAD``), or "unknown" outside a checkout.

    Parameters
    ----------
    directory : Where to ask git; the refsim package's directory by default.
    """
    directory = Path(__file__).resolve().parent if directory is None else Path(directory)
    try:
        result = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=directory,
            capture_output=True,
            text=True,
            timeout=10,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    commit = result.stdout.strip()
    return commit if result.returncode == 0 and commit else "unknown"
