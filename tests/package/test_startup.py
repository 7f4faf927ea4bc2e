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


def test_importing_the_kernel_modules_compiles_no_kernel(tmp_path):
    # Kernels have no explicit signature: numba compiles (or loads) each on its first call, so a run builds
    # only the kernels it calls. After importing every module of refsim, no kernel has a compiled signature.
    code = (
        "import sys, pkgutil, importlib, json\nimport refsim\n"
        "from numba.core.registry import CPUDispatcher\n"
        "names = [m.name for m in pkgutil.walk_packages(refsim.__path__, 'refsim.')]\n"
        "names = [name for name in names if not name.endswith('__main__')]\n"
        "kernels = {}\n"
        "for name in names:\n"
        "    module = importlib.import_module(name)\n"
        "    for attr, value in vars(module).items():\n"
        "        if isinstance(value, CPUDispatcher) and value.__module__ == name:\n"
        "            kernels[name + '.' + attr] = len(value.signatures)\n"
        "print(json.dumps(kernels))"
    )
    environment = {key: value for key, value in os.environ.items() if key != "NUMBA_CACHE_DIR"}
    environment["XDG_CACHE_HOME"] = str(tmp_path)
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=environment, check=True
    )
    kernels = json.loads(done.stdout.strip().splitlines()[-1])
    assert len(kernels) > 20  # the solvers', geometry's and assembly's kernels were all found
    assert {name: count for name, count in kernels.items() if count} == {}
