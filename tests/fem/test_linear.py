"""Sparse SPD solvers (refsim.fem.linear): every available backend equals a fresh dense factorisation to
round-off, keeps its analysis across refactorisations of one pattern, and the environment variable forces the
choice."""

from __future__ import annotations

import platform
import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp

from refsim.fem.linear import (
    ENVIRONMENT_VARIABLE,
    MKL_RT_VARIABLE,
    LinearSolverError,
    _pardiso_function,
    available_linear_solvers,
    default_linear_solver,
    linear_solver_info,
    make_linear_solver,
)

EPS = np.finfo(float).eps
NEEDS_PARDISO = pytest.mark.skipif(
    "pardiso" not in available_linear_solvers(), reason="pardiso not available on this machine"
)


def spd_matrix(n: int, seed: int, shift: float = 1.0) -> sp.csr_matrix:
    """A 3-D grid Laplacian-like SPD matrix with random positive weights (the pattern of a FEM stiffness)."""
    rng = np.random.default_rng(seed)
    side = round(n ** (1 / 3))
    index = np.arange(side**3).reshape(side, side, side)
    pairs = [
        np.stack([index[:-1].ravel(), index[1:].ravel()], 1),
        np.stack([index[:, :-1].ravel(), index[:, 1:].ravel()], 1),
        np.stack([index[:, :, :-1].ravel(), index[:, :, 1:].ravel()], 1),
    ]
    edges = np.concatenate(pairs)
    weights = rng.uniform(0.5, 2.0, edges.shape[0])
    m = side**3
    off = sp.csr_matrix((-weights, (edges[:, 0], edges[:, 1])), shape=(m, m))
    off = off + off.T
    degree = -np.asarray(off.sum(axis=1)).ravel()
    matrix = (off + sp.diags(degree + shift)).tocsr()
    matrix.sort_indices()
    return matrix


SOLVERS = list(available_linear_solvers()) + ["superlu:COLAMD"]


@pytest.mark.parametrize("name", SOLVERS)
def test_solver_equals_a_fresh_dense_factorisation(name):
    solver = make_linear_solver(name)
    rng = np.random.default_rng(0)
    for seed in range(3):  # one pattern, three numeric factorisations (the analysis is kept)
        matrix = spd_matrix(343, seed, shift=0.1 * (seed + 1))
        solver.factorise(matrix)
        rhs = rng.standard_normal((matrix.shape[0], 5))
        dense = matrix.toarray()
        expected = np.linalg.solve(dense, rhs)
        # Backward-stable direct solves: relative forward error ≲ κ(A) ε (Higham, Accuracy and Stability, ch.
        # 7, 10).
        bound = 10 * np.linalg.cond(dense) * EPS
        np.testing.assert_allclose(solver.solve(rhs), expected, rtol=0, atol=bound * np.abs(expected).max())
        np.testing.assert_allclose(
            solver.solve(rhs[:, 0]), expected[:, 0], rtol=0, atol=bound * np.abs(expected).max()
        )


@pytest.mark.parametrize("name", SOLVERS)
@pytest.mark.parametrize("storage", ["full", "upper"])
def test_a_factorisation_of_the_same_values_keeps_the_factor(name, storage):
    # A tissue at rest assembles the same matrix step after step: the factor of the same values is the same
    # factor, so a solver keeps it. Asserted: no numeric factorisation for the same values in new arrays, the
    # same solution bit for bit; a factorisation for one entry changed, for values changed in place in the
    # very arrays factorised (the copy kept is compared, not the caller's memory), and after a release.
    solver = make_linear_solver(name)
    if storage == "upper" and getattr(solver, "storage", "full") != "upper":
        pytest.skip(f"{name} reads A in full storage")
    full = spd_matrix(125, 3)
    matrix = sp.triu(full, format="csr") if storage == "upper" else full
    rhs = np.random.default_rng(1).standard_normal(125)
    solver.factorise(matrix)
    first, count = solver.solve(rhs), solver.factorisations
    assert count == 1
    again = sp.csr_matrix((matrix.data.copy(), matrix.indices, matrix.indptr), shape=matrix.shape)
    solver.factorise(again)
    assert solver.factorisations == count
    assert np.array_equal(solver.solve(rhs), first)
    bumped = (full + sp.diags(np.eye(125)[7])).tocsr()  # one diagonal entry more: the same pattern, SPD
    changed = sp.triu(bumped, format="csr") if storage == "upper" else bumped
    assert np.array_equal(changed.indices, matrix.indices)
    solver.factorise(changed)
    assert solver.factorisations == count + 1
    assert not np.array_equal(solver.solve(rhs), first)
    scaled = again.copy()
    solver.factorise(scaled)
    assert solver.factorisations == count + 2
    scaled.data *= 2.0  # in place, in the arrays just factorised
    solver.factorise(scaled)
    assert solver.factorisations == count + 3
    bound = 10 * np.linalg.cond(full.toarray()) * EPS  # backward-stable solve (Higham, ch. 7)
    expected = np.linalg.solve(2.0 * full.toarray(), rhs)
    np.testing.assert_allclose(solver.solve(rhs), expected, rtol=0, atol=bound * np.abs(expected).max())
    if hasattr(solver, "release"):
        solver.release()
        solver.factorise(scaled)
        assert solver.factorisations == count + 4


