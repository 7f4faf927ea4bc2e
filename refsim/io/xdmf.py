"""An XDMF 3 sidecar beside a results file, so that ParaView opens it directly (File > Open > RESULT.xdmf,
reader "XDMF Reader" or "Xdmf3ReaderT").

The sidecar has three temporal collections in one domain:

- ``needle``: the needle centreline as a polyline at every step (``steps/needle_positions``);
- ``cut`` (when the run cut): the cut surface triangles at every recorded tissue step, its rest points mapped
  to the deformed tissue by their tets and barycentric coordinates (equation 4 of the paper);
- ``tissue``: the tetrahedra at rest (time 0) and at every recorded tissue step (``tissue/positions``); the
  displacement is ParaView's Calculator away (``coords`` minus the first step's), not stored twice.

The heavy data is not copied: each per-step array is an HDF5 virtual dataset (a view, no data) in the group
``xdmf/`` of the results file that maps onto one entry of the per-step dataset, and the XDMF points at it as
``RESULT.h5:/xdmf/...``. Only what is derived, the deformed cut points (a few hundred points per recorded
step), is stored in ``xdmf/``. The tissue collection comes last, so ``meshio.xdmf.TimeSeriesReader`` reads it.
"""

from __future__ import annotations

from pathlib import Path
from xml.etree import ElementTree as ET

import numpy as np

from refsim.io.schema import (
    XDMF,
    XDMF_GROUP,
    xdmf_path_of,
)  # XDMF_GROUP: the group of the views (re-exported)

__all__ = ["XDMF_GROUP", "write_xdmf", "xdmf_path"]


def xdmf_path(results_path) -> Path:
    """The sidecar's path: the results file with the suffix .xdmf."""
    return Path(results_path).with_suffix(".xdmf")


def _view(handle, name: str, source: str, index: int | slice, entry_shape: tuple, dtype) -> str:
    """A virtual dataset ``name`` of the results file viewing ``source[index]`` (no copy), with the ``units``
    of its source; returns its path."""
    import h5py

    layout = h5py.VirtualLayout(shape=entry_shape, dtype=dtype)
    full = handle[source].shape
    layout[...] = h5py.VirtualSource(".", source, shape=full)[index]
    view = handle.create_virtual_dataset(name, layout)
    view.attrs["units"] = handle[source].attrs.get("units", "1")
    return "/" + name


def _data_item(parent, file_name: str, path: str, shape: tuple, dtype) -> ET.Element:
    kind = np.dtype(dtype)
    number = "Float" if kind.kind == "f" else "Int"
    item = ET.SubElement(
        parent,
        "DataItem",
        DataType=number,
        Dimensions=" ".join(str(s) for s in shape),
        Format="HDF",
        Precision=str(kind.itemsize),
    )
    item.text = f"{file_name}:{path}"
    return item


def _grid(collection, name: str, time: float) -> ET.Element:
    grid = ET.SubElement(collection, "Grid", Name=name, GridType="Uniform")
    ET.SubElement(grid, "Time", Value=repr(float(time)))
    return grid


def _topology(grid, kind: str, count: int, file_name: str, path: str, shape: tuple, **extra) -> None:
    topology = ET.SubElement(grid, "Topology", TopologyType=kind, NumberOfElements=str(count), **extra)
    _data_item(topology, file_name, path, shape, np.int64)


def _geometry(grid, file_name: str, path: str, shape: tuple) -> None:
    geometry = ET.SubElement(grid, "Geometry", GeometryType="XYZ")
    _data_item(geometry, file_name, path, shape, np.float64)


