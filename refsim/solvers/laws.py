"""The constraint laws, as data: one table that every part of :mod:`refsim.solvers` and the problem schema
read.

A law says which multipliers λ and gaps δ = W λ + δ_free are admissible on its rows. Each entry of
:data:`LAWS` gives its name, its integer code (the index of the entry), the number of rows of one block, the
fields of :class:`~refsim.solvers.ConstraintProblem` that hold its rows and parameters (with unit, dtype,
shape and meaning: the HDF5 problem schema is derived from them) and a one-line statement. The compiled
kernels of the laws (one Gauss–Seidel block update, one natural-map block and its generalised Jacobian) are
the ``_*_block`` functions below; the solvers dispatch on the law code.

Laws (codes in this order):

0. ``bilateral``: δ = 0, λ free.
1. ``unilateral`` (Signorini): 0 ≤ δ ⊥ λ ≥ 0.
2. ``contact``: 3-D Coulomb cone on rows (normal, tangent 1, tangent 2): ‖λ_t‖ ≤ μ λ_n with the De Saxcé
   complementarity (friction opposing the slip, δ_n = 0 while in contact).
3. ``group_friction``: |λ_s| ≤ μ (‖λ_G‖ + p) for a friction row s, a group G of any other rows (ragged: any
   number of rows per friction row), a coefficient μ ≥ 0 and a preload p ≥ 0 [N]; stick (δ_s = 0) inside the
   bound, slip at the bound opposing δ_s. Given either as ``group_friction`` rows with ``group_offsets`` /
   ``group_members`` (the group of friction row j is ``group_members[group_offsets[j]:group_offsets[j +
   1]]``), or in the older pair form ``shaft_friction`` / ``shaft_pairs`` (groups of two bilateral rows); both
   forms may be used in one problem and are solved as one law.
4. ``box``: lower ≤ λ ≤ upper with δ = 0 strictly inside, δ ≥ 0 at the lower and δ ≤ 0 at the upper bound.

Adding a law is this module only: one entry in :data:`LAWS` (its fields appear in ``ConstraintProblem``, its
validation, the residual's per-law split, the HDF5 schema and the packed argument :func:`law_arrays` of the
compiled set-up), its vectorised Python forms (``natural_map``, ``bounds``, ``projection`` of its entry: the
natural map of :mod:`refsim.solvers.residual` and the exact solver's QP bounds and least-squares Newton step
loop over the table), its blocks in :func:`assemble_blocks` (and its fixed bounds in the data scales'
:func:`scale_arrays`), and its branch in each compiled kernel (:func:`natural_map_blocks`,
:func:`gauss_seidel_sweep`, :func:`jacobian_blocks`). The kernels are the one definition of each law's
mathematics: the Python forms are tested against them on every law of the table and random inputs
(``tests/solvers/test_law_definitions.py``), and so is the Jacobian kernel against finite differences of the
map.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from refsim.kernel_cache import numba

__all__ = [
    "BILATERAL",
    "BOX",
    "CONTACT",
    "FieldSpec",
    "GROUP_FRICTION",
    "LAWS",
    "LAW_FIELDS",
    "LAW_NAMES",
    "Law",
    "UNILATERAL",
    "assemble_blocks",
    "block_arrays",
    "cone_projection_jacobian",
    "law_arrays",
    "problem_field_specs",
    "project_friction_cone",
    "scale_arrays",
]


@dataclass(frozen=True)
class FieldSpec:
    """One field of :class:`~refsim.solvers.ConstraintProblem` (and one dataset of a recorded problem).

    Attributes
    ----------
    name : Keyword of the field.
    unit : Unit ("m/N", "m", "N", "1" for indices and dimensionless data).
    dtype : "float64" or "int64".
    entry_shape : Shape; "r" the row count, "?" a count of this field's own.
    meaning : One line.
    role : How the field is validated: "rows" (row indices of the law, one per block or (count, block_size)),
        "members" (row indices of groups, ragged), "offsets" (group offsets), "coefficient" (finite ≥ 0, one
        per block), "preload" (finite ≥ 0, one per block, empty means zeros), "bound" (may be ±inf, one per
        block), "matrix" / "vector" (the compliance and the free gap).
    per : For parameters, the rows field they are one per.
    """

    name: str
    unit: str
    dtype: str
    entry_shape: tuple
    meaning: str
    role: str
    per: str = ""

    def empty(self) -> np.ndarray:
        """The default (no entries) of this field."""
        shape = tuple(0 if size == "?" else size for size in self.entry_shape)
        return np.zeros(shape, dtype=np.int64 if self.dtype == "int64" else np.float64)


@dataclass(frozen=True)
class Law:
    """One constraint law of the table.

    Attributes
    ----------
    name : Name used in messages, residual splits and study tables.
    code : Integer code (index in :data:`LAWS`), used by the compiled kernels.
    block_size : Rows of one block (1, or 3 for a contact).
    fields : The problem fields of this law; the "rows" fields list its rows.
    statement : The law in one line.
    validate : Extra checks beyond the per-field ones, called with the problem and a fail(message) callback.
    validate_rows : Extra checks that read only the row-index fields ("rows", "members", "offsets") and the
        row count, called as ``validate``; a problem whose index fields equal those of the last one validated
        skips them with the other checks of its rows (:class:`~refsim.solvers.ConstraintProblem`).
    natural_map : The law's vectorised natural map, ``(problem, λ, δ, ρδ, ρ or None, error)``: writes
        e = λ − Π(λ − ρ δ̂) (bilateral: e = ρ δ) on the law's rows into ``error`` (the Python form of
        :func:`natural_map_blocks`, :func:`refsim.solvers.residual.natural_map_error` loops over the table).
    bounds : ``(problem, λ, lower, upper)``: writes the law's box lower ≤ λ ≤ upper on its rows (the exact
        solver's QP bounds); None for a law without one (bilateral: free; contact: a cone, not a box).
    projection : ``(problem, λ, δ, ρδ, ρ, D_Π, ∂δ̂/∂λ, ∂Π/∂b ∂b/∂λ)``: writes the law's rows of the
        projection's generalised Jacobian D_Π, of the modified gap's derivative (starting as W) and of the
        bound term, all (n, n), for the exact solver's least-squares Newton step (the Python form of
        :func:`jacobian_blocks`).
    """

    name: str
    code: int
    block_size: int
    fields: tuple[FieldSpec, ...]
    statement: str
    validate: Callable | None = None
    natural_map: Callable | None = None
    bounds: Callable | None = None
    projection: Callable | None = None
    validate_rows: Callable | None = None

    @property
    def row_fields(self) -> tuple[str, ...]:
        """Names of the fields holding the law's rows."""
        return tuple(spec.name for spec in self.fields if spec.role == "rows")

    def rows_of(self, problem) -> np.ndarray:
        """Every row of this law in ``problem``, shape (count,)."""
        parts = [np.asarray(getattr(problem, name)).reshape(-1) for name in self.row_fields]
        return np.concatenate(parts).astype(np.int64) if parts else np.zeros(0, dtype=np.int64)


