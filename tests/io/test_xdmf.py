"""The XDMF sidecar read back with meshio: every geometry it points at equals the results file's data."""

from __future__ import annotations

import h5py
import meshio
import numpy as np
import pytest

from refsim.cli import main
from refsim.io import read_results
from refsim.io.xdmf import write_xdmf, xdmf_path


@pytest.fixture(scope="module")
def cut_run(tmp_path_factory):
    """cube_cut on 4 cells per axis, written by `refsim run` (which writes the sidecar at the end)."""
    path = tmp_path_factory.mktemp("xdmf") / "cut.h5"
    code = main(
        [
            "run",
            "cube_cut",
            "-o",
            str(path),
            "-q",
            "--set",
            "mesh.cells=[4, 4, 4]",
            "--set",
            "output.tissue_every=25",
        ]
    )
    assert code == 0
    return path


def _collection(reader, name):
    for grid in reader.domain:
        if grid.get("Name") == name:
            return list(grid)
    raise AssertionError(f"no collection {name}")


def _item(grid, tag):
    return grid.find(f"{tag}/DataItem")


def test_run_writes_the_sidecar(cut_run):
    assert xdmf_path(cut_run).is_file()
    with h5py.File(cut_run, "r") as handle:
        assert handle["xdmf/tissue/positions"][next(iter(handle["xdmf/tissue/positions"]))].is_virtual


def test_tissue_over_time_equals_the_results(cut_run):
    results = read_results(cut_run)
    with meshio.xdmf.TimeSeriesReader(xdmf_path(cut_run)) as reader:
        points, cells = reader.read_points_cells()
        assert np.array_equal(points, results.rest_positions)
        assert cells[0].type == "tetra" and np.array_equal(cells[0].data, results.tets)
        assert reader.num_steps == results.tissue_steps.size + 1
        for k in range(reader.num_steps):
            time, _, _ = reader.read_data(k)
            geometry = reader._read_data_item(_item(reader.collection[k], "Geometry"))
            expected = results.rest_positions if k == 0 else results.tissue_positions[k - 1]
            assert time == (0.0 if k == 0 else results.tissue_times[k - 1])
            assert np.array_equal(geometry, expected)


def test_needle_and_cut_equal_the_results(cut_run):
    results = read_results(cut_run)
    cut = results.cut
    assert cut is not None and cut.triangles.shape[0] > 0
    with meshio.xdmf.TimeSeriesReader(xdmf_path(cut_run)) as reader:
        needle = _collection(reader, "needle")
        assert len(needle) == results.step_count
        for k in (0, results.step_count // 2, results.step_count - 1):
            assert float(needle[k].find("Time").get("Value")) == results.time[k]
            assert np.array_equal(
                reader._read_data_item(_item(needle[k], "Geometry")), results.needle_positions[k]
            )
            assert np.array_equal(
                reader._read_data_item(_item(needle[k], "Topology")),
                np.arange(results.needle_positions.shape[1])[None],
            )
        grids = _collection(reader, "cut")
        cut_steps = [s for s in results.tissue_steps if np.any(cut.triangle_step <= s)]
        assert len(grids) == len(cut_steps) > 0
        for grid, step in zip(grids, cut_steps, strict=True):
            positions = results.tissue_positions[int(np.flatnonzero(results.tissue_steps == step)[0])]
            # equation 4: a cut point follows its tet's nodes by its barycentric coordinates
            deformed = np.einsum("pk,pki->pi", cut.barycentric, positions[results.tets[cut.tet_indices]])
            assert np.allclose(reader._read_data_item(_item(grid, "Geometry")), deformed, rtol=0, atol=1e-15)
            triangles = reader._read_data_item(_item(grid, "Topology"))
            assert np.array_equal(triangles, cut.triangles[cut.triangle_step <= step])


def test_rewriting_replaces_the_views(cut_run):
    first = xdmf_path(cut_run).read_text()
    write_xdmf(cut_run)
    assert xdmf_path(cut_run).read_text() == first
    assert read_results(cut_run).complete  # the results are untouched


def test_sidecar_must_sit_beside_the_results(cut_run, tmp_path):
    with pytest.raises(ValueError, match="must be in the folder"):
        write_xdmf(cut_run, tmp_path / "elsewhere.xdmf")


def test_xdmf_group_is_the_schemas(cut_run):
    """Every dataset of the xdmf/ group is one of refsim.io.schema.XDMF (its step number as NNNNNNN), with the
    schema's units and dtype, and a cut run has every one of them."""
    import re

    from refsim.io import schema

    seen = set()

    def check(name, item):
        if isinstance(item, h5py.Dataset):
            key = re.sub(r"/\d{7}$", "/NNNNNNN", name)
            assert key in {spec.path for spec in schema.XDMF.values()}, f"{name} is not in schema.XDMF"
            spec = next(spec for spec in schema.XDMF.values() if spec.path == key)
            assert item.attrs["units"] == spec.unit, name
            assert item.dtype == np.dtype(spec.dtype), name
            seen.add(key)

    with h5py.File(cut_run, "r") as handle:
        handle[schema.XDMF_GROUP].visititems(lambda name, item: check(f"{schema.XDMF_GROUP}/{name}", item))
    assert seen == {spec.path for spec in schema.XDMF.values()}
