"""Fuzz of what holds and moves the tissue (issue 25): meshes tangled, split into parts and renumbered, and
boundary motions (periodic and sampled), each used by the cube scene (2³ cells, 5 steps of 10 ms).

Each case ends cleanly (exit 0, 2 or 3 as tests/fuzz/test_fuzz_scenes.py defines them) and, beyond that, the
outcome is checked against the input's own truth, computed here independently of refsim's checks:
- a tangled mesh (Σ|V| of its tetrahedra larger than the box it fills) is refused, an untangled one runs;
- a mesh part that no fixed node holds is refused, naming the part;
- fixed nodes given in the file's numbering are the nodes at z = 0 whatever nodes the reader dropped;
- a boundary motion that runs moves its nodes by at most insertion.contact_distance per step and by at most
  the tissue's size; one that does more is refused, naming the boundary.
"""

from __future__ import annotations

import importlib.util
import tempfile
from pathlib import Path

import meshio
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from refsim.geometry.barycentric import signed_volumes
from refsim.io import read_results
from refsim.mesh import box_mesh

_spec = importlib.util.spec_from_file_location("fuzz_scenes", Path(__file__).with_name("test_fuzz_scenes.py"))
_scenes = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_scenes)

EXAMPLES = max(10, settings.default.max_examples // 2)
CELL = 0.05  # the 0.1 m cube on 2 cells per axis
CONTACT = float(_scenes.BASE["insertion"]["contact_distance"])
DT = float(_scenes.BASE["time"]["dt"])
STEPS = int(round(float(_scenes.BASE["time"]["duration"]) / DT))
SIZE = float(np.sqrt(3.0) * 0.1)


def _cube():
    mesh = box_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2), origin=(-0.05, -0.05, 0.0))
    return np.array(mesh.rest_positions), np.array(mesh.tets)


def _run(folder: Path, mesh_path: Path | None = None, **sections) -> tuple[int, str, Path]:
    data = {
        section: dict(table) if isinstance(table, dict) else table for section, table in _scenes.BASE.items()
    }
    if mesh_path is not None:
        data["mesh"] = {"file": str(mesh_path), "fixed_faces": ["zmin"]}
    for section, table in sections.items():
        data.setdefault(section, {}).update(table)
    scene = folder / "scene.toml"
    _scenes.write_scene(data, scene)
    output = folder / "out.h5"
    code, error = _scenes.run_cli(["run", str(scene), "-o", str(output), "-q"])
    return code, error, output


@settings(max_examples=EXAMPLES, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.one_of(st.just(13), st.sampled_from(range(27))),  # node 13 is the one interior node: it tangles
    st.floats(0.0, 1.5 * CELL),
    st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)).filter(lambda v: np.linalg.norm(v) > 0.1),
)
def test_tangled_meshes_are_refused_and_untangled_ones_run(node, distance, direction):
    positions, tets = _cube()
    moved = positions.copy()
    moved[node] += distance * np.asarray(direction) / np.linalg.norm(direction)
    volumes = signed_volumes(moved[tets])
    inside = np.all((moved >= [-0.05, -0.05, 0.0]) & (moved <= [0.05, 0.05, 0.1]))
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        path = folder / "moved.vtu"
        meshio.write(path, meshio.Mesh(moved, [("tetra", tets)]))
        code, error, output = _run(folder, path)
        _scenes.assert_clean_outcome(code, error, output, [str(path), "mesh"])
        if np.any(volumes < 0) and inside and np.abs(volumes).sum() > 1e-3 * (1 + 1e-9):
            assert code == 2 and ("tangled" in error or "degenerate" in error), error  # the overlap is real
        if np.all(volumes > 0) and code == 2:  # untangled: refused only for another named reason
            assert "tangled" not in error, error


@settings(max_examples=EXAMPLES, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from([0.0, 0.01, 0.05, 0.1]), st.booleans())
def test_a_part_that_nothing_holds_is_refused(lift, fixed_box_around_it):
    """Two cubes, the second beside the first (0.2 m away in x) and lifted; zmin holds the first; the second
    is held only when it also touches z = 0 or a fixed box covers its bottom."""
    positions, tets = _cube()
    second = positions + [0.2, 0.0, lift]
    both = np.vstack([positions, second])
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        path = folder / "two.vtu"
        meshio.write(path, meshio.Mesh(both, [("tetra", np.vstack([tets, tets + positions.shape[0]]))]))
        mesh = {"fixed_faces": ["zmin"]}
        if fixed_box_around_it:
            mesh["fixed_box"] = [[0.14, -0.06, lift - 1e-6], [0.26, 0.06, lift + 1e-6]]
        code, error, output = _run(folder, path, mesh=mesh)
        _scenes.assert_clean_outcome(code, error, output, [str(path), "mesh"])
        held = lift == 0.0 or fixed_box_around_it
        assert (code == 2 and "part 2 of 2" in error) == (not held), error


