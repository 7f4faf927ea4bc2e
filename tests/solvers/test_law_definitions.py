"""Each constraint law's mathematics has one definition: the compiled kernels of :mod:`refsim.solvers.laws`.

The Python forms that other parts of the solvers use (the natural map of :mod:`refsim.solvers.residual`, the
bounds and the cone projection's Jacobian of :mod:`refsim.solvers.exact`) are checked here against the
compiled ones on every law of :data:`~refsim.solvers.laws.LAWS`, on random inputs that are not solutions
(every branch of every law: inside, at and beyond its bounds), and the compiled Jacobian against central
finite differences of the compiled map. A law added to the table without its Python forms agreeing fails here.

Tolerances: the two forms evaluate the same expressions in a different order, so they agree to a few units of
round-off of the magnitudes involved (inputs of order one: 1e-12 leaves a factor of about 4,500 over the
double precision ε = 2.2e-16). The finite differences are central with step h = 1e-6 on a piecewise-smooth map
evaluated away from its kinks (points closer than 1e-3 to a branch switch are skipped), whose truncation error
is O(h²) times the map's second derivative (of order one here): 1e-6 leaves room for round-off ε/h ≈ 2e-10.
"""

from __future__ import annotations

import numpy as np
import pytest

from refsim.solvers import laws
from refsim.solvers.cone import cone_bounds as _bounds
from refsim.solvers.laws import cone_projection_jacobian, project_friction_cone
from refsim.solvers.residual import natural_map_error

ROUND_OFF = 1e-12
FD_STEP = 1e-6
FD_TOLERANCE = 1e-6

#: A planted problem with rows of one law (group friction brings its pairs of bilateral rows).
LAW_ROWS = {
    "bilateral": dict(bilateral=6),
    "unilateral": dict(unilateral=9),
    "contact": dict(contacts=6),
    "group_friction": dict(shafts=6, shaft_preload=0.3),
    "box": dict(box=9),
}


def test_every_law_of_the_table_is_covered():
    assert set(LAW_ROWS) == set(laws.LAW_NAMES)


def _problem(planted, rng, law):
    problem, solution, _ = planted(rng, **LAW_ROWS[law])
    return problem, solution


def _random_point(rng, problem, solution):
    """Multipliers around the solution, far enough to leave it (every branch of the laws is visited)."""
    return solution + rng.normal(scale=1.0, size=problem.row_count)


def _compiled_map(problem, multipliers, weight):
    kinds, rows, params, members = laws.block_arrays(problem)
    gap = problem.compliance @ multipliers + problem.free_gap
    error = np.zeros(problem.row_count)
    laws.natural_map_blocks(kinds, rows, params, members, multipliers, gap, weight, error)
    return error


def _contact_equal_weights(problem, weight):
    """ρ equal on the three rows of each contact (the map's requirement)."""
    weight = weight.copy()
    for normal, t1, t2 in np.asarray(problem.contacts):
        weight[[t1, t2]] = weight[normal]
    return weight


@pytest.mark.parametrize("law", sorted(LAW_ROWS))
@pytest.mark.parametrize("weighted", [False, True])
def test_python_natural_map_is_the_compiled_one(planted, rng, law, weighted):
    """e = λ − Π(λ − ρ δ̂) (bilateral e = ρ δ) of refsim.solvers.residual against natural_map_blocks."""
    problem, solution = _problem(planted, rng, law)
    for _ in range(20):
        multipliers = _random_point(rng, problem, solution)
        weight = rng.uniform(0.2, 5.0, problem.row_count) if weighted else np.ones(problem.row_count)
        weight = _contact_equal_weights(problem, weight)
        python, _ = natural_map_error(problem, multipliers, weight if weighted else None)
        compiled = _compiled_map(problem, multipliers, weight)
        scale = 1.0 + np.abs(multipliers).max() + np.abs(weight).max()
        np.testing.assert_allclose(python, compiled, rtol=0, atol=ROUND_OFF * scale)