@pytest.mark.skipif(
    platform.machine().lower() not in ("x86_64", "amd64"), reason="oneMKL wheels are x86-64 only"
)
def test_pardiso_is_available_on_x86_64():
    # pyproject.toml installs pypardiso on x86-64: the PARDISO path must be the one CI tests there.
    assert "pardiso" in available_linear_solvers()


@NEEDS_PARDISO
def test_pardiso_reanalyses_a_new_pattern():
    solver = make_linear_solver("pardiso")
    for size in (125, 216):
        matrix = spd_matrix(size, 1)
        solver.factorise(matrix)
        rhs = np.ones(matrix.shape[0])
        np.testing.assert_allclose(matrix @ solver.solve(rhs), rhs, rtol=0, atol=1e-10)


def test_environment_variable_forces_the_choice(monkeypatch):
    monkeypatch.setenv(ENVIRONMENT_VARIABLE, "superlu")
    assert default_linear_solver() == "superlu"
    assert make_linear_solver().name == "superlu"
    info = linear_solver_info()
    assert info["linear_solver"] == "superlu" and info["environment"] == "superlu"
    assert info["scipy"] is not None
    monkeypatch.setenv(ENVIRONMENT_VARIABLE, "umfpack")
    with pytest.raises(ValueError, match=ENVIRONMENT_VARIABLE):
        default_linear_solver()


def test_unavailable_or_unknown_backends_are_named():
    with pytest.raises(ValueError, match="linear solver"):
        make_linear_solver("umfpack")
    with pytest.raises(ValueError, match="ordering"):
        make_linear_solver("superlu:BEST")
    if "cholmod" not in available_linear_solvers():
        with pytest.raises(LinearSolverError, match="cholmod"):
            make_linear_solver("cholmod")


@NEEDS_PARDISO
def test_pardiso_inverse_block_equals_the_dense_inverse_on_marked_positions():
    matrix = spd_matrix(343, 2, shift=0.2)
    dense = matrix.toarray()
    inverse = np.linalg.inv(dense)
    # Backward-stable solves: relative forward error ≲ κ(A) ε (Higham, Accuracy and Stability, ch. 7, 10).
    bound = 10 * np.linalg.cond(dense) * EPS * np.abs(inverse).max()
    solver = make_linear_solver("pardiso")
    solver.factorise(matrix)  # plain analysis first: marking later analyses and factorises again
    for positions, marks in (
        (np.array([3, 40, 41, 200]), np.array([3, 7, 40, 41, 99, 200, 300])),  # marks a superset
        (np.array([10, 11, 12]), np.array([10, 11, 12])),  # marks moved: a new analysis
    ):
        solver.mark(marks)
        np.testing.assert_array_equal(solver.marked, marks)
        block = solver.inverse_block(positions)
        np.testing.assert_allclose(block, inverse[np.ix_(positions, positions)], rtol=0, atol=bound)
        # full solves stay full after a partial one
        rhs = np.linspace(-1.0, 1.0, matrix.shape[0])
        np.testing.assert_allclose(solver.solve(rhs), inverse @ rhs, rtol=0, atol=bound * matrix.shape[0])
    with pytest.raises(ValueError, match="marked"):
        solver.inverse_block(np.array([0]))


