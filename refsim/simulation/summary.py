"""Aggregates of a run's step records: the end-of-run summary and the paper's Table 1 for our code."""

from __future__ import annotations

from array import array
from dataclasses import dataclass, field

import numpy as np

from refsim.simulation.margins import CriterionSeries, assess
from refsim.simulation.needle_body import STRAIN_WARNING
from refsim.simulation.records import STAGES, StepRecord

__all__ = [
    "PAPER_TABLE_1",
    "RUN_STATUSES",
    "PaperPhase",
    "PhaseStatistics",
    "RunStatus",
    "RunSummary",
    "event_value_text",
    "run_and_keep",
]


@dataclass(frozen=True)
class RunStatus:
    """One way a run can end.

    Attributes
    ----------
    name : ``RunSummary.status``.
    exit_code : `refsim run`'s exit code.
    cause : What stopped the run, in words.
    """

    name: str
    exit_code: int
    cause: str

    @property
    def by_signal(self) -> bool:
        """A signal stopped the run (the exit code is 128 + its number, the shell's convention)."""
        return self.exit_code > 128


#: Every way a run ends, by ``RunSummary.status``: the one list the run driver (refsim.io.driver, whose
#: docstring tabulates it; a test checks the table) and the summary read.
RUN_STATUSES = {
    status.name: status
    for status in (
        RunStatus("complete", 0, "nothing (finished)"),
        RunStatus("numerical", 3, "non-finite or overflowing values, a singular matrix, a diverging solver"),
        RunStatus("write_failed", 3, "a failed write (full disk)"),
        RunStatus("interrupted", 130, "SIGINT (Ctrl-C)"),
        RunStatus("hangup", 129, "SIGHUP (a closed terminal, a dropped ssh)"),
        RunStatus("terminated", 143, "SIGTERM"),
    )
}


@dataclass(frozen=True)
class PaperPhase:
    """One row of the paper's Table 1 (Perrusi, Baksic and Courtecuisse 2021, the 10 cm cube, d_c = d_i =
    0.5 mm, their C++ code in SOFA on their machine, Gauss–Seidel): atomic constraints, solving time [ms] and
    its share of the step, total time per step [ms], and the mean Gauss–Seidel iterations given in the text
    (NaN where the paper gives none)."""

    name: str
    constraints: int
    solve_ms: float
    share: float
    total_ms: float
    iterations: float = float("nan")


#: The paper's Table 1 by our phase names (its "Penetration" is our approach phase: the tip's contact row).
#: Iterations: "2.54 iterations during the insertion and 80 during the cutting phase" (section 5).
PAPER_TABLE_1 = {
    "approach": PaperPhase("penetration", 1, 2.0, 0.132, 15.1),
    "insertion": PaperPhase("insertion", 36, 3.0, 0.194, 15.47, 2.54),
    "cutting": PaperPhase("cutting", 12, 4.0, 0.243, 12.0, 80.0),
}


def event_value_text(value: float, unit: str) -> str:
    """An event's triggering value with its unit (records.Event.unit): "force 0.81 N", "force per length
    207.9 N/m"; the one wording of the summary and the figures."""
    quantity = "force per length" if unit == "N/m" else "force"
    return f"{quantity} {value:.4g} {unit}"


_value_text = event_value_text


@dataclass
class PhaseStatistics:
    """Per-phase sums of one run (the paper's Table 1: rows, solving time and share, total per step)."""

    steps: int = 0
    rows: int = 0
    iterations: int = 0
    solves: int = 0
    stage_seconds: dict = field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))

    @property
    def mean_rows(self) -> float:
        return self.rows / self.steps if self.steps else float("nan")

    @property
    def mean_iterations(self) -> float:
        return self.iterations / self.solves if self.solves else float("nan")

    @property
    def ms_per_step(self) -> float:
        return 1e3 * sum(self.stage_seconds.values()) / self.steps if self.steps else float("nan")

    @property
    def solve_ms_per_step(self) -> float:
        return 1e3 * self.stage_seconds["solve"] / self.steps if self.steps else float("nan")


#: What the peak force reads, said under it.
PEAK_READS = "over every step's end and, in a puncture step, the tip contact's give-way within it"


def _profile_force(part) -> float:
    """The largest ‖force on the needle‖ one step's record (an ``InstrumentRecord``, or a ``StepRecord`` for
    its first instrument) holds: the end of the step's and, at a within-step event (the puncture's give-way),
    the force there."""
    force = float(np.linalg.norm(part.needle_force))
    within = part.within_step
    return force if within is None else max(force, float(np.linalg.norm(within.needle_force)))


