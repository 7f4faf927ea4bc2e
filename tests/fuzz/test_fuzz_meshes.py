"""Fuzz of mesh files (issue 10): degenerate, duplicated, inverted, scaled, truncated, garbled meshes in every
format refsim reads, used by a scene; each case ends cleanly (exit 0, 2 or 3 as tests/fuzz/test_fuzz_scenes.py
defines it; an input error names the mesh file or a mesh key).
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from refsim.mesh import box_mesh

_spec = importlib.util.spec_from_file_location("fuzz_scenes", Path(__file__).with_name("test_fuzz_scenes.py"))
_scenes = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_scenes)

EXAMPLES = max(10, settings.default.max_examples // 2)
FORMATS = [("vtu", ".vtu"), ("gmsh22", ".msh"), ("gmsh", ".msh"), ("vtk", ".vtk"), ("gmsh1", ".msh")]
DEFECTS = [
    "none",
    "duplicated",
    "inverted",
    "degenerate",
    "collapsed_node",
    "scaled_mm",
    "scaled_tiny",
    "truncated",
    "garbage",
    "nan_node",
    "index_out_of_range",
    "empty",
    "no_tets",
    "shuffled",
]


def _write_gmsh_v1(path: Path, positions: np.ndarray, tets: np.ndarray) -> None:
    labels = np.arange(1, positions.shape[0] + 1) * 7  # arbitrary distinct labels
    lines = ["$NOD", str(positions.shape[0])]
    lines += [
        f"{label} {float(x)!r} {float(y)!r} {float(z)!r}"
        for label, (x, y, z) in zip(labels, positions, strict=True)
    ]
    lines += ["$ENDNOD", "$ELM", str(tets.shape[0])]

    def label(node):  # an index out of range becomes a label that $NOD does not list
        return str(labels[node]) if 0 <= node < labels.size else str(7 * (labels.size + 1) + 1)

    lines += [f"{i + 1} 4 1 1 4 " + " ".join(label(n) for n in tet) for i, tet in enumerate(tets)]
    lines += ["$ENDELM"]
    path.write_text("\n".join(lines) + "\n")


def _mesh_file(folder: Path, fmt: str, suffix: str, defect: str, seed: int) -> Path:
    rng = np.random.default_rng(seed)
    mesh = box_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2), origin=(-0.05, -0.05, 0.0))
    positions, tets = np.array(mesh.rest_positions), np.array(mesh.tets)
    if defect == "duplicated":
        positions = positions[tets].reshape(-1, 3)
        tets = np.arange(positions.shape[0]).reshape(-1, 4)
    elif defect == "inverted":
        chosen = rng.choice(tets.shape[0], size=rng.integers(1, tets.shape[0]), replace=False)
        tets[chosen] = tets[chosen][:, [0, 1, 3, 2]]
    elif defect == "degenerate":
        tets = np.vstack([tets, [[0, 1, 2, 2]]])
    elif defect == "collapsed_node":
        tet = tets[rng.integers(tets.shape[0])]
        positions[tet[0]] = positions[tet[1]]
    elif defect == "scaled_mm":
        positions = positions * 1e3
    elif defect == "scaled_tiny":
        positions = positions * 1e-4
    elif defect == "nan_node":
        positions[rng.integers(positions.shape[0]), rng.integers(3)] = np.nan
    elif defect == "index_out_of_range":
        tets[rng.integers(tets.shape[0]), rng.integers(4)] = positions.shape[0] + 5
    elif defect == "shuffled":
        order = rng.permutation(positions.shape[0])
        positions = positions[order]
        tets = np.argsort(order)[tets]
    path = folder / f"tissue_{fmt}{suffix}"
    if defect == "empty":
        path.write_bytes(b"")
        return path
    if defect == "garbage":
        path.write_bytes(rng.integers(0, 256, size=int(rng.integers(1, 3000)), dtype=np.uint8).tobytes())
        return path
    import meshio

    if fmt == "gmsh1":
        _write_gmsh_v1(path, positions, tets if defect != "no_tets" else tets[:0])
    elif defect == "no_tets":
        meshio.write(path, meshio.Mesh(positions, [("triangle", tets[:, :3])]), file_format=fmt)
    else:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            meshio.write(path, meshio.Mesh(positions, [("tetra", tets)]), file_format=fmt)
    if defect == "truncated":
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * rng.uniform(0.05, 0.97))])
    return path


@settings(max_examples=EXAMPLES, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.sampled_from(FORMATS), st.sampled_from(DEFECTS), st.integers(0, 2**16), st.sampled_from([1.0, 1e-3])
)
def test_fuzzed_mesh_files_end_cleanly(fmt, defect, seed, scale):
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        mesh_path = _mesh_file(folder, fmt[0], fmt[1], defect, seed)
        data = {
            section: dict(table) if isinstance(table, dict) else table
            for section, table in _scenes.BASE.items()
        }
        data["mesh"] = {"file": str(mesh_path), "scale": scale, "fixed_faces": ["zmin"]}
        scene = folder / "scene.toml"
        _scenes.write_scene(data, scene)
        output = folder / "out.h5"
        code, error = _scenes.run_cli(["run", str(scene), "-o", str(output), "-q"])
        _scenes.assert_clean_outcome(code, error, output, [str(mesh_path), "mesh.", "[mesh]", "mesh"])
        if defect in ("none", "duplicated", "inverted", "shuffled") and scale == 1.0:
            assert code == 0, error  # repairable defects are repaired (with a warning)
        if defect in (
            "degenerate",
            "collapsed_node",
            "nan_node",
            "index_out_of_range",
            "empty",
            "no_tets",
            "truncated",
        ):
            assert code == 2, error
