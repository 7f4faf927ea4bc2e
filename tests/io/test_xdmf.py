"""The XDMF sidecar read back with meshio and with VTK's XDMF reader (ParaView's): every geometry and point
array it points at equals the results file's data."""

from __future__ import annotations

import h5py
import meshio
import numpy as np
import pytest

from refsim.io import read_results
from refsim.io.xdmf import write_xdmf, xdmf_path


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


def _record_at(results, step):
    """Index of the tissue record shown at ``step`` (the last one at or before it), -1 for rest."""
    return int(np.searchsorted(results.tissue_steps, step, side="right")) - 1


def test_tissue_over_time_equals_the_results(cut_run):
    """meshio reads the rest mesh once, then the point data of every time: rest + displacement is the
    recorded tissue (the last record at or before each step), fixed flags the clamped nodes."""
    results = read_results(cut_run)
    with meshio.xdmf.TimeSeriesReader(xdmf_path(cut_run)) as reader:
        points, cells = reader.read_points_cells()
        assert np.array_equal(points, results.rest_positions)
        assert cells[0].type == "tetra" and np.array_equal(cells[0].data, results.tets)
        assert reader.num_steps == results.step_count + 1
        for k in (0, 1, 24, 25, 26, reader.num_steps - 1):
            time, point_data, _ = reader.read_data(k)
            assert time == (0.0 if k == 0 else results.time[k - 1])
            record = _record_at(results, 0 if k == 0 else results.step[k - 1])
            expected = results.rest_positions if record < 0 else results.tissue_positions[record]
            assert np.array_equal(points + point_data["displacement"], expected)
            geometry = reader._read_data_item(_item(reader.collection[k], "Geometry"))
            assert np.array_equal(geometry, expected)
            assert np.array_equal(np.flatnonzero(point_data["fixed"]), np.sort(results.fixed_nodes))


def test_vtk_reads_sorted_times_and_the_deformation_at_a_step(cut_run):
    """VTK's own XDMF reader (ParaView's "XDMF Reader"): the times are [0, t_1, ..., t_s], sorted; at a
    recorded step the tissue's points and displacement equal the HDF5's, the needle equals the step's and
    the nodal constraint forces sum to minus the force on the needle (Newton's third law)."""
    xdmf2 = pytest.importorskip("vtkmodules.vtkIOXdmf2")
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkCommonDataModel import vtkCompositeDataSet
    from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline

    results = read_results(cut_run)
    reader = xdmf2.vtkXdmfReader()
    reader.SetFileName(str(xdmf_path(cut_run)))
    reader.UpdateInformation()
    times = np.array(reader.GetOutputInformation(0).Get(vtkStreamingDemandDrivenPipeline.TIME_STEPS()))
    np.testing.assert_array_equal(times, np.concatenate([[0.0], results.time]))
    cut_steps = results.step[np.isin(results.step, results.tissue_steps)]
    step = int(cut_steps[-1])  # the last recorded step, after the cut started
    index = int(np.flatnonzero(results.step == step)[0])
    reader.UpdateTimeStep(results.time[index])
    blocks = reader.GetOutputDataObject(0)
    named = {
        blocks.GetMetaData(i).Get(vtkCompositeDataSet.NAME()): blocks.GetBlock(i)
        for i in range(blocks.GetNumberOfBlocks())
    }
    tissue, needle, cut = named["tissue"], named["needle"], named["cut"]
    record = _record_at(results, step)
    positions = results.tissue_positions[record]
    np.testing.assert_array_equal(vtk_to_numpy(tissue.GetPoints().GetData()), positions)
    displacement = vtk_to_numpy(tissue.GetPointData().GetArray("displacement"))
    np.testing.assert_array_equal(displacement, positions - results.rest_positions)
    force = vtk_to_numpy(tissue.GetPointData().GetArray("constraint_force"))
    scale = np.abs(results.constraints_at(step).forces).sum()
    np.testing.assert_allclose(force.sum(axis=0), -results.needle_force[index], rtol=0, atol=1e-12 * scale)
    np.testing.assert_array_equal(vtk_to_numpy(needle.GetPoints().GetData()), results.needle_positions[index])
    assert cut.GetNumberOfCells() == np.count_nonzero(results.cut.triangle_step <= step) > 0
    reader.UpdateTimeStep(0.0)
    rest = reader.GetOutputDataObject(0)
    named = {rest.GetMetaData(i).Get(vtkCompositeDataSet.NAME()): rest.GetBlock(i) for i in range(3)}
    np.testing.assert_array_equal(
        vtk_to_numpy(named["needle"].GetPoints().GetData()), results.needle_rest_nodes
    )
    assert named["cut"] is None  # nothing is cut at rest


