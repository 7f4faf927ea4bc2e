"""Constraint rows: one row of H per body for each atomic constraint, with its gap and its kind.

A block of rows (:class:`RowBlock`) comes from one builder (penetration, insertion, cutting) and carries one
Jacobian H_b per body it touches, by body name (:data:`TISSUE`, :data:`NEEDLE`; a kinematic body such as a
rigid needle has no DoFs and no Jacobian); blocks are concatenated into the rows of a step
(:func:`concatenate`), which give the solver's :class:`~refsim.solvers.ConstraintProblem` once the compliance
W = Σ_b H_b A_b⁻¹ H_bᵀ is known.

Sign convention: a row along the unit direction n measures δ = nᵀ(x_needle − x_tissue) [m]; its multiplier λ
[N] pushes the needle along +n and the tissue along −n. Unilateral rows keep δ ≥ 0 (n points from the tissue
towards the needle); friction rows measure the relative tangential displacement over the step.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field
from dataclasses import fields as dataclass_fields
from types import MappingProxyType

import numpy as np
import scipy.sparse as sp

from refsim.solvers import ConstraintProblem

__all__ = [
    "TISSUE",
    "NEEDLE",
    "BILATERAL",
    "UNILATERAL",
    "FRICTION",
    "ROW_KIND_NAMES",
    "SOURCE_NAMES",
    "PENETRATION",
    "INSERTION",
    "CUT_SLIDE",
    "CUT_BORDER",
    "SHAFT_CONTACT",
    "ROLE_NAMES",
    "NORMAL",
    "TANGENT",
    "LATERAL_FIRST",
    "LATERAL_SECOND",
    "AXIAL_FRICTION",
    "TIP",
    "SLIDING",
    "FRONT",
    "CUT_FRICTION",
    "BORDER",
    "RowBlock",
    "concatenate",
    "empty_block",
    "gap_roundoff",
    "orthonormal_basis",
    "point_rows",
    "stack_jacobians",
    "zero_compliance",
]

#: The names of the bodies rows refer to (``RowBlock.jacobians`` keys, ``Body.name`` of the simulation's
#: bodies).
TISSUE, NEEDLE = "tissue", "needle"

BILATERAL, UNILATERAL, FRICTION = 0, 1, 2
ROW_KIND_NAMES = ("bilateral", "unilateral", "friction")
PENETRATION, INSERTION, CUT_SLIDE, CUT_BORDER, SHAFT_CONTACT = 0, 1, 2, 3, 4
SOURCE_NAMES = ("penetration", "insertion", "cut_slide", "cut_border", "shaft_contact")
#: What a row is (``RowBlock.role``): a contact's normal row and its tangent (friction) rows; an insertion
#: point's two lateral rows and its axial shaft friction row; the tip's cutting row; the cut's sliding rows,
#: crack-front rows, friction rows on the cut surface and border rows. Code reads rows by these roles and by
#: ``RowBlock.point``, never by their position in a block.
(
    NORMAL,
    TANGENT,
    LATERAL_FIRST,
    LATERAL_SECOND,
    AXIAL_FRICTION,
    TIP,
    SLIDING,
    FRONT,
    CUT_FRICTION,
    BORDER,
) = range(10)
ROLE_NAMES = (
    "normal",
    "tangent",
    "lateral_first",
    "lateral_second",
    "axial_friction",
    "tip",
    "sliding",
    "front",
    "cut_friction",
    "border",
)
#: Role of the rows of each source (indexed by source) when a builder gives none.
_DEFAULT_ROLE = np.array([NORMAL, LATERAL_FIRST, SLIDING, BORDER, NORMAL], dtype=np.int8)


@dataclass(frozen=True, kw_only=True)
class RowBlock:
    """Rows of one builder.

    Attributes
    ----------
    jacobians : H_b of each body the rows touch, by body name (a read-only mapping): ``jacobians[TISSUE]``
        of shape (row_count, 3·tissue_node_count), ``jacobians[NEEDLE]`` of shape
        (row_count, 6·needle_node_count) for a flexible needle. A body without DoFs (a rigid, kinematic
        needle) has no entry; a None value given at construction is dropped.
    free_gap : δ_free [m], shape (row_count,).
    kind : BILATERAL, UNILATERAL or FRICTION per row, shape (row_count,).
    source : PENETRATION, INSERTION, CUT_SLIDE, CUT_BORDER or SHAFT_CONTACT per row, shape (row_count,).
    points : Tissue-side point of each row [m], shape (row_count, 3).
    directions : Unit direction n of each row, shape (row_count, 3).
    contacts : Row indices (normal, tangent 1, tangent 2) of Coulomb contacts, shape (k, 3).
    contact_friction : Friction coefficient of each contact, shape (k,).
    shaft_rows : Row indices of shaft friction rows, shape (m,).
    shaft_pairs : The two bilateral rows whose force bounds each shaft row, shape (m, 2).
    shaft_friction_coefficient : shape (m,).
    shaft_normal_preload : Normal force added to the pair force norm in each shaft row's Coulomb bound [N],
        shape (m,) (empty: zeros).
    force_limit : Largest force each row can carry [N], shape (row_count,), > 0, inf for none (empty: all
        inf). A unilateral row with a finite limit L has 0 ≤ λ ≤ L and gives way (δ < 0) at L; a bilateral
        row |λ| ≤ L. This is how a row models a strength: the tissue's resistance to puncture, to cutting at
        the tip, to tearing at the front of a cut.
    compliance_diagonal : Compliance added to the diagonal of W for each row [m/N], shape (row_count,), ≥ 0
        (empty: zeros): the part of a row's flexibility the mesh does not resolve (the sub-grid compliance of
        the well-posed coupling, :mod:`refsim.constraints.coupling`, and of the cut's sliding rows).
    group_rows : Friction rows bounded by a group of other rows (the solvers' group-friction law), shape (g,).
    group_offsets, group_members : The group of friction row j is
        ``group_members[group_offsets[j]:group_offsets[j + 1]]``; shapes (g + 1,) and (Σ sizes,).
    group_coefficient : Friction coefficient of each group friction row, shape (g,); the bound is
        μ_j ‖λ_Gj‖ (friction on the cut surface bounded by its sliding row's force).
    role : What each row is (NORMAL, TANGENT, LATERAL_FIRST, LATERAL_SECOND, AXIAL_FRICTION, TIP, SLIDING,
        FRONT, CUT_FRICTION, BORDER), shape (row_count,) (empty: NORMAL for every row).
    point : The insertion point each row belongs to (its index in the path the block was built from), −1 for
        rows of no insertion point, shape (row_count,) (empty: all −1).
    anchor : For the axial friction rows of insertion points, the needle arc length [m] at which the point's
        sub-grid annulus is unstretched (its stick anchor, :mod:`refsim.constraints.friction`); NaN for every
        other row, shape (row_count,) (empty: all NaN).
    instrument : The instrument each row belongs to (its index in the scene's instruments), shape
        (row_count,) (empty: −1, no instrument named; the step sets it for every row it solves).
    """

    jacobians: Mapping[str, sp.csr_matrix]
    free_gap: np.ndarray
    kind: np.ndarray
    source: np.ndarray
    points: np.ndarray
    directions: np.ndarray
    contacts: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.int64))
    contact_friction: np.ndarray = field(default_factory=lambda: np.zeros(0))
    shaft_rows: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    shaft_pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    shaft_friction_coefficient: np.ndarray = field(default_factory=lambda: np.zeros(0))
    shaft_normal_preload: np.ndarray = field(default_factory=lambda: np.zeros(0))
    force_limit: np.ndarray = field(default_factory=lambda: np.zeros(0))
    compliance_diagonal: np.ndarray = field(default_factory=lambda: np.zeros(0))
    group_rows: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    group_offsets: np.ndarray = field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    group_members: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    group_coefficient: np.ndarray = field(default_factory=lambda: np.zeros(0))
    role: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int8))
    point: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    anchor: np.ndarray = field(default_factory=lambda: np.zeros(0))
    instrument: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __post_init__(self) -> None:
        rows = self.free_gap.shape[0]
        jacobians = {name: matrix for name, matrix in dict(self.jacobians).items() if matrix is not None}
        for name, matrix in jacobians.items():
            if matrix.shape[0] != rows:
                raise ValueError(f"the Jacobian of body {name!r} has {matrix.shape[0]} rows, expected {rows}")
        object.__setattr__(self, "jacobians", MappingProxyType(jacobians))
        for name in ("role", "point", "anchor", "instrument"):
            value = np.asarray(getattr(self, name))
            if value.size and value.shape != (rows,):
                raise ValueError(f"{name} must have shape ({rows},), got {value.shape}")
        limit = np.asarray(self.force_limit, dtype=float)
        if limit.size and (limit.shape != (rows,) or not limit.min() > 0.0):  # (NaN's min: NaN, not > 0)
            raise ValueError(f"force_limit must have shape ({rows},) with values in (0, inf], got {limit!r}")
        _check_compliance_diagonal(np.asarray(self.compliance_diagonal, dtype=float), rows)

    @property
    def row_count(self) -> int:
        """Number of rows."""
        return int(self.free_gap.shape[0])

    @staticmethod
    def concatenate(blocks: list[RowBlock]) -> RowBlock:
        """The blocks stacked in order, every per-row field kept (:func:`concatenate`)."""
        return concatenate(blocks)

    def of_instrument(self, index: int, body: str) -> RowBlock:
        """The block with every row marked as instrument ``index``'s and the needle's Jacobian keyed by that
        instrument's body name ``body`` (the builders key it :data:`NEEDLE`)."""
        jacobians = dict(self.jacobians)
        if body != NEEDLE and NEEDLE in jacobians:
            jacobians[body] = jacobians.pop(NEEDLE)
        # the other fields are this valid block's, the instrument field has the rows' shape: no checks again
        return _replaced(self, jacobians=jacobians, instrument=np.full(self.row_count, index, dtype=np.int64))

    def with_compliance_diagonal(self, compliance_diagonal: np.ndarray) -> RowBlock:
        """The block with that ``compliance_diagonal`` (checked as the constructor checks it; the other
        fields, this valid block's, are not checked again)."""
        _check_compliance_diagonal(np.asarray(compliance_diagonal, dtype=float), self.row_count)
        return _replaced(self, compliance_diagonal=compliance_diagonal)

    @property
    def instruments(self) -> np.ndarray:
        """The instrument of each row, shape (row_count,) (the field, or −1 everywhere when it was left
        empty)."""
        return _instruments(self)

    @property
    def roles(self) -> np.ndarray:
        """Role of each row, shape (row_count,) (the field, or NORMAL everywhere when it was left empty)."""
        return _roles(self)

    @property
    def points_of_rows(self) -> np.ndarray:
        """Insertion point of each row, −1 for none, shape (row_count,)."""
        return _points(self)

    @property
    def anchors(self) -> np.ndarray:
        """Stick anchor of each row [m], NaN but on insertion points' axial friction rows, (row_count,)."""
        return _anchors(self)

    def problem_compliance_diagonal(self) -> np.ndarray:
        """The compliance added to W's diagonal for each row [m/N], shape (row_count,) (zeros when none)."""
        return _compliance_diagonal(self)

    def rows_of(self, role: int, source: int | None = None) -> np.ndarray:
        """Indices of the rows with that role (and source, when given), shape (k,)."""
        selected = self.roles == role
        if source is not None:
            selected &= self.source == source
        return np.flatnonzero(selected)

    def problem(self, compliance: np.ndarray, *, name: str = "", roundoff: float = 0.0):
        """The solver's :class:`~refsim.solvers.ConstraintProblem` of these rows with compliance W [m/N],
        shape (row_count, row_count): the one place where row kinds become solver laws.

        ``roundoff``: the free gaps' round-off [m] (:func:`gap_roundoff` of the positions they were measured
        on). A row of zero compliance (W_ii at most 1e-14 of the largest diagonal, Gauss–Seidel's floor: it
        moves a rigid needle and held tissue nodes only) whose free gap lies within it gets a gap of zero:
        no force changes that gap, so its sign alone — round-off — would decide the row (a rigid needle at
        rest on held tissue pressed into it to f_p by −8e-17 m). Rows with compliance keep their gaps: there
        round-off moves λ by δ/W_ii, nothing."""
        sets = self.index_sets()
        free_gap = self.free_gap
        added = _compliance_diagonal(self)
        if added.any():
            square = (added.size, added.size)
            if (
                isinstance(compliance, np.ndarray)
                and compliance.dtype == np.float64
                and compliance.shape == square
            ):
                # compliance + np.diag(added)'s bits without the dense diagonal: every entry plus +0.0, the
                # diagonal's plus its added compliance
                diagonal = np.diag(compliance) + added
                compliance = compliance + 0.0
                np.fill_diagonal(compliance, diagonal)
            else:
                compliance = compliance + np.diag(added)
        if roundoff > 0.0 and free_gap.size:
            closed = zero_compliance(compliance) & (np.abs(free_gap) <= roundoff) & (free_gap != 0.0)
            if closed.any():
                free_gap = np.where(closed, 0.0, free_gap)
        limit = _force_limit(self)
        boxed = np.flatnonzero(np.isfinite(limit))
        bilateral, unilateral = sets["bilateral"], sets["unilateral"]
        box_lower = np.where(self.kind[boxed] == UNILATERAL, 0.0, -limit[boxed])
        box_upper = limit[boxed]
        if boxed.size:
            # the index sets are sorted and unique: dropping the boxed rows keeps what np.setdiff1d returns
            in_box = np.zeros(self.row_count, dtype=bool)
            in_box[boxed] = True
            bilateral = bilateral[~in_box[bilateral]]
            unilateral = unilateral[~in_box[unilateral]]
        return ConstraintProblem(
            compliance=compliance,
            free_gap=free_gap,
            bilateral=bilateral,
            unilateral=unilateral,
            box_rows=boxed,
            box_lower=box_lower,
            box_upper=box_upper,
            group_friction=self.group_rows,
            group_offsets=self.group_offsets,
            group_members=self.group_members,
            group_friction_coefficient=self.group_coefficient,
            contacts=sets["contacts"],
            contact_friction=self.contact_friction,
            shaft_friction=sets["shaft_rows"],
            shaft_pairs=self.shaft_pairs,
            shaft_friction_coefficient=self.shaft_friction_coefficient,
            shaft_normal_preload=self.shaft_normal_preload,
            name=name,
        )

    def index_sets(self) -> dict[str, np.ndarray]:
        """Row index sets by solver kind: bilateral and unilateral rows outside contacts, contacts, shaft
        rows."""
        in_contact = np.zeros(self.row_count, dtype=bool)
        in_contact[self.contacts.ravel()] = True
        in_shaft = np.zeros(self.row_count, dtype=bool)
        in_shaft[self.shaft_rows] = True
        rows = np.arange(self.row_count)
        return {
            "bilateral": rows[(self.kind == BILATERAL) & ~in_contact],
            "unilateral": rows[(self.kind == UNILATERAL) & ~in_contact],
            "contacts": self.contacts,
            "shaft_rows": self.shaft_rows,
        }


def zero_compliance(compliance: np.ndarray) -> np.ndarray:
    """The rows whose compliance W_ii [m/N] is zero, at most 1e-14 of the largest diagonal (Gauss-Seidel's
    floor), shape (row_count,) bool: their multipliers change no gap (a rigid needle on held tissue nodes)."""
    diagonal = np.diag(compliance)
    if diagonal.size == 0:
        return np.zeros(0, dtype=bool)
    return diagonal <= 1e-14 * max(float(np.abs(diagonal).max()), np.finfo(float).tiny)


#: The round-off of a free gap, in units of ε L (:func:`gap_roundoff`).
GAP_ROUNDOFF_ULPS = 64.0


def gap_roundoff(*coordinates: np.ndarray) -> float:
    """The round-off of a row's free gap δ = nᵀ(x_needle − x_tissue) [m] between bodies at ``coordinates``
    [m] (arrays of positions): 64 ε L, L the largest coordinate's magnitude. Each point carries an error of a
    few ε L (a needle point is its base plus a rotated arc length, a contact's tissue point an interpolation
    of three or four nodes), and so does the projection on n: 64 ε L bounds the sum with a margin. A gap
    within it is zero to the precision the positions have (a tilted rigid needle brought to rest on the
    cube's top face: −8.3e-17 m, against 64 ε L = 6e-15 m)."""
    scale = max((float(np.abs(array).max()) for array in coordinates if np.size(array)), default=0.0)
    return GAP_ROUNDOFF_ULPS * float(np.finfo(float).eps) * scale


def empty_block(dof_counts: Mapping[str, int | None]) -> RowBlock:
    """A block without rows, with an empty Jacobian for each body of ``dof_counts`` (body name -> DoF count;
    None or 0 for a kinematic body, which gets none)."""
    return RowBlock(
        jacobians={name: sp.csr_matrix((0, count)) for name, count in dof_counts.items() if count},
        free_gap=np.zeros(0),
        kind=np.zeros(0, dtype=np.int8),
        source=np.zeros(0, dtype=np.int8),
        points=np.zeros((0, 3)),
        directions=np.zeros((0, 3)),
    )


def trusted_block(**values) -> RowBlock:
    """``RowBlock(**values)`` without :meth:`RowBlock.__post_init__`'s checks, for a builder whose fields are
    valid by construction (every per-row field built with the block's row count, force limits and added
    compliance checked by the builder or left empty): the same object, the Jacobians stored as the
    constructor stores them (read-only, None values dropped), the omitted fields their defaults."""
    block = object.__new__(RowBlock)
    state = block.__dict__
    for name, factory in _FIELD_FACTORIES:
        if name not in values:
            state[name] = factory()
    state.update(values)
    state["jacobians"] = MappingProxyType(
        {name: matrix for name, matrix in dict(values["jacobians"]).items() if matrix is not None}
    )
    return block


#: (name, default factory) of RowBlock's fields that have a default, in field order (trusted_block).
_FIELD_FACTORIES = tuple(
    (spec.name, spec.default_factory)
    for spec in dataclass_fields(RowBlock)
    if spec.default_factory is not MISSING
)


def _check_compliance_diagonal(added: np.ndarray, rows: int) -> None:
    # (finite and >= 0: a NaN makes the min NaN, which fails the comparison)
    if added.size and (added.shape != (rows,) or not (added.min() >= 0.0 and added.max() < np.inf)):
        raise ValueError(f"compliance_diagonal must have shape ({rows},) with finite values >= 0 [m/N]")


def _replaced(block: RowBlock, **changes) -> RowBlock:
    """``dataclasses.replace(block, **changes)`` without :meth:`RowBlock.__post_init__`'s checks, for changes
    known valid (fields of valid blocks, or checked by the caller); a ``jacobians`` change is stored as the
    constructor stores it (read-only, None values dropped)."""
    new = object.__new__(RowBlock)
    new.__dict__.update(block.__dict__)
    new.__dict__.update(changes)
    if "jacobians" in changes:
        new.__dict__["jacobians"] = MappingProxyType(
            {name: matrix for name, matrix in dict(changes["jacobians"]).items() if matrix is not None}
        )
    return new


def concatenate(blocks: list[RowBlock]) -> RowBlock:
    """Stack blocks, offsetting their contact, shaft and group row indices; every per-row field is kept.

    Stacked from valid blocks, the result is valid by construction (every per-row field has the stacked row
    count, the index fields point at the stacked rows): it is not checked again."""
    blocks = [b for b in blocks if b is not None]
    if len(blocks) == 1:
        return blocks[0]
    fields = [b.__dict__ for b in blocks]
    counts = [f["free_gap"].shape[0] for f in fields]
    offsets = [0]
    for count in counts[:-1]:
        offsets.append(offsets[-1] + count)
    total = offsets[-1] + counts[-1]

    def joined(name: str) -> np.ndarray:
        return np.concatenate([f[name] for f in fields])

    def shifted(name: str, empty_shape: tuple[int, ...]) -> np.ndarray:
        """The blocks' row-index field ``name`` plus each block's row offset, int64 (the blocks without any
        left out: they add nothing)."""
        parts = [f[name] + o for f, o in zip(fields, offsets, strict=True) if f[name].size]
        if not parts:
            return np.zeros(empty_shape, dtype=np.int64)
        return np.concatenate(parts).astype(np.int64, copy=False)

    def per_row(name: str, fill, dtype) -> np.ndarray:
        """A per-row field, each block's own or ``fill`` for the rows of a block that left it empty (the
        blocks' ``_roles``, ``_points``, ... in one pass: the same values)."""
        if all(f[name].size == count for f, count in zip(fields, counts, strict=True)):
            return np.concatenate([f[name] for f in fields]).astype(dtype, copy=False)
        out = np.empty(total, dtype=dtype)
        for f, o, count in zip(fields, offsets, counts, strict=True):
            out[o : o + count] = f[name] if f[name].size else fill
        return out

    grouped = any(f["group_rows"].size or f["group_members"].size for f in fields)
    if grouped:
        member_offsets = [0]
        for f in fields[:-1]:
            member_offsets.append(member_offsets[-1] + f["group_members"].size)
        group_offsets = np.concatenate(
            [np.zeros(1, dtype=np.int64)]
            + [
                f["group_offsets"][1:] + m
                for f, m in zip(fields, member_offsets, strict=True)
                if f["group_offsets"].size > 1
            ]
        ).astype(np.int64, copy=False)
    else:
        group_offsets = np.zeros(1, dtype=np.int64)
    roles = [_roles(b) for b in blocks]
    stacked = dict(
        jacobians=MappingProxyType(stack_jacobians([f["jacobians"] for f in fields], counts)),
        free_gap=joined("free_gap"),
        kind=joined("kind"),
        source=joined("source"),
        points=joined("points"),
        directions=joined("directions"),
        contacts=shifted("contacts", (0, 3)),
        contact_friction=joined("contact_friction"),
        shaft_rows=shifted("shaft_rows", (0,)),
        shaft_pairs=shifted("shaft_pairs", (0, 2)),
        shaft_friction_coefficient=joined("shaft_friction_coefficient"),
        shaft_normal_preload=np.concatenate([_shaft_preload(b) for b in blocks]),
        force_limit=per_row("force_limit", np.inf, float),
        compliance_diagonal=per_row("compliance_diagonal", 0.0, float),
        group_rows=shifted("group_rows", (0,)),
        group_members=shifted("group_members", (0,)),
        group_offsets=group_offsets,
        group_coefficient=joined("group_coefficient"),
        role=np.concatenate(roles).astype(np.int8, copy=False),
        point=per_row("point", -1, np.int64),
        anchor=per_row("anchor", np.nan, float),
        instrument=per_row("instrument", -1, np.int64),
    )
    block = object.__new__(RowBlock)
    block.__dict__.update(stacked)
    return block


def _instruments(block: RowBlock) -> np.ndarray:
    """The rows' instruments, shape (row_count,): −1 everywhere when the block left the field empty."""
    if block.instrument.size == 0 and block.row_count:
        return np.full(block.row_count, -1, dtype=np.int64)
    return np.asarray(block.instrument, dtype=np.int64)


def stack_jacobians(
    parts: list[Mapping[str, sp.csr_matrix]], row_counts: list[int] | None = None
) -> dict[str, sp.csr_matrix]:
    """Each body's Jacobian of stacked row sets, by body name.

    Parameters
    ----------
    parts : The Jacobians of each row set (body name -> H_b, None or absent for a body the set does not
        touch), in stacking order.
    row_counts : Rows of each set; by default the rows of any Jacobian it has.

    Returns
    -------
    Body name -> vertically stacked H_b (CSR) for every body of any part, in order of first appearance; a part
    that lacks a body contributes zero rows of the width that body has elsewhere.
    """
    parts = [{name: h for name, h in part.items() if h is not None} for part in parts]
    if row_counts is None:
        row_counts = []
        for part in parts:
            if not part:
                raise ValueError("a row set without any Jacobian needs its row count")
            row_counts.append(next(iter(part.values())).shape[0])
    widths: dict[str, int] = {}
    for part in parts:
        for name, matrix in part.items():
            if widths.setdefault(name, matrix.shape[1]) != matrix.shape[1]:
                raise ValueError(
                    f"the Jacobians of body {name!r} have {widths[name]} and {matrix.shape[1]} columns"
                )
    return {
        name: _stack_csr([part.get(name) for part in parts], row_counts, width)
        for name, width in widths.items()
    }


def _stack_csr(matrices: list[sp.csr_matrix | None], row_counts: list[int], width: int) -> sp.csr_matrix:
    """CSR matrices stacked vertically (None: that many empty rows), their data and indices concatenated as
    ``sp.vstack(..., format="csr")`` does (no arithmetic: the same bits), without its per-call checks."""
    if any(m is not None and m.format != "csr" for m in matrices):
        return sp.vstack(
            [
                sp.csr_matrix((rows, width)) if m is None else m
                for m, rows in zip(matrices, row_counts, strict=True)
            ],
            format="csr",
        )
    present = [m for m in matrices if m is not None]
    total_rows = int(sum(row_counts))
    nnz = sum(m.nnz for m in present)
    index_dtype = np.int32 if max(nnz, total_rows, width) < 2**31 - 1 else np.int64
    pointers = [np.zeros(1, dtype=index_dtype)]
    offset = 0
    for matrix, rows in zip(matrices, row_counts, strict=True):
        if matrix is None:
            pointers.append(np.full(rows, offset, dtype=index_dtype))
            continue
        pointers.append((matrix.indptr[1:] + offset).astype(index_dtype))
        offset += matrix.nnz
    data = np.concatenate([m.data[: m.nnz] for m in present]) if present else np.zeros(0)
    indices = (
        np.concatenate([m.indices[: m.nnz] for m in present]).astype(index_dtype, copy=False)
        if present
        else np.zeros(0, dtype=index_dtype)
    )
    # (the parts' arrays stacked: a valid CSR matrix, canonical when every part is)
    canonical = all(_canonical(m) for m in present)
    return trusted_csr(data, indices, np.concatenate(pointers), (total_rows, width), canonical=canonical)


def _canonical(matrix: sp.csr_matrix) -> bool:
    """Whether a CSR matrix is known canonical (sorted, duplicate-free indices) without computing it: its
    flag as set (or computed before); False when never set."""
    return bool(getattr(matrix, "_has_canonical_format", False))


def _roles(block: RowBlock) -> np.ndarray:
    """The rows' roles, shape (row_count,): the source's default role when the block left the field empty."""
    if block.role.size == 0 and block.row_count:
        return _DEFAULT_ROLE[np.asarray(block.source, dtype=np.int64)]
    return np.asarray(block.role, dtype=np.int8)


def _points(block: RowBlock) -> np.ndarray:
    """The rows' insertion points, shape (row_count,): −1 when the block left the field empty."""
    if block.point.size == 0:
        return np.full(block.row_count, -1, dtype=np.int64)
    return np.asarray(block.point, dtype=np.int64)


def _anchors(block: RowBlock) -> np.ndarray:
    """The rows' stick anchors [m], shape (row_count,): NaN when the block left the field empty."""
    if block.anchor.size == 0:
        return np.full(block.row_count, np.nan)
    return np.asarray(block.anchor, dtype=float)


def _force_limit(block: RowBlock) -> np.ndarray:
    """The rows' force limits [N], shape (row_count,): inf when the block left the field empty."""
    if block.force_limit.size == 0:
        return np.full(block.row_count, np.inf)
    return np.asarray(block.force_limit, dtype=float)


def _compliance_diagonal(block: RowBlock) -> np.ndarray:
    """The rows' added compliance [m/N], shape (row_count,): zeros when the block left the field empty."""
    if block.compliance_diagonal.size == 0:
        return np.zeros(block.row_count)
    return np.asarray(block.compliance_diagonal, dtype=float)


def _shaft_preload(block: RowBlock) -> np.ndarray:
    """The block's shaft preloads [N], shape (m,): zeros when the block left the field empty."""
    if block.shaft_normal_preload.size == 0:
        return np.zeros(block.shaft_rows.shape[0])
    return np.asarray(block.shaft_normal_preload, dtype=float)


def orthonormal_basis(tangents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to each tangent and to each other, continuous in the tangent.

    Parameters
    ----------
    tangents : Unit vectors, shape (k, 3).

    Returns
    -------
    (first, second) : shape (k, 3) each; (first, second, tangent) is right-handed.
    """
    tangents = np.ascontiguousarray(tangents, dtype=float).reshape(-1, 3)
    if np.all(np.isfinite(tangents)):
        from refsim.constraints.kernels import basis_of  # numba: imported on first use

        return basis_of(tangents)
    return _orthonormal_basis_numpy(tangents)


def _orthonormal_basis_numpy(tangents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`orthonormal_basis` in NumPy (the compiled pass's reference; tangents with NaN)."""
    # The helper axis is the world axis least aligned with the tangent.
    helper = np.eye(3)[np.argmin(np.abs(tangents), axis=1)]
    first = np.cross(helper, tangents)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    second = np.cross(tangents, first)
    return first, second


def point_rows(
    node_indices: np.ndarray,
    weights: np.ndarray,
    directions: np.ndarray,
    dof_count: int,
    *,
    sign: float = -1.0,
) -> sp.csr_matrix:
    """Rows of H for points interpolated from mesh nodes, projected on directions.

    Row i is ``sign · Σ_k weights[i, k] · directions[i]ᵀ`` on the three DoFs of node ``node_indices[i, k]``.
    The entries are made and summed in compiled passes, in the order SciPy's COO-to-CSR conversion sums them
    (:mod:`refsim.constraints.kernels`): the matrix is that conversion's, bit for bit.

    Parameters
    ----------
    node_indices : Nodes of each point (tet or face), shape (row_count, p).
    weights : Barycentric weights, shape (row_count, p).
    directions : Row directions, shape (row_count, 3).
    dof_count : 3 · node_count.
    sign : −1 for the tissue side of the convention δ = nᵀ(x_needle − x_tissue).
    """
    node_indices = np.ascontiguousarray(node_indices, dtype=np.int64)
    row_count, per_point = node_indices.shape
    width = 3 * per_point
    if row_count == 0 or per_point == 0 or max(row_count * width, dof_count) >= 2**31:
        return _point_rows_coo(node_indices, weights, directions, dof_count, sign=sign)
    from refsim.constraints.kernels import planned_rows  # numba: imported on first use

    entry = _summation_plan(node_indices, dof_count)
    weight_at, direction_at, starts, indices, indptr = entry.plan
    weights = np.ascontiguousarray(weights, dtype=float)
    directions = np.ascontiguousarray(directions, dtype=float)
    # The same inputs, bit for bit, give the same data: kept with the plan (an insertion point's rows while
    # its ring and the needle's direction do not change)
    inputs = (weights.tobytes(), directions.tobytes(), float(sign))
    if entry.inputs != inputs:
        entry.data = planned_rows(weights, directions, float(sign), weight_at, direction_at, starts)
        entry.inputs = inputs
    return trusted_csr(entry.data.copy(), indices.copy(), indptr.copy(), (row_count, dof_count))


def trusted_csr(
    data: np.ndarray,
    indices: np.ndarray,
    indptr: np.ndarray,
    shape: tuple[int, int],
    *,
    canonical: bool = True,
):
    """A CSR matrix from arrays known to be a valid one (float64 data, int32 or int64 indices and pointers of
    one dtype), without SciPy's checks of its ``(data, indices, indptr)`` constructor (tens of µs per call, a
    few calls per step): the attributes that constructor sets, set directly
    (``tests/constraints/test_rows.py`` holds it to the checked constructor). ``canonical``: the indices are
    known sorted and duplicate-free (flagged so); False leaves SciPy to find out when asked."""
    matrix = sp.csr_matrix.__new__(sp.csr_matrix)
    matrix._shape = (int(shape[0]), int(shape[1]))
    matrix.maxprint = _MAXPRINT
    matrix.data, matrix.indices, matrix.indptr = data, indices, indptr
    if canonical:
        matrix.has_sorted_indices = True
        matrix.has_canonical_format = True
    return matrix


#: SciPy's default ``maxprint`` of a matrix (what its constructors set).
_MAXPRINT = sp.csr_matrix((0, 0)).maxprint


class _PlanEntry:
    """A summation plan (:func:`refsim.constraints.kernels.summation_plan`) with the nodes it was made for,
    and the data of the last call on it with the bytes of that call's inputs (weights, directions, sign)."""

    __slots__ = ("nodes", "plan", "inputs", "data")

    def __init__(self, nodes: np.ndarray, plan: tuple[np.ndarray, ...]) -> None:
        self.nodes, self.plan = nodes, plan
        self.inputs: tuple | None = None
        self.data: np.ndarray | None = None


#: The plans of :func:`_summation_plan`, by the nodes' shape, the DoF count and the nodes' first and last
#: columns (a list per key, at most _PLANS_KEPT plans in all).
_PLANS: dict[tuple, list[_PlanEntry]] = {}
_PLANS_KEPT = 32


def _summation_plan(node_indices: np.ndarray, dof_count: int) -> _PlanEntry:
    """The summation plan of :func:`point_rows` for rows on ``node_indices`` (r, p) int64
    (:func:`refsim.constraints.kernels.summation_plan`): a function of the nodes alone, kept with them and
    found again by comparing them (a step's insertion points have the last step's nodes while their rings do
    not change, the tip's ring while it stays in the same tets; comparing costs less than hashing them)."""
    key = (node_indices.shape, dof_count, node_indices[:, 0].tobytes(), node_indices[:, -1].tobytes())
    kept = _PLANS.get(key, ())
    for entry in kept:
        if np.array_equal(entry.nodes, node_indices):
            return entry
    from refsim.constraints.kernels import row_entries, summation_plan  # numba: imported on first use
    from refsim.kernel_cache import readonly

    row_count, per_point = node_indices.shape
    columns, _, pattern, firsts = row_entries(
        readonly(node_indices), np.zeros((row_count, per_point)), np.zeros((row_count, 3)), 1.0
    )
    order = _sort_order(columns[firsts], dof_count)
    entry = _PlanEntry(node_indices.copy(), summation_plan(columns, order, pattern))
    if sum(len(entries) for entries in _PLANS.values()) >= _PLANS_KEPT:
        _PLANS.clear()
    _PLANS.setdefault(key, []).append(entry)
    return entry


#: The permutations of :func:`_sort_order` by their patterns (at most _SORT_ORDERS_KEPT sets kept).
_SORT_ORDERS: dict[tuple, np.ndarray] = {}
_SORT_ORDERS_KEPT = 64


def _sort_order(patterns: np.ndarray, dof_count: int) -> np.ndarray:
    """The permutation SciPy's row sort applies to each distinct pattern (its columns, (u, w) int32), shape
    (u, w): sort a probe whose data are the entries' positions (the sort compares columns only; SciPy sorts
    every row, or none when all are sorted).

    The permutation is a function of the patterns alone (std::sort is deterministic), so it is kept by their
    bytes: the rows of a step's insertion points have the patterns of the last step while their rings and
    the tets of their material points do not change."""
    key = (patterns.shape, patterns.tobytes())
    order = _SORT_ORDERS.get(key)
    if order is not None:
        return order
    count, width = patterns.shape
    probe = sp.csr_matrix(
        (
            np.tile(np.arange(width, dtype=float), count),
            patterns.ravel(),
            np.arange(0, (count + 1) * width, width, dtype=np.int32),
        ),
        shape=(count, dof_count),
    )
    probe.sort_indices()
    # (left writable: a read-only array is another type for the compiled sum, compiled again)
    order = probe.data.astype(np.int64).reshape(count, width)
    if len(_SORT_ORDERS) >= _SORT_ORDERS_KEPT:
        _SORT_ORDERS.clear()
    _SORT_ORDERS[key] = order
    return order


def _point_rows_coo(
    node_indices: np.ndarray, weights: np.ndarray, directions: np.ndarray, dof_count: int, *, sign: float
) -> sp.csr_matrix:
    """:func:`point_rows` through SciPy's COO matrix (the reference of the compiled path's bits; used for
    empty blocks and index ranges beyond int32)."""
    node_indices = np.asarray(node_indices, dtype=np.int64)
    row_count, per_point = node_indices.shape
    values = sign * weights[:, :, None] * directions[:, None, :]  # (r, p, 3)
    columns = 3 * node_indices[:, :, None] + np.arange(3)  # (r, p, 3)
    rows = np.broadcast_to(np.arange(row_count)[:, None, None], columns.shape)
    matrix = sp.csr_matrix((values.ravel(), (rows.ravel(), columns.ravel())), shape=(row_count, dof_count))
    matrix.sum_duplicates()
    return matrix
