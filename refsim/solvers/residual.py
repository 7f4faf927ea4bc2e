"""The natural-map residual of a constraint problem, the one error measure every solver is judged by.

Per row kind, with δ = W λ + δ_free (Siconos' error measure, ``fc3d_compute_error`` and ``lcp_compute_error``,
extended to the kinds of :class:`~refsim.solvers.ConstraintProblem`):

- bilateral: e = δ;
- unilateral: e = λ − max(0, λ − δ);
- contact: e = λ − P_K(λ − δ̂), δ̂ = δ + μ ‖δ_t‖ e_n (De Saxcé), K = {‖λ_t‖ ≤ μ λ_n};
- group friction: e = λ − clip(λ − δ, −b, b), b = μ (‖λ_G‖ + p), G the row's group and p its preload;
- box: e = λ − clip(λ − δ, lower, upper).

The residual is ‖e‖₂ / max(‖δ_free‖, ‖λ‖, ‖δ‖); it is zero exactly at a solution. Because ‖λ‖ is in its
denominator, a diverging λ makes it small: it is the measure of the external problem sets, not a proof.

:func:`data_residual` cannot be shrunk that way: the same error e divided by scales of the problem's data
only, max(‖δ_free‖ [m], F_data [N]), where the data force scale F_data = max(‖ρ δ_free‖, ‖finite box bounds‖,
‖μ p‖ of the group-friction preloads) [N] with ρ_i = 1/W_ii [N/m] (‖ρ δ_free‖: the forces that would close
each free gap alone) replaces ‖λ‖, and ‖δ_free‖ replaces ‖δ‖. Per law, e is a gap [m] on rows where the law's
projection is the identity (δ must vanish) and a force [N] where it clamps; the two data scales are the
references of these units. A solver reports ``converged`` only when both residuals meet the tolerance.
"""

from __future__ import annotations

import numpy as np

from refsim.kernel_cache import numba
from refsim.solvers.laws import (
    LAW_NAMES,
    LAWS,
    block_arrays,
    natural_map_blocks,
    project_friction_cone,
    scale_arrays,
)
from refsim.solvers.problem import ConstraintProblem

__all__ = [
    "data_residual",
    "data_residual_by_kind",
    "data_scales",
    "natural_map_error",
    "natural_residual",
    "natural_residual_by_kind",
    "project_friction_cone",
]


