"""The needle's compiled kernels (refsim.fem.needle_kernels) hold the bits of the NumPy code they replace."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.fem import beam_element, needle_kernels
from refsim.fem.needle import NeedleModel
from refsim.geometry import rotations
from refsim.geometry.rotations import rotation_matrix


def _einsum_two_lanes() -> bool:
    """Whether this NumPy's ``einsum`` sums a contiguous axis of 3 in two lanes, (p₀ + p₂) + p₁ (the order the
    kernels repeat; NumPy's wheels built for SSE2/x86-64-v2 do). 1 + 2⁻⁶⁰ − 1 is 2⁻⁶⁰ in that order, 0 left
    to right."""
    a = np.array([[1.0, 2.0**-60, -1.0]])
    return bool(np.einsum("mi,mi->m", a, np.ones_like(a))[0] != 0.0)


TWO_LANES = _einsum_two_lanes()


def _same_bits(a, b) -> bool:
    """The bits of the NumPy code; on a NumPy that sums in another order (another SIMD width), agreement to
    rounding: 1e-12 of the result's largest entry (a dozen sums of a dozen terms, each within 1e-16)."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    if TWO_LANES or a.tobytes() == b.tobytes():
        return a.tobytes() == b.tobytes()
    scale = float(np.max(np.abs(b), initial=0.0))
    return bool(np.allclose(a, b, rtol=0.0, atol=1e-12 * max(scale, np.finfo(float).tiny)))


def _model(element_count=12):
    return NeedleModel(
        length=0.12,
        radius=4e-4,
        element_count=element_count,
        youngs_modulus=2e11,
        poisson_ratio=0.3,
        density=7850.0,
        base_position=np.array([0.01, -0.02, 0.03]),
        direction=np.array([0.3, -0.2, 1.0]),
    )


def _configuration(model, kind, seed=0):
    """The needle straight at rest, straight and moved rigidly, slightly bent or strongly bent."""
    positions, frames = model.rest_state()
    if kind == "rest":
        return positions, frames
    rng = np.random.default_rng(seed)
    if kind == "rigid":
        delta = np.tile(
            np.concatenate([rng.normal(size=3) * 1e-3, rng.normal(size=3) * 0.3]), model.node_count
        )
        return model.apply_increment(positions, frames, delta)
    scale = {"slightly bent": 1e-4, "bent": 0.3}[kind]
    delta = rng.normal(size=(model.node_count, 6)) * np.array([scale * 1e-2] * 3 + [scale] * 3)
    return model.apply_increment(positions, frames, delta.ravel())


KINDS = ["rest", "rigid", "slightly bent", "bent"]


def test_thresholds_are_the_numpy_code_s():
    assert needle_kernels._ROTATION_SMALL_ANGLE == rotations._SMALL_ANGLE
    assert needle_kernels._JACOBIAN_SMALL_ANGLE == beam_element._SMALL_ANGLE


def test_dot3_is_numpy_s_stacked_matmul():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(50, 3, 3)), rng.normal(size=(50, 3, 12))
    expected = a @ b
    fused = needle_kernels.matmul_fused()
    got = np.array(
        [
            [[needle_kernels._dot3(*a[s, i], *b[s, :, j], fused) for j in range(12)] for i in range(3)]
            for s in range(50)
        ]
    )
    assert _same_bits(got, expected)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("seed", range(4))
def test_element_kinematics_and_forces_have_the_numpy_bits(kind, seed):
    model = _model()
    positions, frames = _configuration(model, kind, seed)
    ends = (positions[:-1], positions[1:], frames[:-1], frames[1:])
    rest = np.full(model.element_count, model.element_length)
    got = beam_element.local_deformations(*ends, rest)
    expected = beam_element.local_deformations_reference(*ends, rest)
    assert got.keys() == expected.keys()
    for key in expected:
        assert _same_bits(got[key], expected[key]), key
    for a, b in zip(
        beam_element.corotational_frames(*ends),
        beam_element.corotational_frames_reference(*ends),
        strict=True,
    ):
        assert _same_bits(a, b)
    stiffness = model._reduced_stiffness
    for a, b in zip(
        beam_element.beam_element_forces(*ends, rest, stiffness),
        beam_element.beam_element_forces_reference(*ends, rest, stiffness),
        strict=True,
    ):
        assert _same_bits(a, b)


def test_element_kinematics_on_random_elements():
    # Elements far from any needle: random lengths, frames and rotations up to about 2 rad, one by one and in
    # stacks of every size from 1 to 20.
    rng = np.random.default_rng(2)
    for m in range(1, 21):
        a = rng.normal(size=(m, 3))
        b = a + rng.normal(size=(m, 3))
        qa = rotation_matrix(rng.normal(size=(m, 3)))
        qb = rotation_matrix(rng.normal(size=(m, 3)) * 0.5) @ qa
        rest = rng.uniform(0.5, 1.5, m)
        got = beam_element.local_deformations(a, b, qa, qb, rest)
        expected = beam_element.local_deformations_reference(a, b, qa, qb, rest)
        for key in expected:
            assert _same_bits(got[key], expected[key]), (m, key)
        k7 = rng.normal(size=(m, 7, 7))
        for x, y in zip(
            beam_element.beam_element_forces(a, b, qa, qb, rest, k7),
            beam_element.beam_element_forces_reference(a, b, qa, qb, rest, k7),
            strict=True,
        ):
            assert _same_bits(x, y)


