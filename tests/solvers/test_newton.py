"""The semismooth Newton path of the exact solver (refsim.solvers.newton): every law on hand-made problems
with solutions worked out by hand, warm starts, non-symmetric W, the sparse path, FCLib's global form, and
agreement with Gauss-Seidel on random well-posed problems."""

import h5py
import numpy as np
import pytest
import scipy.sparse as sparse
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from refsim.solvers import (
    ConstraintProblem,
    data_residual,
    natural_map_error,
    natural_residual,
    solve_exact,
    solve_gauss_seidel,
)
from refsim.solvers.newton import solve_newton
from refsim.solvers.readers import condense_global, read_fclib

from .conftest import planted_problem

# Hand-made problems with W = I (rows decouple), solutions by hand (each law's own statement).
HAND_MADE = {
    # bilateral: δ = λ + δ_free = 0
    "bilateral": (dict(free_gap=[-1.5, 2.0], bilateral=[0, 1]), [1.5, -2.0]),
    # Signorini: λ = max(0, −δ_free)
    "unilateral": (dict(free_gap=[-1.0, 2.0, 0.0], unilateral=[0, 1, 2]), [1.0, 0.0, 0.0]),
    # Coulomb, μ = 0.5, δ_free = (−1, 2, 0): λ_n = 1; sticking needs |λ_t| = 2 > μ λ_n, so it slips:
    # λ_t = −μ λ_n (1, 0), δ_t = (1.5, 0); De Saxcé: δ̂ = (0.75, 1.5, 0) ∈ K*, λ·δ̂ = 0
    "contact slip": (
        dict(free_gap=[-1.0, 2.0, 0.0], contacts=[[0, 1, 2]], contact_friction=[0.5]),
        [1.0, -0.5, 0.0],
    ),
    # stick: |(0.2, −0.1)| < 0.5: λ_t = −δ_free,t
    "contact stick": (
        dict(free_gap=[-1.0, 0.2, -0.1], contacts=[[0, 1, 2]], contact_friction=[0.5]),
        [1.0, -0.2, 0.1],
    ),
    # separation: δ_free,n > 0 gives λ = 0
    "contact open": (
        dict(free_gap=[1.0, 3.0, 0.0], contacts=[[0, 1, 2]], contact_friction=[0.5]),
        [0.0, 0.0, 0.0],
    ),
    # box [−1, 1]: λ = clip(−δ_free, −1, 1)
    "box": (
        dict(free_gap=[-2.0, 0.5, 3.0], box_rows=[0, 1, 2], box_lower=[-1.0] * 3, box_upper=[1.0] * 3),
        [1.0, -0.5, -1.0],
    ),
    # group friction: rows 0, 1 bilateral λ = (3, 4); row 2 bounded by {0, 1}, μ = 0.1, p = 0.5:
    # b = 0.1 (5 + 0.5) = 0.55 < 2 = |δ_free,2| so it slips, λ_2 = −0.55
    "group friction": (
        dict(
            free_gap=[-3.0, -4.0, 2.0],
            bilateral=[0, 1],
            group_friction=[2],
            group_offsets=[0, 2],
            group_members=[0, 1],
            group_friction_coefficient=[0.1],
            group_preload=[0.5],
        ),
        [3.0, 4.0, -0.55],
    ),
}


@pytest.mark.parametrize("case", list(HAND_MADE))
def test_every_law_by_hand(case):
    fields, solution = HAND_MADE[case]
    n = len(fields["free_gap"])
    problem = ConstraintProblem(compliance=np.eye(n), **fields)
    multipliers, report = solve_exact(problem, tolerance=1e-12, method="newton")
    assert report.converged and report.path == "newton", report.message
    np.testing.assert_allclose(multipliers, solution, atol=1e-12)


@pytest.mark.parametrize(
    "kinds",
    [
        dict(bilateral=3, unilateral=4, box=3),
        dict(contacts=5),
        dict(shafts=3, unilateral=2),
        dict(bilateral=2, unilateral=3, contacts=3, shafts=2, box=3),
    ],
)
@pytest.mark.parametrize("rank", [None, 6])
def test_planted_problems_every_law(kinds, rank):
    rng = np.random.default_rng(7)
    problem, _, _ = planted_problem(rng, rank=rank, **kinds)
    multipliers, report = solve_exact(problem, tolerance=1e-10, method="newton")
    # Newton, finished by Gauss-Seidel sweeps where it stalls (W of rank 6: friction bounds along its null
    # space)
    assert report.converged and report.path in ("newton", "newton+gauss_seidel"), report.message
    assert natural_residual(problem, multipliers) <= 1e-10


