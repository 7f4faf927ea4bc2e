"""The liver scenes: the phantom with a breathing boundary and a robot-held needle, and an outside organ mesh
(SOFA's liver) under the same [boundary] section."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from refsim.scene import load_scene
from refsim.simulation import Simulation

SHARED = Path(
    os.environ.get("REFSIM_SHARED_DATA", Path(__file__).resolve().parents[2].parent / "shared" / "data")
)
SOFA_LIVER = SHARED / "meshes" / "liver_gmsh22.msh"


@pytest.mark.parametrize("name", ["liver_rigid", "liver_flexible"])
def test_the_liver_scenes_load_with_their_robot_trajectory_and_breathing(name):
    scene = load_scene(name)
    simulation = Simulation(scene)
    controls = simulation.controls
    assert controls.boundary is not None and controls.boundary.nodes.size > 10
    assert set(controls.boundary.nodes) <= set(simulation.tissue.fixed_nodes)
    # The robot follows the target: its base moves across the needle as the breathing moves the target, by
    # an amplitude inside the liver's superior-inferior motion in quiet breathing that the scenes cite,
    # 10-25 mm (AAPM TG-76, Keall et al. 2006, Table I).
    trajectory = simulation.models.trajectory
    across = trajectory.base_positions[:, [0, 2]] - trajectory.base_positions[0, [0, 2]]
    assert 0.010 <= np.abs(across).max() <= 0.025
    assert scene.needle.length == pytest.approx(0.12) and not scene.needle.rigid


def _entry(mesh, target, direction) -> np.ndarray:
    """Where the line through ``target`` along ``direction`` leaves the mesh backwards (the needle's entry)
    [m], shape (3,): the crossing of a boundary triangle, on the side the needle comes from."""
    rest = mesh.rest_positions
    a, b, c = (rest[mesh.boundary_faces[:, k]] for k in range(3))
    # target − s d = a + u (b − a) + v (c − a), s > 0, for every triangle at once
    matrices = np.stack([b - a, c - a, np.broadcast_to(direction, a.shape)], axis=2)
    u, v, s = np.linalg.solve(matrices, (target - a)[..., None])[..., 0].T
    hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (s > 0)
    return target - s[hit].max() * direction


@pytest.mark.parametrize("resolution", ["coarse", "medium"])
def test_breathing_acts_on_the_diaphragmatic_face_and_leaves_the_entry_free(resolution):
    # The scenes' breathing drives the liver through its superior (diaphragmatic) face: every prescribed node
    # is a surface node turned up (its outward normal's cranial part above cos 45°) and in the organ's upper
    # part; the anterior face the needle enters through is free: the nearest prescribed node is more than
    # twice the mean edge of the tets at the entry away (h: 20 mm coarse, 10 mm medium), so the needle is
    # not bonded to tissue a distance h from a prescribed motion (docs/liver.md, "the breathing's surface").
    import sys

    from refsim.mesh import liver_phantom

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "studies" / "liver"))
    import make_trajectory

    mesh = liver_phantom(resolution)
    mesh_file = f'mesh.file="../mesh/data/liver_phantom_{resolution}.vtu"'
    simulation = Simulation(make_trajectory._scene_without_trajectory("liver_rigid", [mesh_file]))
    nodes = simulation.controls.boundary.nodes
    rest = mesh.rest_positions
    faces = mesh.boundary_faces
    corners = rest[faces]
    area_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals = np.zeros_like(rest)
    for k in range(3):
        np.add.at(normals, faces[:, k], area_normals)
    up = normals[nodes, 2] / np.linalg.norm(normals[nodes], axis=1)
    assert nodes.size > 50 and np.all(up >= np.cos(np.radians(45.0)) - 1e-12)
    assert set(nodes.tolist()) <= set(np.unique(faces).tolist())
    assert np.median(rest[nodes, 2]) > np.median(rest[:, 2])
    entry = _entry(mesh, make_trajectory.TARGET, make_trajectory.DIRECTION)
    assert entry[1] > 0.06  # on the anterior face
    tets = rest[mesh.tets]
    near = np.any(np.linalg.norm(tets - entry, axis=2) < 0.02, axis=1)
    pairs = [(i, j) for i in range(4) for j in range(i + 1, 4)]
    h = np.mean([np.linalg.norm(tets[near, i] - tets[near, j], axis=1) for i, j in pairs])
    gap = np.linalg.norm(rest[nodes] - entry, axis=1).min()
    assert gap > 2.0 * h, (gap, h)


@pytest.mark.parametrize("name", ["liver_rigid", "liver_flexible"])
def test_the_liver_scenes_take_their_tissue_breathing_and_toughness_inside_the_cited_ranges(name):
    # The ranges the scene files cite: G_c 76-225 J/m² (needle insertion and blade cutting of liver), E
    # between
    # healthy-liver elastography (about 5 kPa) and in vivo indentation at surgical strains (270 kPa), ν from
    # Chui et al. (0.43 ± 0.16, 0.47 ± 0.15), liver superior-inferior breathing 10-25 mm (AAPM TG-76), a quiet
    # breathing period of 3-5 s; and both scenes share them.
    scene, other = load_scene(name), load_scene("liver_flexible" if name == "liver_rigid" else "liver_rigid")
    assert 76.0 <= scene.cutting.fracture_energy <= 225.0
    # The published G_c lies above the model's window (docs/liver.md): at it neither needle cuts.
    assert scene.cutting.fracture_energy > WINDOW[1]
    assert 5e3 <= scene.tissue.youngs_modulus <= 270e3
    assert 0.43 - 0.16 <= scene.tissue.poisson_ratio < 0.5
    assert 0.010 <= np.linalg.norm(scene.boundary.amplitude) <= 0.025
    assert 3.0 <= scene.boundary.period <= 5.0
    for section in ("tissue", "boundary", "cutting", "insertion", "trajectory", "time"):
        assert getattr(scene, section) == getattr(other, section), section


@pytest.mark.skipif(not SOFA_LIVER.is_file(), reason=f"shared organ meshes absent ({SOFA_LIVER})")
def test_sofa_liver_runs_with_the_same_boundary_section():
    import tomllib
    from importlib import resources

    from refsim.mesh import read_mesh
    from refsim.scene.loader import scene_from_dict

    mesh = read_mesh(SOFA_LIVER).scaled(0.04)
    rest = mesh.rest_positions
    centre = 0.5 * (rest.min(axis=0) + rest.max(axis=0))
    top = rest[:, 1].max()
    # Straight down (−y) from 4 mm above the organ's top at its middle, 4 cm of travel in 2 s.
    tip0 = np.array([centre[0], top + 0.004, centre[2]])
    base0 = tip0 + [0.0, 0.12, 0.0]
    path = Path(str(resources.files("refsim") / "scenes" / "liver_flexible.toml"))
    data = tomllib.loads(path.read_text(encoding="utf-8"))
    data["mesh"] = {"file": str(SOFA_LIVER), "scale": 0.04, "fixed_nodes": [3, 39, 64]}
    # The scenes' breathing law; its nodes a patch at the top of this organ (its own up is +y), which the
    # needle enters through (this test runs an outside mesh, not the experiment).
    for key in ("facing", "facing_angle"):
        data["boundary"].pop(key, None)
    data["boundary"].update(
        {
            "patch_point": [float(centre[0]), float(top), float(centre[2])],
            "patch_distance": 0.05,
            "amplitude": [0.0, -0.008, 0.0],
        }
    )
    data["trajectory"] = {
        "times": [0.0, 2.0],
        "base_positions": [base0.tolist(), (base0 - [0, 0.04, 0]).tolist()],
        "directions": [[0.0, -1.0, 0.0], [0.0, -1.0, 0.0]],
    }
    data["time"] = {"dt": 0.01, "duration": 2.0}
    scene = scene_from_dict(data, source="sofa-liver", base_directory=str(path.parent))
    simulation = Simulation(scene)
    assert set([3, 39, 64]) <= set(simulation.tissue.fixed_nodes.tolist())
    records, states = [], []
    simulation.run(on_step=lambda s, r: (records.append(r), states.append(s)))
    names = [e.name for r in records for e in r.events]
    assert "puncture" in names
    assert "cut_start" not in names  # a pure axial push does not cut
    law = simulation.controls.boundary
    moved = states[-1].tissue.positions[law.nodes] - rest[law.nodes]
    np.testing.assert_allclose(moved, law.displacement(states[-1].time), atol=1e-12)
    assert max(np.linalg.norm(r.needle_force) for r in records) < 50.0


def _deflection(record, direction) -> float:
    """Largest distance of the needle's nodes from the straight line of its base along ``direction`` [m]."""
    nodes = record.needle_positions
    offset = nodes - nodes[0]
    along = offset @ direction
    return float(np.linalg.norm(offset - along[:, None] * direction, axis=1).max())


# The window of G_c over which the paper's outcome holds, bisected by studies/liver/window.py to 1 %
# (docs/liver_window.md): the flexible needle cuts below WINDOW[0], the rigid one does not cut above
# WINDOW[1]. It lies below the published G_c of liver (76-225 J/m²).
WINDOW = (25.50, 36.47)
# 1 %: the bisection's bracket, so the assertions hold wherever in its bracket the threshold lies (each end
# is the largest ‖t‖/L_in of a run without cutting, which the bisection brackets).
INSIDE = 0.01


def _cuts(name: str, fracture_energy: float) -> bool:
    """Whether the scene ``name`` at G_c = ``fracture_energy`` cuts (the run stops at its cut start)."""
    simulation = Simulation(load_scene(name, [f"cutting.fracture_energy={fracture_energy!r}"]))
    state = simulation.initial_state()
    for _ in range(simulation.scene.time.step_count):
        state, record = simulation.step(state, record_tissue=False)
        if any(e.name == "cut_start" for e in record.events):
            return True
    return False


@pytest.mark.slow
@pytest.mark.parametrize("end", ["low", "high"])
def test_the_outcome_holds_at_both_ends_of_the_window(end):
    # The paper's liver result over the stated window: at each end, just inside, the flexible needle does
    # not cut and the rigid one does; just outside the end, the needle that sets it changes its outcome.
    low, high = WINDOW
    if end == "low":
        assert not _cuts("liver_flexible", low * (1 + INSIDE))
        assert _cuts("liver_flexible", low * (1 - INSIDE))
        assert _cuts("liver_rigid", low * (1 + INSIDE))
    else:
        assert _cuts("liver_rigid", high * (1 - INSIDE))
        assert not _cuts("liver_rigid", high * (1 + INSIDE))
        assert not _cuts("liver_flexible", high * (1 - INSIDE))


@pytest.mark.slow
def test_the_flexible_needle_bends_and_does_not_cut_the_rigid_one_cuts():
    # The paper's liver result (section 5, Figure 2) at G_c at the window's geometric centre (below the
    # published values: the scenes' 105 J/m² is above the window, docs/liver.md). The rigid needle's cut block
    # is well posed on every cutting step (tests/simulation/test_cutting.py,
    # assert_cut_block_is_positive_definite) and Gauss–Seidel converges on every step.
    from tests.simulation.cutting_cases import watch_cut_blocks
    from tests.simulation.test_cutting import assert_cut_block_is_positive_definite

    runs = {}
    for name in ("liver_flexible", "liver_rigid"):
        centre = (WINDOW[0] * WINDOW[1]) ** 0.5
        simulation = Simulation(load_scene(name, [f"cutting.fracture_energy={centre!r}"]))
        spectra = watch_cut_blocks(simulation)
        records = []
        simulation.run(on_step=lambda s, r, records=records: records.append(r))
        direction = simulation.models.trajectory.directions[0]
        runs[name] = (records, max(_deflection(r, direction) for r in records), spectra)
        assert all(r.solver is None or r.solver.converged for r in records), name
    flexible, rigid = runs["liver_flexible"], runs["liver_rigid"]
    assert not any(e.name == "cut_start" for r in flexible[0] for e in r.events)
    assert any(e.name == "cut_start" for r in rigid[0] for e in r.events)
    assert flexible[1] > rigid[1]  # the flexible needle bends more
    assert_cut_block_is_positive_definite(rigid[2], "liver_rigid")


def test_the_results_file_holds_the_robot_trajectory_and_the_breathing(tmp_path):
    # A file stands alone: the CSV trajectory the scene read and the prescribed boundary displacement are in
    # it.
    from refsim.io import read_results
    from refsim.io.driver import run_scene
    from refsim.scene.trajectory import read_trajectory_csv

    scene = load_scene("liver_flexible")
    path = tmp_path / "liver.h5"
    run_scene(scene, path, overwrite=True, steps=3)
    results = read_results(path)
    csv = read_trajectory_csv(Path(scene.base_directory) / scene.trajectory.file)
    np.testing.assert_array_equal(results.trajectory_samples[:, 0], csv.times)
    np.testing.assert_array_equal(results.trajectory_samples[:, 1:4], csv.base_positions)
    assert results.boundary_nodes.size > 10 and results.boundary_displacement.shape == (
        3,
        results.boundary_nodes.size,
        3,
    )