def natural_map_error(
    problem: ConstraintProblem, multipliers: np.ndarray, gap_weight: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Per-row natural-map error e and the gap δ.

    Parameters
    ----------
    problem : The constraint problem.
    multipliers : Multipliers λ [N], shape (row_count,).
    gap_weight : Optional positive weights ρ [N/m], shape (row_count,), equal on the three rows of a contact:
        the map becomes e = λ − Π(λ − ρ δ̂) (bilateral rows: e = ρ δ), which has the same zeros for any such ρ
        and is better conditioned with ρ ≈ 1/W_ii. None means ρ = 1 (the residual's definition).

    Returns
    -------
    error : Natural-map error of every row (unnormalised, mixed units [N] and [m]), shape (row_count,).
    gap : δ = W λ + δ_free [m], shape (row_count,).
    """
    multipliers = problem.check_multipliers(multipliers)
    gap = problem.compliance @ multipliers + problem.free_gap
    weighted = gap if gap_weight is None else gap_weight * gap
    error = np.zeros(problem.row_count)
    for law in LAWS:  # each law writes its own rows (laws.py: the Python form of natural_map_blocks)
        law.natural_map(problem, multipliers, gap, weighted, gap_weight, error)
    return error, gap


@numba.njit(cache=True)
def _compiled_norm(vector):
    largest = 0.0
    for value in vector:
        magnitude = abs(value)
        if magnitude != magnitude:  # NaN
            return magnitude
        largest = max(largest, magnitude)
    if largest == 0.0 or not np.isfinite(largest):
        return largest
    total = 0.0
    for value in vector:
        total += (value / largest) ** 2
    return largest * np.sqrt(total)


def _norm(vector: np.ndarray) -> float:
    """Euclidean norm without overflow for entries up to the largest float (compiled: no NumPy call
    overhead)."""
    return float(_compiled_norm(np.asarray(vector, dtype=np.float64).reshape(-1)))


def _denominator(problem: ConstraintProblem, multipliers: np.ndarray, gap: np.ndarray) -> float:
    scale = max(_norm(problem.free_gap), _norm(multipliers), _norm(gap))
    return float(scale) if scale > 0.0 else 1.0


def _compiled_error(problem: ConstraintProblem, multipliers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """natural_map_error with ρ = 1 through the compiled kernel (same values to round-off, less overhead)."""
    multipliers = problem.check_multipliers(multipliers)
    kinds, rows, params, members = block_arrays(problem)
    gap = problem.compliance @ multipliers + problem.free_gap
    error = np.zeros(problem.row_count)
    natural_map_blocks(kinds, rows, params, members, multipliers, gap, np.ones(problem.row_count), error)
    return error, gap


# : Below this many rows W λ is a compiled loop rather than numba's BLAS call (gemv), whose fixed cost
# dominates : small products (measured, one thread, compiled loops: 0.011 / 0.13 / 0.26 µs against 0.22 / 0.30
# / 0.30 µs at : n = 3 / 15 / 24; 0.49 against 0.34 µs at n = 32).
_LOOP_PRODUCT_BELOW = 24


@numba.njit(cache=True)
def _gap_into(compliance, multipliers, free_gap, out):
    """out = W λ + δ_free in place (W C-contiguous): a compiled loop below :data:`_LOOP_PRODUCT_BELOW` rows,
    else numba's BLAS product."""
    n = out.shape[0]
    if n < _LOOP_PRODUCT_BELOW:
        for i in range(n):
            total = 0.0
            for j in range(n):
                total += compliance[i, j] * multipliers[j]
            out[i] = total + free_gap[i]
        return
    np.dot(compliance, multipliers, out)
    for i in range(n):
        out[i] += free_gap[i]


@numba.njit(cache=True)
def _residual_pair(compliance, free_gap, kinds, rows, params, members, multipliers, force_scale):
    """(natural residual, data residual) of ``multipliers``: one gap, one error, the norms of
    :func:`_norm`."""
    n = free_gap.shape[0]
    gap = np.empty(n)
    _gap_into(compliance, multipliers, free_gap, gap)
    error = np.empty(n)
    natural_map_blocks(kinds, rows, params, members, multipliers, gap, np.ones(n), error)
    norm = _compiled_norm(error)
    free = _compiled_norm(free_gap)
    scale = max(free, max(_compiled_norm(multipliers), _compiled_norm(gap)))
    if not scale > 0.0:
        scale = 1.0
    return norm / scale, norm / max(free, force_scale)


def _pair(problem: ConstraintProblem, multipliers: np.ndarray) -> tuple[float, float]:
    kinds, rows, params, members = block_arrays(problem)
    _, force_scale = data_scales(problem)
    natural, data = _residual_pair(
        np.ascontiguousarray(problem.compliance),
        problem.free_gap,
        kinds,
        rows,
        params,
        members,
        np.ascontiguousarray(multipliers),
        float(force_scale),
    )
    return (
        float(natural) if np.isfinite(natural) else float("inf"),
        float(data) if np.isfinite(data) else float("inf"),
    )


def natural_residual(problem: ConstraintProblem, multipliers: np.ndarray) -> float:
    """Normalised natural-map residual ‖e‖₂ / max(‖δ_free‖, ‖λ‖, ‖δ‖) of ``multipliers``.

    Parameters
    ----------
    problem : The constraint problem.
    multipliers : Multipliers λ [N], shape (row_count,).

    Returns
    -------
    The residual [-]; 0 exactly at a solution (1 when everything is zero is impossible: then e = 0).
    """
    return _pair(problem, problem.check_multipliers(multipliers))[0]


def residuals(problem: ConstraintProblem, multipliers: np.ndarray) -> tuple[float, float]:
    """(:func:`natural_residual`, :func:`data_residual`) of ``multipliers`` from one gap and one natural-map
    error (the same values as the two calls; non-finite multipliers raise, as in :func:`natural_residual`)."""
    return _pair(problem, problem.check_multipliers(multipliers))


def natural_residual_by_kind(problem: ConstraintProblem, multipliers: np.ndarray) -> dict[str, float]:
    """The residual of :func:`natural_residual` split by row kind (same denominator).

    Returns
    -------
    A dict mapping each name of :data:`refsim.solvers.laws.LAW_NAMES` to
    ‖e_kind‖₂ / max(‖δ_free‖, ‖λ‖, ‖δ‖);
    the squares of the values sum to the square of :func:`natural_residual`.
    """
    error, gap = natural_map_error(problem, multipliers)
    denominator = _denominator(problem, np.asarray(multipliers, float), gap)
    kinds = problem.row_kinds()
    return {name: _norm(error[kinds == code]) / denominator for code, name in enumerate(LAW_NAMES)}


def data_scales(problem: ConstraintProblem) -> tuple[np.ndarray, float]:
    """Row weights ρ [N/m] and the data force scale F_data [N] used by :func:`data_residual`.

    ρ_i = 1/W_ii (the mean over the three rows of a contact, so the cone is unchanged; rows whose W_ii is not
    above 1e-14 of the largest diagonal get 1/max_j W_jj). F_data = max(‖ρ δ_free‖, ‖finite nonzero box
    bounds‖, ‖μ_j p_j‖ over group friction rows); 1 when all are zero.

    Returns
    -------
    weight : ρ [N/m], shape (row_count,).
    scale : F_data [N].
    """
    cached = problem.__dict__.get("_data_scales")
    if cached is not None:  # the problem is immutable: compute once
        return cached
    contacts, lower, upper, coefficient, preload = scale_arrays(problem)
    weight, scale = _scales(
        problem.compliance, problem.free_gap, contacts, lower, upper, coefficient, preload
    )
    weight.setflags(write=False)
    result = (weight, float(scale))
    object.__setattr__(problem, "_data_scales", result)
    return result


@numba.njit(cache=True)
def _scales(compliance, free_gap, contacts, lower, upper, coefficient, preload):
    """(ρ, F_data) of :func:`data_scales` in one compiled pass from the laws' :func:`scale_arrays` (contact
    rows, fixed lower and upper bounds, group friction coefficients and preloads)."""
    n = free_gap.shape[0]
    largest = 0.0
    if n:
        largest = compliance[0, 0]
        for i in range(1, n):
            largest = max(largest, compliance[i, i])
    if not largest > 0.0:
        largest = 1.0
    safe = np.empty(n)
    for i in range(n):
        value = compliance[i, i]
        safe[i] = value if value > 1e-14 * largest else largest
    for c in range(contacts.shape[0]):
        mean = (safe[contacts[c, 0]] + safe[contacts[c, 1]] + safe[contacts[c, 2]]) / 3.0
        safe[contacts[c, 0]] = mean
        safe[contacts[c, 1]] = mean
        safe[contacts[c, 2]] = mean
    weight = 1.0 / safe
    scale = _compiled_norm(weight * free_gap)
    count = lower.shape[0] + upper.shape[0]
    if count:
        bounds = np.empty(count)
        kept = 0
        for value in lower:
            if np.isfinite(value):
                bounds[kept] = value
                kept += 1
        for value in upper:
            if np.isfinite(value):
                bounds[kept] = value
                kept += 1
        scale = max(scale, _compiled_norm(bounds[:kept]))
    if coefficient.shape[0]:
        scale = max(scale, _compiled_norm(coefficient * preload))
    return weight, (scale if scale > 0.0 else 1.0)


def _data_error(problem: ConstraintProblem, multipliers: np.ndarray) -> tuple[np.ndarray, float]:
    _, force_scale = data_scales(problem)
    scale = max(_norm(problem.free_gap), force_scale)
    multipliers = np.asarray(multipliers, dtype=np.float64)
    if not np.all(np.isfinite(multipliers)):
        return np.full(problem.row_count, np.inf), scale
    error, _ = _compiled_error(problem, multipliers)
    return error, scale


def data_residual(problem: ConstraintProblem, multipliers: np.ndarray) -> float:
    """Natural-map error over scales of the data only, ‖e‖₂ / max(‖δ_free‖, F_data) [-] (see the module
    notes).

    Unlike :func:`natural_residual`, its denominator does not depend on λ: a diverging λ cannot make it small.
    Zero exactly at a solution; inf for non-finite multipliers.
    """
    multipliers = np.asarray(multipliers, dtype=np.float64)
    if multipliers.shape != (problem.row_count,):
        problem.check_multipliers(multipliers)  # raises, naming the shape
    if not np.all(np.isfinite(multipliers)):
        return float("inf")
    return _pair(problem, multipliers)[1]


def data_residual_by_kind(problem: ConstraintProblem, multipliers: np.ndarray) -> dict[str, float]:
    """:func:`data_residual` split by law: ‖e_law‖₂ / max(‖δ_free‖, F_data) for each name of ``LAW_NAMES``
    (squares sum to the square of the total)."""
    error, scale = _data_error(problem, multipliers)
    kinds = problem.row_kinds()
    return {name: _norm(error[kinds == code]) / scale for code, name in enumerate(LAW_NAMES)}