def test_warm_start_from_a_solution_and_from_a_nearby_point():
    rng = np.random.default_rng(8)
    problem, _, _ = planted_problem(rng, bilateral=2, unilateral=4, contacts=4, shafts=2, box=2)
    cold = solve_newton(problem, tolerance=1e-11)
    assert cold.converged and cold.iterations > 1
    again = solve_newton(problem, tolerance=1e-11, warm_start=cold.multipliers)
    assert again.converged and again.iterations == 0
    nearby = cold.multipliers * (1.0 + 1e-4 * rng.standard_normal(problem.row_count))
    warm = solve_newton(problem, tolerance=1e-11, warm_start=nearby)
    assert warm.converged and warm.iterations < cold.iterations
    _, report = solve_exact(problem, tolerance=1e-11, warm_start=cold.multipliers, method="auto")
    assert report.iterations == 0 and report.converged


@pytest.mark.parametrize("asymmetry", [1e-5, 1e-3, 1e-1])
def test_non_symmetric_w_solved_as_given(asymmetry):
    # planted solution (λ*, δ*) for W + ε S, S skew: δ_free = δ* − (W + ε S) λ*, so (λ*, δ*) solves it exactly
    rng = np.random.default_rng(9)
    base, force, gap = planted_problem(rng, unilateral=4, contacts=4, box=2)
    skew = rng.standard_normal((base.row_count,) * 2)
    skew = skew - skew.T
    compliance = base.compliance + asymmetry * np.linalg.norm(base.compliance) / np.linalg.norm(skew) * skew
    fields = {
        name: getattr(base, name)
        for name in ("unilateral", "contacts", "contact_friction", "box_rows", "box_lower", "box_upper")
    }
    problem = ConstraintProblem(compliance=compliance, free_gap=gap - compliance @ force, **fields)
    assert problem.asymmetry() == pytest.approx(asymmetry * np.sqrt(2), rel=0.5)
    assert natural_residual(problem, force) < 1e-13
    multipliers, report = solve_exact(problem, tolerance=1e-10, method="auto")
    assert report.converged, report.message
    assert report.residual == natural_residual(problem, multipliers)  # measured with W as given
    assert report.asymmetry == problem.asymmetry()


def test_sparse_path_matches_dense():
    # 120 decoupled-by-blocks contacts (W block-diagonal plus a weak chain coupling): 360 rows, 1.7 % dense
    rng = np.random.default_rng(10)
    blocks = []
    for _ in range(120):
        factor = rng.standard_normal((3, 3))
        blocks.append(factor @ factor.T + np.eye(3))
    compliance = sparse.block_diag(blocks).toarray()
    chain = 0.1 * (np.eye(360, k=3) + np.eye(360, k=-3))
    problem = ConstraintProblem(
        compliance=compliance + chain,
        free_gap=rng.standard_normal(360),
        contacts=np.arange(360).reshape(-1, 3),
        contact_friction=np.full(120, 0.3),
    )
    sparse_result = solve_newton(problem, tolerance=1e-10)
    dense_result = solve_newton(problem, tolerance=1e-10, sparse_above=10_000)
    assert sparse_result.storage == "sparse" and dense_result.storage == "dense"
    assert sparse_result.converged and dense_result.converged
    np.testing.assert_allclose(
        problem.gap(sparse_result.multipliers),
        problem.gap(dense_result.multipliers),
        atol=1e-7 * np.linalg.norm(problem.free_gap),
    )


def _write_matrix(group, name, matrix):
    matrix = sparse.csc_matrix(matrix)
    sub = group.create_group(name)
    sub["m"], sub["n"], sub["nz"], sub["nzmax"] = [matrix.shape[0]], [matrix.shape[1]], [-1], [matrix.nnz]
    sub["p"], sub["i"], sub["x"] = matrix.indptr, matrix.indices, matrix.data


