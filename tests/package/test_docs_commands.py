"""The commands the README and docs/ quote still run: each `refsim ...` line parses with the command line's
own parser, its scene keys (``--set``, ``--sweep``) load on the named scene, the files it reads exist, and
each ``python studies/...`` script it names exists and takes the options quoted.

A page that quotes a command the code no longer accepts fails here, so the pages stay true by construction.
Placeholders of a synopsis (``SCENE``, ``RESULT.h5``, ...) are replaced by a concrete value first; optional
parts in brackets are kept (they must parse too); alternatives (``a|b``) and ellipses are not checked."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from refsim.cli import _parser
from refsim.scene import load_scene
from refsim.scene.loader import builtin_scenes

ROOT = Path(__file__).resolve().parents[2]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

PLACEHOLDERS = {
    "SCENE.toml": "cube",
    "SCENE": "cube",
    "RESULT.h5": "result.h5",
    "STUDY.h5": "study.h5",
    "STUDY.toml": "studies/convergence/cube_mesh.toml",
    "FIG.png": "figure.png",
    "OUT.h5": "out.h5",
    "SET.h5": "set.h5",
    "OUT.gif": "out.gif",
    "F.csv": "force.csv",
    "FORCE.csv": "force.csv",
    "FOLDER": "fclib",
    "DIR": "fclib",
    "STEP": "1",
    "N": "1",
    "K": "2",
    "Z": "1.5",
    "section.key=value": "time.dt=0.01",
    "key=v1,v2": "time.dt=0.01,0.005",
}
SUBCOMMANDS = (
    "run",
    "study",
    "export",
    "render",
    "plot",
    "bench",
    "verify",
    "interactive",
    "reference",
    "compare",
)
COMMAND = re.compile(r"refsim (?:" + "|".join(SUBCOMMANDS) + r")\b[^`\n]*")
SCRIPT = re.compile(r"python (studies/[\w/]+\.py)([^`&\n]*)")


def _quoted(pattern: re.Pattern) -> list[tuple[str, re.Match]]:
    """(page name, match) for every inline code span and code-block line of the pages."""
    found = []
    for page in PAGES:
        text = page.read_text(encoding="utf-8")
        spans = re.findall(r"`([^`\n]+)`", text)
        blocks = [
            line for block in re.findall(r"```\w*\n(.*?)```", text, flags=re.S) for line in block.split("\n")
        ]
        for snippet in spans + blocks:
            found.extend((page.name, match) for match in pattern.finditer(snippet.split(" #")[0]))
    return found


def _concrete(command: str) -> list[str] | None:
    """The command's arguments with placeholders replaced; None for a synopsis that cannot be made
    concrete."""
    if "..." in command or "|" in command:
        return None
    command = command.replace("[", " ").replace("]", " ")
    try:
        words = shlex.split(command)
    except ValueError:
        return None
    return [PLACEHOLDERS.get(word, word) for word in words[1:]]


COMMANDS = [(page, match.group(0).strip()) for page, match in _quoted(COMMAND)]
SCRIPTS = [(page, match.group(1), match.group(2)) for page, match in _quoted(SCRIPT)]


def test_the_pages_quote_commands():
    # The check below must have something to check: the README alone quotes run, study, export and render.
    assert len(COMMANDS) >= 20 and len(SCRIPTS) >= 10


@pytest.mark.parametrize(("page", "command"), COMMANDS, ids=[f"{p}:{c[:60]}" for p, c in COMMANDS])
def test_quoted_refsim_command_parses_and_its_scene_keys_load(page, command):
    argv = _concrete(command)
    if argv is not None and len(argv) == 1:  # a mention of the subcommand (`refsim plot`): it must exist
        assert argv[0] in _parser()._subparsers._group_actions[0].choices, f"{page}: no command `{command}`"
        return
    if argv is None:
        pytest.skip(f"{page}: a synopsis with alternatives or an ellipsis: {command}")
    try:
        args = _parser().parse_args(argv)
    except SystemExit:
        pytest.fail(f"{page} quotes `{command}`, which the command line rejects")
    scene = getattr(args, "scene", None)
    if scene is None:
        return
    if scene not in builtin_scenes():
        if not (ROOT / scene).is_file():
            assert scene.startswith(("/", "..")), f"{page}: `{command}` names {scene}, which does not exist"
        return
    overrides = list(getattr(args, "set", None) or [])
    load_scene(scene, overrides)  # a key or value the scene rejects raises SceneError here
    for sweep in getattr(args, "sweep", None) or []:
        key, values = sweep.split("=", 1)
        for value in re.split(r",(?![^\[]*\])", values):
            load_scene(scene, [*overrides, f"{key}={value}"])


@pytest.mark.parametrize(("page", "script", "options"), SCRIPTS, ids=[f"{p}:{s}" for p, s, _ in SCRIPTS])
def test_quoted_study_script_exists_and_takes_its_options(page, script, options):
    path = ROOT / script
    assert path.is_file(), f"{page} quotes {script}, which does not exist"
    source = path.read_text(encoding="utf-8")
    for option in re.findall(r"--[\w-]+", options):
        assert f'"{option}"' in source or f"'{option}'" in source, f"{page}: {script} has no option {option}"
