"""Start-up: ``import refsim`` and ``refsim --help`` import no heavy dependency, and numba's kernel cache is
set up only when a module that defines kernels is imported (refsim.kernel_cache). Each check runs in a fresh
interpreter, because this test process has imported everything already."""

from __future__ import annotations

import json
import os
import subprocess
import sys

HEAVY = (
    "numba",
    "llvmlite",
    "numpy",
    "scipy",
    "h5py",
    "skfem",
    "pyvista",
    "vtk",
    "matplotlib",
    "distributed",
)


def _modules_after(code: str, environment: dict[str, str] | None = None) -> set[str]:
    """Top-level module names loaded after running ``code`` in a fresh interpreter."""
    script = f"{code}\nimport json, sys\nprint(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}})))"
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=environment, check=True
    )
    return set(json.loads(done.stdout.strip().splitlines()[-1]))


def test_import_refsim_imports_nothing_heavy():
    assert not _modules_after("import refsim").intersection(HEAVY)


def test_help_imports_nothing_heavy():
    code = (
        "import contextlib, io\nfrom refsim.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    try:\n        main(['--help'])\n    except SystemExit:\n        pass"
    )
    assert not _modules_after(code).intersection(HEAVY)


def test_import_refsim_sets_up_no_kernel_cache(tmp_path):
    environment = {key: value for key, value in os.environ.items() if key != "NUMBA_CACHE_DIR"}
    environment["XDG_CACHE_HOME"] = str(tmp_path)
    _modules_after("import refsim, refsim.cli", environment)
    assert not (tmp_path / "refsim").exists()
    loaded = _modules_after("import refsim.solvers.laws", environment)
    assert "numba" in loaded and (tmp_path / "refsim" / "numba").is_dir()