def test_fclib_global_form_condensed(tmp_path):
    # Two bodies of 3 dofs (masses 2 and 3 on the diagonal), two contacts and one equality (G, b).
    # Reference: FCLib's global form M v = H r + G λ + f, Gᵀ v + b = 0, u = Hᵀ v + w; condensed
    # W = Bᵀ M⁻¹ B and δ_free = Bᵀ M⁻¹ f + (w, b), B = [H G] (computed densely here).
    rng = np.random.default_rng(12)
    mass = np.diag([2.0, 2.0, 2.0, 3.0, 3.0, 3.0])
    contact = rng.standard_normal((6, 6))
    equality = rng.standard_normal((6, 1))
    force, offset, equality_offset = rng.standard_normal(6), rng.standard_normal(6), rng.standard_normal(1)
    offset[[0, 3]] = -np.abs(offset[[0, 3]]) - 0.5  # closing normal gaps: the contacts are active
    mu = np.array([0.3, 0.6])
    path = tmp_path / "global.hdf5"
    with h5py.File(path, "w") as handle:
        group = handle.create_group("fclib_global")
        group["spacedim"] = [3]
        _write_matrix(group, "M", mass)
        _write_matrix(group, "H", contact)
        _write_matrix(group, "G", equality)
        vectors = group.create_group("vectors")
        vectors["f"], vectors["w"], vectors["mu"], vectors["b"] = force, offset, mu, equality_offset
    problem = read_fclib(path)
    operator = np.hstack([contact, equality])
    inverse = np.linalg.inv(mass)
    np.testing.assert_allclose(problem.compliance, operator.T @ inverse @ operator, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(
        problem.free_gap,
        operator.T @ inverse @ force + np.concatenate([offset, equality_offset]),
        rtol=1e-12,
        atol=1e-14,
    )
    np.testing.assert_array_equal(problem.contacts, [[0, 1, 2], [3, 4, 5]])
    np.testing.assert_array_equal(problem.bilateral, [6])
    multipliers, report = solve_exact(problem, tolerance=1e-12, method="auto")
    assert report.converged, report.message
    # back in the global form: v = M⁻¹ (H r + G λ + f) satisfies Gᵀ v + b = 0 and u = Hᵀ v + w = δ
    velocity = inverse @ (operator @ multipliers + force)
    assert abs(equality[:, 0] @ velocity + equality_offset[0]) < 1e-10
    np.testing.assert_allclose(contact.T @ velocity + offset, problem.gap(multipliers)[:6], atol=1e-12)
    same = condense_global(
        mass, contact, force, offset, mu, equality_operator=equality, equality_offset=equality_offset
    )
    np.testing.assert_allclose(same.compliance, problem.compliance)


@settings(
    max_examples=15,
    deadline=None,
    database=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    seed=st.integers(0, 10**6),
    bilateral=st.integers(0, 4),
    unilateral=st.integers(0, 6),
    box=st.integers(0, 4),
    scale=st.sampled_from([1e-4, 1.0, 1e3]),
)
def test_property_exact_and_gauss_seidel_agree_frictionless(seed, bilateral, unilateral, box, scale):
    # W symmetric positive definite (full rank): the solution λ* is unique and, for the natural map of a
    # strongly monotone problem, ‖λ − λ*‖ ≤ (1 + ‖W‖₂) / σ_min(W) ‖e(λ)‖ (Mathias and Pang 1990; Facchinei and
    # Pang 2003, Prop. 10.3.5 with unit map weight). Both solvers' answers must satisfy that bound against the
    # planted λ*, so they agree within the sum of the two bounds.
    if bilateral + unilateral + box == 0:
        return
    rng = np.random.default_rng(seed)
    problem, force, _ = planted_problem(rng, bilateral=bilateral, unilateral=unilateral, box=box, scale=scale)
    eigenvalues = np.linalg.eigvalsh(problem.compliance)
    bound = (1.0 + eigenvalues[-1]) / eigenvalues[0]
    exact, report = solve_exact(problem, tolerance=1e-11, method="auto")
    gs, gs_report = solve_gauss_seidel(problem, tolerance=1e-11, max_iterations=200_000)
    assert report.converged, report.message
    for answer in (exact, gs) if gs_report.converged else (exact,):
        error, _ = natural_map_error(problem, answer)
        assert np.linalg.norm(answer - force) <= bound * np.linalg.norm(error) * (1 + 1e-6) + 1e-13 * max(
            1.0, np.linalg.norm(force)
        )


@settings(
    max_examples=10,
    deadline=None,
    database=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    seed=st.integers(0, 10**6),
    contacts=st.integers(1, 5),
    shafts=st.integers(0, 2),
    friction=st.sampled_from([0.1, 0.5, 1.0]),
)
def test_property_exact_and_gauss_seidel_both_solve_friction(seed, contacts, shafts, friction):
    # With friction λ need not be unique; both must reach the tolerance on the same (planted, solvable)
    # problem.
    rng = np.random.default_rng(seed)
    problem, _, _ = planted_problem(rng, unilateral=2, contacts=contacts, shafts=shafts, friction=friction)
    _, report = solve_exact(problem, tolerance=1e-10, method="auto")
    assert report.converged, report.message
    _, gs_report = solve_gauss_seidel(problem, tolerance=1e-8, max_iterations=100_000)
    if gs_report.converged:
        assert gs_report.residual <= 1e-8


def test_stops_at_the_tolerance_asked():
    # The stopping test is the residual asked for, not a polish far beyond it: a loose tolerance takes fewer
    # iterations, and every answer meets its own tolerance in both residuals.
    rng = np.random.default_rng(13)
    problem, _, _ = planted_problem(rng, unilateral=6, contacts=6, box=3)
    loose = solve_newton(problem, tolerance=1e-3)
    tight = solve_newton(problem, tolerance=1e-12)
    assert loose.converged and tight.converged
    assert loose.iterations < tight.iterations
    assert loose.residual <= 1e-3 and loose.data_residual <= 1e-3
    assert tight.residual <= 1e-12 and tight.data_residual <= 1e-12


@pytest.mark.parametrize("eta", [0.0, 1e-3])
@pytest.mark.parametrize("seed", range(4))
def test_reduced_direction_equals_the_full_solve(seed, eta):
    """The Newton step with the explicit rows (separated, slipping, at a bound) eliminated solves the same
    system: reference np.linalg.solve of the full J + ηI; tolerance 1e3 ε cond(J)."""
    from refsim.solvers.laws import block_arrays, jacobian_blocks
    from refsim.solvers.linear import PIVOT_DTYPE, DirectionWork, _dense_jacobian, _reduced_direction_into
    from refsim.solvers.residual import data_scales

    rng = np.random.default_rng(seed)
    problem, _, _ = planted_problem(rng, bilateral=3, unilateral=5, contacts=3, shafts=4, box=3)
    kinds, rows, params, members = block_arrays(problem)
    weight, _ = data_scales(problem)
    n = problem.row_count
    tested = 0
    for _ in range(20):
        multipliers = rng.normal(size=n) * rng.choice([0.1, 1.0, 10.0])
        gap = problem.compliance @ multipliers + problem.free_gap
        local, factor = np.empty((kinds.size, 3, 3)), np.empty((kinds.size, 3, 3))
        bounds = np.zeros(members.size)
        jacobian_blocks(kinds, rows, params, members, multipliers, gap, weight, local, factor, bounds)
        jacobian = np.empty((n, n))
        _dense_jacobian(problem.compliance, kinds, rows, local, factor, members, bounds, eta, jacobian)
        rhs = rng.normal(size=n)
        direction = np.empty(n)
        work = DirectionWork(
            jacobian=jacobian,
            rhs=rhs,
            local=local,
            gap_factor=factor,
            bound_values=bounds,
            position=np.empty(n, dtype=np.int64),
            active=np.empty(n, dtype=np.int64),
            values=np.empty(n),
            reduced_rhs=np.empty(n),
            factors=np.empty((n, n)),
            pivots=np.empty(n, dtype=PIVOT_DTYPE),
            lu_out=np.empty(n),
            direction=direction,
        )
        ok = _reduced_direction_into(kinds, rows, members, work)
        condition = np.linalg.cond(jacobian)
        if not ok or condition > 1e8:
            continue
        tested += 1
        reference = np.linalg.solve(jacobian, rhs)
        np.testing.assert_allclose(
            direction, reference, rtol=0, atol=1e3 * np.finfo(float).eps * condition * np.abs(reference).max()
        )
    assert tested >= 5  # the reduction applied (some rows explicit) on enough random points


@pytest.mark.parametrize("size", [1, 2, 3, 9, 15, 23])
@pytest.mark.parametrize("condition", [1.0, 1e6, 1e12])
def test_small_lu_solve_is_backward_stable(size, condition):
    """The compiled elimination of small Newton systems (linear._small_lu_inplace) against Gaussian
    elimination's backward-error bound (Higham 2002, Thm. 9.5: (A + ΔA) x = b with |ΔA| ≤ γ_3n |L||U|, γ_k = k
    ε / (1 − k ε)): the residual ‖b − A x‖_∞ ≤ γ_3n ‖|L||U|‖_∞ ‖x‖_∞, with L, U of the same pivoting
    (scipy.linalg.lu); and its answer within the forward bound cond(A) · that backward error of LAPACK's."""
    import scipy.linalg

    from refsim.solvers.linear import _small_lu_inplace

    rng = np.random.default_rng(size)
    left, _ = np.linalg.qr(rng.standard_normal((size, size)))
    right, _ = np.linalg.qr(rng.standard_normal((size, size)))
    matrix = left @ np.diag(np.geomspace(1.0, 1.0 / condition, size)) @ right.T
    rhs = rng.standard_normal(size)
    solution = rhs.copy()
    assert _small_lu_inplace(matrix.copy(), solution)
    _, lower, upper = scipy.linalg.lu(matrix)
    gamma = 3 * size * np.finfo(float).eps / (1 - 3 * size * np.finfo(float).eps)
    bound = gamma * np.abs(np.abs(lower) @ np.abs(upper)).sum(axis=1).max() * np.abs(solution).max()
    assert np.abs(rhs - matrix @ solution).max() <= bound
    reference = np.linalg.solve(matrix, rhs)
    forward = np.linalg.cond(matrix, np.inf) * bound / np.abs(matrix).sum(axis=1).max()
    assert (
        np.abs(solution - reference).max() <= 2 * forward + 4 * np.finfo(float).eps * np.abs(reference).max()
    )


def test_small_lu_solve_reports_a_singular_matrix():
    from refsim.solvers.linear import PIVOT_DTYPE, _lu_direction_into, _small_lu_inplace

    # LAPACK's info > 0: an exactly zero pivot (rank 1 here, and the zero matrix), or one that is not a number
    singular = np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 0.0, 0.0]])
    for matrix in (singular, np.zeros((3, 3)), np.full((3, 3), np.nan)):
        assert not _small_lu_inplace(matrix.copy(), np.ones(3))
        work, out, pivots = np.empty((3, 3)), np.empty(3), np.empty(3, dtype=PIVOT_DTYPE)
        assert not _lu_direction_into(matrix, np.ones(3), work, out, pivots)[1]