BILATERAL, UNILATERAL, CONTACT, GROUP_FRICTION, BOX = 0, 1, 2, 3, 4


def _check_groups(problem, fail) -> None:
    """Offsets of the group form and the pair form of group friction (row-index fields only)."""
    rows = problem.group_friction
    offsets = problem.group_offsets
    members = problem.group_members
    if rows.size == 0 and offsets.size == 0:
        if members.size:
            fail(f"group_members has {members.size} rows but group_friction is empty")
    else:
        if offsets.shape != (rows.size + 1,):
            fail(
                f"group_offsets has shape {offsets.shape}, expected ({rows.size + 1},): group_friction row j "
                "has the group group_members[group_offsets[j]:group_offsets[j + 1]]"
            )
        if offsets[0] != 0 or offsets[-1] != members.size or (np.diff(offsets) < 0).any():
            fail(
                f"group_offsets must start at 0, never decrease and end at len(group_members) = "
                f"{members.size}, "
                f"got {offsets[:3].tolist()}...{offsets[-1:].tolist()}"
            )
        friction = np.zeros(problem.row_count, dtype=bool)
        friction[rows] = True
        friction[problem.shaft_friction] = True
        in_group = friction[members]
        if in_group.any():
            fail(
                f"group_members holds row {int(members[in_group][0])}, a group friction row; a group may "
                f"hold "
                "any rows but friction rows"
            )
    if len(problem.shaft_pairs) != len(problem.shaft_friction):
        fail(
            f"shaft_pairs has {len(problem.shaft_pairs)} pairs for {len(problem.shaft_friction)} "
            "shaft_friction rows; one pair per row is required"
        )
    bilateral = np.zeros(problem.row_count, dtype=bool)
    bilateral[problem.bilateral] = True
    not_bilateral = ~bilateral[problem.shaft_pairs]
    if not_bilateral.any():
        row = int(problem.shaft_pairs[not_bilateral][0])
        fail(
            f"shaft_pairs references row {row}, which is {LAW_NAMES[problem.row_kinds()[row]]}; the pair of "
            f"a "
            "shaft friction row must be bilateral rows (use group_friction for any other group)"
        )


def _check_box(problem, fail) -> None:
    lower, upper = problem.box_lower, problem.box_upper
    if (lower > upper).any():
        index = int(np.argmax(lower > upper))
        fail(
            f"box row {int(problem.box_rows[index])} has box_lower {lower[index]} > box_upper {upper[index]}"
        )


