"""The constraint problem of one time step: δ = W λ + δ_free with a law per row.

Every row of the problem belongs to exactly one kind:

- bilateral: δ = 0, λ free;
- unilateral (Signorini): 0 ≤ δ ⊥ λ ≥ 0;
- contact (3 rows: normal, tangent 1, tangent 2): Coulomb cone ‖λ_t‖ ≤ μ λ_n with the De Saxcé
  complementarity (friction opposing the slip, δ_n = 0 while in contact);
- shaft friction: |λ_s| ≤ μ (‖(λ_b1, λ_b2)‖ + p) where (b1, b2) is a pair of bilateral rows and p ≥ 0 a given
  normal preload, stick inside the bound, slip at the bound opposing δ_s (the friction along the needle shaft;
  p is the tissue's radial grip on the needle, which the two centreline rows do not see);
- box: box_lower ≤ λ ≤ box_upper with δ = 0 strictly inside, δ ≥ 0 at the lower and δ ≤ 0 at the upper bound
  (a one-dimensional friction law with a given bound, Siconos' "relay").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["ConstraintProblem", "KIND_NAMES"]

#: Names of the row kinds, in the order of the integer codes of :meth:`ConstraintProblem.row_kinds`.
KIND_NAMES = ("bilateral", "unilateral", "contact", "shaft_friction", "box")


def _empty_rows() -> np.ndarray:
    return np.zeros(0, dtype=np.int64)


def _empty_values() -> np.ndarray:
    return np.zeros(0, dtype=np.float64)


def _empty_contacts() -> np.ndarray:
    return np.zeros((0, 3), dtype=np.int64)


def _empty_pairs() -> np.ndarray:
    return np.zeros((0, 2), dtype=np.int64)


@dataclass(frozen=True, kw_only=True)
class ConstraintProblem:
    """A constraint problem δ = W λ + δ_free with one law per row.

    Arrays are converted to read-only float64 / int64 copies on construction. Validation raises a
    ``ValueError`` naming the field, the offending value and what is allowed. The compliance need not be
    symmetric here (the Gauss–Seidel solver accepts any W); :func:`refsim.solvers.solve_exact` rejects a
    non-symmetric one.

    Attributes
    ----------
    compliance : Compliance (Delassus operator) W [m/N], shape (row_count, row_count).
    free_gap : Free-motion gap δ_free [m], shape (row_count,).
    bilateral : Bilateral rows (δ = 0, λ free), shape (b,).
    unilateral : Unilateral (Signorini) rows, shape (u,).
    contacts : Contact rows (normal, tangent 1, tangent 2), shape (k, 3).
    contact_friction : Coulomb friction coefficient of each contact [-], shape (k,), ≥ 0.
    shaft_friction : Shaft friction rows, shape (m,).
    shaft_pairs : The two bilateral rows whose force norm bounds each shaft friction row, shape (m, 2).
    shaft_friction_coefficient : Friction coefficient of each shaft row [-], shape (m,), ≥ 0.
    shaft_normal_preload : Normal force added to the pair force norm in each shaft row's Coulomb bound [N],
        shape (m,), finite, ≥ 0; empty (the default) means zeros. The bound of row j is
        μ_j (‖(λ_b1, λ_b2)‖ + preload_j).
    box_rows : Rows with fixed bounds, shape (r,).
    box_lower : Lower bound of each box row [N], shape (r,), may be -inf.
    box_upper : Upper bound of each box row [N], shape (r,), ≥ box_lower, may be +inf.
    name : Optional name used in messages and study tables.
    """

    compliance: np.ndarray
    free_gap: np.ndarray
    bilateral: np.ndarray = field(default_factory=_empty_rows)
    unilateral: np.ndarray = field(default_factory=_empty_rows)
    contacts: np.ndarray = field(default_factory=_empty_contacts)
    contact_friction: np.ndarray = field(default_factory=_empty_values)
    shaft_friction: np.ndarray = field(default_factory=_empty_rows)
    shaft_pairs: np.ndarray = field(default_factory=_empty_pairs)
    shaft_friction_coefficient: np.ndarray = field(default_factory=_empty_values)
    shaft_normal_preload: np.ndarray = field(default_factory=_empty_values)
    box_rows: np.ndarray = field(default_factory=_empty_rows)
    box_lower: np.ndarray = field(default_factory=_empty_values)
    box_upper: np.ndarray = field(default_factory=_empty_values)
    name: str = ""

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
        self._set("bilateral", self._rows("bilateral", self.bilateral, (-1,), row_count))
        self._set("unilateral", self._rows("unilateral", self.unilateral, (-1,), row_count))
        self._set("contacts", self._rows("contacts", self.contacts, (-1, 3), row_count))
        self._set("shaft_friction", self._rows("shaft_friction", self.shaft_friction, (-1,), row_count))
        self._set("shaft_pairs", self._rows("shaft_pairs", self.shaft_pairs, (-1, 2), row_count))
        self._set("box_rows", self._rows("box_rows", self.box_rows, (-1,), row_count))
        self._set("contact_friction",
                  self._coefficients("contact_friction", self.contact_friction, len(self.contacts)))
        self._set("shaft_friction_coefficient",
                  self._coefficients("shaft_friction_coefficient", self.shaft_friction_coefficient,
                                     len(self.shaft_friction)))
        self._set("shaft_normal_preload", self._preload(len(self.shaft_friction)))
        self._validate_box()
        self._validate_coverage()
        self._validate_shaft_pairs()

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

    def _rows(self, name: str, value, shape: tuple[int, ...], row_count: int) -> np.ndarray:
        array = np.asarray(value)
        if array.size == 0:
            return np.zeros((0,) + shape[1:], dtype=np.int64)
        if not (np.issubdtype(array.dtype, np.integer)
                or (np.issubdtype(array.dtype, np.floating) and np.all(array == np.round(array)))):
            self._fail(f"{name} must hold integer row indices, got dtype {array.dtype}")
        array = np.array(array, dtype=np.int64, copy=True)
        if array.ndim != len(shape) or (len(shape) == 2 and array.shape[1] != shape[1]):
            expected = "(count,)" if len(shape) == 1 else f"(count, {shape[1]})"
            self._fail(f"{name} must have shape {expected}, got {array.shape}")
        outside = (array < 0) | (array >= row_count)
        if outside.any():
            self._fail(f"{name} holds row {int(array[outside][0])}, outside [0, {row_count})")
        return array

    def _coefficients(self, name: str, value, count: int) -> np.ndarray:
        array = self._float_array(name, np.atleast_1d(np.asarray(value, dtype=float)) if np.size(value)
                                  else np.zeros(0), ndim=1)
        if array.shape != (count,):
            self._fail(f"{name} has shape {array.shape}, expected ({count},), one per row or contact")
        if (array < 0).any():
            self._fail(f"{name} has a negative coefficient {array[array < 0][0]}, valid range [0, inf)")
        return array

    def _preload(self, count: int) -> np.ndarray:
        name = "shaft_normal_preload"
        if np.size(self.shaft_normal_preload) == 0:
            return np.zeros(count)
        array = self._float_array(name, np.atleast_1d(np.asarray(self.shaft_normal_preload, dtype=object)),
                                  ndim=1)
        if array.shape != (count,):
            self._fail(f"{name} has shape {array.shape}, expected ({count},), one per shaft_friction row")
        if (array < 0).any():
            self._fail(f"{name} has a negative value {array[array < 0][0]} N, valid range [0, inf)")
        return array

    def _validate_box(self) -> None:
        count = len(self.box_rows)
        lower = self._float_array("box_lower", np.zeros(0) if np.size(self.box_lower) == 0 else
                                  np.atleast_1d(self.box_lower), ndim=1, allow_inf=True)
        upper = self._float_array("box_upper", np.zeros(0) if np.size(self.box_upper) == 0 else
                                  np.atleast_1d(self.box_upper), ndim=1, allow_inf=True)
        for label, array in (("box_lower", lower), ("box_upper", upper)):
            if array.shape != (count,):
                self._fail(f"{label} has shape {array.shape}, expected ({count},), one per box row")
        if (lower > upper).any():
            index = int(np.argmax(lower > upper))
            self._fail(f"box row {int(self.box_rows[index])} has box_lower {lower[index]} > box_upper "
                       f"{upper[index]}")
        self._set("box_lower", lower)
        self._set("box_upper", upper)

    def _validate_coverage(self) -> None:
        row_count = self.row_count
        owners = np.full(row_count, -1, dtype=np.int64)
        for code, rows in enumerate(self._kind_rows()):
            taken = owners[rows] >= 0
            duplicate = np.bincount(rows, minlength=row_count)[rows] > 1
            clash = taken | duplicate
            if clash.any():
                row = int(rows[clash][0])
                other = KIND_NAMES[owners[row]] if owners[row] >= 0 else KIND_NAMES[code]
                self._fail(f"row {row} is listed as {other} and again as {KIND_NAMES[code]}; "
                           "every row must belong to exactly one kind")
            owners[rows] = code
        if (owners < 0).any():
            missing = np.flatnonzero(owners < 0)
            self._fail(f"{missing.size} row(s) belong to no kind, first {missing[:5].tolist()}; every row "
                       "must be bilateral, unilateral, contact, shaft_friction or box")

    def _validate_shaft_pairs(self) -> None:
        if len(self.shaft_pairs) != len(self.shaft_friction):
            self._fail(f"shaft_pairs has {len(self.shaft_pairs)} pairs for {len(self.shaft_friction)} "
                       "shaft_friction rows; one pair per row is required")
        kinds = self.row_kinds()
        not_bilateral = kinds[self.shaft_pairs] != 0
        if not_bilateral.any():
            row = int(self.shaft_pairs[not_bilateral][0])
            self._fail(f"shaft_pairs references row {row}, which is {KIND_NAMES[kinds[row]]}; the pair of a "
                       "shaft friction row must be bilateral rows")

    def _kind_rows(self) -> tuple[np.ndarray, ...]:
        return (self.bilateral, self.unilateral, self.contacts.reshape(-1), self.shaft_friction,
                self.box_rows)

    # ------------------------------------------------------------------ public helpers
    @property
    def row_count(self) -> int:
        """Number of rows (constraints) of the problem."""
        return int(self.compliance.shape[0])

    def row_kinds(self) -> np.ndarray:
        """Kind code of every row (index into :data:`KIND_NAMES`), shape (row_count,)."""
        kinds = np.full(self.row_count, -1, dtype=np.int64)
        for code, rows in enumerate(self._kind_rows()):
            kinds[rows] = code
        return kinds

    def shaft_bounds(self, multipliers: np.ndarray) -> np.ndarray:
        """Coulomb bound μ_j (‖(λ_b1, λ_b2)‖ + preload_j) [N] of every shaft row, shape (m,), for multipliers λ
        [N] of shape (row_count,) (not checked: this is called in inner loops)."""
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
        if not np.isfinite(array).all():
            self._fail("multipliers hold a non-finite value")
        return array

    def asymmetry(self) -> float:
        """Relative asymmetry ‖W − Wᵀ‖_F / ‖W‖_F (0 for a zero matrix)."""
        scale = np.linalg.norm(self.compliance)
        if scale == 0.0:
            return 0.0
        return float(np.linalg.norm(self.compliance - self.compliance.T) / scale)