def test_barely_improving_presweeps_leave_newtons_start():
    """Pre-sweeps abandoned by their rate rule without halving the start's residual
    (newton_kernel._KEEP_SWEPT) are dropped: Newton then runs from the start exactly as without pre-sweeps
    (same bits). The bilateral chain W = tridiag(−1, 2 + 1e-6, −1), n = 60: Gauss–Seidel contracts by
    cos²(π/61) ≈ 0.9973 per sweep."""
    n = 60
    compliance = (2.0 + 1e-6) * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1)
    problem = ConstraintProblem(
        compliance=compliance, free_gap=np.linspace(-1.0, 1.0, n), bilateral=np.arange(n)
    )
    swept = solve_newton(problem, tolerance=1e-10, presweeps=30)
    plain = solve_newton(problem, tolerance=1e-10)
    assert swept.presweeps == 3 and plain.presweeps == 0
    np.testing.assert_array_equal(swept.multipliers, plain.multipliers)
    assert swept.iterations == plain.iterations and swept.converged


def test_halving_presweeps_become_newtons_start():
    """Sweeps that halve the start's residual are kept even when their rate rule stops them: with no Newton
    iteration allowed the answer is the swept point, Gauss–Seidel's own after the same sweeps from zero (W
    diagonally dominant: about 0.3 per sweep, too slow for 1e-14 in a budget of 8)."""
    rng = np.random.default_rng(2)
    n = 12
    coupling = 0.3 * rng.standard_normal((n, n)) / np.sqrt(n)
    compliance = np.eye(n) + coupling @ coupling.T
    problem = ConstraintProblem(
        compliance=compliance, free_gap=rng.standard_normal(n), unilateral=np.arange(n)
    )
    start = max(natural_residual(problem, np.zeros(n)), data_residual(problem, np.zeros(n)))
    result = solve_newton(problem, tolerance=1e-14, presweeps=8, max_iterations=0)
    assert 0 < result.presweeps < 8
    swept, _ = solve_gauss_seidel(problem, tolerance=1e-300, max_iterations=result.presweeps)
    assert max(result.residual, result.data_residual) <= 0.5 * start
    np.testing.assert_allclose(result.multipliers, swept, rtol=0, atol=1e-14 * np.abs(swept).max())