# ---------------------------------------------------------------------- the laws: vectorised Python forms
# One natural map, box bounds and projection Jacobian per law (the fields of its Law entry); each is tested
# against the law's compiled kernels below on random inputs (tests/solvers/test_law_definitions.py).
def project_friction_cone(points: np.ndarray, friction_coefficient: np.ndarray) -> np.ndarray:
    """Euclidean projection onto the Coulomb cones K = {‖x_t‖ ≤ μ x_n}.

    Parameters
    ----------
    points : Points (normal, tangent 1, tangent 2) [N], shape (k, 3).
    friction_coefficient : Friction coefficient μ of each cone [-], shape (k,).

    Returns
    -------
    Projected points [N], shape (k, 3).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    mu = np.asarray(friction_coefficient, dtype=np.float64).reshape(-1)
    normal = points[:, 0]
    tangent = points[:, 1:]
    tangent_norm = np.linalg.norm(tangent, axis=1)
    inside = tangent_norm <= mu * normal
    polar = mu * tangent_norm <= -normal
    projected_normal = np.maximum((normal + mu * tangent_norm) / (1.0 + mu * mu), 0.0)
    safe_norm = np.where(tangent_norm > 0.0, tangent_norm, 1.0)
    direction = tangent / safe_norm[:, None]
    result = np.empty_like(points)
    result[:, 0] = projected_normal
    result[:, 1:] = (mu * projected_normal)[:, None] * direction
    result[inside] = points[inside]
    result[polar & ~inside] = 0.0
    return result


def cone_projection_jacobian(points: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """Jacobian of the projection onto K = {‖x_t‖ ≤ μ x_n} at ``points`` (k, 3); shape (k, 3, 3)."""
    normal = points[:, 0]
    tangent = points[:, 1:]
    norm = np.linalg.norm(tangent, axis=1)
    inside = norm <= mu * normal
    polar = ~inside & (mu * norm <= -normal)
    boundary = ~inside & ~polar
    jacobian = np.zeros((len(points), 3, 3))
    jacobian[inside] = np.eye(3)
    if boundary.any():
        m = mu[boundary]
        t = np.maximum(norm[boundary], 1e-300)
        direction = tangent[boundary] / t[:, None]
        ray = np.column_stack([np.ones(m.size), m[:, None] * direction])  # (1, μ ŵ)
        height = (normal[boundary] + m * t) / (1.0 + m * m)
        # d/dz_n: ray / (1 + μ²); d/dz_t: μ ray ŵᵀ / (1 + μ²) + height (0, μ (I − ŵŵᵀ) / t)
        block = np.zeros((m.size, 3, 3))
        block[:, :, 0] = ray / (1.0 + m * m)[:, None]
        block[:, :, 1:] = (m / (1.0 + m * m))[:, None, None] * ray[:, :, None] * direction[:, None, :]
        projector = np.eye(2)[None] - direction[:, :, None] * direction[:, None, :]
        block[:, 1:, 1:] += (height * m / t)[:, None, None] * projector
        jacobian[boundary] = block
    return jacobian


def _bilateral_map(problem, multipliers, gap, weighted, gap_weight, error) -> None:
    rows = problem.bilateral
    error[rows] = weighted[rows]


def _unilateral_map(problem, multipliers, gap, weighted, gap_weight, error) -> None:
    rows = problem.unilateral
    error[rows] = multipliers[rows] - np.maximum(0.0, multipliers[rows] - weighted[rows])


def _contact_map(problem, multipliers, gap, weighted, gap_weight, error) -> None:
    if len(problem.contacts):
        contacts = problem.contacts
        mu = problem.contact_friction
        local_gap = gap[contacts]
        modified = local_gap.copy()
        modified[:, 0] += mu * np.linalg.norm(local_gap[:, 1:], axis=1)
        if gap_weight is not None:
            modified *= gap_weight[contacts]
        local_force = multipliers[contacts]
        error[contacts] = local_force - project_friction_cone(local_force - modified, mu)


def _group_map(problem, multipliers, gap, weighted, gap_weight, error) -> None:
    rows = problem.friction_groups()[0]
    if len(rows):
        bound = problem.friction_bounds(multipliers)
        error[rows] = multipliers[rows] - np.clip(multipliers[rows] - weighted[rows], -bound, bound)


def _box_map(problem, multipliers, gap, weighted, gap_weight, error) -> None:
    rows = problem.box_rows
    error[rows] = multipliers[rows] - np.clip(
        multipliers[rows] - weighted[rows], problem.box_lower, problem.box_upper
    )


def _unilateral_bounds(problem, multipliers, lower, upper) -> None:
    lower[problem.unilateral] = 0.0


def _group_bounds(problem, multipliers, lower, upper) -> None:
    rows = problem.friction_groups()[0]
    if len(rows):
        bound = problem.friction_bounds(multipliers)
        lower[rows] = -bound
        upper[rows] = bound


def _box_bounds(problem, multipliers, lower, upper) -> None:
    lower[problem.box_rows] = problem.box_lower
    upper[problem.box_rows] = problem.box_upper


def _bilateral_projection(problem, multipliers, gap, weighted, weight, projection, gap_jacobian, bound_term):
    rows = problem.bilateral
    projection[rows, rows] = 1.0


def _unilateral_projection(problem, multipliers, gap, weighted, weight, projection, gap_jacobian, bound_term):
    rows = problem.unilateral
    projection[rows, rows] = (multipliers[rows] - weighted[rows] > 0.0).astype(float)


def _contact_projection(problem, multipliers, gap, weighted, weight, projection, gap_jacobian, bound_term):
    if not len(problem.contacts):
        return
    contacts = problem.contacts
    mu = problem.contact_friction
    local_gap = gap[contacts]
    slip = np.linalg.norm(local_gap[:, 1:], axis=1)
    modified = local_gap.copy()
    modified[:, 0] += mu * slip
    slip_direction = local_gap[:, 1:] / np.maximum(slip, 1e-300)[:, None]
    normal_rows = contacts[:, 0]
    gap_jacobian[normal_rows] += (
        mu[:, None, None] * slip_direction[:, :, None] * problem.compliance[contacts[:, 1:]]
    ).sum(axis=1)
    modified *= weight[contacts]
    blocks = cone_projection_jacobian(multipliers[contacts] - modified, mu)
    projection[contacts[:, :, None], contacts[:, None, :]] = blocks


def _group_projection(problem, multipliers, gap, weighted, weight, projection, gap_jacobian, bound_term):
    rows, offsets, members, coefficient, _ = problem.friction_groups()
    if not len(rows):
        return
    sizes = np.diff(offsets)
    owner = np.repeat(np.arange(rows.size), sizes)
    member_force = multipliers[members]
    group_norm = np.sqrt(np.bincount(owner, weights=member_force**2, minlength=rows.size))
    bound = problem.friction_bounds(multipliers)  # the preload is constant: ∂b/∂λ is the group term only
    z = multipliers[rows] - weighted[rows]
    inside = np.abs(z) < bound
    projection[rows, rows] = inside.astype(float)
    slope = np.where(
        (~inside & (group_norm > 0.0))[owner],
        (np.sign(z) * coefficient)[owner] * member_force / np.maximum(group_norm, 1e-300)[owner],
        0.0,
    )
    np.add.at(bound_term, (rows[owner], members), slope)


def _box_projection(problem, multipliers, gap, weighted, weight, projection, gap_jacobian, bound_term):
    rows = problem.box_rows
    z = multipliers[rows] - weighted[rows]
    projection[rows, rows] = ((z > problem.box_lower) & (z < problem.box_upper)).astype(float)


#: The law table. Field order here is the keyword order of ConstraintProblem and of the problem schema.
LAWS: tuple[Law, ...] = (
    Law(
        "bilateral",
        BILATERAL,
        1,
        (FieldSpec("bilateral", "1", "int64", ("?",), "bilateral rows", "rows"),),
        "δ = 0, λ free",
        natural_map=_bilateral_map,
        projection=_bilateral_projection,
    ),
    Law(
        "unilateral",
        UNILATERAL,
        1,
        (FieldSpec("unilateral", "1", "int64", ("?",), "unilateral (Signorini) rows", "rows"),),
        "0 ≤ δ ⊥ λ ≥ 0 (Signorini)",
        natural_map=_unilateral_map,
        bounds=_unilateral_bounds,
        projection=_unilateral_projection,
    ),
    Law(
        "contact",
        CONTACT,
        3,
        (
            FieldSpec(
                "contacts", "1", "int64", ("?", 3), "contact rows (normal, tangent 1, tangent 2)", "rows"
            ),
            FieldSpec(
                "contact_friction",
                "1",
                "float64",
                ("?",),
                "Coulomb friction coefficient of each contact",
                "coefficient",
                per="contacts",
            ),
        ),
        "‖λ_t‖ ≤ μ λ_n, De Saxcé complementarity (3-D Coulomb cone)",
        natural_map=_contact_map,
        projection=_contact_projection,
    ),
    Law(
        "group_friction",
        GROUP_FRICTION,
        1,
        (
            FieldSpec(
                "shaft_friction",
                "1",
                "int64",
                ("?",),
                "friction rows bounded by a pair of bilateral rows (pair form of group friction)",
                "rows",
            ),
            FieldSpec(
                "shaft_pairs",
                "1",
                "int64",
                ("?", 2),
                "the two bilateral rows bounding each shaft_friction row",
                "members",
                per="shaft_friction",
            ),
            FieldSpec(
                "shaft_friction_coefficient",
                "1",
                "float64",
                ("?",),
                "friction coefficient of each shaft_friction row",
                "coefficient",
                per="shaft_friction",
            ),
            FieldSpec(
                "shaft_normal_preload",
                "N",
                "float64",
                ("?",),
                "preload p added to the pair force norm in each shaft_friction row's bound (empty: zeros)",
                "preload",
                per="shaft_friction",
            ),
            FieldSpec(
                "group_friction", "1", "int64", ("?",), "friction rows bounded by a group of rows", "rows"
            ),
            FieldSpec(
                "group_offsets",
                "1",
                "int64",
                ("?",),
                "group of group_friction row j: group_members[group_offsets[j]:group_offsets[j+1]]",
                "offsets",
                per="group_friction",
            ),
            FieldSpec(
                "group_members",
                "1",
                "int64",
                ("?",),
                "rows of all groups, concatenated",
                "members",
                per="group_friction",
            ),
            FieldSpec(
                "group_friction_coefficient",
                "1",
                "float64",
                ("?",),
                "friction coefficient of each group_friction row",
                "coefficient",
                per="group_friction",
            ),
            FieldSpec(
                "group_preload",
                "N",
                "float64",
                ("?",),
                "preload p of each group_friction row's bound (empty: zeros)",
                "preload",
                per="group_friction",
            ),
        ),
        "|λ_s| ≤ μ (‖λ_G‖ + p), stick inside, slip at the bound opposing δ_s",
        validate_rows=_check_groups,
        natural_map=_group_map,
        bounds=_group_bounds,
        projection=_group_projection,
    ),
    Law(
        "box",
        BOX,
        1,
        (
            FieldSpec("box_rows", "1", "int64", ("?",), "rows with fixed bounds", "rows"),
            FieldSpec(
                "box_lower",
                "N",
                "float64",
                ("?",),
                "lower bound of each box row (may be -inf)",
                "bound",
                per="box_rows",
            ),
            FieldSpec(
                "box_upper",
                "N",
                "float64",
                ("?",),
                "upper bound of each box row (may be +inf)",
                "bound",
                per="box_rows",
            ),
        ),
        "lower ≤ λ ≤ upper; δ = 0 inside, δ ≥ 0 at lower, δ ≤ 0 at upper (Siconos' relay)",
        _check_box,
        natural_map=_box_map,
        bounds=_box_bounds,
        projection=_box_projection,
    ),
)

#: Names of the laws, in the order of their codes (:meth:`ConstraintProblem.row_kinds`).
LAW_NAMES: tuple[str, ...] = tuple(law.name for law in LAWS)

#: Every law field, in keyword order.
LAW_FIELDS: tuple[FieldSpec, ...] = tuple(spec for law in LAWS for spec in law.fields)

_DATA_FIELDS = (
    FieldSpec("compliance", "m/N", "float64", ("r", "r"), "compliance (Delassus operator) W", "matrix"),
    FieldSpec("free_gap", "m", "float64", ("r",), "free-motion gap delta_free", "vector"),
)

assert all(law.code == index for index, law in enumerate(LAWS)), "law codes must be their table index"
assert all(law.natural_map and law.projection for law in LAWS), "every law has its natural map and projection"


def problem_field_specs() -> tuple[FieldSpec, ...]:
    """Every array field of :class:`~refsim.solvers.ConstraintProblem`: W, δ_free, then the law fields."""
    return _DATA_FIELDS + LAW_FIELDS


# ---------------------------------------------------------------------------------------------------- blocks
def friction_groups(problem) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Both forms of group friction merged: (rows (m,), offsets (m + 1,), members, coefficient (m,), preload
    (m,)).

    Pair-form rows come first (each with its two bilateral rows as members), then the group-form rows.
    """
    return merge_friction_groups(
        problem.shaft_friction,
        problem.shaft_pairs,
        problem.shaft_friction_coefficient,
        problem.shaft_normal_preload,
        problem.group_friction,
        problem.group_offsets,
        problem.group_members,
        problem.group_friction_coefficient,
        problem.group_preload,
    )