def test_needle_and_cut_equal_the_results(cut_run):
    results = read_results(cut_run)
    cut = results.cut
    assert cut is not None and cut.triangles.shape[0] > 0
    with meshio.xdmf.TimeSeriesReader(xdmf_path(cut_run)) as reader:
        needle = _collection(reader, "needle")
        assert len(needle) == results.step_count + 1
        for k in (1, results.step_count // 2, results.step_count):
            assert float(needle[k].find("Time").get("Value")) == results.time[k - 1]
            assert np.array_equal(
                reader._read_data_item(_item(needle[k], "Geometry")), results.needle_positions[k - 1]
            )
            assert np.array_equal(
                reader._read_data_item(_item(needle[k], "Topology")),
                np.arange(results.needle_positions.shape[1])[None],
            )
        grids = _collection(reader, "cut")
        cut_steps = [s for s in results.step if np.any(cut.triangle_step <= s)]
        assert len(grids) == len(cut_steps) > 0
        for grid, step in zip(grids, cut_steps, strict=True):
            record = _record_at(results, step)
            positions = results.rest_positions if record < 0 else results.tissue_positions[record]
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


def _xdmf_group_keys(results_path):
    """The schema key (path with NNNNNNN, for each instrument: "" the first) of every dataset of the xdmf/
    group, checked against its spec's units and dtype: {(instrument name or "", key)}."""
    import re

    from refsim.io import schema

    specs = {spec.path: spec for spec in schema.XDMF.values()}
    further = f"{schema.XDMF_GROUP}/{schema.INSTRUMENTS_GROUP}/"
    seen = set()

    def check(name, item):
        if not isinstance(item, h5py.Dataset):
            return
        key, owner = re.sub(r"/\d{7}$", "/NNNNNNN", name), ""
        if key.startswith(further):
            owner, rest = key[len(further) :].split("/", 1)
            key = f"{schema.XDMF_GROUP}/{rest}"
            assert key in schema.XDMF_INSTRUMENT_DATASETS, f"{name} is not in schema.XDMF_INSTRUMENT_DATASETS"
        assert key in specs, f"{name} is not in schema.XDMF"
        assert item.attrs["units"] == specs[key].unit, name
        assert item.dtype == np.dtype(specs[key].dtype), name
        seen.add((owner, key))

    with h5py.File(results_path, "r") as handle:
        handle[schema.XDMF_GROUP].visititems(lambda name, item: check(f"{schema.XDMF_GROUP}/{name}", item))
    return seen


def test_xdmf_group_is_the_schemas(cut_run):
    """Every dataset of the xdmf/ group is one of refsim.io.schema.XDMF (its step number as NNNNNNN), with the
    schema's units and dtype, and a cut run has every one of them (a one-needle file: none under
    xdmf/instruments/)."""
    from refsim.io import schema

    assert _xdmf_group_keys(cut_run) == {("", spec.path) for spec in schema.XDMF.values()}


def _referenced_items(results_path):
    """Every DataItem of the sidecar: (its HDF5 path, its Dimensions, DataType, Precision)."""
    from xml.etree import ElementTree as ET

    root = ET.parse(xdmf_path(results_path)).getroot()
    items = []
    for item in root.iter("DataItem"):
        file_name, path = item.text.split(":", 1)
        assert file_name == results_path.name  # relative to the sidecar, in the same folder
        dims = tuple(int(d) for d in item.get("Dimensions").split())
        items.append((path, dims, item.get("DataType"), int(item.get("Precision"))))
    return items


@pytest.mark.parametrize("run", ["cut_run", "two_needle_run"])
def test_every_referenced_path_exists_with_its_declared_shape(run, request):
    results_path = request.getfixturevalue(run)
    items = _referenced_items(results_path)
    assert items
    with h5py.File(results_path, "r") as handle:
        for path, dims, number, precision in items:
            assert path in handle, path
            dataset = handle[path]
            assert dataset.shape == dims, path
            assert dataset.dtype.itemsize == precision, path
            assert {"Float": "f", "Int": "i", "Char": "i"}[number] == dataset.dtype.kind, path


def test_one_needle_collection_per_instrument(two_needle_run):
    """Each instrument has its own temporal collection, named by it and in the scene's order, before the
    tissue (last, for meshio); at every time its polyline is the instrument's needle (rest nodes at t = 0,
    steps/needle_positions of that instrument after); its datasets are the schema's, a further one's under
    xdmf/instruments/<name>/."""
    from refsim.io import schema

    results = read_results(two_needle_run)
    names = results.instrument_names
    assert names == ("cutter", "holder")
    with meshio.xdmf.TimeSeriesReader(xdmf_path(two_needle_run)) as reader:
        order = [grid.get("Name") for grid in reader.domain]
        assert order == [*names, "tissue"]  # nothing cut within 1.2 s
        for name in names:
            own = results.instrument(name)
            assert own.phase_names[own.phase[-1]] == "insertion"  # both punctured within 1.2 s
            grids = _collection(reader, name)
            assert len(grids) == results.step_count + 1
            k = own.needle_rest_nodes.shape[0]
            assert np.array_equal(reader._read_data_item(_item(grids[0], "Geometry")), own.needle_rest_nodes)
            for index in (1, results.step_count // 2, results.step_count):
                grid = grids[index]
                assert grid.get("Name") == f"{name}_{int(results.step[index - 1]):07d}"
                assert float(grid.find("Time").get("Value")) == results.time[index - 1]
                positions = reader._read_data_item(_item(grid, "Geometry"))
                assert np.array_equal(positions, own.needle_positions[index - 1])
                assert np.array_equal(reader._read_data_item(_item(grid, "Topology")), np.arange(k)[None])
        first, second = (_item(_collection(reader, name)[-1], "Geometry") for name in names)
        assert not np.array_equal(reader._read_data_item(first), reader._read_data_item(second))
    keys = _xdmf_group_keys(two_needle_run)
    instrument_keys = set(schema.XDMF_INSTRUMENT_DATASETS)
    assert {key for owner, key in keys if owner == "holder"} == instrument_keys
    assert {owner for owner, _ in keys} == {"", "holder"}
    assert instrument_keys <= {key for owner, key in keys if owner == ""}  # the first's at one-needle paths


def test_vtk_reads_every_needle(two_needle_run):
    """VTK's XDMF reader (ParaView's) shows one block per instrument, named by it, at a step: its points are
    that instrument's needle."""
    xdmf2 = pytest.importorskip("vtkmodules.vtkIOXdmf2")
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkCommonDataModel import vtkCompositeDataSet

    results = read_results(two_needle_run)
    reader = xdmf2.vtkXdmfReader()
    reader.SetFileName(str(xdmf_path(two_needle_run)))
    reader.UpdateInformation()
    index = results.step_count - 1
    reader.UpdateTimeStep(results.time[index])
    blocks = reader.GetOutputDataObject(0)
    named = {
        blocks.GetMetaData(i).Get(vtkCompositeDataSet.NAME()): blocks.GetBlock(i)
        for i in range(blocks.GetNumberOfBlocks())
    }
    assert set(named) == {*results.instrument_names, "tissue"}
    for name in results.instrument_names:
        points = vtk_to_numpy(named[name].GetPoints().GetData())
        np.testing.assert_array_equal(points, results.instrument(name).needle_positions[index])


def test_constraint_force_is_every_instruments(two_needle_run):
    """At a recorded step the tissue's nodal constraint forces sum to minus the sum of every instrument's
    force on its needle (Newton's third law; the barycentric weights of each row sum to 1, so only
    round-off of the order of 1e-12 of the rows' total |lambda| separates the two)."""
    results = read_results(two_needle_run)
    with meshio.xdmf.TimeSeriesReader(xdmf_path(two_needle_run)) as reader:
        reader.read_points_cells()
        step = int(results.tissue_steps[-1])
        index = int(np.flatnonzero(results.step == step)[0])
        _, point_data, _ = reader.read_data(index + 1)  # time 0 is rest
    forces = [results.instrument(name).needle_force[index] for name in results.instrument_names]
    assert all(np.linalg.norm(force) > 0 for force in forces)  # both needles press on the tissue
    scale = np.abs(results.constraints_at(step).forces).sum()
    np.testing.assert_allclose(
        point_data["constraint_force"].sum(axis=0), -np.sum(forces, axis=0), rtol=0, atol=1e-12 * scale
    )


def test_one_needle_sidecar_keeps_its_names(cut_run):
    """A one-needle file's sidecar is the same as before several instruments: collections needle, cut and
    tissue in this order, the needle's grids named needle_NNNNNNN and its datasets at xdmf/needle/."""
    from xml.etree import ElementTree as ET

    results = read_results(cut_run)
    assert results.instrument_names == ("needle",)
    domain = ET.parse(xdmf_path(cut_run)).getroot().find("Domain")
    assert [grid.get("Name") for grid in domain] == ["needle", "cut", "tissue"]
    needle = list(domain[0])
    assert [grid.get("Name") for grid in needle] == [f"needle_{s:07d}" for s in [0, *results.step]]
    assert _item(needle[0], "Topology").text == f"{cut_run.name}:/xdmf/needle/polyline"
    assert _item(needle[0], "Geometry").text == f"{cut_run.name}:/scene/needle/rest_nodes"
    step = int(results.step[-1])
    assert _item(needle[-1], "Geometry").text == f"{cut_run.name}:/xdmf/needle/positions/{step:07d}"
