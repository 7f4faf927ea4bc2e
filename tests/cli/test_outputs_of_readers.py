"""The commands that read a results file (export, plot, render), and compare and reference: their outputs
are checked before anything is written (suffix, a folder, the results file itself), and a run that did not
complete is said so. Every case is bad input (exit 2) that names the path, leaves the results file byte for
byte and writes nothing."""

from __future__ import annotations

import pytest

from refsim.cli import EXIT_INPUT, main
from refsim.io.driver import run_scene
from refsim.scene import load_scene

SMALL = ["mesh.cells=[3, 3, 3]", "time.duration=0.3", "output.tissue_every=2"]  # 30 steps


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """A complete run of the cube on 3³ cells, and the same run stopped after 7 steps (its file says
    complete = false and why)."""
    folder = tmp_path_factory.mktemp("readers")
    complete = folder / "run.h5"
    assert run_scene(load_scene("cube", SMALL), complete).complete

    def stop(state, record):
        if record.step == 7:
            raise KeyboardInterrupt

    interrupted = folder / "stopped.h5"
    summary = run_scene(load_scene("cube", SMALL), interrupted, on_step=stop)
    assert summary.status == "interrupted" and summary.steps_written == 7
    return complete, interrupted


@pytest.mark.parametrize(
    ("arguments", "fragments"),
    [
        (["export", "{run}", "--csv", "{run}"], ["is the results file", "force CSV"]),
        (["export", "{run}", "--problems", "{run}"], ["is the results file", "problem set"]),
        (
            ["export", "{run}", "--vtu", "last", "--vtu-folder", "{run}"],
            ["--vtu-folder", "is a file, not a folder"],
        ),
        (["export", "{run}", "--csv", "{dir}"], ["is a directory", "force CSV"]),
        (
            ["export", "{run}", "--csv", "{dir}/f.csv", "--fclib", "{dir}"],
            ["--fclib", "goes with --problems"],
        ),
        (["export", "{run}", "--xdmf", "--vtu-folder", "{dir}"], ["--vtu-folder", "goes with --vtu"]),
        (["plot", "{run}", "-o", "{run}"], ["the plot must be a file ending in", ".png", ".pdf"]),
        (["plot", "{run}", "-o", "{dir}"], ["the plot must be a file ending in"]),  # before: wrote DIR.png
        (["plot", "{run}", "-o", "{dir}/forces.txt"], ["forces.txt", "the plot must be a file ending in"]),
        (["render", "{run}", "-o", "{dir}/picture.txt"], ["picture.txt", "must be a file ending in .png"]),
        (["render", "{run}", "-o", "{run}/picture.png"], ["is a file, not a folder"]),
        (["render", "{run}", "--animate", "{run}"], ["the animation must be a file ending in .gif, .mp4"]),
    ],
)
def test_an_output_that_cannot_be_written_is_refused_before_anything(
    results, tmp_path, capsys, arguments, fragments
):
    run, _ = results
    before = run.read_bytes()
    folder = tmp_path / "out"
    folder.mkdir()
    code = main([a.format(run=run, dir=folder) for a in arguments])
    error = capsys.readouterr().err
    assert code == EXIT_INPUT, error
    for fragment in fragments:
        assert fragment in error
    assert "internal error" not in error and "Errno" not in error
    assert run.read_bytes() == before  # before: `export RUN --csv RUN` replaced the results by the CSV
    assert list(folder.iterdir()) == []
    assert not (tmp_path / "out.png").exists()


@pytest.mark.parametrize("option", ["--xdmf", "--csv"])
def test_a_missing_results_file_is_named_as_the_input(tmp_path, capsys, option):
    missing = tmp_path / "none.h5"
    code = main(["export", str(missing), option, *([str(tmp_path / "f.csv")] if option == "--csv" else [])])
    error = capsys.readouterr().err
    assert code == EXIT_INPUT
    assert f"{missing}: no such results file" in error
    assert (
        "Errno" not in error and "writing" not in error
    )  # before: "[Errno None] none.xdmf: writing ... failed"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("arguments", "output"),
    [
        (["export", "{run}", "--csv", "{dir}/force.csv"], "force.csv"),
        (["plot", "{run}", "-o", "{dir}/forces.pdf"], "forces.pdf"),
    ],
)
def test_a_run_that_did_not_complete_is_said_so(results, tmp_path, capsys, arguments, output):
    complete, interrupted = results
    assert main([a.format(run=complete, dir=tmp_path) for a in arguments]) == 0
    assert "did not complete" not in capsys.readouterr().err
    assert main([a.format(run=interrupted, dir=tmp_path) for a in arguments]) == 0
    error = capsys.readouterr().err
    assert f"{interrupted} holds a run that did not complete (interrupted by SIGINT)" in error
    assert "its 7 completed steps are used" in error
    assert (tmp_path / output).is_file()


def test_an_interrupted_problem_export_leaves_no_file(tmp_path, monkeypatch, capsys):
    """The problem set is written under a temporary name and renamed once complete: Ctrl-C during its exact
    solves leaves nothing at the path."""
    import refsim.solvers

    run = tmp_path / "run.h5"
    scene = load_scene("cube", [*SMALL, "output.record_problems=true", "time.duration=0.1"])
    assert run_scene(scene, run).complete
    solve = refsim.solvers.solve_exact
    calls = []

    def interrupted(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return solve(*args, **kwargs)

    monkeypatch.setattr(refsim.solvers, "solve_exact", interrupted)
    problems = tmp_path / "problems.h5"
    assert main(["export", str(run), "--problems", str(problems)]) == 130
    assert len(calls) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5"]  # no problems.h5, no partial file


@pytest.mark.parametrize(
    ("arguments", "fragments"),
    [
        (["reference", "page"], ["--package DIR", "-o PAGE.md"]),  # before: internal error (TypeError)
        (["reference", "page", "--package", "{dir}"], ["--package DIR", "-o PAGE.md"]),
        (["reference", "page", "--package", "{dir}", "-o", "{dir}"], ["is a directory", "the page"]),
        (["reference", "build", "-o", "{file}"], ["is a file; expected the package folder"]),
        (["compare", "puncture", "{file}", "-o", "{file}/figure.png"], ["is a file, not a folder"]),
        (["run", "{dir}", "-o", "{dir}/run.h5"], ["is a directory; expected a scene file"]),
        # before: the strategy table ran, then an internal error (MemoryError)
        (["bench", "--cells", "2000"], ["--cells 2000", "in [1, 256]"]),
        (["bench", "--cells", "8", "256"], ["--cells = 256", "tetrahedra need about"]),
    ],
)
def test_missing_options_and_wrong_kinds_of_path_are_named(tmp_path, capsys, arguments, fragments):
    afile = tmp_path / "a.csv"
    afile.write_text("quantity,x,value\n")
    folder = tmp_path / "folder"
    folder.mkdir()
    code = main([a.format(dir=folder, file=afile) for a in arguments])
    error = capsys.readouterr().err
    assert code == EXIT_INPUT, error
    for fragment in fragments:
        assert fragment in error
    assert "internal error" not in error and "Errno" not in error
    assert list(folder.iterdir()) == []
