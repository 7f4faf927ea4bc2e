"""refsim's supernodal Cholesky (refsim.fem.supernodal, the "supernodal" linear solver): its symbolic
structure equals a brute-force elimination, its factor meets Cholesky's backward error bound, its solves,
partial inverse blocks and marked solves equal dense references within κ(A) ε bounds, on FEM-like patterns and
the cube's step matrix."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from refsim.fem.linear import LinearSolverError, available_linear_solvers, make_linear_solver
from refsim.fem.supernodal import SymbolicFactor
from tests.fem.test_linear import spd_matrix

EPS = np.finfo(float).eps
ORDERINGS = ["minimum-degree"] + (["metis"] if "pardiso" in available_linear_solvers() else [])


def node_block_matrix(nodes: int, seed: int, shift: float = 0.5) -> sp.csr_matrix:
    """An SPD matrix with the pattern of a 3-D elasticity stiffness: a random node graph (a grid's edges plus
    random long ones) with a dense 3×3 block per node pair, made SPD by diagonal dominance."""
    rng = np.random.default_rng(seed)
    side = round(nodes ** (1 / 3))
    grid = spd_matrix(side**3, seed)  # the grid's edges
    extra = rng.integers(0, side**3, size=(side**3 // 4, 2))
    graph = sp.csr_matrix((np.ones(extra.shape[0]), (extra[:, 0], extra[:, 1])), shape=grid.shape)
    graph = ((abs(grid) + graph + graph.T) > 0).astype(float)
    graph.setdiag(0.0)
    graph.eliminate_zeros()
    coo = sp.triu(graph).tocoo()
    blocks = rng.uniform(-1.0, 1.0, size=(coo.nnz, 3, 3))
    m = 3 * graph.shape[0]
    rows = (3 * coo.row[:, None, None] + np.arange(3)[:, None]).repeat(3, 2)
    cols = (3 * coo.col[:, None, None] + np.arange(3)[None, :]).repeat(3, 1)
    off = sp.csr_matrix((blocks.ravel(), (rows.ravel(), cols.ravel())), shape=(m, m))
    off = off + off.T
    dominance = np.asarray(abs(off).sum(axis=1)).ravel()
    matrix = (off + sp.diags(dominance + shift)).tocsr()
    matrix.sort_indices()
    return matrix


def cube_matrix() -> sp.csr_matrix:
    """The cube's step matrix A = M/dt² + C/dt + K on its free DoFs at rest (8 cells per axis: 1944 DoFs)."""
    from refsim.fem.bench import _DT, cube_model
    from refsim.fem.tissue import TissueState

    model = cube_model(8)
    state = TissueState(positions=model.rest_positions, velocities=np.zeros_like(model.rest_positions))
    matrix = sp.csr_matrix(model.assemble_step(state, _DT).matrix)
    matrix.sort_indices()
    return matrix


def order_of(matrix: sp.csr_matrix, ordering: str) -> np.ndarray:
    return make_linear_solver(f"supernodal:{ordering}")._order(matrix)


def brute_force_structure(matrix: sp.csr_matrix, order: np.ndarray) -> np.ndarray:
    """The structural pattern of L by symbolic Gaussian elimination on the dense boolean pattern of P A Pᵀ
    (no cancellation): column j's pattern joins every later column it touches."""
    pattern = matrix[order][:, order].toarray() != 0
    n = pattern.shape[0]
    lower = np.tril(pattern | pattern.T)
    for j in range(n):
        below = np.flatnonzero(lower[j + 1 :, j]) + j + 1
        lower[np.ix_(below, below)] |= np.tril(np.ones((below.size, below.size), bool))
    return lower


def factor_dense(factor: SymbolicFactor) -> np.ndarray:
    """L from the supernodal storage, dense, in the factor's order."""
    dense = np.zeros((factor.n, factor.n))
    for s in range(factor.first.size - 1):
        width = factor.first[s + 1] - factor.first[s]
        rows = factor.rows[factor.row_start[s] : factor.row_start[s + 1]]
        block = factor.values[factor.value_start[s] : factor.value_start[s + 1]].reshape(width, rows.size).T
        dense[np.ix_(rows, np.arange(factor.first[s], factor.first[s + 1]))] = np.tril(block, 0)[: rows.size]
    return np.tril(dense)


