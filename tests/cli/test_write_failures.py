"""A full disk while writing a figure or an export (issue 25): exit 3, the path named, no partial file left;
and the smallest time step the positions resolve."""

from __future__ import annotations

import errno

import pytest

from refsim.cli import main

SMALL = ["--set", "mesh.cells=[3, 3, 3]", "--set", "time.duration=0.05", "-q"]


def _fill_then_fail(path, *_args, **_kwargs):
    """What a full disk does to a writer: part of the file, then ENOSPC."""
    from pathlib import Path

    Path(path).write_bytes(b"\x89PNG partial")
    raise OSError(errno.ENOSPC, "No space left on device")


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    path = tmp_path_factory.mktemp("run") / "run.h5"
    assert main(["run", "cube", "-o", str(path), *SMALL]) == 0
    return path


def test_a_figure_on_a_full_disk_is_named_and_removed(tmp_path, capsys, monkeypatch):
    import refsim.viz

    monkeypatch.setattr(refsim.viz, "render_result", lambda result, figure, **kw: _fill_then_fail(figure))
    figure = tmp_path / "picture.png"
    code = main(["run", "cube", "-o", str(tmp_path / "run.h5"), "--figure", str(figure), *SMALL])
    assert code == 3
    error = capsys.readouterr().err
    assert f"{figure}: writing the figure failed (No space left on device)" in error
    assert not figure.exists() and (tmp_path / "run.h5").is_file()


def test_an_export_on_a_full_disk_is_named_and_removed(tmp_path, capsys, monkeypatch, results):
    import refsim.io.export

    monkeypatch.setattr(refsim.io.export, "export_force_csv", lambda result, path: _fill_then_fail(path))
    csv = tmp_path / "force.csv"
    assert main(["export", str(results), "--csv", str(csv)]) == 3
    assert f"{csv}: writing the force CSV failed (No space left on device)" in capsys.readouterr().err
    assert not csv.exists()


def test_a_time_step_below_round_off_is_refused(tmp_path, capsys):
    """dt = 1e-300 s: 1e-302 m of tip travel per step, below 1000 float64 epsilons of the cube scene's 0.74 m
    coordinates (1.6e-13 m); before, a ZeroDivisionError at step 1, exit 3."""
    code = main(
        [
            "run",
            "cube",
            "-o",
            str(tmp_path / "run.h5"),
            "--set",
            "time.dt=1e-300",
            "--set",
            "time.duration=1e-300",
        ]
    )
    assert code == 2
    error = capsys.readouterr().err
    assert "time.dt = 1e-300 s" in error and "use time.dt >= 1.6" in error
    assert not (tmp_path / "run.h5").exists()


def test_a_mesh_that_does_not_fit_in_memory_is_refused_before_it_is_generated(tmp_path, capsys, monkeypatch):
    """mesh.cells = 256³ (the documented maximum: 100,663,296 tets) needs 1.2 TiB at 13,000 bytes per tet;
    with 2 GiB available it is refused before box_mesh allocates anything (before: a MemoryError)."""
    import refsim.scene.build as build

    monkeypatch.setattr(build, "available_memory", lambda: 2 * 2**30)
    monkeypatch.setattr(build, "box_mesh", lambda **kw: pytest.fail("the mesh was generated"))
    code = main(["run", "cube", "-o", str(tmp_path / "run.h5"), "--set", "mesh.cells=[256, 256, 256]"])
    assert code == 2
    error = capsys.readouterr().err
    assert "mesh.cells = [256, 256, 256]: 100663296 tetrahedra need about 1.22e+03 GiB" in error
    assert "at most about 165191 tetrahedra fit" in error


def test_an_insertion_spacing_too_small_for_the_memory_is_refused(tmp_path, capsys, monkeypatch):
    """d_i = 1e-7 m on the cube: the tip's path over the run is 0.019 m (17 mm deep from 2 mm above), so up
    to 1.9e5 points, 5.7e5 rows, a dense W of 8 × (5.7e5)² bytes = 2.4e3 GiB; with 2 GiB available the
    smallest d_i is 3 × 0.019 / (√(2 GiB / 8) − 3) = 3.5e-6 m."""
    import refsim.scene.build as build

    monkeypatch.setattr(build, "available_memory", lambda: 2 * 2**30)
    code = main(["run", "cube", "-o", str(tmp_path / "run.h5"), "--set", "insertion.spacing=1e-7"])
    assert code == 2
    error = capsys.readouterr().err
    assert "insertion.spacing = 1e-07 m (d_i): up to 1.9e+05 insertion points along the 0.019 m" in error
    assert "needs 2.42e+03 GiB; 2 GiB are available: use insertion.spacing >= 3.48e-06 m" in error


def test_a_cut_point_spacing_too_small_for_the_memory_is_refused(tmp_path, capsys, monkeypatch):
    """d_c = 1e-7 m on cube_cut: every d_c of inserted needle adds a sliding and a front row (no cut-face
    friction), so the rows of the cut (2 per d_c) outnumber the insertion rows (3 per d_i = 0.5 mm) and
    W = 8 × rows² bytes is beyond 2 GiB: refused naming cutting.point_spacing. The smallest d_c given is the
    one whose rows, with the insertion rows, fill exactly √(2 GiB / 8) rows."""
    import numpy as np

    import refsim.scene.build as build

    free = 2 * 2**30
    monkeypatch.setattr(build, "available_memory", lambda: free)
    code = main(["run", "cube_cut", "-o", str(tmp_path / "run.h5"), "--set", "cutting.point_spacing=1e-7"])
    assert code == 2
    error = capsys.readouterr().err
    assert "cutting.point_spacing = 1e-07 m (d_c): up to " in error and "cut samples along the " in error
    inserted = float(error.split("cut samples along the ")[1].split(" m")[0])
    smallest = float(error.split("use cutting.point_spacing >= ")[1].split(" m")[0])
    insertion_rows = 3 * (inserted / 5e-4 + 1)
    cut_rows = 2 * (inserted / smallest + 1)
    assert insertion_rows + cut_rows == pytest.approx(np.sqrt(free / 8), rel=2e-3)  # 3 printed digits
    assert not (tmp_path / "run.h5").exists()
