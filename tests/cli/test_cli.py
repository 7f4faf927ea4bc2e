"""The command line: exit codes, messages that name the problem, and no half-written results file."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import h5py
import pytest

from refsim.cli import main


def _refsim(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "refsim", *args], capture_output=True, text=True, cwd=cwd, timeout=600
    )


@pytest.mark.parametrize(
    ("arguments", "fragments"),
    [
        (["run", "cube", "--set", "needle.radius=-1"], ["cube.toml", "radius", "-1", "(0.0, inf]"]),
        (["run", "cube", "--set", "tissue.colour=1"], ["unknown key tissue.colour"]),
        (["run", "no_such_scene"], ["neither a scene file nor a built-in scene"]),
        (["run", "cube", "--set", "nonsense"], ["section.key=value"]),
    ],
)
def test_bad_input_exits_2_names_the_problem_and_writes_nothing(tmp_path, capsys, arguments, fragments):
    output = tmp_path / "result.h5"
    code = main([*arguments, "-o", str(output)])
    error = capsys.readouterr().err
    assert code == 2
    for fragment in fragments:
        assert fragment in error
    assert "Traceback" not in error
    assert not output.exists()


@pytest.mark.parametrize("name", ["result.xdmf", "result.csv", "result", "result.vtu"])
def test_a_results_file_not_named_as_hdf5_exits_2_and_nothing_is_written(tmp_path, capsys, name):
    # With out.xdmf the ParaView sidecar (the results path with .xdmf) would replace the HDF5 results.
    output = tmp_path / name
    code = main(["run", "cube", "-o", str(output), "--set", "time.duration=0.02"])
    error = capsys.readouterr().err
    assert code == 2 and name in error and ".h5 or .hdf5" in error and "Traceback" not in error
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "command", [["run", "cube"], ["bench", "cube"], ["interactive", "cube", "--no-window"]], ids=str
)
def test_a_key_set_twice_on_the_command_line_exits_2_naming_both(tmp_path, capsys, command):
    # One of the two values would be dropped without a word.
    output = tmp_path / "result.h5"
    arguments = [*command, "--set", "needle.radius=0.001", "--set", "needle.radius = 0.002"]
    if command[0] != "bench":
        arguments += ["-o", str(output)]
    code = main(arguments)
    error = capsys.readouterr().err
    assert code == 2 and "needle.radius=0.001" in error and "needle.radius = 0.002" in error
    assert "give each key once" in error and "Traceback" not in error
    assert list(tmp_path.iterdir()) == []


def test_bench_refuses_a_strategy_set_beside_its_strategies(capsys):
    code = main(["bench", "cube", "--strategies", "exact", "fast", "--set", 'compliance.strategy="fast"'])
    error = capsys.readouterr().err
    assert code == 2 and "--set compliance.strategy" in error and "--strategies" in error


def test_bench_against_exact_gives_each_strategys_time_as_a_share_of_the_exact_step(capsys):
    # Issue 26's measure of the fast mode (its step against the exact one, side by side): each strategy timed
    # on --repeats interleaved runs, its time their median (printed with their range); the share printed
    # beside the errors is the ratio of the two medians printed above it (each to 0.01 ms, the share to 0.01),
    # with the range of the rounds' own ratios.
    import re

    code = main(
        ["bench", "cube", "--strategies", "fast", "--against-exact", "--repeats", "3"]
        + ["--set", "mesh.cells=[2, 2, 2]", "--set", "time.duration=0.2"]
    )
    out = capsys.readouterr().out
    assert code == 0
    found = re.findall(
        r"compliance (\w+) \(.*?; ([0-9.]+) ms per step \(median of 3 runs, ([0-9.]+) to ([0-9.]+)\)", out
    )
    times = {name: tuple(map(float, values)) for name, *values in found}
    share = re.search(
        r"^  fast +time ([0-9.]+) of the exact step \(each round: ([0-9.]+) to ([0-9.]+)\), position",
        out,
        re.MULTILINE,
    )
    assert set(times) == {"exact", "fast"} and share is not None
    for median, low, high in times.values():
        assert low <= median <= high
    exact, fast = times["exact"][0], times["fast"][0]
    rounding = 0.005 + fast / exact * (0.005 / exact + 0.005 / fast)
    assert abs(float(share.group(1)) - fast / exact) <= rounding
    assert float(share.group(2)) <= float(share.group(3))


def test_bench_refuses_a_repeat_count_out_of_range(capsys):
    code = main(["bench", "cube", "--repeats", "0"])
    error = capsys.readouterr().err
    assert code == 2 and "--repeats 0" in error and "[1, 50]" in error and "Traceback" not in error


def test_bad_mesh_file_is_named(tmp_path, capsys):
    scene = Path(__file__).resolve().parents[2] / "refsim" / "scenes" / "cube.toml"
    text = scene.read_text().replace('generator = "box"', f'file = "{tmp_path / "broken.msh"}"')
    (tmp_path / "broken.msh").write_text("not a mesh\n")
    path = tmp_path / "scene.toml"
    path.write_text(text)
    code = main(["run", str(path), "-o", str(tmp_path / "out.h5")])
    error = capsys.readouterr().err
    assert code == 2 and "broken.msh" in error and not (tmp_path / "out.h5").exists()


def test_existing_results_file_is_not_overwritten_silently(tmp_path, capsys):
    output = tmp_path / "result.h5"
    output.write_bytes(b"precious")
    code = main(["run", "cube", "-o", str(output), "--set", "time.duration=0.02"])
    assert code == 2 and "--overwrite" in capsys.readouterr().err
    assert output.read_bytes() == b"precious"


def test_run_writes_results_and_summary(tmp_path):
    output = tmp_path / "short.h5"
    process = _refsim(
        "run", "cube", "-o", str(output), "-q", "--set", "mesh.cells=[4, 4, 4]", "--set", "time.duration=0.4"
    )
    assert process.returncode == 0, process.stderr
    assert "puncture" in process.stdout and "steps/s" in process.stdout
    with h5py.File(output, "r") as results:
        assert bool(results.attrs["complete"])
        assert int(results.attrs["steps_completed"]) == 40


# slow: runs every verification case (about 11 s); each case has its own test in tests/verification/.
@pytest.mark.slow
def test_verify_prints_the_table_and_passes():
    process = _refsim("verify")
    assert process.returncode == 0, process.stdout + process.stderr
    assert "needle cantilever, small load" in process.stdout
    assert " 0 failed" in process.stdout


@pytest.mark.parametrize(
    ("extra", "fragments"),
    [
        (["--set", 'needle.youngs_modulus="soft"'], ["override --set", "needle.youngs_modulus = 'soft'"]),
        (["--set", "insertion.spacing=abc"], ["override --set", "insertion.spacing = 'abc'"]),
        (["--set", "tissue.density=1e300"], ["tissue.density", "out of range"]),
        (["--set", 'solver.backend="nosuch"'], ["solver.backend", "installed qpsolvers"]),
        (["--figure", "FOLDER/picture.txt"], ["--figure", ".png"]),
        (["--figure", "AFILE/picture.png"], ["afile is a file, not a folder"]),
    ],
)
def test_issue_10_inputs_exit_2_before_anything_is_written(tmp_path, capsys, extra, fragments):
    (tmp_path / "afile").write_text("x")
    extra = [
        part.replace("FOLDER", str(tmp_path)).replace("AFILE", str(tmp_path / "afile")) for part in extra
    ]
    output = tmp_path / "result.h5"
    code = main(["run", "cube", "-o", str(output), "-q", *extra])
    error = capsys.readouterr().err
    assert code == 2, error
    for fragment in fragments:
        assert fragment in error, (fragment, error)
    assert "Traceback" not in error and not output.exists()


def test_parent_of_the_output_is_a_file(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    code = main(["run", "cube", "-o", str(tmp_path / "afile" / "out.h5"), "-q"])
    error = capsys.readouterr().err
    assert code == 2 and "afile is a file, not a folder" in error and "Errno" not in error


@pytest.mark.skipif(
    not hasattr(__import__("os"), "geteuid") or __import__("os").geteuid() != 0,
    reason="needs root to mount a tmpfs",
)
def test_full_disk_exits_3_with_a_readable_file(tmp_path, capsys):
    """A 1 MiB tmpfs fills up during the run: exit 3, a one-line message, every written step readable (and no
    XDMF sidecar written into the file on the full disk)."""
    from refsim.io import read_results

    disk = tmp_path / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(disk)]).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        code = main(
            [
                "run",
                "cube",
                "-o",
                str(disk / "out.h5"),
                "-q",
                "--set",
                "mesh.cells=[4, 4, 4]",
                "--set",
                "time.duration=2.2",
                "--set",
                "output.tissue_every=1",
            ]
        )
        error = capsys.readouterr().err
        assert code == 3 and "no space left" in error and "internal error" not in error, error
        results = read_results(disk / "out.h5")
        assert 0 < results.step_count < 220 and not results.complete and "space" in results.stop_reason
    finally:
        subprocess.run(["umount", str(disk)])


@pytest.mark.parametrize(
    ("replace", "overrides", "fragments"),
    [
        # a scene file that sets f_c under the energy law (the law it names in the file)
        (
            ('law = "energy"', 'law = "energy"\ncutting_force = 1.0'),
            [],
            ["cutting_force", "'paper'", "'energy'"],
        ),
        # the law chosen by --set, a key of the other law in the file: the override is blamed
        (
            ('law = "energy"', 'law = "energy"\nfracture_energy = 150.0'),
            ["cutting.law=paper"],
            ["fracture_energy", "'energy' cutting law", "law = 'paper'", "--set 'cutting.law=paper'"],
        ),
    ],
)
def test_a_key_of_the_cutting_law_not_chosen_exits_2_and_is_named(
    tmp_path, capsys, replace, overrides, fragments
):
    scene = Path(__file__).resolve().parents[2] / "refsim" / "scenes" / "cube_cut.toml"
    text = scene.read_text()
    assert text.count(replace[0]) == 1
    path = tmp_path / "scene.toml"
    path.write_text(text.replace(*replace))
    output = tmp_path / "out.h5"
    code = main(["run", str(path), "-o", str(output), *(a for o in overrides for a in ("--set", o))])
    error = capsys.readouterr().err
    assert code == 2, error
    assert "scene.toml" in error and "Traceback" not in error and not output.exists()
    for fragment in fragments:
        assert fragment in error, error
