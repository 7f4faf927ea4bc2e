"""Constraint rows: Jacobians against the gap functions they linearise, bases, offsets and the path."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import scipy.sparse as sp

from refsim.constraints import (
    BILATERAL,
    FRICTION,
    InsertionPath,
    RigidNeedleGeometry,
    StepGeometry,
    concatenate,
    grow_path,
    insertion_block,
    orthonormal_basis,
    point_rows,
    points_beyond_tip,
)
from refsim.constraints.rows import (
    RowBlock,
    _orthonormal_basis_numpy,
    _point_rows_coo,
    stack_jacobians,
    trusted_block,
)
from refsim.geometry import TetLocator
from refsim.mesh import box_mesh


@pytest.mark.parametrize(
    "tangent",
    [[0, 0, 1], [0, 0, -1], [1, 0, 0], [1, 1e-12, 0], [1, 1, 1], [0.3, -0.2, 0.9], [1, 1, 0]],
)
def test_orthonormal_basis(tangent):
    t = np.asarray(tangent, float)[None, :]
    t /= np.linalg.norm(t)
    first, second = orthonormal_basis(t)
    frame = np.stack([first[0], second[0], t[0]], axis=1)
    np.testing.assert_allclose(frame.T @ frame, np.eye(3), atol=1e-15)
    assert np.linalg.det(frame) == pytest.approx(1.0, abs=1e-14)


def test_orthonormal_basis_compiled_is_numpys_bit_for_bit():
    # Random directions, axis ties (|t_i| equal: the first smallest axis is the helper) and signed zeros.
    rng = np.random.default_rng(3)
    tangents = rng.standard_normal((2000, 3)) * 10.0 ** rng.integers(-6, 1, size=(2000, 3))
    ties = np.array([[1, 1, 0], [1, 1, 1], [0, 0, 1], [-0.0, 0.0, -1], [1, -1, 1e-300], [0.6, 0.0, -0.8]])
    tangents = np.concatenate([tangents, ties])
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    got = orthonormal_basis(tangents)
    expected = _orthonormal_basis_numpy(tangents)
    for a, b in zip(got, expected, strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(np.signbit(a), np.signbit(b))


def test_point_rows_linearise_the_gap_exactly():
    # δ(x) = nᵀ(p − Σ_k w_k x_k) is affine in x, so H Δx = δ(x + Δx) − δ(x) to round-off.
    rng = np.random.default_rng(1)
    node_count = 20
    positions = rng.normal(size=(node_count, 3))
    nodes = rng.integers(0, node_count, size=(7, 4))
    weights = rng.dirichlet(np.ones(4), size=7)
    directions = rng.normal(size=(7, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    anchor = rng.normal(size=(7, 3))

    def gap(x):
        return np.einsum("ij,ij->i", directions, anchor - np.einsum("ik,ikj->ij", weights, x[nodes]))

    jacobian = point_rows(nodes, weights, directions, 3 * node_count)
    step = 1e-3 * rng.normal(size=(node_count, 3))
    np.testing.assert_allclose(jacobian @ step.ravel(), gap(positions + step) - gap(positions), atol=1e-14)


def _ring_like_rows(rng, points, per_point, nodes, repeats):
    """Rows as a ring coupling makes them: ``repeats`` rows per point on the same nodes (many shared, so
    each row has columns repeated three or more times), weights summing to one, unit directions."""
    node_rows = np.repeat(rng.integers(0, nodes, size=(points, per_point)), repeats, axis=0)
    weights = np.repeat(rng.dirichlet(np.ones(per_point), size=points), repeats, axis=0)
    directions = rng.standard_normal((points * repeats, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return node_rows, weights, directions


@pytest.mark.parametrize(
    ("points", "per_point", "nodes", "repeats"),
    [(26, 68, 60, 3), (26, 68, 729, 2), (5, 4, 30, 1), (1, 36, 10, 1), (40, 4, 2000, 3)],
)
def test_point_rows_are_the_coo_conversion_bit_for_bit(points, per_point, nodes, repeats):
    # SciPy sums a row's equal columns in the order its unstable row sort leaves them; the compiled path
    # sums in that same order (a probe sorted per distinct pattern), so data, indices and pointers are equal.
    rng = np.random.default_rng(per_point + nodes)
    node_rows, weights, directions = _ring_like_rows(rng, points, per_point, nodes, repeats)
    dof_count = 3 * nodes
    got = point_rows(node_rows, weights, directions, dof_count)
    expected = _point_rows_coo(node_rows, weights, directions, dof_count, sign=-1.0)
    assert got.shape == expected.shape
    np.testing.assert_array_equal(got.indptr, expected.indptr)
    np.testing.assert_array_equal(got.indices, expected.indices)
    np.testing.assert_array_equal(got.data, expected.data)
    assert got.indices.dtype == expected.indices.dtype and got.indptr.dtype == expected.indptr.dtype
    if (points, per_point, nodes) == (26, 68, 60):
        # The order matters: summing each column's entries in input order (a stable sort) changes bits.
        stable = np.zeros((len(node_rows), dof_count))
        for row, (row_nodes, row_weights, n) in enumerate(zip(node_rows, weights, directions, strict=True)):
            for node, weight in zip(row_nodes, row_weights, strict=True):
                stable[row, 3 * node : 3 * node + 3] += -weight * n
        assert not np.array_equal(stable, expected.toarray())


def test_point_rows_already_sorted_are_summed_in_input_order():
    # Rows whose columns are all non-decreasing are not sorted by SciPy (it checks first): equal columns are
    # summed in input order, which the compiled path keeps.
    nodes = np.array([[0, 0, 0, 1], [2, 2, 3, 3]])
    weights = np.array([[0.1, 0.7, 1e-17, 0.2], [0.3, 0.3, 0.3, 0.1]])
    directions = np.array([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8]])
    got = point_rows(nodes, weights, directions, 12)
    expected = _point_rows_coo(nodes, weights, directions, 12, sign=-1.0)
    np.testing.assert_array_equal(got.toarray(), expected.toarray())
    np.testing.assert_array_equal(got.indices, expected.indices)


def test_concatenate_offsets_contacts_and_shaft_rows():
    mesh = box_mesh(size=(0.02, 0.02, 0.02), cells=(2, 2, 2))
    locator = TetLocator(mesh.rest_positions, mesh.tets)
    points = np.array([[0.011, 0.012, 0.015], [0.011, 0.012, 0.01]])
    tets, bary = locator.locate(points)
    path = InsertionPath.empty().appended(tets, bary, 1)
    needle = RigidNeedleGeometry(np.array([0.011, 0.012, 0.05]), np.array([0.0, 0.0, -1.0]), 0.045)
    geometry = StepGeometry(mesh.tets, mesh.rest_positions, mesh.rest_positions, needle, needle)
    block = insertion_block(path, geometry, friction_coefficient=0.2)
    both = concatenate([block, block])
    assert both.row_count == 12
    np.testing.assert_array_equal(both.shaft_rows, [2, 5, 8, 11])
    np.testing.assert_array_equal(both.shaft_pairs[2:], [[6, 7], [9, 10]])
    sets = both.index_sets()
    assert set(sets["bilateral"]) == {0, 1, 3, 4, 6, 7, 9, 10}


def test_insertion_gaps_measure_the_lateral_offset_and_the_axial_slip():
    mesh = box_mesh(size=(0.02, 0.02, 0.02), cells=(2, 2, 2))
    locator = TetLocator(mesh.rest_positions, mesh.tets)
    points = np.array([[0.011, 0.012, 0.015], [0.011, 0.012, 0.01], [0.011, 0.012, 0.005]])
    tets, bary = locator.locate(points)
    path = InsertionPath.empty().appended(tets, bary, 1)
    direction = np.array([0.0, 0.0, -1.0])
    previous = RigidNeedleGeometry(np.array([0.011, 0.012, 0.05]), direction, 0.048)
    shift = np.array([1e-4, -2e-4, -3e-4])  # lateral (x, y) and axial (along −z, i.e. +3e-4 along the needle)
    free = RigidNeedleGeometry(previous.base + shift, direction, 0.048)
    geometry = StepGeometry(mesh.tets, mesh.rest_positions, mesh.rest_positions, previous, free)
    block = insertion_block(path, geometry, friction_coefficient=0.3)
    kinds = block.kind.reshape(3, 3)
    assert np.all(kinds[:, :2] == BILATERAL) and np.all(kinds[:, 2] == FRICTION)
    gaps = block.free_gap.reshape(3, 3)
    directions = block.directions.reshape(3, 3, 3)
    # The two bilateral gaps are the lateral offset in the plane normal to the needle.
    lateral = np.einsum("pkj,j->pk", directions[:, :2], shift)
    np.testing.assert_allclose(gaps[:, :2], lateral, atol=1e-15)
    # The friction gap is the axial slip over the step: the needle moved 3e-4 m along its direction.
    np.testing.assert_allclose(gaps[:, 2], 3e-4, atol=1e-15)
    np.testing.assert_allclose(block.shaft_friction_coefficient, 0.3)


@pytest.mark.parametrize("moves_per_step", [0.4, 1.0, 3.0])
def test_path_has_no_gaps_whatever_the_tip_speed(moves_per_step):
    # Issue 4: no two consecutive points farther apart than d_i, even when the tip moves 3 d_i per step.
    mesh = box_mesh(size=(0.02, 0.02, 0.02), cells=(3, 3, 3))
    spacing = 1e-3
    start = np.array([0.0101, 0.0093, 0.02])
    locator = TetLocator(mesh.rest_positions, mesh.tets)
    tets, bary = locator.locate(start[None, :] - [0, 0, 1e-9])
    path = InsertionPath.empty().appended(tets, bary, 0)
    depth = 0.0
    for step in range(1, int(0.015 / (moves_per_step * spacing)) + 1):
        depth = step * moves_per_step * spacing
        tip = start - np.array([0.0, 0.0, depth])
        path, _ = grow_path(
            path,
            tip=tip,
            tissue_positions=mesh.rest_positions,
            mesh_tets=mesh.tets,
            locator=locator,
            spacing=spacing,
            step=step,
        )
    positions = path.positions(mesh.rest_positions, mesh.tets)
    gaps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    assert np.all(gaps <= spacing * (1 + 1e-9))
    # Points every d_i from the entry to within d_i of the tip: depth/d_i (+1 for the entry point), ±1.
    assert abs(path.point_count - (depth // spacing + 1)) <= 1


@pytest.mark.parametrize("offset", [-1e-12, 0.0, 1e-12, -1e-9])
def test_a_tip_a_whole_spacing_deep_lays_its_point_whatever_the_round_off(offset):
    # A tip stopped a whole number of spacings below its entry (a scene's design depth) must get its point in
    # every run: the distance to the last point is d_i up to the solver's last digits (GS and exact once
    # differed by one point on cube_cut). SPACING_TOLERANCE = 1e-6 of d_i: offsets of 1e-12 and 1e-9 of d_i
    # (round-off, a solve to 1e-8 of the displacement) all lay the point; one of 1e-5 d_i short does not.
    from refsim.constraints.insertion import SPACING_TOLERANCE

    mesh = box_mesh(size=(0.02, 0.02, 0.02), cells=(3, 3, 3))
    spacing = 1e-3
    start = np.array([0.0101, 0.0093, 0.0199])
    locator = TetLocator(mesh.rest_positions, mesh.tets)

    def grown(depth):
        tets, bary = locator.locate(start[None, :])
        path = InsertionPath.empty().appended(tets, bary, 0)
        path, added = grow_path(
            path,
            tip=start - np.array([0.0, 0.0, depth]),
            tissue_positions=mesh.rest_positions,
            mesh_tets=mesh.tets,
            locator=locator,
            spacing=spacing,
            step=1,
        )
        return path, added

    path, added = grown(2 * spacing * (1.0 + offset))
    assert added == 2 and path.point_count == 3
    _, short = grown(spacing * (1.0 - 10 * SPACING_TOLERANCE))
    assert short == 0


def test_points_beyond_tip_after_withdrawal():
    needle = RigidNeedleGeometry(
        np.array([0.0, 0.0, 0.1]), np.array([0.0, 0.0, -1.0]), 0.05
    )  # tip at z = 0.05
    points = np.array(
        [[0.0, 0.0, 0.06], [0.0, 0.0, 0.05 + 1e-12], [0.0, 0.0, 0.05 - 1e-12], [0.001, 0.0, 0.04]]
    )
    path = InsertionPath.empty().appended(np.zeros(4, int), np.full((4, 4), 0.25), 0)
    np.testing.assert_array_equal(points_beyond_tip(path, points, needle), [False, False, True, True])


def _two_rows(**fields):
    import scipy.sparse as sp

    from refsim.constraints import TISSUE, UNILATERAL, RowBlock

    return RowBlock(
        jacobians={TISSUE: sp.csr_matrix(np.eye(2, 6))},
        free_gap=np.array([-1e-3, 2e-3]),
        kind=np.array([UNILATERAL, BILATERAL], dtype=np.int8),
        source=np.zeros(2, dtype=np.int8),
        points=np.zeros((2, 3)),
        directions=np.eye(3)[:2],
        **fields,
    )


def test_force_limits_become_box_rows_and_compliance_diagonal_joins_the_diagonal():
    # A unilateral row limited to L has 0 <= λ <= L; a bilateral one |λ| <= L (the box law of the solvers).
    block = _two_rows(force_limit=np.array([0.8, 2.0]), compliance_diagonal=np.array([1e-3, 0.0]))
    problem = block.problem(np.eye(2))
    np.testing.assert_array_equal(problem.box_rows, [0, 1])
    np.testing.assert_allclose(problem.box_lower, [0.0, -2.0])
    np.testing.assert_allclose(problem.box_upper, [0.8, 2.0])
    assert problem.unilateral.size == 0 and problem.bilateral.size == 0
    np.testing.assert_allclose(problem.compliance, np.diag([1.001, 1.0]))
    both = concatenate([block, _two_rows()])
    np.testing.assert_allclose(both.force_limit, [0.8, 2.0, np.inf, np.inf])
    np.testing.assert_allclose(both.compliance_diagonal, [1e-3, 0.0, 0.0, 0.0])


@pytest.mark.parametrize(
    "fields",
    [
        dict(force_limit=np.array([0.0, 1.0])),
        dict(force_limit=np.array([1.0, -np.inf])),
        dict(force_limit=np.array([np.nan, 1.0])),
        dict(force_limit=np.array([1.0, 2.0, 3.0])),
        dict(compliance_diagonal=np.array([-1.0, 0.0])),
        dict(compliance_diagonal=np.array([0.0, np.nan])),
        dict(compliance_diagonal=np.array([np.inf, 0.0])),
        dict(compliance_diagonal=np.array([0.0])),
    ],
)
def test_bad_limits_and_compliance_are_rejected(fields):
    with pytest.raises(ValueError):
        _two_rows(**fields)
    if "compliance_diagonal" in fields:
        with pytest.raises(ValueError, match="compliance_diagonal"):
            _two_rows().with_compliance_diagonal(fields["compliance_diagonal"])


def test_trusted_block_is_the_checked_constructors_block():
    # The builders whose fields are valid by construction skip RowBlock's checks: the same fields, the
    # Jacobians stored read-only without None values, the omitted fields their defaults (fresh arrays).
    checked = _two_rows(force_limit=np.array([0.8, np.inf]), compliance_diagonal=np.array([1e-3, 0.0]))
    given = {name: getattr(checked, name) for name in ("free_gap", "kind", "source", "points", "directions")}
    given.update(force_limit=checked.force_limit, compliance_diagonal=checked.compliance_diagonal)
    trusted = trusted_block(jacobians={**checked.jacobians, "other": None}, **given)
    assert type(trusted) is RowBlock and type(trusted.jacobians) is type(checked.jacobians)
    assert set(trusted.jacobians) == set(checked.jacobians)
    for name in checked.__dataclass_fields__:
        if name != "jacobians":
            a, b = getattr(trusted, name), getattr(checked, name)
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), name
    assert trusted.contacts is not trusted_block(jacobians={}, **given).contacts  # defaults not shared


def test_jacobians_by_body_stack_and_a_block_without_a_body_gives_it_zero_rows():
    from dataclasses import replace

    import scipy.sparse as sp

    from refsim.constraints import NEEDLE, TISSUE, empty_block

    rng = np.random.default_rng(7)
    tissue, needle = sp.csr_matrix(rng.standard_normal((2, 6))), sp.csr_matrix(rng.standard_normal((2, 12)))
    both = _two_rows()
    both = replace(both, jacobians={TISSUE: tissue, NEEDLE: needle})
    tissue_only = _two_rows()  # a block that does not touch the needle (e.g. a second needle's rows)
    stacked = concatenate([both, tissue_only])
    assert list(stacked.jacobians) == [TISSUE, NEEDLE]
    np.testing.assert_array_equal(stacked.jacobians[TISSUE].toarray()[:2], tissue.toarray())
    np.testing.assert_array_equal(stacked.jacobians[TISSUE].toarray()[2:], np.eye(2, 6))
    np.testing.assert_array_equal(stacked.jacobians[NEEDLE].toarray()[:2], needle.toarray())
    np.testing.assert_array_equal(stacked.jacobians[NEEDLE].toarray()[2:], 0.0)
    # A kinematic body (None, or no DoFs in empty_block) has no entry.
    assert NEEDLE not in replace(both, jacobians={TISSUE: tissue, NEEDLE: None}).jacobians
    assert set(empty_block({TISSUE: 6, NEEDLE: None}).jacobians) == {TISSUE}
    assert empty_block({TISSUE: 6, NEEDLE: 12}).jacobians[NEEDLE].shape == (0, 12)
    # The mapping is read-only, and Jacobians must match the rows and each other's widths.
    with pytest.raises(TypeError):
        stacked.jacobians[NEEDLE] = None
    with pytest.raises(ValueError, match="3 rows, expected 2"):
        replace(both, jacobians={TISSUE: sp.csr_matrix((3, 6))})
    narrow = replace(both, jacobians={TISSUE: sp.csr_matrix((2, 5))})
    with pytest.raises(ValueError, match="columns"):
        concatenate([both, narrow])


def test_stacked_jacobians_are_scipys_vstack():
    # The stacking concatenates data, indices and pointers as sp.vstack does: equal arrays, equal dtypes,
    # with blocks lacking a body (zero rows), empty blocks and duplicate-free canonical parts.
    import scipy.sparse as sp

    from refsim.constraints import NEEDLE, TISSUE

    rng = np.random.default_rng(4)
    parts = [
        {TISSUE: sp.random(5, 30, density=0.2, format="csr", random_state=1)},
        {TISSUE: sp.csr_matrix((0, 30))},
        {NEEDLE: sp.random(3, 12, density=0.5, format="csr", random_state=2)},
        {TISSUE: sp.csr_matrix(rng.standard_normal((2, 30))), NEEDLE: sp.csr_matrix((2, 12))},
    ]
    counts = [5, 0, 3, 2]
    got = stack_jacobians(parts, counts)
    for name, width in ((TISSUE, 30), (NEEDLE, 12)):
        expected = sp.vstack(
            [part.get(name, sp.csr_matrix((rows, width))) for part, rows in zip(parts, counts, strict=True)],
            format="csr",
        )
        for field in ("data", "indices", "indptr"):
            np.testing.assert_array_equal(getattr(got[name], field), getattr(expected, field))
            assert getattr(got[name], field).dtype == getattr(expected, field).dtype
        assert got[name].shape == expected.shape


def test_row_block_concatenate_keeps_every_per_row_field_of_each_instrument():
    # Two instruments' rows in one block: each block marked with its instrument and its needle's Jacobian
    # keyed by its body name (RowBlock.of_instrument); stacking keeps every per-row field in order, offsets
    # the index fields, and gives each needle zero rows in the other's part.
    import dataclasses

    import scipy.sparse as sp

    from refsim.constraints import AXIAL_FRICTION, LATERAL_FIRST, NEEDLE, TISSUE, RowBlock

    rng = np.random.default_rng(3)

    def block(seed: int):
        rows = _two_rows(
            force_limit=np.array([0.5 + seed, np.inf]),
            compliance_diagonal=np.array([1e-4 * seed, 0.0]),
            role=np.array([LATERAL_FIRST, AXIAL_FRICTION], dtype=np.int8),
            point=np.array([seed, -1]),
            anchor=np.array([np.nan, 0.01 * seed]),
        )
        needle = sp.csr_matrix(rng.standard_normal((2, 12)))
        return dataclasses.replace(rows, jacobians={**rows.jacobians, NEEDLE: needle}), needle

    (first, first_needle), (second, second_needle) = block(1), block(2)
    stacked = RowBlock.concatenate([first.of_instrument(0, "cutter"), second.of_instrument(1, "holder")])
    assert list(stacked.jacobians) == [TISSUE, "cutter", "holder"]
    np.testing.assert_array_equal(stacked.instrument, [0, 0, 1, 1])
    np.testing.assert_array_equal(stacked.instruments, [0, 0, 1, 1])
    np.testing.assert_array_equal(
        stacked.jacobians["cutter"].toarray(), np.vstack([first_needle.toarray(), np.zeros((2, 12))])
    )
    np.testing.assert_array_equal(
        stacked.jacobians["holder"].toarray(), np.vstack([np.zeros((2, 12)), second_needle.toarray()])
    )
    for name in (
        "free_gap",
        "kind",
        "source",
        "points",
        "directions",
        "force_limit",
        "compliance_diagonal",
        "role",
        "point",
    ):
        np.testing.assert_array_equal(
            getattr(stacked, name), np.concatenate([getattr(first, name), getattr(second, name)]), name
        )
    np.testing.assert_array_equal(stacked.anchor, np.concatenate([first.anchor, second.anchor]))
    # A block nobody marked has no instrument (−1), also after stacking with marked ones.
    np.testing.assert_array_equal(
        RowBlock.concatenate([first, second.of_instrument(1, "holder")]).instruments, [-1, -1, 1, 1]
    )


def test_point_rows_sort_orders_kept_by_pattern_give_the_fresh_bits():
    # The probe's permutation is kept per set of row patterns: the same patterns with other weights and
    # directions reuse it, other patterns (a changed node) get their own; each is the COO conversion's bits,
    # from an empty store and from a filled one.
    from refsim.constraints import rows as rows_module

    rng = np.random.default_rng(11)
    node_rows, weights, directions = _ring_like_rows(rng, 12, 36, 50, 3)
    other_weights, other_directions = rng.random(weights.shape), rng.standard_normal(directions.shape)
    changed = node_rows.copy()
    changed[4, 7] = (changed[4, 7] + 1) % 50
    rows_module._SORT_ORDERS.clear()
    rows_module._PLANS.clear()
    for nodes, w, n in (
        (node_rows, weights, directions),
        (node_rows, other_weights, other_directions),
        (changed, weights, directions),
        (node_rows, weights, directions),
    ):
        got = point_rows(nodes, w, n, 150)
        expected = _point_rows_coo(nodes, w, n, 150, sign=-1.0)
        np.testing.assert_array_equal(got.indptr, expected.indptr)
        np.testing.assert_array_equal(got.indices, expected.indices)
        np.testing.assert_array_equal(got.data, expected.data)
    assert len(rows_module._SORT_ORDERS) == 2  # the two pattern sets
    assert sum(len(plans) for plans in rows_module._PLANS.values()) == 2  # and their summation plans


def test_point_rows_keep_explicit_zeros_as_the_coo_conversion_does():
    # Ring points outside the tissue have weight 0 (and a ring's entries can cancel exactly): SciPy's
    # conversion keeps those entries as stored zeros, and so does the planned sum (same indices, same data,
    # signed zeros included).
    nodes = np.array([[0, 1, 1, 2], [3, 3, 0, 0]])
    weights = np.array([[0.0, 0.5, -0.5, 0.0], [0.0, 0.0, 0.25, 0.75]])
    directions = np.array([[1.0, 0.0, 0.0], [0.0, -0.6, 0.8]])
    got = point_rows(nodes, weights, directions, 12)
    expected = _point_rows_coo(nodes, weights, directions, 12, sign=-1.0)
    np.testing.assert_array_equal(got.indptr, expected.indptr)
    np.testing.assert_array_equal(got.indices, expected.indices)
    np.testing.assert_array_equal(got.data, expected.data)
    np.testing.assert_array_equal(np.signbit(got.data), np.signbit(expected.data))
    assert np.count_nonzero(got.data == 0.0) > 0 and got.nnz == expected.nnz


def test_summation_plan_kernels_match_their_numpy_reference():
    # The plan (positions of the entries in summation order, the start of each sum, indices, indptr) and the
    # planned sums against NumPy: a stable argsort per row of the probe's permutation, runs of equal columns.
    from refsim.constraints import rows as rows_module
    from refsim.constraints.kernels import planned_rows, row_entries, summation_plan

    rng = np.random.default_rng(5)
    node_rows, weights, directions = _ring_like_rows(rng, 9, 20, 30, 3)
    columns, values, pattern, firsts = row_entries(node_rows, weights, directions, -1.0)
    order = rows_module._sort_order(columns[firsts], 90)
    weight_at, direction_at, starts, indices, indptr = summation_plan(columns, order, pattern)
    width = columns.shape[1]
    expected_positions, expected_starts, expected_indices, expected_indptr = [], [0], [], [0]
    for row in range(columns.shape[0]):
        permutation = order[pattern[row]]
        sorted_columns = columns[row, permutation]
        assert np.all(np.diff(sorted_columns) >= 0)
        expected_positions.extend(row * width + permutation)
        breaks = np.flatnonzero(np.diff(sorted_columns)) + 1
        expected_starts.extend(row * width + np.append(breaks, width))
        expected_indices.extend(sorted_columns[np.append(0, breaks)])
        expected_indptr.append(len(expected_indices))
    expected_positions = np.array(expected_positions)
    rows_of, slots = np.divmod(expected_positions, width)
    np.testing.assert_array_equal(weight_at, rows_of * (width // 3) + slots // 3)
    np.testing.assert_array_equal(direction_at, rows_of * 3 + slots % 3)
    np.testing.assert_array_equal(starts, expected_starts)
    np.testing.assert_array_equal(indices, expected_indices)
    np.testing.assert_array_equal(indptr, expected_indptr)
    data = planned_rows(weights, directions, -1.0, weight_at, direction_at, starts)
    flat = values.ravel()[expected_positions]
    expected_data = [
        functools.reduce(lambda a, b: a + b, flat[s:e]) for s, e in zip(starts[:-1], starts[1:], strict=True)
    ]
    np.testing.assert_array_equal(data, expected_data)


def test_trusted_csr_is_the_checked_constructors_matrix():
    # The unchecked construction sets what SciPy's (data, indices, indptr) constructor sets: the same class,
    # shape, arrays and flags, and it behaves as that matrix in the operations the step uses.
    from refsim.constraints.rows import trusted_csr

    checked = sp.random(7, 40, density=0.2, format="csr", random_state=3)
    checked.sum_duplicates()
    fast = trusted_csr(checked.data.copy(), checked.indices.copy(), checked.indptr.copy(), checked.shape)
    assert type(fast) is type(checked) and fast.format == "csr" and fast.shape == checked.shape
    assert fast.has_sorted_indices and fast.has_canonical_format and fast.maxprint == checked.maxprint
    assert fast.indices.dtype == checked.indices.dtype and fast.indptr.dtype == checked.indptr.dtype
    fast.check_format(full_check=True)
    vector = np.arange(40.0)
    np.testing.assert_array_equal(fast @ vector, checked @ vector)
    np.testing.assert_array_equal(fast.T.toarray(), checked.T.toarray())
    stacked = sp.vstack([fast, checked]).toarray()
    np.testing.assert_array_equal(stacked, sp.vstack([checked, checked]).toarray())
    np.testing.assert_array_equal(fast[[1, 3]].toarray(), checked[[1, 3]].toarray())
    assert repr(fast) == repr(checked)


def test_interpolated_points_are_einsums_bits():
    # The compiled interpolation of material points against its NumPy reference, np.einsum("qk,qkj->qj"),
    # on ring-sized and tet-sized rows with zeros, signed zeros and mixed magnitudes: the same bits.
    from refsim.constraints.kernels import interpolated_points

    rng = np.random.default_rng(17)
    for trial in range(120):
        count = int(rng.integers(0, 30))
        per_point = (1, 3, 4, 12, 36, 68)[trial % 6]
        positions = rng.standard_normal((300, 3)) * 10.0 ** float(rng.integers(-4, 2))
        nodes = rng.integers(0, 300, size=(count, per_point))
        weights = rng.standard_normal((count, per_point))
        weights[rng.random(weights.shape) < 0.2] = 0.0
        weights[rng.random(weights.shape) < 0.05] = -0.0
        expected = np.einsum("qk,qkj->qj", weights, positions[nodes])
        got = interpolated_points(weights, positions, nodes)
        np.testing.assert_array_equal(got, expected)
        np.testing.assert_array_equal(np.signbit(got), np.signbit(expected))


def test_point_rows_kept_data_answer_only_for_the_same_bits():
    # The data of the last call on a plan is kept with its inputs' bytes: the same inputs give it again (a
    # copy: the matrices share no data), other weights or directions, even a zero of the other sign, give
    # their own data, each the COO conversion's.
    from refsim.constraints import rows as rows_module

    rows_module._PLANS.clear()
    nodes = np.array([[0, 1, 1, 2], [3, 3, 0, 0]])
    weights = np.array([[0.0, 0.5, 0.25, 0.25], [0.5, 0.5, 0.0, 0.0]])
    negative_zero = weights.copy()
    negative_zero[weights == 0.0] = -0.0
    directions = np.array([[1.0, 0.0, 0.0], [0.0, -0.6, 0.8]])
    first = point_rows(nodes, weights, directions, 12)
    again = point_rows(nodes, weights, directions, 12)
    assert again.data is not first.data
    np.testing.assert_array_equal(again.data, first.data)
    for w, n in ((negative_zero, directions), (weights, -directions), (weights, directions)):
        got = point_rows(nodes, w, n, 12)
        expected = _point_rows_coo(nodes, w, n, 12, sign=-1.0)
        np.testing.assert_array_equal(got.data, expected.data)
        np.testing.assert_array_equal(np.signbit(got.data), np.signbit(expected.data))
    assert not np.array_equal(
        np.signbit(point_rows(nodes, negative_zero, directions, 12).data), np.signbit(first.data)
    )


def test_problem_adds_the_compliance_diagonal_with_the_dense_sums_bits():
    # W + diag(c) without the dense diagonal: the same bits, a −0.0 off the diagonal turned +0.0 as the sum
    # with diag's zeros turns it; a float32 W or a non-square one takes the dense sum itself.
    rng = np.random.default_rng(3)
    added = np.array([1e-3, 0.0])
    block = _two_rows(compliance_diagonal=added)
    for compliance in (rng.standard_normal((2, 2)), np.array([[1.0, -0.0], [-0.0, 2.0]])):
        expected = compliance + np.diag(added)
        got = block.problem(compliance).compliance
        assert np.array_equal(got, expected) and np.array_equal(np.signbit(got), np.signbit(expected))
    single = rng.standard_normal((2, 2)).astype(np.float32)
    np.testing.assert_array_equal(block.problem(single).compliance, single + np.diag(added))
    with pytest.raises(ValueError):
        block.problem(np.ones((2, 3)))
