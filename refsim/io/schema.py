"""The results file's schema: the single source of every dataset path, its unit and its meaning.

The writer (:mod:`refsim.io.writer`), the reader (:mod:`refsim.io.reader`) and ``docs/results.md`` all take
their paths from here. A dataset is described by a :class:`DatasetSpec`: path, unit (the ``units`` attribute
written on it), dtype, the shape of one entry (per-step datasets grow along their first axis) and a one-line
meaning. Change the layout here, bump :data:`SCHEMA_VERSION`, and update ``docs/results.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from refsim.simulation.records import EVENT_UNITS
from refsim.solvers.laws import problem_field_specs

__all__ = [
    "FORMAT_NAME",
    "SCHEMA_VERSION",
    "SUPPORTED_SCHEMA_VERSIONS",
    "PHASE_NAMES",
    "ROOT_ATTRIBUTES",
    "DatasetSpec",
    "STATIC",
    "STEPS",
    "SOLVER",
    "TISSUE",
    "CONSTRAINTS",
    "EVENTS",
    "EVENT_VALUE_DATASETS",
    "CRITERIA",
    "OPTIONAL_DATASETS",
    "CUT",
    "INSTRUMENTS_GROUP",
    "INSTRUMENT_DATASETS",
    "INSTRUMENT_STEP_QUANTITIES",
    "WITHIN_STEP_QUANTITIES",
    "StepQuantity",
    "instrument_location",
    "PROBLEM_FIELDS",
    "PROBLEMS_GROUP",
    "XDMF",
    "XDMF_GROUP",
    "XDMF_INSTRUMENT_DATASETS",
    "problem_group_name",
    "xdmf_instrument_path",
    "xdmf_path_of",
    "all_datasets",
    "numpy_dtype",
]

#: Value of the root attribute ``format``: what marks an HDF5 file as a refsim results file.
FORMAT_NAME = "refsim-results"
#: Version of the layout written by this code (root attribute ``schema_version``). 2: the within-step event
#: quantities (``steps/event_*``, :data:`WITHIN_STEP_QUANTITIES`), and a puncture step's other quantities
#: are its end state (the step solved again after the tip contact gave way). 3: ``steps/needle_strain``.
SCHEMA_VERSION = 3
#: Versions the reader understands. A version-1 file has no ``steps/event_*``: the reader gives them as NaN
#: (no within-step state recorded), and its puncture step's ``steps/needle_force`` and constraint rows are
#: the give-way's (version 1 solved that step once, ending it at the give-way), which is what
#: ``Results.profile_force`` reads for it. A file of version 1 or 2 has no ``steps/needle_strain`` (NaN).
SUPPORTED_SCHEMA_VERSIONS = (1, 2, 3)

#: Phase names, in the order of the int8 codes of ``steps/phase``.
PHASE_NAMES = ("approach", "insertion", "cutting")

#: Root attributes and their meaning.
ROOT_ATTRIBUTES = {
    "format": f'always "{FORMAT_NAME}"',
    "schema_version": "layout version (integer)",
    "refsim_version": "refsim.__version__ of the writer",
    "git_commit": 'commit of the refsim checkout that wrote the file (`git rev-parse HEAD`), or "unknown"',
    "created": "creation time, ISO 8601 in UTC",
    "scene": "the full scene as JSON (refsim.scene.scene_to_json)",
    "scene_name": "the scene's name",
    "complete": "True once the run finished and the file was closed normally",
    "steps_completed": "number of steps fully written; the reader trusts this count, not dataset lengths",
    "instruments": "only in a file of several instruments: JSON list of {name, location}, one per "
    "instrument in the scene's order; the first one's location is \"\" (its datasets at the paths below), "
    'each further one\'s "instruments/<name>" (the same names and shapes under it)',
    "stop_reason": "why the run stopped early (interrupted by SIGINT/SIGTERM, a numerical error, a failed "
    "write); "
    '"" for a complete run',
}


@dataclass(frozen=True)
class DatasetSpec:
    """One dataset of the results file.

    Attributes
    ----------
    path : Path from the file's root.
    unit : The ``units`` attribute ("m", "N", "s", "1" for dimensionless or index data, "m/N").
    dtype : numpy dtype name, or "str" for variable-length UTF-8 strings.
    entry_shape : Shape of one entry; per-step (growing) datasets hold (count,) + entry_shape. Symbols: n
        tissue nodes, m tets, f faces, k needle nodes, r rows of the problem, "?" any.
    meaning : What the data is, in one line.
    growing : True for datasets appended along their first axis as the run goes.
    """

    path: str
    unit: str
    dtype: str
    entry_shape: tuple
    meaning: str
    growing: bool = True

    @property
    def name(self) -> str:
        """Last component of the path."""
        return self.path.rsplit("/", 1)[-1]


def _specs(group: str, rows: list[tuple], *, growing: bool = True) -> dict[str, DatasetSpec]:
    return {
        name: DatasetSpec(f"{group}/{name}", unit, dtype, shape, meaning, growing)
        for name, unit, dtype, shape, meaning in rows
    }


#: Static data, written once when the file is created.
STATIC = _specs(
    "scene",
    [
        ("tissue/rest_positions", "m", "float64", ("n", 3), "tissue node positions at rest"),
        ("tissue/tets", "1", "int64", ("m", 4), "tetrahedra (node indices)"),
        ("tissue/faces", "1", "int64", ("f", 3), "boundary triangles, oriented outward (node indices)"),
        ("tissue/fixed_nodes", "1", "int64", ("?",), "indices of the clamped tissue nodes"),
        (
            "tissue/boundary_nodes",
            "1",
            "int64",
            ("?",),
            "indices of the nodes a boundary motion moves (empty: none)",
        ),
        (
            "trajectory/samples",
            "-",
            "float64",
            ("?", 7),
            "the needle base's trajectory as the run used it: t [s], base x, y, z [m], unit direction dx, "
            "dy, dz "
            "(a CSV trajectory is copied here, so the file stands alone)",
        ),
        (
            "needle/rest_nodes",
            "m",
            "float64",
            ("k", 3),
            "needle nodes at the trajectory's initial pose (t = 0)",
        ),
    ],
    growing=False,
)


@dataclass(frozen=True)
class StepQuantity:
    """One quantity every instrument records each step: the dataset ``steps/<name>`` (a further instrument's
    under its location, :data:`INSTRUMENT_DATASETS`), the ``Results`` attribute ``<name>`` ((s,) + shape) and
    the attribute of ``refsim.simulation.records.InstrumentRecord`` it is written from (which
    ``StepRecord`` reads from its first instrument). Writer, reader and the instrument datasets loop over
    :data:`INSTRUMENT_STEP_QUANTITIES`.

    Attributes
    ----------
    name : Dataset name under ``steps/`` and the ``Results`` attribute.
    unit, dtype, entry_shape, meaning : As in :class:`DatasetSpec` ("k": the instrument's needle nodes).
    attribute : The ``InstrumentRecord`` attribute holding the step's value (a dotted path into a field that
        may be None: the step's value is then NaN).
    codes : For a coded quantity, the names its integer codes index (its dataset's attribute ``names``); the
        record holds the name, the file and ``Results`` the code.
    since : The schema version that added it: a file of an older version lacks it, and the reader gives it
        as NaN.
    """

    name: str
    unit: str
    dtype: str
    entry_shape: tuple
    meaning: str
    attribute: str
    codes: tuple = ()
    since: int = 1

    def value(self, record):
        """Its value in ``record`` (an ``InstrumentRecord``): the attribute, a dotted path read through
        (``within_step.needle_force``); NaN of its shape when a step has none (the path meets None)."""
        value = record
        for name in self.attribute.split("."):
            value = getattr(value, name)
            if value is None:
                return np.full(self.entry_shape, np.nan)
        return value

    def row(self) -> tuple:
        """(name, unit, dtype, entry_shape, meaning): its row of :data:`STEPS`."""
        return (self.name, self.unit, self.dtype, self.entry_shape, self.meaning)


#: The per-instrument step quantities, in the order of their datasets in ``steps/``.
INSTRUMENT_STEP_QUANTITIES = (
    StepQuantity(
        "phase",
        "1",
        "int8",
        (),
        "phase after the step's events; code into the attribute `names`",
        "phase",
        PHASE_NAMES,
    ),
    StepQuantity("base_position", "m", "float64", (3,), "needle base position", "base_position"),
    StepQuantity("needle_positions", "m", "float64", ("k", 3), "needle node positions", "needle_positions"),
    StepQuantity(
        "needle_frames",
        "1",
        "float64",
        ("k", 3, 3),
        "needle node frames (rotation matrices)",
        "needle_frames",
    ),
    StepQuantity(
        "needle_force",
        "N",
        "float64",
        (3,),
        "force of the tissue on the needle, sum of multiplier x direction",
        "needle_force",
    ),
    StepQuantity(
        "insertion_point_count", "1", "int64", (), "insertion points after the step", "insertion_point_count"
    ),
    StepQuantity(
        "needle_strain",
        "1",
        "float64",
        (),
        "largest strain of the needle's element chords after the step, |chord / rest length - 1| (0 for a "
        "rigid needle): the error of the step's one Newton iteration on the beam (a needle's axial strain is "
        "about 1e-6; above 0.01 the run warns, above 0.1 it stops)",
        "needle_strain",
        since=3,
    ),
)

#: The state at an event located inside the step (refsim.simulation.records.WithinStep: the puncture through
#: the capped tip contact, at its give-way), NaN in the steps without one; the step's other quantities are its
#: end state.
WITHIN_STEP_QUANTITIES = (
    StepQuantity(
        "event_needle_force",
        "N",
        "float64",
        (3,),
        "force of the tissue on the needle in the solve that located a within-step event (the puncture "
        "step's give-way of the tip contact at f_p: the force profile's peak); NaN in steps without one",
        "within_step.needle_force",
        since=2,
    ),
    StepQuantity(
        "event_tip_force",
        "N",
        "float64",
        (3,),
        "force of the tip's contact rows on the needle at that event (normal f_p and friction); NaN in "
        "steps without one",
        "within_step.tip_force",
        since=2,
    ),
    StepQuantity(
        "event_point",
        "m",
        "float64",
        (3,),
        "where that event happened: the tip contact's surface point, where the tip is at the give-way; NaN "
        "in steps without one",
        "within_step.point",
        since=2,
    ),
)
INSTRUMENT_STEP_QUANTITIES = INSTRUMENT_STEP_QUANTITIES + WITHIN_STEP_QUANTITIES

#: One entry per step.
STEPS = _specs(
    "steps",
    [
        ("step", "1", "int64", (), "step index, from 1"),
        ("time", "s", "float64", (), "time at the end of the step"),
        *(quantity.row() for quantity in INSTRUMENT_STEP_QUANTITIES),
        ("cut_point_count", "1", "int64", (), "cut surface points after the step"),
        ("cut_triangle_count", "1", "int64", (), "cut surface triangles after the step"),
        ("triangulation_seconds", "s", "float64", (), "wall-clock time of the cut triangulation in the step"),
        (
            "stage_seconds",
            "s",
            "float64",
            ("stages",),
            "wall-clock time of each stage; columns in attribute `names`",
        ),
        (
            "boundary_displacement",
            "m",
            "float64",
            ("b", 3),
            "prescribed displacement from rest of the nodes scene/tissue/boundary_nodes at the end of the "
            "step "
            "(one row of zeros without a boundary motion)",
        ),
    ],
)

#: Constraint solve of each step (one entry per step; NaN / -1 when the step had no constraint).
SOLVER = _specs(
    "solver",
    [
        ("iterations", "1", "int64", (), "solver iterations (Gauss-Seidel sweeps); -1 when no solve"),
        ("residual", "1", "float64", (), "natural residual of the returned multipliers; NaN when no solve"),
        ("converged", "1", "int8", (), "1 converged, 0 not converged, -1 no solve"),
        ("seconds", "s", "float64", (), "wall-clock time of the solve; NaN when no solve"),
        (
            "increment",
            "m",
            "float64",
            (),
            "Gauss-Seidel increment measure sum |W_jj dlambda_j|; NaN otherwise",
        ),
        ("name", "1", "str", (), 'solver name ("gauss_seidel", "exact/clarabel", ...); "" when no solve'),
        ("message", "1", "str", (), "why the solver stopped (set when not converged)"),
    ],
)

#: Tissue positions, recorded every k-th step (scene key output.tissue_every) and at the last step.
TISSUE = _specs(
    "tissue",
    [
        ("step", "1", "int64", (), "step of each recorded tissue state"),
        ("time", "s", "float64", (), "time of each recorded tissue state"),
        ("positions", "m", "float64", ("n", 3), "tissue node positions"),
    ],
)

#: Constraint rows of every step, as ragged arrays: rows of the i-th step (0-based) are
#: ``offsets[i]:offsets[i + 1]``; ``offsets`` has steps_completed + 1 entries and starts with 0.
CONSTRAINTS = _specs(
    "constraints",
    [
        (
            "offsets",
            "1",
            "int64",
            (),
            "row offsets; step i's rows are offsets[i]:offsets[i+1] (length steps + 1)",
        ),
        (
            "kind",
            "1",
            "int8",
            (),
            "row kind; code into the attribute `names` (bilateral, unilateral, friction)",
        ),
        (
            "source",
            "1",
            "int8",
            (),
            "row source; code into the attribute `names` (penetration, insertion, ...)",
        ),
        ("points", "m", "float64", (3,), "tissue-side point of each row"),
        (
            "directions",
            "1",
            "float64",
            (3,),
            "unit direction n of each row (delta = n.(x_needle - x_tissue))",
        ),
        ("forces", "N", "float64", (), "multiplier lambda of each row"),
        (
            "instrument",
            "1",
            "int64",
            (),
            "only in a file of several instruments: the instrument of each row (index into the root "
            "attribute `instruments`)",
        ),
    ],
)

#: Events, one entry per event, in the order they happened.
EVENTS = _specs(
    "events",
    [
        ("step", "1", "int64", (), "step of the event"),
        ("time", "s", "float64", (), "time at the end of that step"),
        (
            "name",
            "1",
            "str",
            (),
            "puncture, reentry, cut_start, cut_resume, tear, leave_cut, retraction, withdrawal, exit",
        ),
        (
            "force",
            "N",
            "float64",
            (),
            "force that triggered the event: puncture (tip normal force), tear, cut_start of the paper law "
            "(lateral force per insertion point); NaN when the event has no force or its value is in "
            "events/force_per_length",
        ),
        (
            "force_per_length",
            "N/m",
            "float64",
            (),
            "force per unit length that triggered the event: cut_start of the energy law (lateral force per "
            "inserted length, compared with G_c); NaN otherwise",
        ),
    ],
)

#: The criteria the events compared, one entry per criterion and step, in step order
#: (refsim.simulation.margins: what each criterion is, its accuracy, and how an event's margin is read).
CRITERIA = _specs(
    "criteria",
    [
        ("step", "1", "int64", (), "step at whose end the criterion was evaluated"),
        (
            "name",
            "1",
            "str",
            (),
            "criterion: puncture (tip normal force vs f_p), tip_slip (tip friction ratio vs mu_p), "
            "cut_start (the law's cut-start load vs its threshold), tear (crack front's strongest row vs its "
            "threshold), advance (energy law: the front row nearest its give-way decision, its force asked "
            "for over its strength vs 1), layer (energy law: the crack tip's distance from the last layer "
            "vs d_c)",
        ),
        ("value", "-", "float64", (), "the quantity the event compares, in the entry's criteria/unit"),
        ("threshold", "-", "float64", (), "what it is compared with, in the entry's criteria/unit"),
        (
            "accuracy",
            "-",
            "float64",
            (),
            "how far the value can be from the exact solution's at the solver's tolerance, in criteria/unit "
            "(|value - threshold| <= accuracy: within the solver's accuracy of the threshold)",
        ),
        ("unit", "1", "str", (), 'unit of value, threshold and accuracy: "N", "N/m", "m" or "1"'),
    ],
)

#: Datasets an older file may lack (one of the same schema version written before them, or of an older
#: version: a step quantity's ``since``); the reader takes them as absent.
OPTIONAL_DATASETS = frozenset(
    {
        "events/force_per_length",
        "constraints/instrument",
        *(spec.path for spec in CRITERIA.values()),
        *(STEPS[quantity.name].path for quantity in INSTRUMENT_STEP_QUANTITIES if quantity.since > 1),
    }
)

#: The dataset of ``events/`` holding an event's value, by the value's unit (refsim.simulation.records.Event's
#: ``unit``): each dataset has one unit, so its ``units`` attribute is true for every entry.
EVENT_VALUE_DATASETS = {"N": "force", "N/m": "force_per_length"}
if set(EVENT_VALUE_DATASETS) != set(EVENT_UNITS) or any(
    EVENTS[name].unit != unit for unit, name in EVENT_VALUE_DATASETS.items()
):  # pragma: no cover - a schema edit that forgot an event unit
    raise ImportError("refsim.io.schema: EVENT_VALUE_DATASETS does not cover records.EVENT_UNITS")

#: Cut surface history, rewritten whole by ResultWriter.write_cut_surface; absent when nothing was cut.
CUT = _specs(
    "cut",
    [
        ("points", "m", "float64", (3,), "cut surface points in rest coordinates (equation 4 of the paper)"),
        ("point_step", "1", "int64", (), "step at which each point was created"),
        ("triangles", "1", "int64", (3,), "cut surface triangles (point indices)"),
        ("triangle_step", "1", "int64", (), "step at which each triangle was created"),
        ("tet_indices", "1", "int64", (), "tissue tet holding each point (optional)"),
        ("barycentric", "1", "float64", (4,), "barycentric coordinates of each point in its tet (optional)"),
    ],
    growing=False,
)

#: Group holding one subgroup per recorded constraint problem (scene key output.record_problems).
PROBLEMS_GROUP = "problems"

#: Datasets of one problem subgroup ``problems/step_NNNNNNN``: every array field of
# : refsim.solvers.ConstraintProblem, derived from the solvers' law table (refsim.solvers.laws), so a new law
# or : field is recorded and read back without touching this file. Fields absent from an older file take their
#: defaults when read.
PROBLEM_FIELDS = _specs(
    "problems/step_NNNNNNN",
    [(spec.name, spec.unit, spec.dtype, spec.entry_shape, spec.meaning) for spec in problem_field_specs()],
    growing=False,
)


#: Group of the views and derived arrays of the XDMF sidecar (refsim.io.xdmf), added by ``write_xdmf`` (every
#: results file of ``refsim run`` and of a study has it; a file written by ResultWriter alone does not).
XDMF_GROUP = "xdmf"

#: Datasets of the ``xdmf/`` group; NNNNNNN is a step number (7 digits), one dataset per step. The views are
#: HDF5 virtual datasets mapping onto one entry of a per-step dataset (no copy of the data).
XDMF = _specs(
    XDMF_GROUP,
    [
        ("needle/polyline", "1", "int64", (1, "k"), "the needle's polyline connectivity, 0 .. k-1"),
        (
            "needle/positions/NNNNNNN",
            "m",
            "float64",
            ("k", 3),
            "view of steps/needle_positions at step NNNNNNN (virtual dataset)",
        ),
        (
            "cut/points/NNNNNNN",
            "m",
            "float64",
            ("?", 3),
            "every cut surface point mapped into the tissue deformed at recorded step NNNNNNN (equation 4: "
            "its tet's "
            "nodes at tissue/positions weighted by cut/barycentric); derived, stored",
        ),
        (
            "cut/triangles/NNNNNNN",
            "1",
            "int64",
            ("?", 3),
            "the cut triangles existing at step NNNNNNN, shared by the later steps until the cut grows: a "
            "view of the first rows of cut/triangles (virtual dataset), a copy when the triangles are not in "
            "step order",
        ),
        (
            "tissue/positions/NNNNNNN",
            "m",
            "float64",
            ("n", 3),
            "view of tissue/positions at recorded step NNNNNNN (virtual dataset)",
        ),
        (
            "tissue/displacement/NNNNNNN",
            "m",
            "float64",
            ("n", 3),
            "tissue node displacement from rest at recorded step NNNNNNN (0000000: rest, zeros); derived, "
            "stored (point data `displacement`)",
        ),
        (
            "tissue/constraint_force/NNNNNNN",
            "N",
            "float64",
            ("n", 3),
            "force of the needles on the tissue at recorded step NNNNNNN, each row's -lambda n spread on the "
            "nodes of the tet holding its point by barycentric weights (its sum is minus every instrument's "
            "steps/needle_force summed); derived, stored (point data `constraint_force`)",
        ),
        (
            "tissue/fixed",
            "1",
            "int8",
            ("n",),
            "1 for the clamped tissue nodes (scene/tissue/fixed_nodes), else 0 (point data `fixed`)",
        ),
    ],
    growing=False,
)


#: The ``xdmf/`` datasets each instrument has (paths of a one-needle file): its needle's polyline and views
#: of its positions. A further instrument's are under ``xdmf/instruments/<name>/`` with the same names
#: (:func:`xdmf_instrument_path`), views of its own ``instruments/<name>/steps/needle_positions``.
XDMF_INSTRUMENT_DATASETS = {
    spec.path: spec for spec in (XDMF["needle/polyline"], XDMF["needle/positions/NNNNNNN"])
}


def xdmf_path_of(spec: DatasetSpec, step: int) -> str:
    """Path of the ``xdmf/`` dataset ``spec`` (one of :data:`XDMF`) for ``step`` (NNNNNNN replaced)."""
    return spec.path.replace("NNNNNNN", f"{int(step):07d}")


def xdmf_instrument_path(spec: DatasetSpec, index: int, name: str, step: int | None = None) -> str:
    """Path of instrument ``index``'s (called ``name``) ``xdmf/`` dataset ``spec`` (one of
    :data:`XDMF_INSTRUMENT_DATASETS`), for ``step`` when per step: the one-needle path for the first,
    ``xdmf/instruments/<name>/...`` for a further one."""
    path = spec.path if step is None else xdmf_path_of(spec, step)
    if index == 0:
        return path
    return f"{XDMF_GROUP}/{instrument_location(index, name)}/{path[len(XDMF_GROUP) + 1 :]}"


def problem_group_name(step: int) -> str:
    """Path of the group holding the constraint problem of ``step``."""
    return f"{PROBLEMS_GROUP}/step_{int(step):07d}"


#: Where further instruments' datasets are: ``instruments/<name>/`` (the first instrument's are at the paths
#: of a one-needle file).
INSTRUMENTS_GROUP = "instruments"

#: The datasets each instrument has (paths of a one-needle file): its per-step needle data, its events, its
#: trajectory and its needle at t = 0. A further instrument writes them under its location.
INSTRUMENT_DATASETS = {
    spec.path: spec
    for spec in (
        *(STEPS[quantity.name] for quantity in INSTRUMENT_STEP_QUANTITIES),
        *EVENTS.values(),
        *CRITERIA.values(),
        STATIC["trajectory/samples"],
        STATIC["needle/rest_nodes"],
    )
}


def instrument_location(index: int, name: str) -> str:
    """Where instrument ``index`` (called ``name``) keeps its datasets: "" for the first, else
    ``instruments/<name>``."""
    return "" if index == 0 else f"{INSTRUMENTS_GROUP}/{name}"


def all_datasets() -> list[DatasetSpec]:
    """Every dataset of the schema, in documentation order."""
    groups = (STATIC, STEPS, SOLVER, TISSUE, CONSTRAINTS, EVENTS, CRITERIA, CUT, PROBLEM_FIELDS)
    return [spec for group in groups for spec in group.values()]


def numpy_dtype(spec: DatasetSpec):
    """The numpy / h5py dtype of a dataset."""
    if spec.dtype == "str":
        import h5py

        return h5py.string_dtype()
    return np.dtype(spec.dtype)


def reference_markdown() -> str:
    """The schema as Markdown: ``docs/results.md`` is this text (a test checks it is current)."""
    lines = [
        "# Results file (HDF5)",
        "",
        "Generated by `refsim.io.schema.reference_markdown()`; `tests/io/test_results.py` checks this page "
        "is current.",
        "",
        f"One file per run, written step by step by `refsim run` (`refsim.io.ResultWriter`); schema version "
        f"{SCHEMA_VERSION}. Per-step datasets grow along their first axis. The writer buffers steps and "
        f"writes "
        "them in blocks (32 steps by default, one resize and one write per dataset per block); the run "
        "driver "
        "(`refsim.io.driver.run_scene`) writes the buffered steps whenever a run stops, so an interrupted "
        "run "
        "(Ctrl-C, SIGTERM), a run stopped by a numerical error and a run whose disk filled up all keep every "
        "completed step (a full disk: every step of the blocks written before the failure). The root "
        "attribute "
        "`steps_completed` says how many, `complete` stays false and `stop_reason` says why. Only a hard "
        "kill "
        "(SIGKILL) can lose the last buffered block. Every dataset carries a `units` attribute.",
        "",
        "| how the run ended | exit code of `refsim run` | `complete` | `stop_reason` |",
        "|---|---|---|---|",
        '| finished | 0 | true | "" |',
        "| bad input (scene, mesh, paths) | 2 | no file is written | - |",
        "| numerical problem (non-finite or overflowing values, singular factorisation, diverging solver) "
        "| 3 | false | what was detected, at which step |",
        "| failed write (disk full) | 3 | false "
        "| the write error; the steps of earlier blocks are readable |",
        "| SIGINT (Ctrl-C) | 130 | false | interrupted by SIGINT |",
        "| SIGTERM | 143 | false | interrupted by SIGTERM |",
        "",
        "Read it with `refsim.io.read_results(path)`, or with h5py directly:",
        "",
        "```python",
        "import h5py, json",
        'with h5py.File("results/cube.h5", "r") as f:',
        '    scene = json.loads(f.attrs["scene"])            # the full scene',
        '    steps = int(f.attrs["steps_completed"])',
        '    time = f["steps/time"][:steps]                    # [s]',
        '    force = f["steps/needle_force"][:steps]          # [N], force of the tissue on the needle',
        '    offsets = f["constraints/offsets"][:]             # rows of step i: offsets[i]:offsets[i + 1]',
        '    forces = f["constraints/forces"][offsets[-2]:offsets[-1]]  # multipliers of the last step [N]',
        "```",
        "",
        "## Root attributes",
        "",
        "| attribute | meaning |",
        "|---|---|",
    ]
    lines += [f"| `{name}` | {meaning} |" for name, meaning in ROOT_ATTRIBUTES.items()]
    lines += [
        "",
        "## Datasets",
        "",
        f'Symbols in shapes: n tissue nodes, m tets, f faces, k needle nodes, r rows, "?" any; a leading '
        f"`steps` "
        f"means one entry per step. Constraint problems (with `output.record_problems = true`) are in groups "
        f"`{PROBLEMS_GROUP}/step_NNNNNNN`.",
        "",
        "| path | shape | dtype | unit | meaning |",
        "|---|---|---|---|---|",
    ]
    lines += [_row(spec) for spec in all_datasets()]
    lines += [
        "",
        "## A step's end and its within-step event",
        "",
        "Every per-step dataset holds the step's end state: what the next step starts from (positions, "
        "`steps/needle_force`, the constraint rows and their multipliers, the solver's report). A step in "
        "which an event happens inside the step also holds the state at that event, in `steps/event_*` (NaN "
        "in the other steps). The one such event is the puncture through the capped tip contact "
        "(`insertion.puncture_within_step`): its solve ends with the contact at f_p, giving way; the step is "
        "then solved again from its start with the insertion phase's rows (the entry point's, the tip's "
        "cutting row), which hold the tip for the rest of the step, and the step's rows, forces, solver "
        "report and recorded problem (`output.record_problems`) are that second solve's. "
        "`steps/event_needle_force` is the force of the give-way solve, the force profile's peak; "
        "`criteria/` holds the criteria the events were decided on (the give-way solve's). "
        "`Results.profile_force` is the force profile users plot: the event's force where a step has one, "
        "else the end force; `refsim plot`, the run summary's peak force, the sweep quantities "
        "`needle_force@EVENT` (and its axial and lateral parts) and the reference set's force curves read "
        "it. A plain tip contact (`insertion.puncture_within_step = false`) holds the tip to the step's "
        "end: its puncture is decided after the step, which records no within-step event. The events that "
        "change what holds the needle (a cut start, taking up a cut the tissue keeps, leaving the cut, a "
        "re-entry into a hole, a withdrawal, an exit through a far face, a retraction: `STEP_SOLVED_AGAIN`) "
        "also solve their step again from its "
        'start, with the rows after the step\'s events (docs/cutting.md, "When an event takes effect"), '
        "and record no within-step event: the step's datasets are the second solve's, "
        "its `criteria/` the first solve's, on which the events were decided.",
        "",
        f"Files of schema version 1 have no `steps/event_*`: `read_results` gives them as NaN. That version "
        f"solved the puncture step once, so its `steps/needle_force` and constraint rows there are the "
        f"give-way's, which `Results.profile_force` reads. Files of schema versions 1 and 2 have no "
        f"`steps/needle_strain` (NaN). The reader reads versions "
        f"{', '.join(map(str, SUPPORTED_SCHEMA_VERSIONS))}.",
        "",
        "## Several instruments",
        "",
        "A run of a scene with `[[instruments]]` writes the first instrument's needle data at the paths "
        f"above and each further instrument's under `{INSTRUMENTS_GROUP}/<name>/`, with the same names "
        "and shapes (k: that instrument's needle nodes); the root attribute `instruments` lists them in "
        "order with their locations, and `constraints/instrument` says which instrument each row belongs "
        "to. The tissue, the solver, the constraints and the cut are the run's (one problem per step for "
        "every instrument). A one-needle file has neither. Each instrument's datasets:",
        "",
        "| path under the instrument's location | shape | dtype | unit | meaning |",
        "|---|---|---|---|---|",
    ]
    lines += [_row(spec) for spec in INSTRUMENT_DATASETS.values()]
    lines += [
        "",
        f"## The `{XDMF_GROUP}/` group (ParaView sidecar)",
        "",
        "`refsim.io.xdmf.write_xdmf` (called by `refsim run`, by every run of a study and by "
        "`refsim export RESULT.h5 --xdmf`) writes `RESULT.xdmf` beside the file and this group into it; it "
        "replaces the group when run again. The sidecar holds temporal collections (one needle per "
        "instrument, the cut, the tissue) on one sorted time list, rest (t = 0) and the end of every step; "
        "between two recorded tissue steps the tissue and the cut show the last record. The tissue carries "
        "the point data `displacement` [m], `fixed` and `constraint_force` [N]. NNNNNNN is a step number "
        "(7 digits). Views are HDF5 virtual datasets onto one entry of a per-step dataset (no data copied); "
        "stored are the derived arrays (deformed cut points, displacement, nodal constraint forces) of each "
        "recorded tissue step. The group's attribute `description` says the same. `refsim export RESULT.h5 "
        "--vtu STEP` (or `last`, or `all` with a `.pvd` series) writes the tissue, the cut and every needle "
        "(its centreline, `STEM_<name>_NNNNNNN.vtu`) of recorded steps as `.vtu` files with the same point "
        "data.",
        "",
        "| path | shape | dtype | unit | meaning |",
        "|---|---|---|---|---|",
    ]
    lines += [_row(spec) for spec in XDMF.values()]
    lines += [
        "",
        "A file of several instruments has one needle collection per instrument in the sidecar, named by "
        "the instrument (a one-needle file's is `needle`), before the cut and the tissue. Each instrument "
        "has the datasets below: the first at these paths, each further one with the leading "
        f"`{XDMF_GROUP}/` replaced by `{XDMF_GROUP}/{INSTRUMENTS_GROUP}/<name>/` (e.g. "
        f"`{xdmf_instrument_path(XDMF['needle/polyline'], 1, '<name>')}`), views of its own "
        f"`{INSTRUMENTS_GROUP}/<name>/{STEPS['needle_positions'].path}`. The tissue's `constraint_force` "
        "is the force of every instrument's rows.",
        "",
        "| path (first instrument) | shape | dtype | unit | meaning |",
        "|---|---|---|---|---|",
    ]
    lines += [_row(spec) for spec in XDMF_INSTRUMENT_DATASETS.values()]
    return "\n".join(lines)


def _row(spec: DatasetSpec) -> str:
    shape = ("steps",) + tuple(spec.entry_shape) if spec.growing else tuple(spec.entry_shape)
    dims = ", ".join(str(s) for s in shape)
    return f"| `{spec.path}` | ({dims}) | {spec.dtype} | {spec.unit} | {spec.meaning} |"