def _cone_points(rng, count=400):
    """Points in every region of the cone projection: inside, polar, between, on the axis (z_t = 0)."""
    points = rng.normal(scale=2.0, size=(count, 3))
    points[: count // 8, 1:] = 0.0
    mu = rng.uniform(0.0, 2.0, count)
    mu[count // 8 : count // 4] = 0.0
    return points, mu


def test_python_cone_projection_is_the_compiled_one(rng):
    points, mu = _cone_points(rng)
    python = project_friction_cone(points, mu)
    compiled = np.array([laws.project_cone(p[0], p[1], p[2], m) for p, m in zip(points, mu, strict=True)])
    np.testing.assert_allclose(python, compiled, rtol=0, atol=ROUND_OFF * (1.0 + np.abs(points).max()))


def _cone_region(points, mu):
    """0 inside, 1 polar, 2 projected onto the boundary; and the distance to the nearest region switch."""
    normal, tangent = points[:, 0], np.linalg.norm(points[:, 1:], axis=1)
    inside = tangent - mu * normal
    polar = mu * tangent + normal
    region = np.where(inside <= 0.0, 0, np.where(polar <= 0.0, 1, 2))
    return region, np.minimum(np.abs(inside), np.abs(polar))


def test_python_cone_jacobian_is_the_compiled_one_and_the_derivative(rng):
    points, mu = _cone_points(rng)
    region, margin = _cone_region(points, mu)
    keep = (margin > 1e-3) & (np.linalg.norm(points[:, 1:], axis=1) > 1e-3)
    points, mu, region = points[keep], mu[keep], region[keep]
    assert set(np.unique(region)) == {0, 1, 2}
    python = cone_projection_jacobian(points, mu)
    compiled = np.zeros_like(python)
    for k, (point, m) in enumerate(zip(points, mu, strict=True)):
        laws._cone_jacobian(point[0], point[1], point[2], m, compiled[k])
    np.testing.assert_allclose(python, compiled, rtol=0, atol=ROUND_OFF)
    difference = np.zeros_like(python)
    for j in range(3):
        step = np.zeros(3)
        step[j] = FD_STEP
        difference[:, :, j] = (
            project_friction_cone(points + step, mu) - project_friction_cone(points - step, mu)
        ) / (2.0 * FD_STEP)
    np.testing.assert_allclose(compiled, difference, rtol=0, atol=FD_TOLERANCE)


@pytest.mark.parametrize("law", sorted(LAW_ROWS))
def test_exact_solver_bounds_are_the_compiled_laws_bounds(planted, rng, law):
    """The exact solver's lower ≤ λ ≤ upper per row against the bounds the compiled block update projects
    onto (unilateral [0, ∞), box [lower, upper], group friction ±μ(‖λ_G‖ + p), free otherwise; contacts are
    a cone, not a box, and get ±∞ in both)."""
    problem, solution = _problem(planted, rng, law)
    kinds, rows, params, members = laws.block_arrays(problem)
    for _ in range(10):
        multipliers = _random_point(rng, problem, solution)
        lower, upper = _bounds(problem, multipliers)
        expected_lower = np.full(problem.row_count, -np.inf)
        expected_upper = np.full(problem.row_count, np.inf)
        for b, kind in enumerate(kinds):  # building the expectation, not a hot path
            row = rows[b, 0]
            if kind == laws.UNILATERAL:
                expected_lower[row] = 0.0
            elif kind == laws.BOX:
                expected_lower[row], expected_upper[row] = params[b]
            elif kind == laws.GROUP_FRICTION:
                bound = laws.group_bound(
                    multipliers, members, rows[b, 1], rows[b, 2], params[b, 0], params[b, 1]
                )
                expected_lower[row], expected_upper[row] = -bound, bound
        np.testing.assert_allclose(lower, expected_lower, rtol=ROUND_OFF, atol=0)
        np.testing.assert_allclose(upper, expected_upper, rtol=ROUND_OFF, atol=0)


@pytest.mark.parametrize("law", sorted(LAW_ROWS))
def test_gauss_seidel_block_update_leaves_a_solution_unchanged(planted, rng, law):
    """Each law's Gauss–Seidel block update is a projection onto the same law: a solution is its fixed
    point (the sweep's increment Σ|W_jj Δλ_j| vanishes to round-off)."""
    problem, solution = _problem(planted, rng, law)
    kinds, rows, params, members = laws.block_arrays(problem)
    compliance = np.ascontiguousarray(problem.compliance)
    multipliers = solution.copy()
    gap = compliance @ multipliers + problem.free_gap
    increment = laws.gauss_seidel_sweep(
        compliance.T.copy(), np.diag(compliance).copy(), kinds, rows, params, members, multipliers, gap, 1.0
    )
    assert increment <= ROUND_OFF * (1.0 + np.abs(solution).max()) * problem.row_count
    np.testing.assert_allclose(multipliers, solution, rtol=0, atol=ROUND_OFF * (1.0 + np.abs(solution).max()))


def _jacobian_product(problem, multipliers, weight, direction):
    """J d with J = N + M W − G from the compiled factors of jacobian_blocks."""
    kinds, rows, params, members = laws.block_arrays(problem)
    gap = problem.compliance @ multipliers + problem.free_gap
    local = np.zeros((kinds.size, 3, 3))
    gap_factor = np.zeros((kinds.size, 3, 3))
    bound_values = np.zeros(members.size)
    laws.jacobian_blocks(
        kinds, rows, params, members, multipliers, gap, weight, local, gap_factor, bound_values
    )
    gap_direction = problem.compliance @ direction
    product = np.zeros(problem.row_count)
    for b, kind in enumerate(kinds):  # building the expectation, not a hot path
        block = rows[b] if kind == laws.CONTACT else rows[b, :1]
        size = block.size
        product[block] = (
            local[b, :size, :size] @ direction[block] + gap_factor[b, :size, :size] @ gap_direction[block]
        )
        if kind == laws.GROUP_FRICTION:
            group = members[rows[b, 1] : rows[b, 2]]
            product[block[0]] -= bound_values[rows[b, 1] : rows[b, 2]] @ direction[group]
    return product


@pytest.mark.parametrize("law", sorted(LAW_ROWS))
def test_compiled_jacobian_is_the_derivative_of_the_compiled_map(planted, rng, law):
    """J d against (e(λ + h d) − e(λ − h d)) / 2h, e the weighted natural map with δ = W λ + δ_free, at random
    points where the map is smooth along d (the same branches at λ ± h d: checked by a second difference)."""
    problem, solution = _problem(planted, rng, law)
    checked = 0
    for _ in range(60):
        multipliers = _random_point(rng, problem, solution)
        direction = rng.normal(size=problem.row_count)
        direction /= np.linalg.norm(direction)
        weight = _contact_equal_weights(problem, rng.uniform(0.5, 2.0, problem.row_count))
        plus = _compiled_map(problem, multipliers + FD_STEP * direction, weight)
        minus = _compiled_map(problem, multipliers - FD_STEP * direction, weight)
        centre = _compiled_map(problem, multipliers, weight)
        if np.abs(plus - 2.0 * centre + minus).max() > 1e-9:  # a kink between λ − h d and λ + h d
            continue
        difference = (plus - minus) / (2.0 * FD_STEP)
        product = _jacobian_product(problem, multipliers, weight, direction)
        np.testing.assert_allclose(product, difference, rtol=0, atol=FD_TOLERANCE)
        checked += 1
    assert checked >= 20, f"only {checked} smooth points of 60"