@numba.njit(cache=True)
def merge_friction_groups(
    shaft_friction,
    shaft_pairs,
    shaft_coefficient,
    shaft_preload,
    group_friction,
    group_offsets,
    group_members,
    group_coefficient,
    group_preload,
):
    """:func:`friction_groups` from the problem's arrays, in compiled code (the fresh-problem kernel of
    :mod:`refsim.solvers.newton` calls it directly)."""
    pairs = shaft_friction.shape[0]
    groups = group_friction.shape[0]
    rows = np.empty(pairs + groups, dtype=np.int64)
    offsets = np.empty(pairs + groups + 1, dtype=np.int64)
    members = np.empty(2 * pairs + group_members.shape[0], dtype=np.int64)
    coefficient = np.empty(pairs + groups)
    preload = np.empty(pairs + groups)
    for j in range(pairs):
        rows[j] = shaft_friction[j]
        offsets[j] = 2 * j
        members[2 * j] = shaft_pairs[j, 0]
        members[2 * j + 1] = shaft_pairs[j, 1]
        coefficient[j] = shaft_coefficient[j]
        preload[j] = shaft_preload[j]
    offsets[pairs] = 2 * pairs
    for j in range(groups):
        rows[pairs + j] = group_friction[j]
        offsets[pairs + j + 1] = 2 * pairs + group_offsets[j + 1]
        coefficient[pairs + j] = group_coefficient[j]
        preload[pairs + j] = group_preload[j]
    for k in range(group_members.shape[0]):
        members[2 * pairs + k] = group_members[k]
    return rows, offsets, members, coefficient, preload


