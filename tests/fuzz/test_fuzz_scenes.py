"""Fuzz of scene files (issue 10): any key, in and out of range, of the wrong type; each case must end in a
clean run (exit 0), a clean input error (exit 2: a message naming the key or its section, no traceback, no
file) or a clean numerical stop (exit 3: a readable file with complete = false and the reason).

Runs are tiny (2³ cells, at most 8 steps: the needle approaches the cube) so the default suite's share stays
small; HYPOTHESIS_PROFILE=slow runs 50 times more examples.
"""

from __future__ import annotations

import contextlib
import copy
import io
import json
import math
import tempfile
import tomllib
from pathlib import Path

import h5py
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from refsim.cli import main
from refsim.scene.loader import _resolve

BASE = tomllib.loads(_resolve("cube").read_text(encoding="utf-8"))
BASE["mesh"]["cells"] = [2, 2, 2]
BASE["time"]["duration"] = 0.05
BASE["output"] = {"tissue_every": 2, "record_problems": False}
KEYS = [(section, key) for section, table in BASE.items() if isinstance(table, dict) for key in table]
EXTRA_KEYS = [
    ("mesh", "file"),
    ("mesh", "scale"),
    ("mesh", "fixed_box"),
    ("mesh", "face_tolerance"),
    ("trajectory", "file"),
    ("solver", "criterion"),
    ("insertion", "shaft_normal_force"),
    ("needle", "rayleigh_mass"),
    ("needle", "rayleigh_stiffness"),
    ("output", "record_problems"),
]
EXAMPLES = settings.default.max_examples  # 40 in the ci profile, 2000 in slow


def _scale_value(value):
    """Values near and far from a valid one: scaled, negated, zero, huge, tiny."""
    return st.sampled_from([0.0, -1.0, 0.5, 2.0, 10.0, 1e-6, 1e6, 1e300, -1e300]).map(
        lambda f: value * f if isinstance(value, float) else f
    )


junk = st.one_of(
    st.text(max_size=8),
    st.booleans(),
    st.integers(-(10**6), 10**6),
    st.floats(allow_nan=True, allow_infinity=True),
    st.lists(st.floats(-1e3, 1e3), max_size=4),
    st.lists(st.lists(st.integers(-3, 3), min_size=3, max_size=3), max_size=3),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
)


@st.composite
def mutated_scenes(draw):
    """The tiny cube with one to three keys changed: each to a scaled value, a junk value or removed."""
    data = copy.deepcopy(BASE)
    changed = []
    for _ in range(draw(st.integers(1, 3))):
        section, key = draw(st.sampled_from(KEYS + EXTRA_KEYS))
        table = data.setdefault(section, {})
        current = table.get(key)
        how = draw(st.sampled_from(["scale", "junk", "remove"] if current is not None else ["junk"]))
        if how == "remove":
            table.pop(key, None)
        elif how == "scale" and isinstance(current, (int, float)) and not isinstance(current, bool):
            table[key] = draw(_scale_value(float(current)))
            if isinstance(current, int):
                table[key] = int(max(min(table[key], 1e9), -1e9))
        elif (
            how == "scale"
            and isinstance(current, list)
            and current
            and all(isinstance(v, (int, float)) for v in current)
        ):
            factor = draw(_scale_value(1.0))
            table[key] = [
                type(v)(v * factor) if math.isfinite(v * factor) and abs(v * factor) < 1e18 else v * factor
                for v in current
            ]
        else:
            table[key] = draw(junk)
        changed.append((section, key))
    return data, changed


def _string(text: str) -> str:
    """A TOML basic string: JSON's escapes are valid TOML ones; TOML also forbids a raw DEL (0x7f)."""
    return json.dumps(text, ensure_ascii=False).replace("\x7f", "\\u007f")


def _toml(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return {math.inf: "inf", -math.inf: "-inf"}.get(value, "nan" if math.isnan(value) else repr(value))
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return _string(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_string(k)} = {_toml(v)}" for k, v in value.items()) + "}"
    raise TypeError(type(value))


def write_scene(data: dict, path: Path) -> None:
    lines = [f"name = {_toml(data.get('name', 'fuzz'))}"]
    for section, table in data.items():
        if isinstance(table, dict):
            lines.append(f"[{section}]")
            lines += [f"{_string(key)} = {_toml(value)}" for key, value in table.items()]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def run_cli(arguments: list[str]) -> tuple[int, str]:
    """refsim in this process; (exit code, stderr)."""
    error = io.StringIO()
    with contextlib.redirect_stderr(error), contextlib.redirect_stdout(io.StringIO()):
        code = main(arguments)
    return code, error.getvalue()


def assert_clean_outcome(code: int, error: str, output: Path, names: list[str]) -> None:
    """Exit 0, 2 or 3 as issue 10 defines them; ``names``: one of them must be in an input error's message."""
    assert "Traceback" not in error and "internal error" not in error, error
    assert code in (0, 2, 3), (code, error)
    if code == 2:
        assert not output.exists(), f"exit 2 but {output} was written: {error}"
        assert any(name in error for name in names), (names, error)
        return
    with h5py.File(output, "r") as handle:
        complete = bool(handle.attrs["complete"])
        reason = str(handle.attrs["stop_reason"])
        steps = int(handle.attrs["steps_completed"])
    from refsim.io import read_results

    results = read_results(output)
    assert results.step_count == steps
    if code == 0:
        assert complete and reason == ""
    else:
        assert not complete and reason, reason


@settings(max_examples=EXAMPLES, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(mutated_scenes())
def test_fuzzed_scene_files_end_cleanly(case):
    data, changed = case
    with tempfile.TemporaryDirectory() as folder:
        scene = Path(folder) / "scene.toml"
        output = Path(folder) / "out" / "result.h5"
        write_scene(data, scene)
        code, error = run_cli(["run", str(scene), "-o", str(output), "-q"])
        names = [f"{section}.{key}" for section, key in changed] + [f"[{section}]" for section, _ in changed]
        names += [key for _, key in changed] + [section for section, _ in changed]
        assert_clean_outcome(code, error, output, names)


override_values = st.one_of(
    st.sampled_from(
        [
            "abc",
            '"x"',
            "true",
            "[1, 2]",
            "{a = 1}",
            "nan",
            "-inf",
            "1e400",
            "",
            "[[0, 0, -1]]",
            "0",
            "-1",
            "1e300",
        ]
    ),
    st.floats(allow_nan=False).map(repr),
    st.integers(-5, 10**7).map(str),
)


@settings(max_examples=EXAMPLES, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(KEYS + EXTRA_KEYS), override_values)
def test_fuzzed_overrides_are_blamed_on_the_override(key, value):
    section, name = key
    text = f"{section}.{name}={value}"
    with tempfile.TemporaryDirectory() as folder:
        scene = Path(folder) / "scene.toml"
        write_scene(BASE, scene)
        output = Path(folder) / "result.h5"
        code, error = run_cli(["run", str(scene), "-o", str(output), "-q", "--set", text])
        assert_clean_outcome(code, error, output, [f"{section}.{name}", f"[{section}]", name, section])
        if code == 2 and "override --set" not in error:
            # An error not blamed on the override must come from the check of the mesh or the trajectory
            # against the scene, which names the file and the keys involved.
            assert str(scene) in error, error
