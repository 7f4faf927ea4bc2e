"""What the commands print: tables whose columns hold their values, and the run's tqdm progress."""

from __future__ import annotations

from refsim.cli import main
from refsim.fem.bench import format_rows


def test_bench_table_columns_hold_their_widest_value():
    rows = [
        {"strategy": "refreshed_first_order", "total_ms": 12.345678, "pcg_iterations": 3},
        {"strategy": "exact", "total_ms": 1234567.0, "pcg_iterations": 12},
    ]
    heading, *lines = format_rows(rows).splitlines()
    assert {len(line) for line in lines} == {len(heading)}  # every row as wide as the heading
    # Right-aligned: each value ends where its heading ends, so the columns never run into each other.
    ends = [heading.index(key) + len(key) for key in ("strategy", "total_ms", "pcg_iterations")]
    for line, expected in zip(lines, (["refreshed_first_order", "12.35", "3"], ["exact", "1.235e+06", "12"]),
                              strict=True):  # fmt: skip
        assert line.split() == expected
        assert [
            line.index(value, (ends[i - 1] if i else 0)) + len(value) for i, value in enumerate(expected)
        ] == ends


def test_run_shows_a_tqdm_progress_bar(tmp_path, capsys):
    assert main(["run", "cube", "-o", str(tmp_path / "r.h5"), "--set", "mesh.cells=[2, 2, 2]", "--set",
                 "time.duration=0.05"]) == 0  # fmt: skip
    error = capsys.readouterr().err
    assert "5/5" in error and "step" in error and "100%" in error