def law_arrays(problem) -> tuple:
    """The problem's law fields as one tuple, in the order of :data:`LAW_FIELDS` (the table's): the one packed
    argument of the compiled set-up :func:`assemble_blocks` (a new law's fields join it by its entry)."""
    return tuple(getattr(problem, spec.name) for spec in LAW_FIELDS)


def _law_setup(problem) -> tuple:
    """:func:`assemble_blocks` of the problem, computed once and cached on it (the problem is immutable:
    frozen, read-only arrays)."""
    cached = problem.__dict__.get("_block_arrays")
    if cached is not None:
        return cached
    kind, row, param, members, scaling = assemble_blocks(law_arrays(problem))
    result = (kind, row, param, np.ascontiguousarray(members, dtype=np.int64), scaling)
    for array in result[:4] + scaling:
        array.setflags(write=False)
    object.__setattr__(problem, "_block_arrays", result)
    return result


def block_arrays(problem) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The problem as blocks sorted by first row, for the compiled kernels (one compiled pass, cached on the
    problem).

    Returns
    -------
    kinds : Law code of each block, shape (b,).
    rows : Rows of each block, shape (b, 3): (row, 0, 0) for one-row laws, (normal, t1, t2) for a contact, and
        (row, start, end) for group friction, the group being members[start:end].
    params : Parameters, shape (b, 2): (μ, 0) contact, (μ, p) group friction, (lower, upper) box, else zeros.
    members : Group members, shape (g,).
    """
    return _law_setup(problem)[:4]


def scale_arrays(problem) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What the data scales of :func:`refsim.solvers.residual.data_scales` read of the laws: (contact rows
    (k, 3), whose weights are averaged; lower and upper fixed bounds, whose finite values are forces of the
    data; group friction coefficients and preloads (m,), whose products μ p are too). Cached with
    :func:`block_arrays`."""
    return _law_setup(problem)[4]


