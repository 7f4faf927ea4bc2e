"""Reading and writing tetrahedral meshes: every volume format meshio reads, plus Gmsh's legacy v1 format.

Gmsh v1 files (``$NOD``/``$ENDNOD``, ``$ELM``/``$ENDELM``, no ``$MeshFormat`` header) are common for organ
meshes (SOFA ships its liver in it) but meshio cannot read them; they are recognised by content, not by
extension. The v1 ``$ELM`` records are ``number type physical-region elementary-region node-count nodes...``,
type 4 being the 4-node tetrahedron; node labels are arbitrary distinct positive integers, listed in ``$NOD``
as ``label x y z``.
"""

from __future__ import annotations

import contextlib
import io
import logging
from pathlib import Path

import numpy as np

from refsim.mesh.tetmesh import TetMesh
from refsim.mesh.validation import MeshError, validate_mesh

__all__ = ["read_mesh", "write_mesh"]

logger = logging.getLogger(__name__)

_GMSH_V1_TETRAHEDRON = 4
# Bytes read to recognise a Gmsh v1 file.
_HEADER_BYTES = 4096


def read_mesh(path: str | Path, *, fix_orientation: bool = True) -> TetMesh:
    """Read a linear tetrahedral mesh from a file.

    Parameters
    ----------
    path : A volume mesh file meshio reads (.msh v2/v4, .vtu, .vtk, .xdmf, .med, ...) or a Gmsh legacy v1
        file. Coordinates are taken as they are: convert units with `TetMesh.scaled`.
    fix_orientation : Fix inverted tetrahedra by swapping two of their nodes, with a logged warning; when
        False they are an error.

    Returns
    -------
    The mesh, with its tetrahedra (all "tetra" cell blocks); other cell types (triangles, lines, points,
    quadratic elements) are ignored, and nodes used by no tetrahedron are dropped with a logged warning. When
    nodes were merged or dropped, ``mesh.node_map`` maps the file's node indices to the mesh's
    (``mesh.file_nodes``), so that indices given in the file's numbering still name the same nodes.

    Raises
    ------
    MeshError
        Naming the file and the defect: missing, unreadable or empty file, no tetrahedra, non-finite
        coordinates, node indices out of range, degenerate tetrahedra, a tangled mesh (overlapping
        tetrahedra), or inverted ones when not fixed.
    """
    path = Path(path)
    source = str(path)
    if not path.exists():
        raise MeshError(source, "file does not exist")
    if not path.is_file():
        raise MeshError(source, "not a regular file")
    try:
        with path.open("rb") as stream:
            header = stream.read(_HEADER_BYTES)
    except OSError as error:
        raise MeshError(source, f"cannot read the file ({error})") from None
    if not header.strip():
        raise MeshError(source, "file is empty")
    if header.lstrip().startswith(b"$NOD"):
        positions, tets = _read_gmsh_v1(path)
    else:
        positions, tets = _read_meshio(path)
    positions, tets, node_map = validate_mesh(
        positions,
        tets,
        source=source,
        fix_orientation=fix_orientation,
        drop_unused_nodes=True,
        merge_duplicates=True,
        return_node_map=True,
    )
    renumbered = not np.array_equal(node_map, np.arange(node_map.shape[0]))
    mesh = TetMesh(positions, tets, source=source, node_map=node_map if renumbered else None)
    logger.info("read %s: %d nodes, %d tetrahedra", source, mesh.node_count, mesh.tet_count)
    return mesh