def write_xdmf(results_path, output=None) -> Path:
    """Write the XDMF sidecar of a results file (and its views in the file's ``xdmf/`` group).

    Parameters
    ----------
    results_path : The results file (.h5); it is opened for appending (its ``xdmf/`` group is replaced).
    output : The sidecar path; :func:`xdmf_path` (results_path) by default. It must be in the results file's
        folder (the XDMF names the HDF5 file relative to itself).

    Returns
    -------
    The sidecar's path.
    """
    import h5py

    from refsim.io import read_results, schema

    results_path = Path(results_path)
    results = read_results(results_path)  # validates the file; counts of completed steps
    output = xdmf_path(results_path) if output is None else Path(output)
    if output.resolve().parent != results_path.resolve().parent:
        raise ValueError(f"{output}: the XDMF sidecar must be in the folder of {results_path}")
    file_name = results_path.name
    steps = results.step_count
    nodes, tets = results.rest_positions.shape[0], results.tets.shape[0]
    needle_nodes = results.needle_positions.shape[1] if steps else results.needle_rest_nodes.shape[0]

    root = ET.Element("Xdmf", Version="3.0")
    domain = ET.SubElement(root, "Domain")
    with h5py.File(results_path, "a") as handle:
        if XDMF_GROUP in handle:
            del handle[XDMF_GROUP]
        group = handle.create_group(XDMF_GROUP)
        group.attrs["description"] = (
            "views (HDF5 virtual datasets, no data) and derived arrays of the XDMF "
            "sidecar; rewritten by refsim.io.xdmf.write_xdmf; its datasets are listed in "
            "refsim.io.schema.XDMF and docs/results.md"
        )
        # needle: a polyline per step
        needle = ET.SubElement(
            domain, "Grid", Name="needle", GridType="Collection", CollectionType="Temporal"
        )
        connectivity = handle.create_dataset(
            XDMF["needle/polyline"].path, data=np.arange(needle_nodes, dtype=np.int64)[None]
        )
        connectivity.attrs["units"] = XDMF["needle/polyline"].unit
        for index in range(steps):
            step = int(results.step[index])
            path = _view(
                handle,
                xdmf_path_of(XDMF["needle/positions/NNNNNNN"], step),
                schema.STEPS["needle_positions"].path,
                index,
                (needle_nodes, 3),
                np.float64,
            )
            grid = _grid(needle, f"needle_{step:07d}", results.time[index])
            _topology(
                grid,
                "Polyline",
                1,
                file_name,
                connectivity.name,
                (1, needle_nodes),
                NodesPerElement=str(needle_nodes),
            )
            _geometry(grid, file_name, path, (needle_nodes, 3))
        # cut surface at the recorded tissue steps
        cut = results.cut
        if cut is not None and cut.triangles.shape[0] and cut.tet_indices is not None:
            collection = ET.SubElement(
                domain, "Grid", Name="cut", GridType="Collection", CollectionType="Temporal"
            )
            corners = results.tets[cut.tet_indices]  # (p, 4)
            point_count = cut.points.shape[
                0
            ]  # every point: later ones are unused until their triangles exist
            in_order = bool(np.all(np.diff(cut.triangle_step) >= 0))
            for index, step in enumerate(results.tissue_steps):
                existing = cut.triangle_step <= step
                triangle_count = int(np.count_nonzero(existing))
                if triangle_count == 0:
                    continue
                positions = results.tissue_positions[index]
                deformed = np.einsum("pk,pki->pi", cut.barycentric, positions[corners])
                points = handle.create_dataset(xdmf_path_of(XDMF["cut/points/NNNNNNN"], step), data=deformed)
                points.attrs["units"] = XDMF["cut/points/NNNNNNN"].unit
                name = xdmf_path_of(XDMF["cut/triangles/NNNNNNN"], step)
                if in_order:  # the triangles of the step are a prefix: a view
                    triangles = _view(
                        handle,
                        name,
                        schema.CUT["triangles"].path,
                        slice(0, triangle_count),
                        (triangle_count, 3),
                        np.int64,
                    )
                else:
                    copy = handle.create_dataset(name, data=cut.triangles[existing])
                    copy.attrs["units"] = XDMF["cut/triangles/NNNNNNN"].unit
                    triangles = copy.name
                grid = _grid(collection, f"cut_{int(step):07d}", results.tissue_times[index])
                _topology(grid, "Triangle", triangle_count, file_name, triangles, (triangle_count, 3))
                _geometry(grid, file_name, points.name, (point_count, 3))
        # tissue at the recorded steps (last: meshio's TimeSeriesReader reads the last temporal collection)
        tissue = ET.SubElement(
            domain, "Grid", Name="tissue", GridType="Collection", CollectionType="Temporal"
        )
        records = [(0, 0.0, None)] + [
            (int(s), float(t), i)
            for i, (s, t) in enumerate(zip(results.tissue_steps, results.tissue_times, strict=True))
        ]
        for step, time, index in records:
            if index is None:
                path = "/" + schema.STATIC["tissue/rest_positions"].path
            else:
                path = _view(
                    handle,
                    xdmf_path_of(XDMF["tissue/positions/NNNNNNN"], step),
                    schema.TISSUE["positions"].path,
                    index,
                    (nodes, 3),
                    np.float64,
                )
            grid = _grid(tissue, f"tissue_{step:07d}", time)
            _topology(
                grid, "Tetrahedron", tets, file_name, "/" + schema.STATIC["tissue/tets"].path, (tets, 4)
            )
            _geometry(grid, file_name, path, (nodes, 3))
    ET.indent(root)
    output.write_text(
        '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n", encoding="utf-8"
    )
    return output
