"""Results files (layer 6): one self-describing HDF5 file per run, written step by step.

The layout (paths, units, meanings) lives in :mod:`refsim.io.schema` and is documented in ``docs/results.md``.
h5py is imported only when a file is opened.
"""

from refsim.io.provenance import git_commit
from refsim.io.reader import (
    CutHistory,
    RecordedEvent,
    Results,
    ResultsError,
    StepConstraints,
    read_problems,
    read_results,
)
from refsim.io.schema import FORMAT_NAME, SCHEMA_VERSION
from refsim.io.writer import ResultWriter

__all__ = [
    "FORMAT_NAME",
    "SCHEMA_VERSION",
    "CutHistory",
    "RecordedEvent",
    "ResultWriter",
    "Results",
    "ResultsError",
    "StepConstraints",
    "git_commit",
    "read_problems",
    "read_results",
]