@NEEDS_PARDISO
def test_pardiso_in_single_precision_solves_to_float32s_bound_in_every_phase():
    # precision="single" (the fast mode's rest factor): the factor and the solves in float32, float64 in and
    # out. Backward-stable solves: relative forward error ≲ κ(A) ε₃₂ (Higham, ch. 7, 10), where the double
    # factor's is κ(A) ε₆₄; the float32 one is measured above float64's bound (it is in single precision).
    matrix = spd_matrix(343, 3, shift=0.2)
    dense = matrix.toarray()
    inverse = np.linalg.inv(dense)
    condition = np.linalg.cond(dense)
    bound = 10 * condition * np.finfo(np.float32).eps
    single = make_linear_solver("pardiso", precision="single")
    single.factorise(matrix)
    rng = np.random.default_rng(3)
    rhs = rng.standard_normal((matrix.shape[0], 4))
    expected = inverse @ rhs
    for given, wanted in ((rhs, expected), (rhs[:, 0], expected[:, 0])):
        solved = single.solve(given)
        assert solved.dtype == np.float64 and solved.shape == wanted.shape
        error = np.abs(solved - wanted).max() / np.abs(wanted).max()
        assert 10 * condition * EPS < error <= bound
    half = single.half_solve(rhs)  # Yᵀ Y = rhsᵀ A⁻¹ rhs
    assert half.dtype == np.float64
    compliance = rhs.T @ expected
    assert np.abs(half.T @ half - compliance).max() <= bound * np.abs(compliance).max()
    positions, marks = np.array([3, 40, 41]), np.array([3, 7, 40, 41])
    single.mark(marks)
    block = single.inverse_block(positions)
    assert block.dtype == np.float64
    reference = inverse[np.ix_(positions, positions)]
    assert np.abs(block - reference).max() <= bound * np.abs(inverse).max()
    load = np.zeros(matrix.shape[0])
    load[marks] = rng.standard_normal(marks.size)
    marked = single.solve_marked(load)
    assert marked.dtype == np.float64
    assert np.abs(marked - inverse @ load).max() <= bound * np.abs(inverse @ load).max()
    assert single.description["precision"] == "single"
    with pytest.raises(ValueError, match="precision"):
        make_linear_solver("pardiso", precision="half")


@NEEDS_PARDISO
def test_pardiso_factor_is_a_function_of_the_marks_not_of_their_history():
    # What makes a restarted run's bits those of the uninterrupted run (the marks are carried in the state).
    first, second = spd_matrix(216, 3), spd_matrix(216, 4)
    marks = np.array([5, 6, 7, 100])
    rhs = np.arange(216, dtype=float)
    travelled = make_linear_solver("pardiso")
    travelled.factorise(first)
    travelled.mark(np.array([1, 2]))
    travelled.mark(marks)
    travelled.factorise(second)
    fresh = make_linear_solver("pardiso")
    fresh.mark(marks)
    fresh.factorise(second)
    np.testing.assert_array_equal(travelled.solve(rhs), fresh.solve(rhs))
    np.testing.assert_array_equal(travelled.inverse_block(marks), fresh.inverse_block(marks))


@NEEDS_PARDISO
def test_pardiso_partial_solve_depends_on_no_earlier_one():
    # inverse_block keeps its (n, k) load and solution arrays from call to call: a block must not see the
    # loads or solutions of the calls before it (the same count of positions reuses them, another count not).
    matrix = spd_matrix(216, 5)
    marks = np.array([2, 3, 50, 51, 120, 180, 181])
    travelled, fresh = make_linear_solver("pardiso"), make_linear_solver("pardiso")
    for solver in (travelled, fresh):
        solver.mark(marks)
        solver.factorise(matrix)
    for positions in (
        np.array([2, 3, 50]),
        np.array([120, 180, 181]),
        np.array([3, 51]),
        np.array([2, 3, 50]),
    ):
        expected = make_linear_solver("pardiso")
        expected.mark(marks)
        expected.factorise(matrix)
        np.testing.assert_array_equal(travelled.inverse_block(positions), expected.inverse_block(positions))
    np.testing.assert_array_equal(travelled.inverse_block(marks), fresh.inverse_block(marks))


@NEEDS_PARDISO
def test_pardiso_solve_of_a_load_on_the_marks_equals_the_full_solve():
    # solve_marked skips the forward substitution's work on zeros only: the same bits as solve
    matrix = spd_matrix(343, 6)
    marks = np.array([4, 5, 6, 170, 171, 300])
    solver = make_linear_solver("pardiso")
    solver.mark(marks)
    solver.factorise(matrix)
    load = np.zeros(343)
    load[marks] = np.random.default_rng(7).standard_normal(marks.size)
    np.testing.assert_array_equal(solver.solve_marked(load), solver.solve(load))
    load[[4, 300]] = 0.0  # a load on part of the marks
    np.testing.assert_array_equal(solver.solve_marked(load), solver.solve(load))
    load[10] = 1.0
    with pytest.raises(ValueError, match="off the marked"):
        solver.solve_marked(load)


