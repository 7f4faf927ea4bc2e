"""An XDMF 3 sidecar beside a results file, so that ParaView opens it directly (File > Open > RESULT.xdmf,
reader "XDMF Reader").

The sidecar has temporal collections in one domain, on one sorted time list: t = 0 (rest) and the end of
every step.

- one per instrument, named by it (``needle`` in a one-needle file), in the scene's order: its needle
  centreline as a polyline (``scene/needle/rest_nodes`` at t = 0, then ``steps/needle_positions``, both at
  the instrument's location: ``instruments/<name>/`` for a further instrument; its views and polyline in
  ``xdmf/instruments/<name>/needle/``, the first one's in ``xdmf/needle/``);
- ``cut`` (when the run cut): the cut surface triangles existing at each step, from the first step that has
  one, its rest points mapped to the deformed tissue by their tets and barycentric coordinates (equation 4 of
  the paper);
- ``tissue``: the tetrahedra, with point data ``displacement`` [m] (from rest), ``fixed`` (1 for a clamped
  node) and ``constraint_force`` [N] (the force of every instrument's needle on the tissue, spread on the
  nodes).

The tissue is recorded every ``output.tissue_every`` steps: between two records the tissue and the cut show
the last recorded state (``output.tissue_every = 1`` for every step). Every collection has a grid at every
time of the list, so VTK's XDMF reader (ParaView's) lists the times sorted and shows them all at each.

The heavy data is not copied: each per-step array is an HDF5 virtual dataset (a view, no data) in the group
``xdmf/`` of the results file that maps onto one entry of the per-step dataset, and the XDMF points at it as
``RESULT.h5:/xdmf/...``; a step between records points at the same view as the record before it. Stored are
only what is derived: the deformed cut points, the displacement and the constraint forces at each recorded
step. The tissue collection comes last, so ``meshio.xdmf.TimeSeriesReader`` reads it (the rest mesh once,
then the point data of each time: the deformation is rest + ``displacement``); ``meshio.read`` reads single
meshes only: ``refsim export RESULT.h5 --vtu STEP`` writes those.
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

__all__ = ["XDMF_GROUP", "nodal_constraint_forces", "write_xdmf", "xdmf_path"]


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
    number = "Float" if kind.kind == "f" else ("Char" if kind.itemsize == 1 else "Int")
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


def _attribute(grid, name: str, center: str, kind: str, file_name: str, path: str, shape: tuple, dtype):
    attribute = ET.SubElement(grid, "Attribute", Name=name, AttributeType=kind, Center=center)
    _data_item(attribute, file_name, path, shape, dtype)


def nodal_constraint_forces(
    positions: np.ndarray, tets: np.ndarray, points: np.ndarray, directions: np.ndarray, forces: np.ndarray
) -> np.ndarray:
    """The force of the needles on the tissue at the nodes [N], shape (n, 3).

    Each constraint row pushes the tissue along −n with its multiplier λ (refsim.constraints.rows); its force
    −λ n is spread on the four nodes of the tet holding its tissue-side point in the tissue at ``positions``
    (n, 3) [m] by the point's barycentric coordinates (the point clamped to the closest tet when it lies
    just outside), so the nodal forces sum to −Σ λ n, the opposite of the sum of every instrument's
    steps/needle_force.

    Parameters
    ----------
    tets : (m, 4). points : Tissue-side points of the rows [m], (r, 3). directions : Row directions, (r, 3).
    forces : Multipliers λ [N], (r,).
    """
    from refsim.geometry.search import TetLocator

    nodal = np.zeros_like(positions)
    if forces.size == 0:
        return nodal
    tet, barycentric = TetLocator(positions, tets).locate_nearest(points)[:2]
    row_force = -forces[:, None] * directions  # (r, 3)
    np.add.at(nodal, tets[tet].ravel(), (barycentric[:, :, None] * row_force[:, None, :]).reshape(-1, 3))
    return nodal


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

    from refsim.io import read_results

    results_path = Path(results_path)
    results = read_results(results_path)  # validates the file; counts of completed steps
    output = xdmf_path(results_path) if output is None else Path(output)
    if output.resolve().parent != results_path.resolve().parent:
        raise ValueError(f"{output}: the XDMF sidecar must be in the folder of {results_path}")
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
        sidecar = _Sidecar(handle, domain, results, results_path.name)
        sidecar.needles()
        fixed_path, record_paths = sidecar.tissue_records()
        sidecar.cut()
        sidecar.tissue(fixed_path, record_paths)  # last: meshio's TimeSeriesReader reads the last collection
    ET.indent(root)
    output.write_text(
        '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n", encoding="utf-8"
    )
    return output


class _Sidecar:
    """The grids of one XDMF sidecar and the datasets of the results file's ``xdmf/`` group they read.

    The time list is rest (step 0), then every completed step; ``record_of`` is the tissue record shown at
    each (-1: rest).
    """

    def __init__(self, handle, domain, results, file_name: str) -> None:
        self.handle, self.domain, self.results, self.file_name = handle, domain, results, file_name
        steps = results.step_count
        self.nodes, self.tets = results.rest_positions.shape[0], results.tets.shape[0]
        self.step_numbers = np.concatenate([[0], results.step[:steps]]).astype(np.int64)
        self.times = np.concatenate([[0.0], results.time[:steps]])
        self.record_of = np.searchsorted(results.tissue_steps, self.step_numbers, side="right") - 1

    def stored(self, spec_key: str, step: int | None, data: np.ndarray, path: str | None = None) -> str:
        """Store a derived array (of XDMF[spec_key], for ``step``; at ``path`` when given) with its unit;
        its HDF5 path."""
        spec = XDMF[spec_key]
        name = path if path is not None else (spec.path if step is None else xdmf_path_of(spec, step))
        dataset = self.handle.create_dataset(name, data=np.asarray(data, dtype=spec.dtype))
        dataset.attrs["units"] = spec.unit
        return dataset.name

    def needles(self) -> None:
        """Every instrument's needle: a polyline at rest, then at every step (views of its
        steps/needle_positions), one temporal collection named by the instrument."""
        for index, name in enumerate(self.results.instrument_names):
            self.needle(index, name)

    def needle(self, index: int, name: str) -> None:
        """The needle of instrument ``index`` (called ``name``): its datasets at the instrument's location."""
        from refsim.io import schema

        location = schema.instrument_location(index, name)
        prefix = location + "/" if location else ""
        needle_nodes = self.results.instrument(name).needle_rest_nodes.shape[0]

        def path_of(key: str, step: int | None) -> str:
            return schema.xdmf_instrument_path(XDMF[key], index, name, step)

        needle = ET.SubElement(
            self.domain, "Grid", Name=name, GridType="Collection", CollectionType="Temporal"
        )
        connectivity = self.stored(
            "needle/polyline", None, np.arange(needle_nodes)[None], path=path_of("needle/polyline", None)
        )
        for step_index, (step, time) in enumerate(zip(self.step_numbers, self.times, strict=True)):
            if step_index == 0:
                path = "/" + prefix + schema.STATIC["needle/rest_nodes"].path
            else:
                path = _view(
                    self.handle,
                    path_of("needle/positions/NNNNNNN", step),
                    prefix + schema.STEPS["needle_positions"].path,
                    step_index - 1,
                    (needle_nodes, 3),
                    np.float64,
                )
            grid = _grid(needle, f"{name}_{step:07d}", time)
            _topology(
                grid,
                "Polyline",
                1,
                self.file_name,
                connectivity,
                (1, needle_nodes),
                NodesPerElement=str(needle_nodes),
            )
            _geometry(grid, self.file_name, path, (needle_nodes, 3))

    def tissue_records(self) -> tuple[str, dict]:
        """The fixed-node flags and, per tissue record (-1: rest), the paths of its positions (a view),
        displacement and nodal constraint forces (derived)."""
        from refsim.io import schema

        results, nodes = self.results, self.nodes
        fixed = np.zeros(nodes, dtype=np.int8)
        fixed[results.fixed_nodes] = 1
        fixed_path = self.stored("tissue/fixed", None, fixed)
        zeros = np.zeros((nodes, 3))
        record_paths = {
            -1: (
                "/" + schema.STATIC["tissue/rest_positions"].path,
                self.stored("tissue/displacement/NNNNNNN", 0, zeros),
                self.stored("tissue/constraint_force/NNNNNNN", 0, zeros),
            )
        }
        for record, step in enumerate(results.tissue_steps):
            positions = results.tissue_positions[record]
            rows = results.constraints_at(int(step))
            record_paths[record] = (
                _view(
                    self.handle,
                    xdmf_path_of(XDMF["tissue/positions/NNNNNNN"], step),
                    schema.TISSUE["positions"].path,
                    record,
                    (nodes, 3),
                    np.float64,
                ),
                self.stored("tissue/displacement/NNNNNNN", step, positions - results.rest_positions),
                self.stored(
                    "tissue/constraint_force/NNNNNNN",
                    step,
                    nodal_constraint_forces(
                        positions, results.tets, rows.points, rows.directions, rows.forces
                    ),
                ),
            )
        return fixed_path, record_paths

    def cut(self) -> None:
        """The cut surface at every step from its first triangle: its points deformed with each tissue
        record, its triangles a view of the prefix existing at the step (a copy when out of order)."""
        from refsim.io import schema

        results, file_name = self.results, self.file_name
        cut = results.cut
        if cut is None or not cut.triangles.shape[0] or cut.tet_indices is None:
            return
        collection = ET.SubElement(
            self.domain, "Grid", Name="cut", GridType="Collection", CollectionType="Temporal"
        )
        corners = results.tets[cut.tet_indices]  # (p, 4)
        point_count = cut.points.shape[0]  # every point: later ones are unused until their triangles exist
        in_order = bool(np.all(np.diff(cut.triangle_step) >= 0))
        counts = np.count_nonzero(cut.triangle_step[None, :] <= self.step_numbers[:, None], axis=1)
        point_paths, triangle_paths = {-1: "/" + schema.CUT["points"].path}, {}
        for step, time, record, count in zip(
            self.step_numbers, self.times, self.record_of, counts, strict=True
        ):
            if count == 0:
                continue
            if record not in point_paths:
                deformed = np.einsum("pk,pki->pi", cut.barycentric, results.tissue_positions[record][corners])
                point_paths[record] = self.stored(
                    "cut/points/NNNNNNN", int(results.tissue_steps[record]), deformed
                )
            if count not in triangle_paths:
                name = xdmf_path_of(XDMF["cut/triangles/NNNNNNN"], step)
                if in_order:  # the triangles of the step are a prefix: a view
                    triangle_paths[count] = _view(
                        self.handle, name, schema.CUT["triangles"].path, slice(0, count), (count, 3), np.int64
                    )
                else:
                    existing = cut.triangles[cut.triangle_step <= step]
                    triangle_paths[count] = self.stored("cut/triangles/NNNNNNN", step, existing)
            grid = _grid(collection, f"cut_{int(step):07d}", time)
            _topology(grid, "Triangle", int(count), file_name, triangle_paths[count], (int(count), 3))
            _geometry(grid, file_name, point_paths[record], (point_count, 3))

    def tissue(self, fixed_path: str, record_paths: dict) -> None:
        """The tissue at every step: its tets on the record's positions, displacement, fixed flags and
        constraint forces."""
        from refsim.io import schema

        nodes, tets, file_name = self.nodes, self.tets, self.file_name
        tissue = ET.SubElement(
            self.domain, "Grid", Name="tissue", GridType="Collection", CollectionType="Temporal"
        )
        for step, time, record in zip(self.step_numbers, self.times, self.record_of, strict=True):
            positions, displacement, force = record_paths[int(record)]
            grid = _grid(tissue, f"tissue_{step:07d}", time)
            _topology(
                grid, "Tetrahedron", tets, file_name, "/" + schema.STATIC["tissue/tets"].path, (tets, 4)
            )
            _geometry(grid, file_name, positions, (nodes, 3))
            _attribute(
                grid, "displacement", "Node", "Vector", file_name, displacement, (nodes, 3), np.float64
            )
            _attribute(grid, "fixed", "Node", "Scalar", file_name, fixed_path, (nodes,), np.int8)
            _attribute(grid, "constraint_force", "Node", "Vector", file_name, force, (nodes, 3), np.float64)