@dataclass
class RunSummary:
    """Running aggregate of step records; feed it with :meth:`add`."""

    events: list = field(default_factory=list)
    criteria: list = field(default_factory=list)  # (step, instrument name or "", Criterion) compared
    phases: dict = field(default_factory=dict)
    peak_force: float = 0.0
    peak_force_step: int = 0
    steps: int = 0
    unconverged: int = 0
    max_residual: float = 0.0
    triangulations: list = field(default_factory=list)  # (step, seconds) of each triangulation
    cut_points: int = 0
    cut_triangles: int = 0
    first_cut_step: int | None = None
    total_steps: int | None = None  # steps the run was to make
    output: str = ""  # the results file
    status: str = "running"  # "running", then a key of RUN_STATUSES (set by finish)
    exit_code: int = 0  # refsim run's exit code, RUN_STATUSES[status].exit_code
    stop_reason: str = ""  # why the run stopped early, "" when complete
    steps_written: int = 0  # steps readable in the results file
    # With several instruments: each event's instrument (parallel to events), and each instrument's peak
    # force and its step, by name, in the scene's order (empty with one instrument).
    event_instruments: list = field(default_factory=list)
    instrument_peaks: dict = field(default_factory=dict)
    # Each needle's largest element strain over the run and its step, by instrument name (a rigid needle's is
    # 0: not listed; InstrumentRecord.needle_strain)
    needle_strains: dict = field(default_factory=dict)
    # Each step's number and time (its stages' sum [s]): 16 bytes a step (interactive sessions run for hours)
    step_numbers: array = field(default_factory=lambda: array("q"))
    step_seconds: array = field(default_factory=lambda: array("d"))
    # The tissue's linear solver in this run: (numeric factorisations, analyses or None), None when unknown
    tissue_linear_counts: tuple | None = None

    @property
    def complete(self) -> bool:
        """True when the run made all its steps and the file was closed normally."""
        return self.status == "complete"

    @property
    def stopped_by_signal(self) -> bool:
        """True when a signal (SIGINT, SIGHUP, SIGTERM) stopped the run."""
        status = RUN_STATUSES.get(self.status)
        return status is not None and status.by_signal

    def finish(self, *, status: str, stop_reason: str, steps_written: int) -> None:
        """Record how the run ended (called by the run driver, refsim.io.driver.run_scene).

        Parameters
        ----------
        status : A key of :data:`RUN_STATUSES`; the exit code is its ``exit_code``.
        stop_reason : Why the run stopped early, "" when complete.
        steps_written : Steps readable in the results file.
        """
        if status not in RUN_STATUSES:
            raise ValueError(f"status = {status!r}: expected one of {', '.join(RUN_STATUSES)}")
        self.status, self.exit_code, self.stop_reason = status, RUN_STATUSES[status].exit_code, stop_reason
        self.steps_written = int(steps_written)

    def add(self, record: StepRecord) -> None:
        self.steps += 1
        parts = tuple(getattr(record, "instruments", ()))
        several = len(parts) > 1
        for part in parts if several else ():
            for event in part.events:
                self.events.append((record.step, record.time, event.name, event.force, event.unit))
                self.event_instruments.append(part.name)
            force = _profile_force(part)
            if force > self.instrument_peaks.get(part.name, (-1.0, 0))[0]:
                self.instrument_peaks[part.name] = (force, record.step)
        for event in () if several else record.events:
            self.events.append((record.step, record.time, event.name, event.force, event.unit))
        for part in parts:
            strain = float(getattr(part, "needle_strain", 0.0))
            if strain > self.needle_strains.get(part.name, (0.0, 0))[0]:
                self.needle_strains[part.name] = (strain, record.step)
        for part in parts if several else ():
            self.criteria.extend((record.step, part.name, criterion) for criterion in part.criteria)
        for criterion in () if several else record.criteria:
            self.criteria.append((record.step, "", criterion))
        # With several instruments a step's phase is every instrument's, in order ("cutting/insertion").
        phase = "/".join(part.phase for part in parts) if several else record.phase
        stats = self.phases.setdefault(phase, PhaseStatistics())
        stats.steps += 1
        stats.rows += int(record.row_forces.size)
        if record.solver is not None:
            stats.solves += 1
            stats.iterations += int(record.solver.iterations)
            if not record.solver.converged:
                self.unconverged += 1
            if np.isfinite(record.solver.residual):
                self.max_residual = max(self.max_residual, float(record.solver.residual))
        for stage, seconds in record.stage_seconds.items():
            stats.stage_seconds[stage] += seconds
        self.step_numbers.append(record.step)
        self.step_seconds.append(sum(record.stage_seconds.values()))
        if record.triangulation_seconds > 0.0:
            self.triangulations.append((record.step, record.triangulation_seconds))
        if record.cut_point_count and self.first_cut_step is None:
            self.first_cut_step = record.step
        self.cut_points, self.cut_triangles = record.cut_point_count, record.cut_triangle_count
        force = _profile_force(record)
        if force > self.peak_force:
            self.peak_force, self.peak_force_step = force, record.step

    def event_margins(self) -> list:
        """Each event's margin (``refsim.simulation.margins.assess`` on the criteria of the run), in event
        order; with several instruments each event is assessed on its own instrument's criteria."""
        return [margin for _, margin in self._owned_margins()]

    def _owned_margins(self) -> list[tuple[str, object]]:
        """(instrument name, margin) of each event with a criterion; the name is "" for a one-needle run."""
        owners = self.event_instruments or [""] * len(self.events)
        owned = []
        for owner in dict.fromkeys(owners):
            mine = [(step, c) for step, name, c in self.criteria if name == owner]
            series = CriterionSeries.of([step for step, _ in mine], [c for _, c in mine])
            events = [(e[0], e[2]) for e, o in zip(self.events, owners, strict=True) if o == owner]
            owned += [(owner, margin) for margin in assess(events, series)]
        return sorted(owned, key=lambda item: item[1].step)

    def format_margins(self) -> list[str]:
        """The event margins as text lines (none when no event has a criterion)."""
        owned = self._owned_margins()
        if not owned:
            return []
        knife = sum(margin.knife_edge for _, margin in owned)
        head = f"event margins (criterion against threshold, solver accuracy; {knife} knife-edge):"
        return [head, *(f"  {owner + ': ' if owner else ''}{margin.text()}" for owner, margin in owned)]

    @property
    def seconds(self) -> float:
        return sum(sum(p.stage_seconds.values()) for p in self.phases.values())

    def format(self) -> str:
        """Events, peak force, solver health and speed, as text."""
        lines = ["events:"]
        owners = self.event_instruments or [""] * len(self.events)
        lines += [
            f"  step {s:5d}  t = {t:.4f} s  {owner + ': ' if owner else ''}{name}"
            + (f"  {_value_text(f, unit)}" if np.isfinite(f) else "")
            for (s, t, name, f, unit), owner in zip(self.events, owners, strict=True)
        ] or ["  none"]
        lines += self.format_margins()
        if self.instrument_peaks:
            lines += [
                f"peak force on {name}'s needle: {force:.4g} N at step {step}"
                for name, (force, step) in self.instrument_peaks.items()
            ]
        else:
            lines.append(f"peak force on the needle: {self.peak_force:.4g} N at step {self.peak_force_step}")
        lines.append(f"  ({PEAK_READS})")
        lines += self.format_strains()
        lines.append(
            f"constraint solves not converged: {self.unconverged}; largest natural residual "
            f"{self.max_residual:.2e}"
        )
        rate = self.steps / self.seconds if self.seconds > 0 else float("nan")
        lines.append(f"{self.steps} steps in {self.seconds:.2f} s: {rate:.1f} steps/s")
        if self.status not in ("running", "complete"):
            lines.append(
                f"stopped early ({self.status}): {self.stop_reason}; {self.steps_written} steps kept in "
                f"{self.output or 'the results file'}"
            )
        if self.cut_points:
            lines.append(self.format_cut())
        return "\n".join(lines)

    def format_strains(self) -> list[str]:
        """Each flexible needle's largest element strain (``InstrumentRecord.needle_strain``), flagged above
        ``STRAIN_WARNING``; no line for rigid needles."""
        lines = []
        for name, (strain, step) in self.needle_strains.items():
            line = f"largest element strain of {name}'s beam: {strain:.2g} at step {step}"
            if strain > STRAIN_WARNING:
                line += (
                    f" (above {STRAIN_WARNING:g}, beyond the yield strain of steel: the step's one Newton "
                    "iteration did not follow the needle's rotation; use a smaller time.dt)"
                )
            lines.append(line)
        return lines

    def format_cut(self) -> str:
        """Cut surface at the end, and how often and how long the triangulation ran."""
        count = len(self.triangulations)
        if count == 0:
            return f"cut surface: {self.cut_points} points, {self.cut_triangles} triangles"
        seconds = np.array([s for _, s in self.triangulations])
        cutting_steps = self.steps - self.first_cut_step + 1
        later = seconds[1:] if count > 1 else seconds
        return (
            f"cut surface: {self.cut_points} points, {self.cut_triangles} triangles; {count} triangulations "
            f"in {cutting_steps} cutting steps (one every {cutting_steps / count:.1f} steps), "
            f"first {1e3 * seconds[0]:.1f} ms "
            f"(includes compiling or loading the kernels), then {1e3 * later.mean():.2f} ms on average"
        )

    def format_table(self, *, beside_paper: bool = False) -> str:
        """The paper's Table 1 for this run: per phase, rows, solving ms and share, total ms per step; with
        ``beside_paper``, each phase followed by the paper's row (:data:`PAPER_TABLE_1`) and the ratio of our
        total per step to theirs."""
        width = max([10, *(len(phase) for phase in self.phases)])  # several instruments: "cutting/insertion"
        header = (
            f"{'phase':<{width}} {'steps':>6} {'rows':>7} {'GS/solver it.':>13} {'solve ms':>9} {'share':>6} "
            f"{'total ms':>9}"
        )
        lines = [header, "-" * len(header)]
        for phase, stats in self.phases.items():
            share = stats.solve_ms_per_step / stats.ms_per_step if stats.steps else float("nan")
            lines.append(
                f"{phase:<{width}} {stats.steps:>6d} {stats.mean_rows:>7.1f} {stats.mean_iterations:>13.2f} "
                f"{stats.solve_ms_per_step:>9.2f} {100 * share:>5.1f}% {stats.ms_per_step:>9.2f}"
            )
            paper = PAPER_TABLE_1.get(phase) if beside_paper else None
            if paper is not None:
                lines.append(
                    f"{'  paper':<{width}} {'':>6} {paper.constraints:>7d} {paper.iterations:>13.2f} "
                    f"{paper.solve_ms:>9.2f} {100 * paper.share:>5.1f}% {paper.total_ms:>9.2f}"
                    f"   ours/paper {stats.ms_per_step / paper.total_ms:.2f}"
                )
        stage_totals = dict.fromkeys(STAGES, 0.0)
        for stats in self.phases.values():
            for stage, seconds in stats.stage_seconds.items():
                stage_totals[stage] += seconds
        if self.steps:
            lines.append(
                "ms per step by stage: "
                + ", ".join(
                    f"{stage} {1e3 * seconds / self.steps:.2f}" for stage, seconds in stage_totals.items()
                )
            )
        if self.step_seconds:
            lines.append(self.format_step_times())
        if self.tissue_linear_counts is not None and self.steps:
            lines.append(self.format_linear_counts())
        return "\n".join(lines)

    def format_linear_counts(self) -> str:
        """How often the tissue's linear solver factorised and analysed in the run, its set-up included (the
        fast mode's one rest factorisation is made there): the factor is kept while the matrix is unchanged
        (a tissue at rest), and an analysis (a new pattern, or PARDISO's new partial-solve marks) costs a step
        about a factorisation and an analysis more."""
        factorisations, analyses = self.tissue_linear_counts
        text = f"tissue matrix: {factorisations} numeric factorisation{'' if factorisations == 1 else 's'}"
        if analyses is not None:
            text += f" and {analyses} analys{'is' if analyses == 1 else 'es'}"
        return text + f" in the set-up and {self.steps} steps"

    def format_step_times(self, slowest: int = 5) -> str:
        """The spread of the steps' times, what a real-time loop meets (its frame budget is per step, not
        on average): median, 95th percentile, the ``slowest`` slowest steps (the first, which analyses and
        first uses the kernels, and the rare costly ones: a re-analysis, a first cut) and the steps over the
        paper's frame time."""
        milliseconds = 1e3 * np.frombuffer(self.step_seconds, dtype=float)
        worst = np.argsort(-milliseconds, kind="stable")[:slowest]
        budget = PAPER_TABLE_1["insertion"].total_ms
        over = int(np.count_nonzero(milliseconds > budget))
        listed = ", ".join(f"{milliseconds[k]:.2f} (step {self.step_numbers[k]})" for k in worst)
        return (
            f"ms per step: median {np.median(milliseconds):.2f}, 95th percentile "
            f"{np.percentile(milliseconds, 95):.2f}, slowest {listed}; "
            f"{over} of {milliseconds.size} steps over {budget:.2f} ms (the paper's insertion step)"
        )


def run_and_keep(simulation) -> tuple[RunSummary, dict]:
    """Run ``simulation`` (a :class:`refsim.simulation.Simulation`) to its end, keeping what a comparison of
    two runs of a scene needs (``refsim.fem.bench.compare_runs``): its summary, and ``{"tissue_positions":
    [(n, 3) positions [m] per step], "needle_force": [(3,) force [N] per step], "events": [(step, name),
    ...]}``."""
    summary = RunSummary()
    kept = {"tissue_positions": [], "needle_force": [], "events": []}

    def on_step(state, record):
        summary.add(record)
        kept["tissue_positions"].append(state.tissue.positions)
        kept["needle_force"].append(record.needle_force)
        kept["events"].extend((record.step, event.name) for event in record.events)

    simulation.run(on_step=on_step)
    summary.tissue_linear_counts = simulation.tissue_compliance.linear_counts()
    return summary, kept
