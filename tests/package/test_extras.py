"""Commands that need an optional extra (pyproject.toml) stop before any work, with exit code 2 and the pip
command that installs it, when a package of the extra is missing. A missing package is simulated by
``sys.modules[name] = None``, which makes its import (and importlib's find_spec) fail as if not installed."""

from __future__ import annotations

import sys

import pytest

from refsim.cli import EXTRA_MODULES, _extra_of, main


def _hide(monkeypatch, *modules: str) -> None:
    for module in modules:
        monkeypatch.setitem(sys.modules, module, None)


@pytest.mark.parametrize(
    ("argv", "hidden", "extra"),
    [
        (["render", "{result}", "-o", "{out}.png"], "pyvista", "viz"),
        (["render", "{result}", "--animate", "{out}.gif"], "imageio", "viz"),
        (["plot", "{result}", "-o", "{out}.png"], "matplotlib", "viz"),
        (["study", "cube", "--sweep", "time.dt=1e-3,2e-3", "-o", "{out}.h5"], "distributed", "study"),
        (["study", "cube", "--sweep", "time.dt=1e-3,2e-3", "-o", "{out}.h5"], "tqdm", "study"),
        (["run", "cube", "-o", "{out}.h5", "--figure", "{out}.png"], "matplotlib", "viz"),
        (["run", "cube", "-o", "{out}.h5", "--figure", "{out}.png"], "pyvista", "viz"),
    ],
)
def test_a_missing_extra_names_the_pip_command_and_writes_nothing(
    tmp_path, monkeypatch, capsys, argv, hidden, extra
):
    _hide(monkeypatch, hidden)
    result, out = tmp_path / "result.h5", tmp_path / "out"
    code = main([a.format(result=result, out=out) for a in argv])
    error = capsys.readouterr().err
    assert code == 2
    assert f"refsim {argv[0]}: error:" in error and hidden in error
    assert f"pip install 'refsim[{extra}]'" in error
    assert "Traceback" not in error
    assert list(tmp_path.iterdir()) == []  # checked before the run: no results file, no figure, no study


def test_a_missing_module_found_where_it_is_used_names_its_extra(monkeypatch, capsys):
    def handler(args):
        raise ModuleNotFoundError("No module named 'vtkmodules.vtkRenderingCore'", name="vtkmodules")

    import refsim.cli as cli

    parser = cli._parser

    def patched():
        built = parser()
        built.set_defaults(handler=handler)
        for action in built._subparsers._group_actions:
            for sub in action.choices.values():
                sub.set_defaults(handler=handler)
        return built

    monkeypatch.setattr(cli, "_parser", patched)
    assert main(["verify"]) == 2
    error = capsys.readouterr().err
    assert "pip install 'refsim[viz]'" in error and "Traceback" not in error


def test_an_unknown_missing_module_is_an_internal_error_not_an_extra(monkeypatch, capsys):
    import refsim.cli as cli

    parser = cli._parser

    def handler(args):
        raise ModuleNotFoundError("No module named 'nosuchthing'", name="nosuchthing")

    def patched():
        built = parser()
        for action in built._subparsers._group_actions:
            for sub in action.choices.values():
                sub.set_defaults(handler=handler)
        return built

    monkeypatch.setattr(cli, "_parser", patched)
    assert main(["verify"]) == 2
    error = capsys.readouterr().err
    assert "internal error" in error and "refsim[" not in error


def test_every_extra_module_maps_back_to_its_extra():
    for extra, modules in EXTRA_MODULES.items():
        for module in modules:
            assert _extra_of(module) == extra
            assert _extra_of(module + ".sub") == extra
    assert _extra_of("vtk") == "viz" and _extra_of("dask.array") == "study"
    assert _extra_of("numpy") is None and _extra_of("") is None


def test_the_osqp_backend_without_its_extra_names_the_pip_command(tmp_path, monkeypatch, capsys):
    import qpsolvers  # its list of backends is fixed when it is imported: hide osqp from it

    monkeypatch.setattr(
        qpsolvers, "available_solvers", [n for n in qpsolvers.available_solvers if n != "osqp"]
    )
    code = main(["run", "cube", "-o", str(tmp_path / "r.h5"), "--set", 'solver.backend="osqp"'])
    error = capsys.readouterr().err
    assert code == 2 and "solver.backend" in error and "pip install 'refsim[osqp]'" in error
    assert list(tmp_path.iterdir()) == []


def test_the_extras_the_cli_names_are_those_of_pyproject():
    import re
    import tomllib
    from pathlib import Path

    pyproject = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())
    extras = pyproject["project"]["optional-dependencies"]
    required = " ".join(pyproject["project"]["dependencies"])
    for extra, modules in EXTRA_MODULES.items():
        names = " ".join(extras[extra])
        for module in modules:  # each import name is a distribution of its extra (dask[distributed] included)
            assert re.search(rf"\b{module}\b", names), (extra, module)
            assert not re.search(rf"\b{module}\b", required), module  # and not a required package
    test = " ".join(extras["test"])
    assert all(extra in test for extra in EXTRA_MODULES)  # the test suite installs every extra