@numba.njit(cache=True)
def assemble_blocks(fields):
    """(kinds, rows, params, members) of :func:`block_arrays` and the data of :func:`scale_arrays`, in one
    compiled pass from the packed law fields of :func:`law_arrays`: group friction's two forms merged, the
    laws in code order, then sorted by first row (first rows are distinct: every row belongs to one law)."""
    (
        bilateral,
        unilateral,
        contacts,
        contact_friction,
        shaft_friction,
        shaft_pairs,
        shaft_coefficient,
        shaft_preload,
        group_friction,
        group_offsets,
        group_members,
        group_coefficient,
        group_preload,
        box,
        box_lower,
        box_upper,
    ) = fields
    if shaft_friction.shape[0] or group_friction.shape[0]:
        f_rows, f_offsets, members, f_mu, f_preload = merge_friction_groups(
            shaft_friction,
            shaft_pairs,
            shaft_coefficient,
            shaft_preload,
            group_friction,
            group_offsets,
            group_members,
            group_coefficient,
            group_preload,
        )
    else:  # no group friction: skip the merging
        f_rows = f_offsets = members = np.zeros(0, dtype=np.int64)
        f_mu = f_preload = np.zeros(0)
    counts = (bilateral.shape[0], unilateral.shape[0], box.shape[0], f_rows.shape[0], contacts.shape[0])
    total = counts[0] + counts[1] + counts[2] + counts[3] + counts[4]
    kind = np.empty(total, dtype=np.int64)
    row = np.zeros((total, 3), dtype=np.int64)
    param = np.zeros((total, 2))
    b = 0
    for i in range(counts[0]):
        kind[b] = BILATERAL
        row[b, 0] = bilateral[i]
        b += 1
    for i in range(counts[1]):
        kind[b] = UNILATERAL
        row[b, 0] = unilateral[i]
        b += 1
    for i in range(counts[2]):
        kind[b] = BOX
        row[b, 0] = box[i]
        param[b, 0] = box_lower[i]
        param[b, 1] = box_upper[i]
        b += 1
    for i in range(counts[3]):
        kind[b] = GROUP_FRICTION
        row[b, 0] = f_rows[i]
        row[b, 1] = f_offsets[i]
        row[b, 2] = f_offsets[i + 1]
        param[b, 0] = f_mu[i]
        param[b, 1] = f_preload[i]
        b += 1
    for i in range(counts[4]):
        kind[b] = CONTACT
        row[b, 0] = contacts[i, 0]
        row[b, 1] = contacts[i, 1]
        row[b, 2] = contacts[i, 2]
        param[b, 0] = contact_friction[i]
        b += 1
    scaling = (contacts, box_lower, box_upper, f_mu, f_preload)
    ordered = True
    for i in range(1, total):
        if row[i, 0] <= row[i - 1, 0]:
            ordered = False
            break
    if ordered:
        return kind, row, param, members, scaling
    # The first rows are distinct row indices: each block is placed by its first row (a counting sort, the
    # order any sort gives; numba's argsort compiled for seconds longer than the rest of this function).
    last = 0
    for i in range(total):
        last = max(last, row[i, 0])
    block_at = np.full(last + 1, -1, dtype=np.int64)
    for i in range(total):
        block_at[row[i, 0]] = i
    sorted_kind = np.empty(total, dtype=np.int64)
    sorted_row = np.empty((total, 3), dtype=np.int64)
    sorted_param = np.empty((total, 2))
    b = 0
    for first in range(last + 1):
        i = block_at[first]
        if i < 0:
            continue
        sorted_kind[b] = kind[i]
        sorted_row[b, 0], sorted_row[b, 1], sorted_row[b, 2] = row[i, 0], row[i, 1], row[i, 2]
        sorted_param[b, 0], sorted_param[b, 1] = param[i, 0], param[i, 1]
        b += 1
    return sorted_kind, sorted_row, sorted_param, members, scaling


# ---------------------------------------------------------------------------------------------------- kernels
@numba.njit(cache=True)
def group_bound(multipliers, members, start, end, coefficient, preload):
    """μ (‖λ_G‖ + p) [N] for the group members[start:end]."""
    total = 0.0
    for k in range(start, end):
        value = multipliers[members[k]]
        total += value * value
    return coefficient * (np.sqrt(total) + preload)