@pytest.mark.parametrize("ordering", ORDERINGS)
@pytest.mark.parametrize("seed", [0, 1])
def test_symbolic_structure_equals_a_brute_force_elimination(ordering, seed):
    matrix = node_block_matrix(64, seed)
    fundamental = SymbolicFactor(matrix, order_of(matrix, ordering), relaxation=())
    structure = brute_force_structure(matrix, fundamental.permutation)
    n = matrix.shape[0]
    # elimination tree: the first off-diagonal row of each column of L (Liu 1990), -1 for a root
    expected_parent = np.array(
        [next(iter(np.flatnonzero(structure[j + 1 :, j]) + j + 1), -1) for j in range(n)]
    )
    np.testing.assert_array_equal(fundamental.parent, expected_parent)
    np.testing.assert_array_equal(fundamental.column_counts, structure.sum(axis=0))
    # fundamental supernodes hold exactly L's pattern: each column's stored rows are its structural rows
    for fundamental_only, factor in (
        (True, fundamental),
        (False, SymbolicFactor(matrix, order_of(matrix, ordering))),  # relaxed: a superset
    ):
        structure = brute_force_structure(matrix, factor.permutation)
        stored = np.zeros((n, n), bool)
        for s in range(factor.first.size - 1):
            rows = factor.rows[factor.row_start[s] : factor.row_start[s + 1]]
            for j in range(factor.first[s], factor.first[s + 1]):
                stored[rows[rows >= j], j] = True
        if fundamental_only:
            np.testing.assert_array_equal(stored, structure)
        else:
            assert np.all(stored[structure])
            assert factor.first.size <= fundamental.first.size


@pytest.mark.parametrize("ordering", ORDERINGS)
@pytest.mark.parametrize(
    "matrix", [node_block_matrix(125, 2), node_block_matrix(216, 3, shift=1e-3), spd_matrix(343, 4, 0.01)]
)
def test_factor_meets_the_cholesky_backward_error_bound(matrix, ordering):
    # Higham, Accuracy and Stability of Numerical Algorithms, Thm 10.3: the computed L satisfies
    # L Lᵀ = P A Pᵀ + ΔA with |ΔA| ≤ γ_{n+1} |L| |Lᵀ|, γ_k = k ε / (1 - k ε), whatever the summation order.
    factor = SymbolicFactor(matrix, order_of(matrix, ordering))
    factor.factorise(matrix.data)
    lower = factor_dense(factor)
    permuted = matrix[factor.permutation][:, factor.permutation].toarray()
    k = matrix.shape[0] + 1
    gamma = k * EPS / (1 - k * EPS)
    bound = gamma * np.abs(lower) @ np.abs(lower).T
    assert np.all(np.abs(lower @ lower.T - permuted) <= bound)


@pytest.mark.parametrize("ordering", ORDERINGS)
def test_solves_equal_scipy_on_fem_patterns(ordering):
    solver = make_linear_solver(f"supernodal:{ordering}")
    rng = np.random.default_rng(5)
    for seed in range(3):  # one pattern, three numeric factorisations (the analysis is kept)
        matrix = node_block_matrix(216, 10, shift=10.0 ** (-seed))
        matrix = sp.csr_matrix((matrix.data * rng.uniform(0.9, 1.1), matrix.indices, matrix.indptr))
        solver.factorise(matrix)
        rhs = rng.standard_normal((matrix.shape[0], 4))
        expected = spla.spsolve(matrix.tocsc(), rhs)
        # both are backward stable: relative forward error ≲ κ(A) ε each (Higham ch. 7, 10)
        bound = 20 * np.linalg.cond(matrix.toarray()) * EPS * np.abs(expected).max()
        np.testing.assert_allclose(solver.solve(rhs), expected, rtol=0, atol=bound)
        np.testing.assert_allclose(solver.solve(rhs[:, 1]), expected[:, 1], rtol=0, atol=bound)
        half = solver.half_solve(rhs)
        reference = rhs.T @ expected
        np.testing.assert_allclose(half.T @ half, reference, rtol=0, atol=bound * np.abs(rhs).sum(0).max())


def test_upper_triangle_alone_gives_the_bits_of_full_storage():
    matrix = node_block_matrix(125, 6)
    full, upper = make_linear_solver("supernodal"), make_linear_solver("supernodal")
    full.factorise(matrix)
    upper.factorise(sp.triu(matrix, format="csr"))
    rhs = np.arange(matrix.shape[0], dtype=float)
    np.testing.assert_array_equal(full.solve(rhs), upper.solve(rhs))


@pytest.mark.parametrize("ordering", ORDERINGS)
def test_partial_inverse_block_equals_the_dense_inverse(ordering):
    matrix = node_block_matrix(216, 7, shift=0.05)
    dense = matrix.toarray()
    inverse = np.linalg.inv(dense)
    bound = 10 * np.linalg.cond(dense) * EPS * np.abs(inverse).max()  # κ(A) ε (Higham ch. 7, 10)
    solver = make_linear_solver(f"supernodal:{ordering}")
    solver.factorise(matrix)
    rhs = np.linspace(-1.0, 1.0, matrix.shape[0])
    unmarked = solver.solve(rhs)
    for positions, marks in (
        (np.array([3, 40, 41, 200]), np.array([3, 7, 40, 41, 99, 200, 300])),  # marks a superset
        (np.array([10, 11, 12]), np.array([10, 11, 12])),
    ):
        solver.mark(marks)
        np.testing.assert_array_equal(solver.marked, marks)
        block = solver.inverse_block(positions)
        np.testing.assert_allclose(block, inverse[np.ix_(positions, positions)], rtol=0, atol=bound)
        # the factor does not depend on the marks: a full solve keeps its bits
        np.testing.assert_array_equal(solver.solve(rhs), unmarked)
    with pytest.raises(ValueError, match="marked"):
        solver.inverse_block(np.array([0]))


