"""The constraint problem of one time step: δ = W λ + δ_free with a law per row.

Every row of the problem belongs to exactly one law of the table :data:`refsim.solvers.laws.LAWS` (bilateral,
unilateral, contact, group friction, box); the fields of :class:`ConstraintProblem` beyond the compliance and
the free gap are the fields of those laws, taken from the table.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from refsim.solvers.array_checks import all_finite, relative_asymmetry
from refsim.solvers.laws import LAW_FIELDS, LAW_NAMES, LAWS, friction_groups

__all__ = ["ConstraintProblem", "LAW_NAMES"]


#: The fields holding row indices (the rows of each law, the groups' members and offsets), in keyword order.
_INDEX_FIELDS = tuple(spec for spec in LAW_FIELDS if spec.role in ("rows", "members", "offsets"))

#: The last (row count and index fields' bytes, their validated read-only int64 copies) of a problem whose
#: rows passed every check of its rows: a time step's rows keep their index sets over many steps, and a
#: problem with the same ones takes these copies (read-only, so shared) instead of checking them again.
_LAST_ROWS: tuple = (None, None)


def _remember_rows(key: tuple, fields: dict) -> None:
    global _LAST_ROWS
    _LAST_ROWS = (key, fields)


def _law_fields(cls):
    """Add one keyword field per law field of the table (defaults: empty arrays), then ``name``."""
    annotations = {"compliance": np.ndarray, "free_gap": np.ndarray}
    for spec in LAW_FIELDS:
        annotations[spec.name] = np.ndarray
        setattr(cls, spec.name, field(default_factory=spec.empty))
    annotations["name"] = str
    cls.name = ""
    cls.__annotations__ = annotations
    lines = [
        f"    {spec.name} : {spec.meaning} [{spec.unit}], shape {spec.entry_shape}." for spec in LAW_FIELDS
    ]
    cls.__doc__ = cls.__doc__.replace("    LAW FIELDS\n", "\n".join(lines) + "\n")
    return cls


@dataclass(frozen=True, kw_only=True)
@_law_fields
class ConstraintProblem:
    """A constraint problem δ = W λ + δ_free with one law per row.

    Arrays are converted to read-only float64 / int64 copies on construction. Validation raises a
    ``ValueError`` naming the field, the offending value and what is allowed. The compliance need not be
    symmetric.

    To bound a friction row s by any group of rows G (e.g. the normal rows of a cut surface): give
    ``group_friction=[s, ...]``, ``group_members`` (all groups concatenated), ``group_offsets`` (length m + 1,
    group j = ``group_members[group_offsets[j]:group_offsets[j + 1]]``), ``group_friction_coefficient`` μ (m,)
    and optionally ``group_preload`` p [N] (m,); the bound is μ_j (‖λ_Gj‖ + p_j). The older pair form
    (``shaft_friction``, ``shaft_pairs``, ``shaft_friction_coefficient``, ``shaft_normal_preload``) is the
    same law with groups of two bilateral rows.

    Attributes
    ----------
    compliance : Compliance (Delassus operator) W [m/N], shape (row_count, row_count).
    free_gap : Free-motion gap δ_free [m], shape (row_count,).
    LAW FIELDS
    name : Optional name used in messages and study tables.
    """

    def __post_init__(self) -> None:
        compliance = self._float_array("compliance", self.compliance, ndim=2)
        row_count = compliance.shape[0]
        if compliance.shape != (row_count, row_count):
            self._fail(f"compliance must be square, got shape {compliance.shape}")
        free_gap = self._float_array("free_gap", self.free_gap, ndim=1)
        if free_gap.shape != (row_count,):
            self._fail(f"free_gap has shape {free_gap.shape}, expected ({row_count},) to match compliance")
        self._set("compliance", compliance)
        self._set("free_gap", free_gap)
        object.__setattr__(
            self, "_row_count", row_count
        )  # read by every solve (the property is on hot paths)
        key = self._rows_key(row_count)
        last = _LAST_ROWS  # (key, validated index fields) of the last problem whose rows were checked
        checked = key is not None and last[0] == key
        if checked:
            # The same index fields as the last problem validated: its checked read-only copies, its checks
            for name, value in last[1].items():
                object.__setattr__(self, name, value)
        else:
            self._validate_index_fields(row_count)
        for spec in LAW_FIELDS:
            if spec.role in ("coefficient", "preload", "bound"):
                count = len(getattr(self, spec.per))
                self._set(spec.name, self._parameters(spec, count))
        if not checked:
            self._validate_coverage()
            for law in LAWS:
                if law.validate_rows is not None:
                    law.validate_rows(self, self._fail)
            if key is not None:
                _remember_rows(key, {spec.name: getattr(self, spec.name) for spec in _INDEX_FIELDS})
        for law in LAWS:
            if law.validate is not None:
                law.validate(self, self._fail)

    def _rows_key(self, row_count: int) -> tuple | None:
        """The row count and the index fields' dtypes, shapes and bytes (None when one is not an integer
        array)."""
        parts = [row_count]
        for spec in _INDEX_FIELDS:
            value = getattr(self, spec.name)
            if not isinstance(value, np.ndarray) or value.dtype.kind not in "iu":
                return None
            parts.append((value.dtype.str, value.shape, value.tobytes()))
        return tuple(parts)

    def _validate_index_fields(self, row_count: int) -> None:
        """Row indices within [0, row_count) of the laws' shapes, offsets one-dimensional; int64 copies."""
        for spec in _INDEX_FIELDS:
            if spec.role in ("rows", "members"):
                self._set(
                    spec.name,
                    self._rows(
                        spec.name, getattr(self, spec.name), (-1,) + tuple(spec.entry_shape[1:]), row_count
                    ),
                )
            else:
                self._set(spec.name, self._offsets(spec.name, getattr(self, spec.name)))

    # ------------------------------------------------------------------ helpers of validation
    def _fail(self, message: str) -> None:
        label = f"ConstraintProblem {self.name!r}" if self.name else "ConstraintProblem"
        raise ValueError(f"{label}: {message}")

    def _set(self, name: str, value: np.ndarray) -> None:
        value.setflags(write=False)
        object.__setattr__(self, name, value)

    def _float_array(self, name: str, value, *, ndim: int, allow_inf: bool = False) -> np.ndarray:
        try:
            array = np.array(value, dtype=np.float64, copy=True)
        except (TypeError, ValueError) as error:
            self._fail(f"{name} is not a numeric array ({error})")
        if array.ndim != ndim:
            self._fail(f"{name} must have {ndim} dimension(s), got shape {array.shape}")
        bad = np.isnan(array) if allow_inf else ~np.isfinite(array)
        if bad.any():
            where = tuple(int(i) for i in np.argwhere(bad)[0])
            self._fail(f"{name} has a non-finite value {array[where]} at index {where}")
        return array

    def _integers(self, name: str, value) -> np.ndarray | None:
        array = np.asarray(value)
        if array.size == 0:
            return None
        if not (
            np.issubdtype(array.dtype, np.integer)
            or (np.issubdtype(array.dtype, np.floating) and np.all(array == np.round(array)))
        ):
            self._fail(f"{name} must hold integer row indices, got dtype {array.dtype}")
        return np.array(array, dtype=np.int64, copy=True)

    def _rows(self, name: str, value, shape: tuple[int, ...], row_count: int) -> np.ndarray:
        array = self._integers(name, value)
        if array is None:
            return np.zeros((0,) + shape[1:], dtype=np.int64)
        if array.ndim != len(shape) or (len(shape) == 2 and array.shape[1] != shape[1]):
            expected = "(count,)" if len(shape) == 1 else f"(count, {shape[1]})"
            self._fail(f"{name} must have shape {expected}, got {array.shape}")
        outside = (array < 0) | (array >= row_count)
        if outside.any():
            self._fail(f"{name} holds row {int(array[outside][0])}, outside [0, {row_count})")
        return array

    def _offsets(self, name: str, value) -> np.ndarray:
        array = self._integers(name, value)
        if array is None:
            return np.zeros(0, dtype=np.int64)
        if array.ndim != 1:
            self._fail(f"{name} must have shape (count + 1,), got {array.shape}")
        return array

    def _parameters(self, spec, count: int) -> np.ndarray:
        value = getattr(self, spec.name)
        if (spec.role == "preload" or count == 0) and np.size(value) == 0:
            return np.zeros(count)  # (what the checks below return for an empty value of no entries)
        if isinstance(value, np.ndarray) and value.dtype == np.float64 and value.shape == (count,):
            # The usual case (the rows' float64 arrays), checked by two reductions: a bound may be ±inf but
            # not NaN, any other value finite and >= 0 (a NaN makes min and max NaN, failing each test).
            # Anything else is sent through the checks below, which name it.
            low, high = value.min(), value.max()
            if (low == low) if spec.role == "bound" else (low >= 0.0 and high < np.inf):
                return value.copy()
        if isinstance(value, np.ndarray) and value.dtype == np.float64 and value.ndim:
            given = value  # what the object-array round trip below would give
        else:
            given = np.atleast_1d(np.asarray(value, dtype=object)) if np.size(value) else np.zeros(0)
        array = self._float_array(spec.name, given, ndim=1, allow_inf=spec.role == "bound")
        if array.shape != (count,):
            self._fail(f"{spec.name} has shape {array.shape}, expected ({count},), one per {spec.per} entry")
        if spec.role != "bound" and (array < 0).any():
            what = "coefficient" if spec.role == "coefficient" else "value"
            unit = f" {spec.unit}" if spec.unit != "1" else ""
            self._fail(f"{spec.name} has a negative {what} {array[array < 0][0]}{unit}, valid range [0, inf)")
        return array

    def _validate_coverage(self) -> None:
        row_count = self.row_count
        owners = np.full(row_count, -1, dtype=np.int64)
        for law in LAWS:
            rows = law.rows_of(self)
            taken = owners[rows] >= 0
            duplicate = np.bincount(rows, minlength=row_count)[rows] > 1
            clash = taken | duplicate
            if clash.any():
                row = int(rows[clash][0])
                other = LAW_NAMES[owners[row]] if owners[row] >= 0 else law.name
                self._fail(
                    f"row {row} is listed as {other} and again as {law.name}; "
                    "every row must belong to exactly one kind"
                )
            owners[rows] = law.code
        if (owners < 0).any():
            missing = np.flatnonzero(owners < 0)
            self._fail(
                f"{missing.size} row(s) belong to no kind, first {missing[:5].tolist()}; every row "
                f"must be {', '.join(LAW_NAMES[:-1])} or {LAW_NAMES[-1]}"
            )

    # ------------------------------------------------------------------ public helpers
    @property
    def row_count(self) -> int:
        """Number of rows (constraints) of the problem."""
        return self._row_count

    def row_kinds(self) -> np.ndarray:
        """Law code of every row (index into :data:`LAW_NAMES`), shape (row_count,)."""
        kinds = np.full(self.row_count, -1, dtype=np.int64)
        for law in LAWS:
            kinds[law.rows_of(self)] = law.code
        return kinds

    def friction_groups(self):
        """Group friction in one form: (rows (m,), offsets (m + 1,), members, μ (m,), preload [N] (m,)), the
        pair-form rows first."""
        return friction_groups(self)

    def friction_bounds(self, multipliers: np.ndarray) -> np.ndarray:
        """Bound μ_j (‖λ_Gj‖ + p_j) [N] of every group friction row, in the order of :meth:`friction_groups`,
        shape (m,), for multipliers λ [N] of shape (row_count,) (not checked)."""
        rows, offsets, members, coefficient, preload = friction_groups(self)
        if rows.size == 0:
            return np.zeros(0)
        squares = np.asarray(multipliers)[members] ** 2
        sizes = np.diff(offsets)
        sums = np.zeros(rows.size)
        nonempty = sizes > 0
        if squares.size:
            sums[nonempty] = np.add.reduceat(squares, offsets[:-1][nonempty])
        return coefficient * (np.sqrt(sums) + preload)

    def shaft_bounds(self, multipliers: np.ndarray) -> np.ndarray:
        """Bound μ_j (‖(λ_b1, λ_b2)‖ + preload_j) [N] of every pair-form (shaft) row, shape (m,)."""
        pair_norm = np.linalg.norm(np.asarray(multipliers)[self.shaft_pairs], axis=1)
        return self.shaft_friction_coefficient * (pair_norm + self.shaft_normal_preload)

    def gap(self, multipliers: np.ndarray) -> np.ndarray:
        """Gap δ = W λ + δ_free [m], shape (row_count,), for multipliers λ [N] of shape (row_count,)."""
        multipliers = self.check_multipliers(multipliers)
        return self.compliance @ multipliers + self.free_gap

    def check_multipliers(self, multipliers: np.ndarray) -> np.ndarray:
        """Return ``multipliers`` as a float64 array of shape (row_count,), or raise a ValueError."""
        array = np.asarray(multipliers, dtype=np.float64)
        if array.shape != (self.row_count,):
            self._fail(f"multipliers have shape {array.shape}, expected ({self.row_count},)")
        if not all_finite(array):
            self._fail("multipliers hold a non-finite value")
        return array

    def asymmetry(self) -> float:
        """Relative asymmetry ‖W − Wᵀ‖_F / ‖W‖_F (0 for a zero matrix); computed once (the problem is
        immutable), possibly by :func:`refsim.solvers.residual.prepare_caches`."""
        cached = self.__dict__.get("_asymmetry")
        if cached is None:
            cached = float(relative_asymmetry(self.compliance))
            object.__setattr__(self, "_asymmetry", cached)
        return cached
