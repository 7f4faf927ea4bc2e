"""Shared helpers for the solver tests: planted problems and the location of the external problems."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from refsim.solvers import ConstraintProblem


def shared_problems() -> Path:
    """Folder of the external Siconos / FCLib problems (REFSIM_SHARED_DATA overrides the default)."""
    base = os.environ.get("REFSIM_SHARED_DATA")
    if base:
        return Path(base) / "solver-problems"
    repository = Path(__file__).resolve().parents[2]
    # ../shared beside a checkout (/work/main), or two levels up for a worktree (/work/wt/NAME)
    candidates = [repository / ".." / "shared" / "data", repository / ".." / ".." / "shared" / "data"]
    for root in candidates:
        if (root / "solver-problems" / "MANIFEST.tsv").is_file():
            return root / "solver-problems"
    return candidates[0] / "solver-problems"


@pytest.fixture
def problems_root() -> Path:
    root = shared_problems()
    if not (root / "MANIFEST.tsv").is_file():
        pytest.skip(f"external solver problems absent ({root})")
    return root


def planted_problem(
    rng: np.random.Generator,
    *,
    bilateral: int = 0,
    unilateral: int = 0,
    contacts: int = 0,
    shafts: int = 0,
    box: int = 0,
    rank: int | None = None,
    friction: float = 0.5,
    scale: float = 1.0,
    shaft_preload: float = 0.0,
) -> tuple[ConstraintProblem, np.ndarray, np.ndarray]:
    """A problem with a known solution (λ*, δ*) satisfying every law; δ_free = δ* − W λ*.

    Every kind gets a mix of its states: unilateral active / separated / degenerate, contacts stick / slip /
    separated, shaft rows stick / slip both ways, box rows inside / at lower / at upper. W = A Aᵀ / rank with
    A of shape (n, rank): singular when rank < n. Each shaft row brings its own pair of bilateral rows. With
    ``shaft_preload`` > 0 every shaft row gets a normal preload p_j ~ U(0.5, 1.5) · shaft_preload [N] (before
    the force scaling), and its bound is μ (‖λ_pair‖ + p_j); with 0 (the default) no random number is drawn
    for it, so the problems of the other tests are unchanged.
    """
    rows = iter(range(10**6))

    def take(count):
        return np.array([next(rows) for _ in range(count)], dtype=np.int64)

    bilateral_rows = take(bilateral)
    pair_rows = take(2 * shafts).reshape(-1, 2)
    unilateral_rows = take(unilateral)
    contact_rows = take(3 * contacts).reshape(-1, 3)
    shaft_rows = take(shafts)
    box_rows = take(box)
    n = bilateral + 2 * shafts + unilateral + 3 * contacts + shafts + box
    rank = n if rank is None else rank
    factor = rng.standard_normal((n, rank))
    compliance = scale * factor @ factor.T / rank + (scale * 0.05 * np.eye(n) if rank == n else 0.0)
    force = np.zeros(n)
    gap = np.zeros(n)
    all_bilateral = np.concatenate([bilateral_rows, pair_rows.reshape(-1)])
    force[all_bilateral] = rng.standard_normal(all_bilateral.size)
    state = np.arange(unilateral) % 3  # 0 active, 1 separated, 2 degenerate (λ = δ = 0)
    force[unilateral_rows[state == 0]] = rng.uniform(0.5, 2.0, np.count_nonzero(state == 0))
    gap[unilateral_rows[state == 1]] = rng.uniform(0.5, 2.0, np.count_nonzero(state == 1))
    mu = np.full(contacts, friction)
    for index, (normal, t1, t2) in enumerate(contact_rows):  # building test data, not a hot path
        kind = index % 3
        angle = rng.uniform(0, 2 * np.pi)
        direction = np.array([np.cos(angle), np.sin(angle)])
        if kind == 0:  # stick: inside the cone, δ = 0
            force[normal] = rng.uniform(0.5, 2.0)
            force[[t1, t2]] = rng.uniform(0.0, 0.8) * mu[index] * force[normal] * direction
        elif kind == 1:  # slip: on the cone, δ_t opposite to λ_t, δ_n = 0
            force[normal] = rng.uniform(0.5, 2.0)
            force[[t1, t2]] = mu[index] * force[normal] * direction
            gap[[t1, t2]] = -rng.uniform(0.5, 2.0) * direction
        else:  # separated: λ = 0, δ_n > 0, any δ_t
            gap[normal] = rng.uniform(0.5, 2.0)
            gap[[t1, t2]] = rng.standard_normal(2)
    shaft_mu = np.full(shafts, friction)
    preload = rng.uniform(0.5, 1.5, shafts) * shaft_preload if shaft_preload > 0.0 else np.zeros(shafts)
    for index, row in enumerate(shaft_rows):
        bound = shaft_mu[index] * (np.linalg.norm(force[pair_rows[index]]) + preload[index])
        kind = index % 3
        if kind == 0:  # stick
            force[row] = rng.uniform(-0.8, 0.8) * bound
        else:  # slip at ∓bound against δ = ±γ
            sign = 1.0 if kind == 1 else -1.0
            gap[row] = sign * rng.uniform(0.5, 2.0)
            force[row] = -sign * bound
    lower = -rng.uniform(0.5, 1.5, box)
    upper = rng.uniform(0.5, 1.5, box)
    state = np.arange(box) % 3
    inside = box_rows[state == 0]
    force[inside] = rng.uniform(0.2, 0.8) * upper[state == 0]
    force[box_rows[state == 1]] = lower[state == 1]
    gap[box_rows[state == 1]] = rng.uniform(0.5, 2.0, np.count_nonzero(state == 1))
    force[box_rows[state == 2]] = upper[state == 2]
    gap[box_rows[state == 2]] = -rng.uniform(0.5, 2.0, np.count_nonzero(state == 2))
    force *= 1.0 / scale  # keep δ of order one whatever the compliance scale
    preload /= scale
    lower /= scale
    upper /= scale
    free_gap = gap - compliance @ force
    problem = ConstraintProblem(
        compliance=compliance,
        free_gap=free_gap,
        bilateral=all_bilateral,
        unilateral=unilateral_rows,
        contacts=contact_rows,
        contact_friction=mu,
        shaft_friction=shaft_rows,
        shaft_pairs=pair_rows,
        shaft_friction_coefficient=shaft_mu,
        shaft_normal_preload=preload,
        box_rows=box_rows,
        box_lower=lower,
        box_upper=upper,
        name="planted",
    )
    return problem, force, gap


@pytest.fixture
def planted():
    """The factory :func:`planted_problem` (fixtures avoid importing conftest by name)."""
    return planted_problem


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20210401)