def test_relative_rotation_near_pi_is_the_numpy_answer():
    # θ̄ within 1e-3 rad of π takes the NumPy code's symmetric-part branch.
    a, b = np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0]])
    # Both nodes turned by nearly π about an axis across the chord: the element frame keeps the chord, so
    # each node is nearly a half turn from it.
    qa = qb = rotation_matrix(np.array([[0.0, 0.0, np.pi - 1e-4]]))
    got = beam_element.local_deformations(a, b, qa, qb, np.ones(1))
    expected = beam_element.local_deformations_reference(a, b, qa, qb, np.ones(1))
    assert np.linalg.norm(got["deformations"][0, 1:4]) > np.pi - 1e-3
    for key in expected:
        assert _same_bits(got[key], expected[key]), key


@pytest.mark.parametrize(
    "second, message",
    [(np.zeros(3), "zero length"), (np.array([0.0, 1.0, 0.0]), "parallel")],
)
def test_degenerate_elements_raise_the_numpy_errors(second, message):
    a = np.zeros((2, 3))
    b = np.array([[1.0, 0.0, 0.0], second])
    frames = np.broadcast_to(np.eye(3), (2, 3, 3)).copy()
    for function in (beam_element.corotational_frames, beam_element.corotational_frames_reference):
        with pytest.raises(ValueError, match=message):
            function(a, b, frames, frames)
    with pytest.raises(ValueError, match=message):
        beam_element.local_deformations(a, b, frames, frames, np.ones(2))


@pytest.mark.parametrize("kind", KINDS)
def test_internal_forces_are_numpy_s_bincount(kind):
    model = _model()
    positions, frames = _configuration(model, kind, seed=3)
    forces, _ = beam_element.beam_element_forces_reference(
        positions[:-1], positions[1:], frames[:-1], frames[1:], model._rest_lengths, model._reduced_stiffness
    )
    expected = np.bincount(model._element_dofs.ravel(), weights=forces.ravel(), minlength=model.dof_count)
    assert _same_bits(model.internal_forces(positions, frames), expected)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("jacobian", [False, True])
def test_centreline_has_the_numpy_bits(kind, jacobian):
    model = _model()
    positions, frames = _configuration(model, kind, seed=4)
    rng = np.random.default_rng(5)
    ends = model.rest_arc_lengths  # element ends, 0 and the length among them
    arcs = np.concatenate([ends, rng.uniform(0.0, model.length, 20), [-1e-13, model.length * (1 + 1e-12)]])
    got = model._centreline(positions, frames, arcs, jacobian=jacobian)
    expected = model._centreline_reference(positions, frames, arcs, jacobian=jacobian)
    assert got.keys() == expected.keys()
    for key in expected:
        assert _same_bits(got[key], expected[key]), key


def test_locate_keeps_its_errors():
    model = _model()
    positions, frames = model.rest_state()
    for bad in ([np.nan], [0.01, -1e-3], [model.length * 1.01]):
        with pytest.raises(ValueError, match="arc lengths must lie in"):
            model.centreline_points(positions, frames, np.array(bad))
    with pytest.raises(ValueError, match="shape"):
        model.centreline_points(positions, frames, np.zeros((2, 2)))


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("samples_per_element", [1, 8])
def test_closest_points_have_the_numpy_bits(kind, samples_per_element):
    model = _model()
    positions, frames = _configuration(model, kind, seed=6)
    rng = np.random.default_rng(7)
    on_curve = model.centreline_points(positions, frames, rng.uniform(0.0, model.length, 12))
    points = np.concatenate(
        [
            on_curve + rng.normal(size=on_curve.shape) * 1e-3,
            on_curve[:2],  # on the centreline
            positions[[0, -1]] + np.array([[-0.01, 0.0, 0.0], [0.0, 0.01, 0.01]]),  # beyond either end
            positions[[3]],  # a node: an element end
        ]
    )
    got = model.project_on_centreline(positions, frames, points, samples_per_element=samples_per_element)
    samples, polyline = model._polyline(positions, frames, samples_per_element)
    expected = model._project_reference(positions, frames, points, samples, polyline)
    for a, b in zip(got, expected, strict=True):
        assert _same_bits(a, b)
    empty = model.project_on_centreline(positions, frames, np.zeros((0, 3)))
    assert [a.shape for a in empty] == [(0,), (0, 3), (0,)]


def test_closest_point_of_a_non_finite_point_raises_the_numpy_error():
    model = _model()
    positions, frames = model.rest_state()
    with pytest.raises(ValueError, match="arc lengths must lie in"):
        model.project_on_centreline(positions, frames, np.array([[np.nan, 0.0, 0.0]]))


@pytest.mark.parametrize("kind", KINDS)
def test_corotated_tangent_has_the_numpy_bits(kind):
    model = _model()
    positions, frames = _configuration(model, kind, seed=8)
    got = model.tangent_stiffness(positions, frames)
    expected = model._corotated_reference(positions, frames)
    assert _same_bits(got.indptr, expected.indptr) and _same_bits(got.indices, expected.indices)
    assert _same_bits(got.data, expected.data)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("scale", [0.0, 1e-6, 1e-4, 0.3, 2.0])
def test_increment_has_the_numpy_bits(kind, scale):
    # Rotation increments below, at and above the series' 1e-4 rad, and zero.
    model = _model()
    positions, frames = _configuration(model, kind, seed=9)
    delta = np.random.default_rng(10).normal(size=model.dof_count) * scale
    got = model.apply_increment(positions, frames, delta)
    expected = model._apply_increment_reference(positions, frames, delta)
    for a, b in zip(got, expected, strict=True):
        assert _same_bits(a, b)
    with pytest.raises(ValueError, match="delta must have shape"):
        model.apply_increment(positions, frames, delta[:-1])
