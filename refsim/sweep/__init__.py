"""Parameter sweeps on Dask (layer 6): studies, their runs, quantities of interest and convergence.

``refsim study`` (refsim.cli) is the command line; :func:`run_study` the function. Dask is imported only when
a study runs, so ``import refsim.sweep`` stays light. Layout of a study file: ``docs/studies.md``.
"""

from refsim.sweep.convergence import (
    ConvergenceResult,
    convergence,
    fitted_order,
    grid_convergence_index,
    observed_order,
    richardson,
)
from refsim.sweep.quantities import QUANTITIES, force_history_error, quantities, quantity
from refsim.sweep.spec import RunSpec, StudySpec, Sweep, load_study, parse_sweep, study_from_options
from refsim.sweep.study import STUDY_FORMAT, read_study, run_study

__all__ = [
    "QUANTITIES",
    "STUDY_FORMAT",
    "ConvergenceResult",
    "RunSpec",
    "StudySpec",
    "Sweep",
    "convergence",
    "fitted_order",
    "force_history_error",
    "grid_convergence_index",
    "load_study",
    "observed_order",
    "parse_sweep",
    "quantities",
    "quantity",
    "read_study",
    "richardson",
    "run_study",
    "study_from_options",
]
