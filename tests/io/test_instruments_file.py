"""A results file of several instruments (refsim/scenes/two_needles.toml, coarse, 1 s: both needles puncture):
the first instrument at the one-needle paths, the holder under instruments/holder/, the rows' instrument; the
reader's per-instrument views; `refsim render` and `refsim plot` draw every needle."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from refsim.io import read_results
from refsim.io.driver import run_scene
from refsim.scene import load_scene


@pytest.fixture(scope="module")
def two_file(tmp_path_factory):
    scene = load_scene("two_needles", ["mesh.cells=[4, 4, 4]", "time.duration=1.0"])
    records = []
    path = tmp_path_factory.mktemp("instruments") / "two.h5"
    summary = run_scene(
        scene, path, on_step=lambda state, record: records.append(record), handle_signals=False
    )
    assert summary.complete
    return path, records, summary


def test_the_layout_of_two_instruments(two_file):
    path, records, _ = two_file
    with h5py.File(path, "r") as handle:
        assert json.loads(handle.attrs["instruments"]) == [
            {"name": "cutter", "location": ""},
            {"name": "holder", "location": "instruments/holder"},
        ]
        assert handle["instruments/holder/steps/needle_force"].shape == (len(records), 3)
        assert handle["instruments/holder/steps/needle_force"].attrs["units"] == "N"
        assert "instruments/cutter" not in handle  # the first instrument is at the one-needle paths
        assert handle["constraints/instrument"].shape == handle["constraints/forces"].shape


def test_writer_and_reader_round_trip_every_instrument(two_file):
    path, records, _ = two_file
    results = read_results(path)
    assert results.instrument_names == ("cutter", "holder")
    views = results.instruments
    for index, view in enumerate(views):
        assert view.instrument_names == (results.instrument_names[index],)
        parts = [record.instruments[index] for record in records]
        np.testing.assert_array_equal(view.needle_force, np.stack([p.needle_force for p in parts]))
        np.testing.assert_array_equal(view.needle_positions, np.stack([p.needle_positions for p in parts]))
        np.testing.assert_array_equal(view.base_position, np.stack([p.base_position for p in parts]))
        assert [view.phase_names[code] for code in view.phase] == [p.phase for p in parts]
        assert [(e.step, e.name) for e in view.events] == [
            (record.step, event.name)
            for record, part in zip(records, parts, strict=True)
            for event in part.events
        ]
        # Each needle at t = 0 starts at its own trajectory's first base position.
        np.testing.assert_array_equal(view.needle_rest_nodes[0], view.trajectory_samples[0, 1:4])
    np.testing.assert_array_equal(
        results.constraint_instrument, np.concatenate([r.row_instrument for r in records])
    )
    assert views[1].trajectory_samples[0, 1] != views[0].trajectory_samples[0, 1]  # entries 4 cm apart
    assert [e.name for e in views[1].events] == ["puncture"]
    with pytest.raises(KeyError, match="no instrument 'nobody'"):
        results.instrument("nobody")


def test_the_summary_speaks_per_instrument(two_file):
    _, _, summary = two_file
    text = summary.format()
    assert "cutter: puncture" in text and "holder: puncture" in text
    assert "peak force on cutter's needle" in text and "peak force on holder's needle" in text


def test_render_and_plot_draw_every_instrument(two_file, tmp_path):
    from refsim.cli import main

    path, _, _ = two_file
    picture, plot = tmp_path / "two.png", tmp_path / "two_force.png"
    assert main(["render", str(path), "-o", str(picture)]) == 0
    assert main(["plot", str(path), "-o", str(plot)]) == 0
    assert picture.stat().st_size > 0 and plot.stat().st_size > 0
    from refsim.viz.plots import force_figure

    figure = force_figure(read_results(path))
    titles = [sub.get_suptitle() for sub in figure.subfigs]
    assert titles == [
        "two_needles: force on cutter's needle base",
        "two_needles: force on holder's needle base",
    ]