@pytest.mark.parametrize("rows", [1, 3, 23, 24, 40])
def test_gap_product_meets_the_dot_product_error_bound(rows):
    # residual._gap_into: a compiled loop below _LOOP_PRODUCT_BELOW rows, BLAS above. Reference: the exact
    # W λ + δ_free in rational arithmetic; each row is a dot product of rows + 1 terms, so the floating-point
    # error is at most γ_(n+1) (|W| |λ| + |δ_free|)_i with γ_k = k u / (1 − k u), u = 2⁻⁵³ (Higham 2002,
    # §3.1).
    from fractions import Fraction

    from refsim.solvers.residual import _LOOP_PRODUCT_BELOW, _gap_into

    assert 3 < _LOOP_PRODUCT_BELOW <= 24  # both branches are among the sizes
    rng = np.random.default_rng(rows)
    compliance = rng.standard_normal((rows, rows))
    multipliers = rng.standard_normal(rows) * 10.0 ** rng.integers(-3, 4, rows)
    free_gap = rng.standard_normal(rows)
    out = np.empty(rows)
    _gap_into(compliance, multipliers, free_gap, out)
    unit = 2.0**-53
    gamma = (rows + 1) * unit / (1 - (rows + 1) * unit)
    bound = gamma * (np.abs(compliance) @ np.abs(multipliers) + np.abs(free_gap))
    for i in range(rows):
        exact = sum(
            (Fraction(compliance[i, j]) * Fraction(multipliers[j]) for j in range(rows)),
            Fraction(free_gap[i]),
        )
        assert abs(Fraction(out[i]) - exact) <= Fraction(bound[i])