@numba.njit(cache=True)
def project_cone(zn, z1, z2, mu):
    """Projection of (zn, z1, z2) onto {‖x_t‖ ≤ μ x_n}."""
    zt = np.sqrt(z1 * z1 + z2 * z2)
    if zt <= mu * zn:
        return zn, z1, z2
    if mu * zt <= -zn:
        return 0.0, 0.0, 0.0
    pn = max((zn + mu * zt) / (1.0 + mu * mu), 0.0)
    ratio = mu * pn / zt if zt > 0.0 else 0.0
    return pn, ratio * z1, ratio * z2


@numba.njit(cache=True)
def natural_map_blocks(kinds, rows, params, members, multipliers, gap, weight, error):
    """Natural-map error e = λ − Π(λ − ρ δ̂) of every block into ``error`` (bilateral: e = ρ δ).

    ``weight`` ρ [N/m] per row (equal on the rows of a contact); ρ = 1 gives the residual's definition.
    """
    for b in range(kinds.shape[0]):
        kind = kinds[b]
        row = rows[b, 0]
        if kind == CONTACT:
            t1 = rows[b, 1]
            t2 = rows[b, 2]
            mu = params[b, 0]
            rho = weight[row]
            slip = np.sqrt(gap[t1] * gap[t1] + gap[t2] * gap[t2])
            pn, p1, p2 = project_cone(
                multipliers[row] - rho * (gap[row] + mu * slip),
                multipliers[t1] - rho * gap[t1],
                multipliers[t2] - rho * gap[t2],
                mu,
            )
            error[row] = multipliers[row] - pn
            error[t1] = multipliers[t1] - p1
            error[t2] = multipliers[t2] - p2
        elif kind == BILATERAL:
            error[row] = weight[row] * gap[row]
        else:
            z = multipliers[row] - weight[row] * gap[row]
            if kind == UNILATERAL:
                error[row] = multipliers[row] - max(z, 0.0)
            elif kind == GROUP_FRICTION:
                bound = group_bound(multipliers, members, rows[b, 1], rows[b, 2], params[b, 0], params[b, 1])
                error[row] = multipliers[row] - min(max(z, -bound), bound)
            else:
                error[row] = multipliers[row] - min(max(z, params[b, 0]), params[b, 1])


@numba.njit(cache=True)
def _apply(transposed, diagonal, multipliers, gap, row, value):
    """Set λ[row] = value and update the gap with W[:, row] Δλ; return |W_rr Δλ|.

    No early return for an unchanged row: its loop gets no trips instead. Measured (one thread, compiled
    loop): with ``if change == 0.0: return 0.0`` one sweep took 265 ns on a 3-row contact problem and 939 ns
    on Rover1040 (15 rows), without it 128 and 215 ns; numba's code for the early exit is that much slower,
    for any form of it tried (a guard on the row count, the update inside an ``if``)."""
    change = value - multipliers[row]
    multipliers[row] = value
    column = transposed[row]
    count = gap.shape[0] if change != 0.0 else 0  # an unchanged row leaves the gap as it is
    for i in range(count):
        gap[i] += column[i] * change
    return abs(diagonal[row] * change)


@numba.njit(cache=True)
def gauss_seidel_sweep(transposed, diagonal, kinds, rows, params, members, multipliers, gap, relaxation):
    """One projected block Gauss–Seidel sweep (SOFA's); returns the increment Σ|W_jj Δλ_j| [m]."""
    increment = 0.0
    for b in range(kinds.shape[0]):
        kind = kinds[b]
        row = rows[b, 0]
        if kind == CONTACT:
            tangent1 = rows[b, 1]
            tangent2 = rows[b, 2]
            friction = params[b, 0]
            normal_force = multipliers[row]
            if diagonal[row] > 0.0:
                normal_force -= relaxation * gap[row] / diagonal[row]
            elif gap[row] > 0.0:  # no compliance, open: the update's limit as W_ii → 0+ (below)
                normal_force = 0.0
            if normal_force <= 0.0:
                increment += _apply(transposed, diagonal, multipliers, gap, row, 0.0)
                increment += _apply(transposed, diagonal, multipliers, gap, tangent1, 0.0)
                increment += _apply(transposed, diagonal, multipliers, gap, tangent2, 0.0)
                continue
            increment += _apply(transposed, diagonal, multipliers, gap, row, normal_force)
            force1 = multipliers[tangent1]
            force2 = multipliers[tangent2]
            tangent_diagonal = diagonal[tangent1] + diagonal[tangent2]
            if tangent_diagonal > 0.0:
                force1 -= 2.0 * relaxation * gap[tangent1] / tangent_diagonal
                force2 -= 2.0 * relaxation * gap[tangent2] / tangent_diagonal
            norm = np.sqrt(force1 * force1 + force2 * force2)
            limit = friction * normal_force
            if norm > limit:
                scale = limit / norm
                force1 *= scale
                force2 *= scale
            increment += _apply(transposed, diagonal, multipliers, gap, tangent1, force1)
            increment += _apply(transposed, diagonal, multipliers, gap, tangent2, force2)
            continue
        force = multipliers[row]
        if diagonal[row] > 0.0:
            force -= relaxation * gap[row] / diagonal[row]
        elif gap[row] != 0.0:
            # A row of no compliance (W_ii zero: its force moves no gap) has the update's limit as W_ii → 0+:
            # the bound its gap pushes it to (a box row held at its upper bound with δ < 0, a friction row
            # slipping at its bound, a unilateral row open at 0), the law's own solution there; where that
            # bound is infinite (a unilateral or bilateral row violated) no force satisfies the row and λ
            # stays as it is.
            force = np.inf if gap[row] < 0.0 else -np.inf
        if kind == UNILATERAL:
            force = max(force, 0.0)
        elif kind == GROUP_FRICTION:
            bound = group_bound(multipliers, members, rows[b, 1], rows[b, 2], params[b, 0], params[b, 1])
            force = min(max(force, -bound), bound)
        elif kind == BOX:
            force = min(max(force, params[b, 0]), params[b, 1])
        if not np.isfinite(force):
            force = multipliers[row]
        increment += _apply(transposed, diagonal, multipliers, gap, row, force)
    return increment


