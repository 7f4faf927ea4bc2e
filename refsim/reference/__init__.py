"""A published reference set (layer 6): canonical needle–tissue cases with converged answers and
uncertainties, their versioned data package, and the comparison of another simulator's results against them.

``refsim reference build`` and ``refsim compare`` (refsim.cli) are the command line; docs/reference.md the
page. The cases are plain TOML files in ``refsim/reference/cases/`` (:mod:`refsim.reference.cases`).
"""

from refsim.reference.build import build_reference, check_manifest, read_case_reference, reference_value
from refsim.reference.cases import (
    Case,
    Quantity,
    case_names,
    case_values,
    load_case,
    results_values,
    sample_curve,
)
from refsim.reference.compare import Comparison, compare, format_comparison, read_their_csv, write_their_csv

__all__ = [
    "Case",
    "Comparison",
    "Quantity",
    "build_reference",
    "case_names",
    "case_values",
    "check_manifest",
    "compare",
    "format_comparison",
    "load_case",
    "read_case_reference",
    "read_their_csv",
    "reference_value",
    "results_values",
    "sample_curve",
    "write_their_csv",
]