@NEEDS_PARDISO
def test_pardiso_loads_mkl_without_pypardiso():
    # oneMKL's runtime is found in the mkl wheel's library folder, not through pypardiso (whose import builds
    # a solver that globs all of sys.prefix, and does it again on first use): a PARDISO factorisation in a
    # fresh interpreter imports no pypardiso.
    code = (
        "import sys, numpy as np, scipy.sparse as sp\n"
        "from refsim.fem.linear import make_linear_solver\n"
        "solver = make_linear_solver('pardiso')\n"
        "solver.factorise(sp.identity(4, format='csr') * 2.0)\n"
        "assert np.allclose(solver.solve(np.ones(4)), 0.5)\n"
        "print('pypardiso' in sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip().splitlines()[-1] == "False"


def test_a_missing_mkl_runtime_is_named(monkeypatch, tmp_path):
    if platform.machine().lower() not in ("x86_64", "amd64"):
        pytest.skip("oneMKL wheels are x86-64 only")
    missing = tmp_path / "libmkl_rt.so.3"
    monkeypatch.setenv(MKL_RT_VARIABLE, str(missing))
    _pardiso_function.cache_clear()
    try:
        with pytest.raises(LinearSolverError, match=f"{missing}.*{MKL_RT_VARIABLE}"):
            make_linear_solver("pardiso")
    finally:
        monkeypatch.delenv(MKL_RT_VARIABLE)
        _pardiso_function.cache_clear()


@NEEDS_PARDISO
def test_pardiso_analyses_a_pattern_once(monkeypatch):
    # One analysis for every matrix made on the same pattern arrays (SciPy hands out views of them, so they
    # are recognised by their memory), and one more for another pattern.
    solver = make_linear_solver("pardiso")
    analyses = []
    original = solver._analyse
    monkeypatch.setattr(solver, "_analyse", lambda: (analyses.append(1), original())[1])
    full = spd_matrix(125, 5)
    base = sp.triu(full, format="csr")  # the upper triangle alone: what PARDISO reads
    expected = np.linalg.solve(full.toarray(), np.ones(125))
    bound = 10 * np.linalg.cond(full.toarray()) * EPS  # backward-stable solve (Higham, ch. 7)
    for scale in (1.0, 2.0, 4.0):
        matrix = sp.csr_matrix((base.data * scale, base.indices, base.indptr), shape=base.shape, copy=False)
        solver.factorise(matrix)
        np.testing.assert_allclose(
            solver.solve(np.ones(125)) * scale, expected, rtol=0, atol=bound * np.abs(expected).max()
        )
    assert len(analyses) == 1
    other = spd_matrix(125, 6)
    solver.factorise(other)  # full storage, another pattern
    assert len(analyses) == 2


@NEEDS_PARDISO
def test_pardiso_analysed_again_after_a_plain_analysis_does_not_corrupt_the_heap():
    # A marked analysis, a plain one, a marked one again on one handle: what a second run of a simulation
    # does (its first step resumes without marks). Re-analysing a handle in place aborted the process
    # ("munmap_chunk(): invalid pointer"); the child must exit cleanly and give a fresh solver's bits.
    code = (
        "import numpy as np\n"
        "from refsim.fem.linear import make_linear_solver\n"
        "from tests.fem.test_linear import spd_matrix\n"
        "matrix, marks, other = spd_matrix(343, 8), np.array([3, 4, 100, 200]), np.array([10, 11])\n"
        "solver = make_linear_solver('pardiso')\n"
        "solver.factorise(matrix)\n"
        "for positions in (marks, None, marks, other, None, marks):\n"
        "    solver.mark(positions)\n"
        "    if positions is not None:\n"
        "        solver.inverse_block(positions)\n"
        "fresh = make_linear_solver('pardiso')\n"
        "fresh.mark(marks)\n"
        "fresh.factorise(matrix)\n"
        "load = np.zeros(343)\n"
        "load[marks] = 1.0\n"
        "print(np.array_equal(solver.inverse_block(marks), fresh.inverse_block(marks)),\n"
        "      np.array_equal(solver.solve_marked(load), fresh.solve_marked(load)))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["True", "True"]


@NEEDS_PARDISO
def test_a_released_pardiso_solver_refuses_to_solve_and_can_start_again():
    matrix, marks = spd_matrix(216, 9), np.array([1, 2, 90])
    rhs = np.arange(216, dtype=float)
    solver = make_linear_solver("pardiso")
    solver.mark(marks)
    solver.factorise(matrix)
    solver.release()
    solver.release()  # the handle is freed once
    load = np.zeros(216)
    for use in (
        lambda: solver.solve(rhs),
        lambda: solver.half_solve(rhs[:, None]),
        lambda: solver.inverse_block(marks),
        lambda: solver.solve_marked(load),
    ):
        with pytest.raises(LinearSolverError, match="after release"):
            use()
    assert solver.marked is None
    solver.factorise(matrix)  # a new analysis, plain: a fresh solver's bits
    fresh = make_linear_solver("pardiso")
    fresh.factorise(matrix)
    np.testing.assert_array_equal(solver.solve(rhs), fresh.solve(rhs))