@pytest.mark.parametrize("size", [24, 30, 69])
def test_in_place_gesv_is_the_solve_of_before(size):
    # linear._lu_direction_into calls LAPACK gesv in place on Jᵀ (J in Fortran order) where numba's
    # np.linalg.solve (linear._gesv, the kernel's call before) copies J to Fortran order first: the same
    # routine on the same numbers, so the same bits; a singular or non-finite J is reported (np.linalg.solve
    # raises)
    from refsim.solvers.linear import PIVOT_DTYPE, _gesv, _lu_direction_into

    rng = np.random.default_rng(size)
    matrix = rng.standard_normal((size, size))
    rhs = rng.standard_normal(size)
    work, out, pivots = np.empty((size, size)), np.empty(size), np.empty(size, dtype=PIVOT_DTYPE)
    direction, ok = _lu_direction_into(matrix, rhs, work, out, pivots)
    reference = _gesv(matrix, rhs)
    assert ok
    assert direction.tobytes() == reference.tobytes()
    assert (
        np.abs(matrix @ direction - rhs).max()
        <= 1e-10 * np.abs(matrix).sum(axis=1).max() * np.abs(direction).max()
    )
    singular = matrix.copy()
    singular[:, size // 2] = (
        0.0  # a zero column stays exactly zero under elimination: a zero pivot (info > 0)
    )
    for bad in (np.zeros((size, size)), singular, np.full((size, size), np.nan)):
        assert not _lu_direction_into(bad, rhs, work, out, pivots)[1]
        with pytest.raises(Exception):  # noqa: B017 (numba raises a plain Exception for a singular matrix)
            _gesv(bad, rhs)
