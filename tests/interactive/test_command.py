"""The command line of `refsim interactive`: bad options and a missing extra are exit 2 with a message that
names the option or the pip command, before anything is written."""

from __future__ import annotations

import importlib.util

import pytest

from refsim import cli


@pytest.mark.parametrize(
    ("arguments", "expected"),
    [
        (["--lockstep"], "--lockstep needs the pose stream"),
        (["--no-window"], "--no-window needs the pose stream"),
        (["--socket", "0", "--no-window", "--screenshot", "x.png"], "--screenshot needs the window"),
        (["--max-speed", "0"], "--max-speed 0.0: expected a positive number [m/s]"),
        (["--max-turn", "nan"], "--max-turn nan: expected a positive number [deg/s]"),
        (["--duration", "-1"], "--duration -1.0: expected a positive number [s]"),
        (["--socket", "70000", "--no-window"], "--socket 70000: expected a TCP port"),
    ],
)
def test_bad_options_are_exit_2_naming_the_option(tmp_path, capsys, arguments, expected):
    output = tmp_path / "x.h5"
    code = cli.main(["interactive", "cube", "-o", str(output), *arguments])
    assert code == 2
    assert expected in capsys.readouterr().err
    assert not output.exists()


def test_the_window_without_pyvista_names_the_extra(tmp_path, capsys, monkeypatch):
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *args: None if name == "pyvista" else find_spec(name, *args)
    )
    output = tmp_path / "x.h5"
    assert cli.main(["interactive", "cube", "-o", str(output)]) == 2
    assert "pip install 'refsim[viz]'" in capsys.readouterr().err and not output.exists()