def test_paths_hold_every_row_a_unit_load_reaches():
    # The forward solve of a unit load on position p is non-zero only on the etree path from p: the
    # supernodes of the marked paths must hold every non-zero of the full forward solves (and be closed
    # under the parent, which the compact numbering needs).
    matrix = node_block_matrix(216, 8)
    solver = make_linear_solver("supernodal")
    solver.factorise(matrix)
    marks = np.array([0, 1, 2, 300, 301, 500])
    solver.mark(marks)
    supernodes, compact, columns = solver._marked_paths()
    factor = solver._factor
    loads = np.zeros((matrix.shape[0], marks.size))
    loads[marks, np.arange(marks.size)] = 1.0
    reached = np.flatnonzero(np.any(factor.forward(loads) != 0.0, axis=1))
    assert np.all(compact[reached] >= 0)
    assert columns == np.count_nonzero(compact >= 0) < matrix.shape[0]
    parent_of = factor._supernode_parent()
    assert set(parent_of[supernodes][parent_of[supernodes] >= 0]) <= set(supernodes)


def test_solve_of_a_load_on_the_marks_equals_the_full_solve():
    matrix = node_block_matrix(216, 9)
    marks = np.array([4, 5, 6, 170, 171, 300])
    solver = make_linear_solver("supernodal")
    solver.mark(marks)
    solver.factorise(matrix)
    load = np.zeros(matrix.shape[0])
    load[marks] = np.random.default_rng(7).standard_normal(marks.size)
    np.testing.assert_array_equal(solver.solve_marked(load), solver.solve(load))
    load[[4, 300]] = 0.0
    np.testing.assert_array_equal(solver.solve_marked(load), solver.solve(load))
    load[10] = 1.0
    with pytest.raises(ValueError, match="off the marked"):
        solver.solve_marked(load)


def test_cube_step_matrix_solves_and_blocks_equal_dense_references():
    matrix = cube_matrix()
    dense = matrix.toarray()
    inverse = np.linalg.inv(dense)
    condition = np.linalg.cond(dense)
    solver = make_linear_solver("supernodal")
    solver.factorise(sp.triu(matrix, format="csr"))  # what the exact strategy hands it (upper storage)
    rhs = np.random.default_rng(11).standard_normal((matrix.shape[0], 3))
    expected = inverse @ rhs
    bound = 10 * condition * EPS * np.abs(expected).max()
    np.testing.assert_allclose(solver.solve(rhs), expected, rtol=0, atol=bound)
    positions = np.sort(np.random.default_rng(12).choice(matrix.shape[0], 21, replace=False))
    solver.mark(positions)
    np.testing.assert_allclose(
        solver.inverse_block(positions),
        inverse[np.ix_(positions, positions)],
        rtol=0,
        atol=10 * condition * EPS * np.abs(inverse).max(),
    )


def test_a_matrix_that_is_not_positive_definite_is_named():
    matrix = node_block_matrix(64, 3)
    indefinite = (matrix - sp.identity(matrix.shape[0]) * 2 * sp.linalg.norm(matrix, 1)).tocsr()
    solver = make_linear_solver("supernodal")
    with pytest.raises(LinearSolverError, match="not positive definite"):
        solver.factorise(indefinite)
    with pytest.raises(LinearSolverError, match="before factorise"):
        solver.solve(np.ones(matrix.shape[0]))


def test_a_released_supernodal_solver_refuses_to_solve_and_can_start_again():
    matrix, marks = node_block_matrix(64, 4), np.array([1, 2, 90])
    rhs = np.arange(matrix.shape[0], dtype=float)
    solver = make_linear_solver("supernodal")
    solver.mark(marks)
    solver.factorise(matrix)
    expected = solver.solve(rhs)
    solver.release()
    for use in (lambda: solver.solve(rhs), lambda: solver.inverse_block(marks)):
        with pytest.raises(LinearSolverError, match="after release"):
            use()
    assert solver.marked is None
    solver.factorise(matrix)
    np.testing.assert_array_equal(solver.solve(rhs), expected)


def test_unknown_supernodal_ordering_is_named():
    with pytest.raises(ValueError, match="supernodal ordering 'amd'"):
        make_linear_solver("supernodal:amd")