@settings(max_examples=EXAMPLES, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**16), st.integers(1, 6))
def test_fixed_nodes_in_the_file_numbering_survive_renumbering(seed, unused):
    """Unused nodes inserted at random places and the nodes shuffled: fixed_nodes lists the file indices of
    the bottom nodes; the run must fix exactly the nodes at z = 0."""
    rng = np.random.default_rng(seed)
    positions, tets = _cube()
    order = rng.permutation(positions.shape[0])
    positions, tets = positions[order], np.argsort(order)[tets]
    slots = np.sort(rng.choice(positions.shape[0] + unused, size=unused, replace=False))
    keep = np.setdiff1d(np.arange(positions.shape[0] + unused), slots)
    written = np.full((positions.shape[0] + unused, 3), 5.0)
    written[keep] = positions
    file_tets = keep[tets]
    bottom = np.flatnonzero(np.isclose(written[:, 2], 0.0))
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        path = folder / "renumbered.vtu"
        meshio.write(path, meshio.Mesh(written, [("tetra", file_tets)]))
        code, error, output = _run(folder, path, mesh={"fixed_faces": [], "fixed_nodes": bottom.tolist()})
        assert code == 0, error
        results = read_results(output)
        held = results.rest_positions[results.fixed_nodes]
        assert held.shape[0] == bottom.size and np.all(held[:, 2] == 0.0)


def _periodic_history(amplitude, period, exponent, times):
    power = 2 * exponent
    profile = 1.0 - np.cos(np.pi * times / period) ** power
    return profile[:, None] * np.asarray(amplitude)


@settings(max_examples=EXAMPLES, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.tuples(*[st.floats(-0.05, 0.05)] * 3).filter(lambda a: np.linalg.norm(a) > 1e-6),
    st.floats(0.005, 10.0),
    st.integers(1, 4),
)
def test_periodic_boundary_motions(amplitude, period, exponent):
    times = DT * np.arange(STEPS + 1)
    history = _periodic_history(amplitude, period, exponent, times)
    per_step = float(np.linalg.norm(np.diff(history, axis=0), axis=1).max())
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        boundary = {
            "motion": "periodic",
            "box": [[-1, -1, -1], [1, 1, 0.001]],
            "amplitude": list(amplitude),
            "period": period,
            "exponent": exponent,
        }
        code, error, output = _run(folder, mesh={"fixed_faces": []}, boundary=boundary)
        _scenes.assert_clean_outcome(code, error, output, ["boundary"])
        if code == 0:
            assert period >= 4 * exponent * DT and per_step <= CONTACT
        if period < 4 * exponent * DT or per_step > CONTACT * (1 + 1e-9):
            assert code == 2, error


@settings(max_examples=EXAMPLES, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.lists(st.floats(0.001, 0.03), min_size=1, max_size=12),
    st.lists(st.tuples(*[st.floats(-0.03, 0.03)] * 3), min_size=12, max_size=12),
)
def test_sampled_boundary_motions(gaps, displacements):
    times = np.concatenate([[0.0], np.cumsum(gaps)])
    values = np.vstack([[0.0, 0.0, 0.0], np.asarray(displacements)[: len(gaps)]])
    step_times = DT * np.arange(STEPS + 1)
    at_steps = np.stack([np.interp(step_times, times, values[:, k]) for k in range(3)], axis=1)
    per_step = float(np.linalg.norm(np.diff(at_steps, axis=0), axis=1).max())
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        csv = folder / "motion.csv"
        csv.write_text(
            "t,dx,dy,dz\n"
            + "".join(f"{t!r},{x!r},{y!r},{z!r}\n" for t, (x, y, z) in zip(times, values, strict=True))
        )
        boundary = {"motion": "file", "box": [[-1, -1, -1], [1, 1, 0.001]], "file": str(csv)}
        code, error, output = _run(folder, mesh={"fixed_faces": []}, boundary=boundary)
        _scenes.assert_clean_outcome(code, error, output, ["boundary"])
        if code == 0:
            assert per_step <= CONTACT * (1 + 1e-9)
            results = read_results(output)  # what the run applied is what the file says at the step times
            np.testing.assert_allclose(
                results.boundary_displacement[:, 0], at_steps[1 : results.step_count + 1], atol=1e-12
            )
        if per_step > CONTACT * (1 + 1e-9):
            assert code == 2, error
