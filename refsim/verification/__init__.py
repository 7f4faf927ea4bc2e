"""Verification cases (layer 6): closed-form and reference problems a user can run (`refsim verify`).

Each case states its reference (an equation or a published value) and derives its tolerance; see the modules
`refsim.verification.needle`, `refsim.verification.tissue` and `refsim.verification.coupling`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

from refsim.verification.result import CaseResult

__all__ = ["CaseResult", "all_cases", "run_cases", "format_table", "needle_cantilever"]


def needle_cantilever(*args, **kwargs):
    """Needle cantilever under a tip load, solved statically to convergence.

    See :func:`refsim.verification.needle.needle_cantilever` (a needle along +x clamped at the origin; the
    result has ``tip_displacement``, shape (3,) [m]).
    """
    from refsim.verification.needle import needle_cantilever as solve

    return solve(*args, **kwargs)


def all_cases() -> list[Callable[[], CaseResult | list[CaseResult]]]:
    """Every registered case: needle, tissue, then the needle–tissue coupling."""
    from refsim.verification import coupling, needle, tissue

    return [*needle.CASES, *tissue.CASES, *coupling.CASES]


def run_cases(cases: Iterable[Callable[[], CaseResult | list[CaseResult]]] | None = None) -> list[CaseResult]:
    """Run cases and flatten their results."""
    results: list[CaseResult] = []
    for case in all_cases() if cases is None else cases:
        outcome = case()
        results.extend(outcome if isinstance(outcome, (list, tuple)) else [outcome])
    return results


def format_table(results: list[CaseResult]) -> str:
    """A plain-text table: case, reference, expected, computed, error, tolerance, pass."""
    header = ("case", "reference", "expected", "computed", "error", "tolerance", "pass")
    rows = [
        (
            r.name,
            r.reference,
            f"{r.expected:.6g} {r.unit}".strip(),
            f"{r.computed:.6g} {r.unit}".strip(),
            f"{r.error:.2e}",
            f"{r.tolerance:.2e}",
            "yes" if r.passed else "NO",
        )
        for r in results
    ]
    widths = [max(len(str(x)) for x in column) for column in zip(header, *rows, strict=False)]
    lines = [
        "  ".join(str(x).ljust(w) for x, w in zip(line, widths, strict=False)) for line in (header, *rows)
    ]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)