def _read_meshio(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import meshio

    source = str(path)
    captured = io.StringIO()
    try:
        # meshio prints its own errors and some readers call sys.exit: keep both out of the user's terminal.
        with contextlib.redirect_stdout(captured), contextlib.redirect_stderr(captured):
            data = meshio.read(path)
    except (Exception, SystemExit) as error:  # meshio raises many types
        said = " ".join(captured.getvalue().split()) or f"{type(error).__name__}: {error}"
        raise MeshError(
            source,
            f"cannot read it as a {_format_name(path)} mesh: {_truncation_hint(path)}"
            f"(meshio said: {said[:300]})",
        ) from None
    blocks = [block.data for block in data.cells if block.type == "tetra"]
    ignored = sorted({block.type for block in data.cells if block.type != "tetra"})
    if not blocks:
        found = ", ".join(ignored) or "none"
        raise MeshError(
            source, f"no tetrahedra (linear 'tetra' cells) in the file; cell types found: {found}"
        )
    if ignored:
        logger.info("%s: ignored cells of type %s", source, ", ".join(ignored))
    points = np.asarray(data.points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise MeshError(source, f"points must be 3-D, got an array of shape {points.shape}")
    return points, np.concatenate(blocks).astype(np.int64)


_FORMAT_NAMES = {
    ".vtu": "VTK XML (.vtu)",
    ".vtk": "legacy VTK (.vtk)",
    ".msh": "Gmsh (.msh)",
    ".xdmf": "XDMF",
    ".med": "MED",
    ".mesh": "Medit (.mesh)",
    ".inp": "Abaqus (.inp)",
}
# The last marker of a complete file, per format: without it the file was cut short.
_END_MARKERS = {".vtu": b"</VTKFile>", ".msh": b"$End"}


def _format_name(path: Path) -> str:
    return _FORMAT_NAMES.get(path.suffix.lower(), f"'{path.suffix or 'unknown'}'")


def _truncation_hint(path: Path) -> str:
    """ "the file is truncated (...)" when its format's closing marker is missing from its end, else "the file
    is malformed or not in this format "."""
    marker = _END_MARKERS.get(path.suffix.lower())
    if marker is None:
        return "the file is truncated, malformed or not in this format "
    try:
        with path.open("rb") as stream:
            head = stream.read(256).lstrip()
            stream.seek(max(0, path.stat().st_size - 4096))
            tail = stream.read()
    except OSError:
        return ""
    if marker == b"$End" and not head.startswith(b"$"):
        return "it is not a Gmsh file (no $MeshFormat header) "
    if marker == b"</VTKFile>" and not head.startswith(b"<"):
        return "it is not an XML VTK file "
    if marker == b"$End":  # Gmsh: the last section must be closed, e.g. $EndElements
        closed = tail.rstrip().splitlines()[-1:] if tail.strip() else []
        if not closed or not closed[0].strip().startswith(b"$End"):
            return "the file is truncated (it does not end with a closing $End... line) "
    elif marker not in tail:
        return f"the file is truncated (no closing {marker.decode()}) "
    return "the file is malformed "


def _section(text: str, begin: str, end: str, source: str) -> list[str]:
    """Lines strictly between the lines ``begin`` and ``end``."""
    lines = text.splitlines()
    stripped = [line.strip() for line in lines]
    if begin not in stripped:
        raise MeshError(source, f"Gmsh v1 file without a {begin} section")
    start = stripped.index(begin) + 1
    if end not in stripped[start:]:
        raise MeshError(source, f"Gmsh v1 section {begin} is not closed by {end} (truncated file?)")
    stop = stripped.index(end, start)
    return [line for line in stripped[start:stop] if line]


def _read_count(lines: list[str], section: str, source: str) -> int:
    try:
        return int(lines[0])
    except (IndexError, ValueError):
        raise MeshError(source, f"Gmsh v1 section {section} does not start with an entry count") from None


def _read_gmsh_v1(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Positions and tetrahedra (0-based) of a Gmsh legacy v1 file; other element types are ignored."""
    source = str(path)
    text = path.read_text(encoding="utf-8", errors="replace")

    node_lines = _section(text, "$NOD", "$ENDNOD", source)
    node_count = _read_count(node_lines, "$NOD", source)
    if len(node_lines) - 1 != node_count:
        raise MeshError(source, f"$NOD announces {node_count} nodes but lists {len(node_lines) - 1}")
    try:
        table = np.array(" ".join(node_lines[1:]).split(), dtype=float)
    except ValueError as error:
        raise MeshError(source, f"$NOD holds a value that is not a number ({error})") from None
    if table.shape[0] != 4 * node_count:
        raise MeshError(source, "$NOD records must be 'label x y z'")
    table = table.reshape(node_count, 4)
    labels = table[:, 0].astype(np.int64)
    if not np.array_equal(labels, table[:, 0]) or np.unique(labels).shape[0] != node_count:
        raise MeshError(source, "$NOD node labels must be distinct integers")

    element_lines = _section(text, "$ELM", "$ENDELM", source)
    element_count = _read_count(element_lines, "$ELM", source)
    if len(element_lines) - 1 != element_count:
        raise MeshError(source, f"$ELM announces {element_count} elements but lists {len(element_lines) - 1}")
    records = [line.split() for line in element_lines[1:]]
    try:
        tet_records = [r for r in records if int(r[1]) == _GMSH_V1_TETRAHEDRON]
        wrong_size = [r[0] for r in tet_records if len(r) != 9 or int(r[4]) != 4]
        tet_labels = np.array([r[5:9] for r in tet_records if len(r) == 9], dtype=np.int64).reshape(-1, 4)
    except (IndexError, ValueError):
        raise MeshError(
            source, "$ELM records must be integers 'number type phys elem node-count nodes...'"
        ) from None
    if wrong_size:
        raise MeshError(source, f"$ELM tetrahedron {wrong_size[0]} does not list exactly 4 nodes")
    ignored = len(records) - len(tet_records)
    if ignored:
        logger.info("%s: ignored %d non-tetrahedral elements", source, ignored)
    if tet_labels.shape[0] == 0:
        raise MeshError(source, "no tetrahedra (elements of type 4) in $ELM")

    order = np.argsort(labels)
    slots = np.clip(np.searchsorted(labels[order], tet_labels), 0, node_count - 1)
    unknown = labels[order][slots] != tet_labels
    if np.any(unknown):
        raise MeshError(
            source, f"tetrahedra reference node labels not in $NOD, e.g. {int(tet_labels[unknown][0])}"
        )
    return table[:, 1:], order[slots]


def write_mesh(path: str | Path, mesh: TetMesh, *, file_format: str | None = None) -> None:
    """Write a mesh with meshio, in the format of the extension unless given (.msh means Gmsh 4.1).

    Parameters
    ----------
    path : Output file.
    mesh : The mesh to write.
    file_format : A meshio format name ("vtu", "gmsh", "gmsh22", ...), or None to infer it from the extension
        (.msh gives "gmsh", Gmsh 4.1, rather than meshio's default for .msh, ANSYS).
    """
    import meshio

    path = Path(path)
    if file_format is None and path.suffix.lower() == ".msh":
        file_format = "gmsh"
    data = meshio.Mesh(np.asarray(mesh.rest_positions), [("tetra", np.asarray(mesh.tets))])
    meshio.write(Path(path), data, file_format=file_format)
