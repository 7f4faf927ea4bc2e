"""The record every verification case returns, and the table `refsim verify` prints."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["CaseResult"]


@dataclass(frozen=True, kw_only=True)
class CaseResult:
    """Outcome of one verification case.

    Attributes
    ----------
    name : Short case name, e.g. "needle cantilever, small load".
    reference : The reference, stated: an equation or a source, e.g. "δ = P L³/(3 E I) + P L/(κ G A)".
    expected : Reference value (a scalar summary, in ``unit``).
    computed : Computed value (same unit).
    error : The error measure the tolerance applies to (relative unless ``unit`` says otherwise).
    tolerance : Largest accepted error, derived from the discretisation or round-off (see ``reference``).
    unit : Unit of ``expected`` and ``computed``.
    """

    name: str
    reference: str
    expected: float
    computed: float
    error: float
    tolerance: float
    unit: str = ""

    @property
    def passed(self) -> bool:
        """True when the error is finite and within the tolerance."""
        return bool(self.error == self.error and self.error <= self.tolerance)
