"""The co-rotational Timoshenko needle model (refsim.fem.needle)."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.fem.needle import NeedleModel, NeedleSection
from refsim.geometry.rotations import rotation_matrix

EPS = np.finfo(float).eps


def _model(**overrides):
    # The paper's cube needle, tilted: 0.32 m, 16 elements, r = 8 mm, E = 100 GPa, ν = 0.4.
    config = dict(
        length=0.32,
        radius=8e-3,
        element_count=16,
        youngs_modulus=1e11,
        poisson_ratio=0.4,
        density=7850.0,
        base_position=np.array([0.01, -0.02, 0.03]),
        direction=np.array([1.0, 2.0, -0.5]),
    )
    config.update(overrides)
    return NeedleModel(**config)


def _deformed(model, seed=0, translation=1e-3, rotation=0.2):
    rng = np.random.default_rng(seed)
    delta = rng.normal(size=(model.node_count, 6)) * np.array([translation] * 3 + [rotation] * 3)
    return model.apply_increment(*model.rest_state(), delta.ravel())


# ---------------------------------------------------------------- configuration
@pytest.mark.parametrize(
    "field, value",
    [
        ("length", 0.0),
        ("radius", -1e-3),
        ("element_count", 0),
        ("element_count", 2.5),
        ("youngs_modulus", np.nan),
        ("poisson_ratio", 0.5),
        ("density", 0.0),
        ("direction", np.zeros(3)),
        ("base_position", np.ones(2)),
        ("up", np.array([2.0, 4.0, -1.0])),
    ],
)
def test_invalid_configuration_names_the_field(field, value):
    with pytest.raises(ValueError, match=field if field != "up" else "parallel"):
        _model(**{field: value})


def test_section_properties():
    # Solid circle: A = πr², I = πr⁴/4, J = πr⁴/2, G = E/(2(1+ν)), κ = 6(1+ν)/(7+6ν) (Cowper 1966).
    section = NeedleSection(radius=2e-3, youngs_modulus=2e11, poisson_ratio=0.3, density=7850.0)
    assert section.area == pytest.approx(np.pi * 4e-6, rel=1e-15)
    assert section.second_moment == pytest.approx(np.pi * 16e-12 / 4, rel=1e-15)
    assert section.polar_moment == pytest.approx(2 * section.second_moment, rel=1e-15)
    assert section.shear_modulus == pytest.approx(2e11 / 2.6, rel=1e-15)
    assert section.shear_coefficient == pytest.approx(7.8 / 8.8, rel=1e-15)


def test_rest_state_and_dof_layout():
    model = _model()
    positions, frames = model.rest_state()
    direction = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    assert positions.shape == (17, 3) and frames.shape == (17, 3, 3) and model.dof_count == 102
    assert np.allclose(positions[-1], model.base_position + 0.32 * direction, atol=1e-15)
    assert np.allclose(frames[:, :, 0], direction, atol=1e-15)
    assert np.allclose(frames @ np.swapaxes(frames, 1, 2), np.eye(3), atol=1e-15)
    assert np.allclose(np.linalg.det(frames), 1.0, atol=1e-15)
    assert np.array_equal(model.base_dofs, np.arange(6))
    assert np.array_equal(model.tip_dofs, 96 + np.arange(6))
    assert np.allclose(model.element_frames(positions, frames), frames[:-1], atol=1e-15)


def test_apply_increment_uses_world_frame_rotations():
    # frames_new = exp(Δθ) frames: a rotation of π/2 about world z maps material axis 0 = x to y.
    model = _model(direction=np.array([1.0, 0.0, 0.0]), element_count=2)
    positions, frames = model.rest_state()
    delta = np.zeros(model.dof_count)
    delta[6 + 5] = np.pi / 2
    delta[6 + 1] = 1e-3
    new_positions, new_frames = model.apply_increment(positions, frames, delta)
    assert np.allclose(new_frames[1][:, 0], [0.0, 1.0, 0.0], atol=1e-15)
    assert np.allclose(new_frames[0], frames[0], atol=0)
    assert new_positions[1] - positions[1] == pytest.approx([0.0, 1e-3, 0.0], abs=1e-17)


# ---------------------------------------------------------------- internal forces and tangents
def test_rigid_motions_give_zero_internal_forces():
    # Reference: co-rotational forces vanish for rigid motions. Round-off: coordinates of size L carry ε L,
    # giving forces ε L (E A / l₀) per node; tolerance 100 of those (moments: ε (E I / l₀) per radian).
    model = _model()
    positions, frames = model.rest_state()
    s = model.section
    force_tol = 100 * EPS * (model.length + 1.0) * s.youngs_modulus * s.area / model.element_length
    moment_tol = 100 * EPS * s.youngs_modulus * s.second_moment / model.element_length
    rotation = rotation_matrix(np.array([[0.0, 0.0, np.pi / 2]]))[0]
    for moved_positions, moved_frames in [
        (positions + np.array([0.3, -1.0, 0.2]), frames),
        (positions @ rotation.T, rotation @ frames),
        (positions @ rotation.T @ rotation.T, rotation @ rotation @ frames),  # 180°
    ]:
        forces = model.internal_forces(moved_positions, moved_frames).reshape(-1, 6)
        assert np.abs(forces[:, :3]).max() < force_tol
        assert np.abs(forces[:, 3:]).max() < moment_tol


def test_internal_forces_are_the_gradient_of_the_strain_energy():
    # f_int = ∂U/∂DoFs with world-frame rotation increments; central differences (relative error ~1e-7).
    model = _model(element_count=4)
    positions, frames = _deformed(model)
    forces = model.internal_forces(positions, frames)
    numeric = np.empty(model.dof_count)
    for i in range(model.dof_count):
        step = 1e-7 * (model.element_length if i % 6 < 3 else 1.0)
        e = np.zeros(model.dof_count)
        e[i] = step
        numeric[i] = (
            model.strain_energy(*model.apply_increment(positions, frames, e))
            - model.strain_energy(*model.apply_increment(positions, frames, -e))
        ) / (2 * step)
    per_node = np.abs(forces.reshape(-1, 6))
    scale = np.concatenate([np.full(3, per_node[:, :3].max()), np.full(3, per_node[:, 3:].max())])
    assert np.all(np.abs(numeric - forces).reshape(-1, 6) < 1e-6 * scale)


def test_consistent_tangent_matches_finite_differences_of_internal_forces():
    # The "consistent" tangent is the derivative of internal_forces (geometric stiffness included); checked
    # against global central differences with a different step (1e-6 instead of the kernel's 1e-5), so both
    # truncation errors are ≤ 1e-10 relative and round-off ≤ 1e-8: tolerance 1e-6 of the column scale.
    model = _model(element_count=5)
    positions, frames = _deformed(model, translation=3e-3, rotation=0.3)
    tangent = model.tangent_stiffness(positions, frames, kind="consistent").toarray()
    for i in range(model.dof_count):
        step = 1e-6 * (model.element_length if i % 6 < 3 else 1.0)
        e = np.zeros(model.dof_count)
        e[i] = step
        column = (
            model.internal_forces(*model.apply_increment(positions, frames, e))
            - model.internal_forces(*model.apply_increment(positions, frames, -e))
        ) / (2 * step)
        assert np.allclose(tangent[:, i], column, rtol=0, atol=1e-6 * np.abs(column).max())


def test_corotated_tangent_is_exact_at_rigidly_moved_rest_states_only():
    # R_e K_e R_eᵀ omits the geometric stiffness, which vanishes when the internal forces vanish: at the rest
    # state rotated by 90° both tangents agree (to the 1e-9 accuracy of the consistent one); on a loaded state
    # they differ by the geometric stiffness, of the order of the internal forces over the element length.
    model = _model(element_count=6)
    rotation = rotation_matrix(np.array([[np.pi / 2, 0.0, 0.0]]))[0]
    positions, frames = model.rest_state()
    positions, frames = positions @ rotation.T, rotation @ frames
    corotated = model.tangent_stiffness(positions, frames).toarray()
    consistent = model.tangent_stiffness(positions, frames, kind="consistent").toarray()
    assert np.allclose(corotated, corotated.T, rtol=0, atol=1e-14 * np.abs(corotated).max())
    assert np.abs(consistent - corotated).max() < 1e-8 * np.abs(corotated).max()
    deformed = _deformed(model, translation=5e-3, rotation=0.3)
    difference = np.abs(
        model.tangent_stiffness(*deformed, kind="consistent") - model.tangent_stiffness(*deformed)
    )
    assert difference.max() > 1e-4 * np.abs(corotated).max()


def test_tangent_sparsity_is_block_tridiagonal():
    model = _model(element_count=7)
    tangent = model.tangent_stiffness(*_deformed(model))
    rows, cols = tangent.nonzero()
    assert np.all(np.abs(rows // 6 - cols // 6) <= 1)
    assert tangent.nnz <= 36 * (3 * model.node_count - 2)


def test_lumped_mass_totals():
    # Σ translational mass per axis = ρ A L; Σ rotary inertia about the needle axis = ρ J L, about a
    # transverse axis ρ I L (lumped, cross-section inertia only). Also with rotated frames.
    model = _model()
    s = model.section
    for frames in (None, _deformed(model)[1]):
        mass = model.mass_matrix(frames).toarray()
        assert np.allclose(mass, mass.T, atol=0)
        assert np.sum(mass[0::6, 0::6]) == pytest.approx(s.density * s.area * model.length, rel=1e-12)
        rotary = mass.reshape(model.node_count, 6, model.node_count, 6)[
            np.arange(model.node_count), 3:, np.arange(model.node_count), 3:
        ]
        assert np.trace(rotary.sum(axis=0)) == pytest.approx(
            s.density * model.length * (s.polar_moment + 2 * s.second_moment), rel=1e-12
        )
    axial = model.direction
    rest_rotary = model.mass_matrix().toarray()[3:6, 3:6]
    assert axial @ rest_rotary @ axial == pytest.approx(s.density * s.polar_moment * model.element_length / 2)


# ---------------------------------------------------------------- centreline
def test_centreline_interpolates_nodes_and_is_straight_at_rest():
    model = _model()
    positions, frames = model.rest_state()
    assert np.allclose(
        model.centreline_points(positions, frames, model.rest_arc_lengths), positions, atol=1e-15
    )
    s = np.linspace(0.0, model.length, 53)
    expected = model.base_position + s[:, None] * model.direction
    assert np.allclose(model.centreline_points(positions, frames, s), expected, atol=1e-15)
    assert np.allclose(model.centreline_tangents(positions, frames, s), model.direction, atol=1e-15)
    deformed = _deformed(model)
    assert np.allclose(model.centreline_points(*deformed, model.rest_arc_lengths), deformed[0], atol=1e-15)
    with pytest.raises(ValueError, match="arc lengths"):
        model.centreline_points(positions, frames, np.array([model.length * 1.01]))


def _circular_arc(model, radius):
    """Nodes on a circle of the given radius [m] in the plane of material axes 0 and 1, frames tangent."""
    s = model.rest_arc_lengths
    angles = s / radius
    d, u = model.rest_frame[:, 0], model.rest_frame[:, 1]
    positions = model.base_position + radius * (
        np.sin(angles)[:, None] * d + (1 - np.cos(angles))[:, None] * u
    )
    axis = np.cross(d, u)
    frames = rotation_matrix(angles[:, None] * axis) @ model.rest_frame
    return positions, frames


def test_centreline_reproduces_a_circular_arc_at_fourth_order():
    # Reference: pure bending makes the needle a circle; a cubic Hermite interpolant with exact end slopes has
    # error O(l⁴/ρ³). Fitted rate 4 ± 0.3 over n = 4..32 elements.
    errors = []
    counts = np.array([4, 8, 16, 32])
    for count in counts:
        model = _model(element_count=int(count))
        radius = 0.5
        positions, frames = _circular_arc(model, radius)
        s = np.linspace(0.0, model.length, 401)
        points = model.centreline_points(positions, frames, s)
        centre = model.base_position + radius * model.rest_frame[:, 1]
        errors.append(np.abs(np.linalg.norm(points - centre, axis=1) - radius).max())
    rate = -np.polyfit(np.log(counts), np.log(errors), 1)[0]
    assert rate == pytest.approx(4.0, abs=0.3)


@pytest.mark.parametrize("offset", [0.0, -1e-12, 1e-12])
def test_centreline_jacobian_matches_finite_differences(offset):
    # J = ∂point/∂DoFs (world-frame rotation increments), at arc lengths inside elements and on nodes (±1e-12,
    # where the element changes), on a deformed state; central differences, tolerance 1e-6 relative to the
    # column scale (translations: 1; rotations: the lever arm ≈ l₀).
    model = _model(element_count=4)
    positions, frames = _deformed(model, translation=3e-3, rotation=0.3)
    s = np.clip(
        np.array([0.0, 0.013, model.element_length, 2 * model.element_length, 0.29, model.length]) + offset,
        0.0,
        model.length,
    )
    jacobian = model.centreline_jacobian(positions, frames, s)
    assert jacobian.shape == (3 * s.size, model.dof_count)
    dense = jacobian.toarray()
    for i in range(model.dof_count):
        step = 1e-7 * (model.element_length if i % 6 < 3 else 1.0)
        e = np.zeros(model.dof_count)
        e[i] = step
        numeric = (
            model.centreline_points(*model.apply_increment(positions, frames, e), s)
            - model.centreline_points(*model.apply_increment(positions, frames, -e), s)
        ) / (2 * step)
        scale = 1.0 if i % 6 < 3 else model.element_length
        assert np.allclose(dense[:, i], numeric.ravel(), rtol=0, atol=1e-6 * scale)


def test_centreline_tangents_are_the_arc_length_derivative():
    # Unit tangents = normalised d point/d s (central differences inside elements, relative error ~1e-8).
    model = _model(element_count=4)
    positions, frames = _deformed(model, translation=3e-3, rotation=0.3)
    s = np.array([0.01, 0.05, 0.13, 0.2, 0.31])
    h = 1e-6
    numeric = (
        model.centreline_points(positions, frames, s + h) - model.centreline_points(positions, frames, s - h)
    ) / (2 * h)
    numeric /= np.linalg.norm(numeric, axis=1, keepdims=True)
    assert np.allclose(model.centreline_tangents(positions, frames, s), numeric, atol=1e-7)


def test_project_on_centreline_recovers_known_closest_points():
    # Points placed at distance 1 mm from the curve along a direction normal to its tangent, at known arc
    # lengths, project back to them (the offset is below the curvature radius, so the foot point is unique).
    # Tolerance: the Gauss–Newton refinement converges to round-off; 1e-9 m.
    model = _model(element_count=8)
    positions, frames = _circular_arc(model, 0.4)
    s = np.linspace(0.004, model.length - 0.004, 40)
    points = model.centreline_points(positions, frames, s)
    tangents = model.centreline_tangents(positions, frames, s)
    normal = np.cross(tangents, model.rest_frame[:, 2] + 0.3 * model.rest_frame[:, 1])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    arc, closest, distance = model.project_on_centreline(positions, frames, points + 1e-3 * normal)
    assert np.allclose(arc, s, atol=1e-9)
    assert np.allclose(closest, points, atol=1e-9)
    assert np.allclose(distance, 1e-3, atol=1e-9)
    # Beyond the tip and behind the base: the end points.
    tip_direction = model.centreline_tangents(positions, frames, np.array([model.length]))[0]
    outside = np.array([positions[-1] + 0.01 * tip_direction, positions[0] - 0.01 * model.direction])
    arc, closest, distance = model.project_on_centreline(positions, frames, outside)
    assert np.allclose(arc, [model.length, 0.0], atol=0)
    assert np.allclose(distance, 0.01, atol=1e-12)


def test_centreline_memo_is_keyed_by_the_configuration_not_the_arrays():
    # The element kinematics kept per configuration (NeedleModel._element_kinematics) give the bits a model
    # without a memo computes, for several configurations evaluated in turn, and an array changed in place
    # is a new configuration.
    model = _model()
    configurations = [_deformed(model, seed=seed) for seed in range(6)]  # more than the memo keeps
    arcs = np.linspace(0.0, model.length, 23)
    for positions, frames in [*configurations, *configurations[::-1]]:
        fresh = _model()
        np.testing.assert_array_equal(
            model.centreline_points(positions, frames, arcs), fresh.centreline_points(positions, frames, arcs)
        )
        np.testing.assert_array_equal(
            model.centreline_jacobian(positions, frames, arcs).toarray(),
            fresh.centreline_jacobian(positions, frames, arcs).toarray(),
        )
        queries = model.centreline_points(positions, frames, arcs) + 1e-3
        for got, expected in zip(
            model.project_on_centreline(positions, frames, queries),
            fresh.project_on_centreline(positions, frames, queries),
            strict=True,
        ):
            np.testing.assert_array_equal(got, expected)
    positions, frames = configurations[0]
    before = model.centreline_points(positions, frames, arcs)
    positions[3] += 1e-3
    after = model.centreline_points(positions, frames, arcs)
    np.testing.assert_array_equal(after, _model().centreline_points(positions, frames, arcs))
    assert not np.array_equal(before, after)