@numba.njit(cache=True)
def _cone_jacobian(zn, z1, z2, mu, out):
    """Jacobian (3, 3) of the cone projection at z into ``out``."""
    zt = np.sqrt(z1 * z1 + z2 * z2)
    out[:, :] = 0.0
    if zt <= mu * zn:
        out[0, 0] = 1.0
        out[1, 1] = 1.0
        out[2, 2] = 1.0
        return
    if mu * zt <= -zn:
        return
    t = max(zt, 1e-300)
    w1 = z1 / t
    w2 = z2 / t
    c = 1.0 / (1.0 + mu * mu)
    ray0, ray1, ray2 = 1.0, mu * w1, mu * w2
    height = (zn + mu * t) * c
    out[0, 0] = ray0 * c
    out[1, 0] = ray1 * c
    out[2, 0] = ray2 * c
    for i, ri in enumerate((ray0, ray1, ray2)):
        out[i, 1] = mu * c * ri * w1
        out[i, 2] = mu * c * ri * w2
    k = height * mu / t
    out[1, 1] += k * (1.0 - w1 * w1)
    out[1, 2] += k * (-w1 * w2)
    out[2, 1] += k * (-w2 * w1)
    out[2, 2] += k * (1.0 - w2 * w2)


@numba.njit(cache=True)
def jacobian_blocks(kinds, rows, params, members, multipliers, gap, weight, local, gap_factor, bound_values):
    """Factors of the generalised Jacobian J = N + M W − G of the weighted natural map (see
    refsim.solvers.newton).

    For block b with rows r (1 or 3): ``local[b]`` = N_b = I − D_Π (on λ_r), ``gap_factor[b]`` = M_b =
    D_Π diag(ρ_r) T_b (on δ_r = W_r λ + δ_free,r, T_b the De Saxcé derivative), both (3, 3) with only the
    leading (s, s) part used; ``bound_values[k]`` = ∂Π/∂b ∂b/∂λ_members[k] of the group friction row owning
    member k (G's entries: row rows[b, 0], column members[k]).
    """
    for b in range(kinds.shape[0]):
        kind = kinds[b]
        row = rows[b, 0]
        local[b, :, :] = 0.0
        gap_factor[b, :, :] = 0.0
        if kind == CONTACT:
            t1 = rows[b, 1]
            t2 = rows[b, 2]
            mu = params[b, 0]
            rho = weight[row]
            slip = np.sqrt(gap[t1] * gap[t1] + gap[t2] * gap[t2])
            zn = multipliers[row] - rho * (gap[row] + mu * slip)
            projection = np.empty((3, 3))
            _cone_jacobian(
                zn, multipliers[t1] - rho * gap[t1], multipliers[t2] - rho * gap[t2], mu, projection
            )
            s1 = gap[t1] / slip if slip > 0.0 else 0.0
            s2 = gap[t2] / slip if slip > 0.0 else 0.0
            for i in range(3):
                local[b, i, i] = 1.0
                for j in range(3):
                    local[b, i, j] -= projection[i, j]
                # M = D_Π ρ T, T = I + μ e_n (0, s1, s2)
                gap_factor[b, i, 0] = rho * projection[i, 0]
                gap_factor[b, i, 1] = rho * (projection[i, 1] + projection[i, 0] * mu * s1)
                gap_factor[b, i, 2] = rho * (projection[i, 2] + projection[i, 0] * mu * s2)
            continue
        rho = weight[row]
        if kind == BILATERAL:
            gap_factor[b, 0, 0] = rho
            continue
        z = multipliers[row] - rho * gap[row]
        if kind == UNILATERAL:
            active = z > 0.0
        elif kind == BOX:
            active = params[b, 0] < z < params[b, 1]
        else:
            start = rows[b, 1]
            end = rows[b, 2]
            bound = group_bound(multipliers, members, start, end, params[b, 0], params[b, 1])
            active = -bound < z < bound
            total = 0.0
            for k in range(start, end):
                total += multipliers[members[k]] ** 2
            norm = np.sqrt(total)
            for k in range(start, end):
                if active or norm <= 0.0:
                    bound_values[k] = 0.0
                else:
                    bound_values[k] = (
                        (1.0 if z > 0.0 else -1.0) * params[b, 0] * multipliers[members[k]] / norm
                    )
        if active:
            gap_factor[b, 0, 0] = rho
        else:
            local[b, 0, 0] = 1.0
