"""Reference data for other implementations, exported from a results file.

- :func:`export_problems`: the constraint problem of every recorded step (a run with
  ``output.record_problems = true``) with its exact solution (:func:`refsim.solvers.solve_exact`), in the
  problem-set format below; and, for the steps FCLib's local format can hold, one FCLib file each
  (:func:`write_fclib`, :func:`coulomb_contacts`).
- :func:`export_force_csv`: the needle force history as CSV.
- :func:`export_vtu`: the deformed tissue (point data displacement [m], fixed, constraint_force [N]), the
  cut surface and every instrument's needle (its centreline as a polyline; point data radius [m] and
  displacement [m]) at a recorded tissue step, or at every one with a ParaView collection (.pvd) each, as
  VTK unstructured grids (.vtu) that ParaView, VTK and ``meshio.read`` open alone.

Problem-set file (HDF5, ``format = "refsim-problem-set"``, ``schema_version = 1``)::

    /                       attributes: format, schema_version, source (results file), scene (JSON),
                            scene_name, git_commit, created, solver (how the solutions were computed),
                            problem_count
    /problems/step_NNNNNNN/ attributes: step, time [s], phase, name, pure_contact (bool), kinds (JSON: rows of
                            each kind)
        compliance (r, r) [m/N], free_gap (r,) [m]      δ = W λ + δ_free
        bilateral, unilateral (?,), contacts (?, 3), contact_friction (?,), shaft_friction (?,),
        shaft_pairs (?, 2), shaft_friction_coefficient (?,), shaft_normal_preload (?,) [N],
        box_rows (?,), box_lower, box_upper (?,) [N]   the laws of the rows (refsim.solvers.ConstraintProblem)
        solution/multipliers (r,) [N], solution/gap (r,) [m]
                            attributes: residual (natural residual), converged, solver, seconds

FCLib local file (one problem, Siconos' u = W r + q; FCLib's ``fclib_local`` layout): ``/fclib_local/W``
({m, n, nz = -1, nzmax, p, i, x}: CSC, int32 indices), ``/fclib_local/vectors/{q, mu}``,
``/fclib_local/spacedim`` = 3, ``/fclib_local/info/{title, description, math_info}``, and ``/solution/{r,
u}``. Rows are reordered so that contact k holds rows 3k (normal), 3k + 1, 3k + 2 (tangents); r = λ, u = δ.

What FCLib's local format holds: 3-D (or 2-D) Coulomb contacts only, u = W r + q with, per contact, r_n ≥ 0,
‖r_t‖ ≤ μ r_n and De Saxcé's complementarity; no equality (bilateral) row, no box bound, no friction bounded
by anything but its own contact's normal force. So the insertion rows (two bilateral lateral rows and a shaft
friction row bounded by μ (‖λ_lateral‖ + the grip's preload)), the cut's sliding and front rows and the tip's
cutting row cannot be written as FCLib problems (FCLib's global format adds equality rows, but its friction is
still Coulomb's per contact, not a bound by other rows' forces plus a preload). The tip contact before
puncture can (:func:`coulomb_contacts`): a normal row with two friction rows bounded by μ λ_n. refsim writes
its normal as a box [0, f_p] (the puncture located within the step) and its friction as two independent bounds
|λ_ti| ≤ μ λ_n (a pyramid); the FCLib file holds the same W, q and μ with Coulomb's cone and a plain
unilateral normal, and its solution r is the exact solution of that problem. A step is written only when the
cap is inactive at r (λ_n < f_p: the cap does not change the answer) and the contact carries load (r ≠ 0).
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import json
from pathlib import Path

import numpy as np

__all__ = [
    "PROBLEM_SET_FORMAT",
    "export_force_csv",
    "coulomb_contacts",
    "export_vtu",
    "export_problems",
    "is_pure_contact",
    "read_problem_set",
    "write_fclib",
]

PROBLEM_SET_FORMAT = "refsim-problem-set"
PROBLEM_SET_SCHEMA_VERSION = 1


def _problem_fields() -> list[str]:
    from refsim.solvers import ConstraintProblem

    return [f.name for f in dataclasses.fields(ConstraintProblem) if f.name != "name"]


def is_pure_contact(problem) -> bool:
    """True when every row of ``problem`` belongs to a 3-D Coulomb contact (an FCLib local problem)."""
    return problem.row_count > 0 and problem.contacts.size == problem.row_count


def coulomb_contacts(problem):
    """The step's problem with FCLib's law: pure 3-D Coulomb contacts on the same W, δ_free and μ, or None.

    A problem qualifies when it has no bilateral and no shaft (pair-form) rows, and its other rows are normal
    rows (unilateral, or a box [0, cap] with cap > 0) each with exactly two friction rows bounded by μ |λ_n|
    of that normal alone (group friction of one member, no preload, the same μ), or are contacts already.

    Returns
    -------
    None, or (contact problem, caps): the :class:`refsim.solvers.ConstraintProblem` with ``contacts`` (k, 3)
    (normal, tangent, tangent; rows in the step's numbering) and ``contact_friction`` (k,), and the cap of
    each contact's normal [N], shape (k,) (inf for a unilateral normal, and for the contacts the problem had).
    """
    from refsim.solvers import ConstraintProblem

    if problem.row_count == 0 or problem.bilateral.size or problem.shaft_friction.size:
        return None
    rows, offsets, members, coefficient, preload = problem.friction_groups()
    if np.any(np.diff(offsets) != 1) or np.any(preload != 0.0):
        return None
    capped = (problem.box_lower == 0.0) & (problem.box_upper > 0.0)
    if not np.all(capped):
        return None
    normals = np.concatenate([problem.unilateral, problem.box_rows])
    caps = np.concatenate([np.full(problem.unilateral.size, np.inf), problem.box_upper])
    owner = members  # the normal row bounding each friction row
    if owner.size != 2 * normals.size or not np.all(np.isin(owner, normals)):
        return None
    pairs = np.argsort(owner, kind="stable").reshape(-1, 2)  # two friction rows per normal, by normal row
    if np.any(owner[pairs[:, 0]] != owner[pairs[:, 1]]):
        return None
    mu = coefficient[pairs[:, 0]]
    if np.any(coefficient[pairs[:, 1]] != mu):
        return None
    built = np.column_stack([owner[pairs[:, 0]], rows[pairs[:, 0]], rows[pairs[:, 1]]])
    order = np.argsort(normals)
    contacts = np.concatenate([problem.contacts.reshape(-1, 3), built])
    covered = np.zeros(problem.row_count, dtype=int)
    np.add.at(covered, contacts.reshape(-1), 1)
    if np.any(covered != 1):
        return None
    contact_problem = ConstraintProblem(
        compliance=problem.compliance,
        free_gap=problem.free_gap,
        contacts=contacts,
        contact_friction=np.concatenate([problem.contact_friction, mu]),
        name=f"{problem.name} (Coulomb contacts)" if problem.name else "Coulomb contacts",
    )
    all_caps = np.concatenate([np.full(problem.contacts.shape[0], np.inf), caps[order]])
    return contact_problem, all_caps


def write_fclib(problem, path, *, solution=None, title: str = "", description: str = "") -> Path:
    """Write a pure frictional-contact problem in FCLib's local format.

    Parameters
    ----------
    problem : A :class:`refsim.solvers.ConstraintProblem` whose rows are all contacts.
    path : The .hdf5 file to write.
    solution : Multipliers λ [N], shape (r,), in the problem's row order; stored as ``/solution/r`` with
        ``/solution/u`` = W r + q (reordered like the rows).
    title, description : ``/fclib_local/info`` texts.

    Raises
    ------
    ValueError
        When the problem has rows that are not contacts (naming how many).
    """
    import h5py
    import scipy.sparse as sparse

    if not is_pure_contact(problem):
        raise ValueError(
            f"problem {problem.name!r}: {problem.row_count - problem.contacts.size} of "
            f"{problem.row_count} rows are not frictional contacts; FCLib's local format holds "
            "contacts only"
        )
    order = problem.contacts.reshape(-1)
    matrix = sparse.csc_matrix(problem.compliance[np.ix_(order, order)])
    matrix.eliminate_zeros()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as handle:
        local = handle.create_group("fclib_local")
        w = local.create_group("W")
        size = np.array([matrix.shape[0]], dtype=np.int32)
        w.create_dataset("m", data=size)
        w.create_dataset("n", data=size)
        w.create_dataset("nz", data=np.array([-1], dtype=np.int32))
        w.create_dataset("nzmax", data=np.array([matrix.nnz], dtype=np.int32))
        w.create_dataset("p", data=matrix.indptr.astype(np.int32))
        w.create_dataset("i", data=matrix.indices.astype(np.int32))
        w.create_dataset("x", data=matrix.data.astype(np.float64))
        vectors = local.create_group("vectors")
        vectors.create_dataset("q", data=problem.free_gap[order])
        vectors.create_dataset("mu", data=np.asarray(problem.contact_friction, dtype=np.float64))
        local.create_dataset("spacedim", data=np.array([3], dtype=np.int32))
        info = local.create_group("info")
        info.create_dataset("title", data=np.bytes_(title or problem.name or path.stem))
        info.create_dataset("description", data=np.bytes_(description or "exported by refsim.io.export"))
        info.create_dataset(
            "math_info", data=np.bytes_("u = W r + q; contact k: rows 3k (normal), 3k+1, 3k+2")
        )
        if solution is not None:
            solution = np.asarray(solution, dtype=np.float64)
            group = handle.create_group("solution")
            group.create_dataset("r", data=solution[order])
            group.create_dataset("u", data=problem.gap(solution)[order])
    return path


#: Units of the problem-set datasets (the others are dimensionless).
_PROBLEM_UNITS = {
    "compliance": "m/N",
    "free_gap": "m",
    "shaft_normal_preload": "N",
    "box_lower": "N",
    "box_upper": "N",
}


def _write_problem(handle, step: int, problem, multipliers, report, results, fields) -> None:
    """One step's group of a problem set: the problem's arrays with units, its attributes (step, time, phase,
    row kinds) and the exact solution (multipliers [N], gap [m], residual, solver report)."""
    from refsim.solvers import natural_residual

    index = results.index_of(step)
    group = handle.create_group(f"problems/step_{step:07d}")
    kinds = np.bincount(problem.row_kinds(), minlength=5)
    group.attrs.update(
        {
            "step": step,
            "time": float(results.time[index]),
            "phase": str(results.phase_name[index]),
            "name": problem.name,
            "pure_contact": is_pure_contact(problem),
            "kinds": json.dumps(
                {
                    name: int(count)
                    for name, count in zip(
                        ("bilateral", "unilateral", "contact", "shaft_friction", "box"),
                        kinds,
                        strict=False,
                    )
                }
            ),
        }
    )
    for name in fields:
        dataset = group.create_dataset(name, data=np.asarray(getattr(problem, name)))
        dataset.attrs["units"] = _PROBLEM_UNITS.get(name, "1")
    solution = group.create_group("solution")
    solution.create_dataset("multipliers", data=multipliers).attrs["units"] = "N"
    solution.create_dataset("gap", data=problem.gap(multipliers)).attrs["units"] = "m"
    solution.attrs.update(
        {
            "residual": float(natural_residual(problem, multipliers)),
            "converged": bool(report.converged),
            "solver": str(report.solver),
            "seconds": float(report.seconds),
        }
    )


def export_problems(
    results_path,
    output,
    *,
    fclib_folder=None,
    tolerance: float = 1e-10,
    backend: str = "clarabel",
    steps=None,
    fclib_steps=None,
) -> dict:
    """Export the recorded constraint problems of a results file with their exact solutions.

    Parameters
    ----------
    results_path : A results file written with ``output.record_problems = true``.
    output : The problem-set file to write (.h5).
    fclib_folder : Also write ``step_NNNNNNN.hdf5`` FCLib files here for the pure-contact steps; none when
    None.
    tolerance : Natural residual the exact solver is asked for.
    backend : QP backend of the exact solver.
    steps : The recorded steps written to ``output`` (an iterable of step numbers); every recorded step when
    None.
    fclib_steps : The recorded steps tried for FCLib files; ``steps`` when None. Only the steps of ``steps``
    and ``fclib_steps`` are read and solved.

    Returns
    -------
    dict: ``problems`` (count written), ``fclib`` (paths written), ``unconverged`` (written steps whose exact
    solve missed the tolerance; they are exported with their best multipliers and ``converged = False``).

    Raises
    ------
    ValueError
        When the results file holds no recorded problem (naming the scene key that records them).
    """
    import h5py

    from refsim.io.provenance import git_commit
    from refsim.io.reader import read_problems, read_results
    from refsim.solvers import natural_residual, solve_exact

    results_path = Path(results_path)
    results = read_results(results_path)
    recorded = {int(step) for step in results.problem_steps}
    if not recorded:
        raise ValueError(
            f"{results_path}: no recorded constraint problems; run the scene with "
            "--set output.record_problems=true"
        )
    written_steps = recorded if steps is None else {int(step) for step in steps}
    fclib_wanted = written_steps if fclib_steps is None else {int(step) for step in fclib_steps}
    missing = sorted((written_steps | fclib_wanted) - recorded)
    if missing:
        raise ValueError(
            f"{results_path}: no recorded constraint problem at step(s) {missing[:5]}"
            f"{' ...' if len(missing) > 5 else ''} (recorded: steps {min(recorded)} to {max(recorded)})"
        )
    problems = read_problems(results_path, steps=written_steps | fclib_wanted)
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    fields = _problem_fields()
    written, unconverged = [], []
    # written under a temporary name, renamed once complete: an interrupted export (the exact solves take
    # time) or a failed write leaves no half-written problem set
    temporary = output.with_name(f".{output.name}.partial")
    with _renamed_when_complete(temporary, output), h5py.File(temporary, "w") as handle:
        handle.attrs.update(
            {
                "format": PROBLEM_SET_FORMAT,
                "schema_version": PROBLEM_SET_SCHEMA_VERSION,
                "source": str(results_path),
                "scene": json.dumps(results.scene, sort_keys=True),
                "scene_name": results.scene_name,
                "git_commit": git_commit(),
                "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                "solver": f"refsim.solvers.solve_exact(tolerance={tolerance:g}, backend={backend!r})",
                "problem_count": len(written_steps),
            }
        )
        for step, problem in problems:
            written_here = step in written_steps
            tried = fclib_folder is not None and step in fclib_wanted
            if not (written_here or tried):
                continue
            multipliers, report = solve_exact(problem, tolerance=tolerance, backend=backend)
            index = results.index_of(step)
            if written_here:
                _write_problem(handle, step, problem, multipliers, report, results, fields)
                if not report.converged:
                    unconverged.append(step)
            if not tried:
                continue
            where = (
                f"refsim needle-tissue problem: scene {results.scene_name}, step {step}, t = "
                f"{results.time[index]:.4g} s, phase {results.phase_name[index]}, from {results_path.name}"
            )
            path = Path(fclib_folder) / f"step_{step:07d}.hdf5"
            if is_pure_contact(problem):
                description = (
                    f"{where}; solution by solve_exact (natural residual "
                    f"{natural_residual(problem, multipliers):.1e})"
                )
                written.append(
                    write_fclib(
                        problem,
                        path,
                        solution=multipliers,
                        title=f"{results.scene_name} step {step}",
                        description=description,
                    )
                )
            else:
                fclib = _coulomb_fclib(problem, path, where, tolerance, backend, results.scene_name, step)
                if fclib is not None:
                    written.append(fclib)
    return {"problems": len(written_steps), "fclib": written, "unconverged": unconverged, "output": output}


def _coulomb_fclib(problem, path, where, tolerance, backend, scene_name, step):
    """Write the step's problem with FCLib's law (:func:`coulomb_contacts`) and its exact solution, when it
    has that form, its solve converged, every cap is inactive at the solution and a contact carries load;
    the path written, or None."""
    from refsim.solvers import natural_residual, solve_exact

    converted = coulomb_contacts(problem)
    if converted is None:
        return None
    contact_problem, caps = converted
    solution, report = solve_exact(contact_problem, tolerance=tolerance, backend=backend)
    normal = solution[contact_problem.contacts[:, 0]]
    if not report.converged or np.any(normal >= caps) or not np.any(solution != 0.0):
        return None
    capped = np.isfinite(caps)
    cap_text = (
        f"the step's normal rows are boxes [0, cap] (the puncture force), inactive here: r_n = "
        f"{', '.join(f'{v:.6g}' for v in normal[capped])} N < cap "
        f"{', '.join(f'{c:g}' for c in caps[capped])} N; "
        if capped.any()
        else ""
    )
    description = (
        f"{where}; FCLib's Coulomb law on the step's W, q and mu: {cap_text}the step bounds each tangent "
        f"row by mu r_n (a pyramid), this file by the cone; r solved for the cone by solve_exact (natural "
        f"residual {natural_residual(contact_problem, solution):.1e})"
    )
    return write_fclib(
        contact_problem, path, solution=solution, title=f"{scene_name} step {step}", description=description
    )


def read_problem_set(path) -> list[tuple[int, object, np.ndarray]]:
    """Read a problem-set file: [(step, ConstraintProblem, exact multipliers [N]), ...] in step order.

    Raises
    ------
    ValueError
        When the file is not a refsim problem set.
    """
    import h5py

    from refsim.solvers import ConstraintProblem

    path = Path(path)
    with h5py.File(path, "r") as handle:
        found = handle.attrs.get("format")
        found = found.decode() if isinstance(found, bytes) else found
        if found != PROBLEM_SET_FORMAT:
            raise ValueError(
                f"{path}: not a refsim problem set (format {found!r}, expected {PROBLEM_SET_FORMAT!r})"
            )
        out = []
        for name in sorted(handle["problems"]):
            group = handle["problems"][name]
            fields = {key: group[key][()] for key in _problem_fields() if key in group}
            label = group.attrs.get("name", name)
            problem = ConstraintProblem(
                **fields, name=label.decode() if isinstance(label, bytes) else str(label)
            )
            out.append((int(group.attrs["step"]), problem, group["solution/multipliers"][()]))
    return out


#: Columns of the force CSV and their units.
FORCE_COLUMNS = (
    "step",
    "time_s",
    "phase",
    "force_x_N",
    "force_y_N",
    "force_z_N",
    "axial_N",
    "lateral_N",
    "tip_depth_m",
    "base_x_m",
    "base_y_m",
    "base_z_m",
    "event_force_x_N",
    "event_force_y_N",
    "event_force_z_N",
)


def export_force_csv(results_path, output) -> Path:
    """Write the needle force history of a results file as CSV (columns :data:`FORCE_COLUMNS`; the force of
    the tissue on the needle at the end of each step, its axial component along the base segment and the
    lateral norm, the tip depth from the puncture point, NaN before a puncture; and the force at a
    within-step event, the puncture's give-way (``steps/event_needle_force``: the force profile's peak), NaN
    in the other steps)."""
    from refsim.io.reader import read_results

    results = read_results(results_path)
    axial, lateral = results.axial_lateral_force(results.needle_force)
    depth = results.tip_depth()
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    lines = [",".join(FORCE_COLUMNS)]
    phases = results.phase_name
    for i in range(results.step_count):
        values = [
            f"{results.step[i]:d}",
            f"{results.time[i]:.9g}",
            str(phases[i]),
            *(f"{v:.9g}" for v in results.needle_force[i]),
            f"{axial[i]:.9g}",
            f"{lateral[i]:.9g}",
            f"{depth[i]:.9g}",
            *(f"{v:.9g}" for v in results.base_position[i]),
            *(f"{v:.9g}" for v in results.event_needle_force[i]),
        ]
        lines.append(",".join(values))
    _write_whole(output, lambda temporary: temporary.write_text("\n".join(lines) + "\n", encoding="utf-8"))
    return output


def _tissue_step_indices(results, step: str | int, path) -> list[int]:
    """Indices into the recorded tissue steps for ``step`` (a step number, "last" or "all")."""
    recorded = results.tissue_steps
    if recorded.size == 0:
        raise ValueError(f"{path}: no tissue state is recorded (the run made no step)")
    if str(step) == "all":
        return list(range(recorded.size))
    if str(step) == "last":
        return [recorded.size - 1]
    try:
        number = int(step)
    except ValueError:
        number = None
    found = np.flatnonzero(recorded == number) if number is not None else np.zeros(0, dtype=int)
    if found.size == 0:
        shown = ", ".join(str(int(s)) for s in recorded[:8]) + (", ..." if recorded.size > 8 else "")
        raise ValueError(
            f"{path}: --vtu {step}: not a recorded tissue step; the tissue is recorded at steps {shown} "
            f"(last {int(recorded[-1])}; scene key output.tissue_every); give one of them, last or all"
        )
    return [int(found[0])]


def export_vtu(results_path, step: str | int, folder=None) -> list[Path]:
    """Write the deformed tissue and the cut surface of recorded tissue steps as VTK unstructured grids.

    Parameters
    ----------
    results_path : The results file (.h5).
    step : A recorded tissue step (``tissue/step``), "last", or "all" (every recorded step, and a ParaView
        collection file per object, ``STEM_tissue.pvd``, ``STEM_cut.pvd`` and ``STEM_NAME.pvd`` per
        instrument, with the times).
    folder : Where to write; the results file's folder by default.

    Returns
    -------
    The files written: ``STEM_tissue_NNNNNNN.vtu`` (tetrahedra at the deformed positions [m]; point data
    ``displacement`` [m] from rest, ``fixed`` (1 for a clamped node), ``constraint_force`` [N], the force
    of every needle on the tissue spread on the nodes, refsim.io.xdmf.nodal_constraint_forces); when
    triangles of the cut exist at the step, ``STEM_cut_NNNNNNN.vtu`` (those triangles, every cut point
    mapped into the deformed tissue by equation 4; point data ``created_step``); and for each instrument,
    named by it (``needle`` in a one-needle file; "tissue" and "cut" are reserved instrument names),
    ``STEM_NAME_NNNNNNN.vtu``: its needle's nodes at the step [m] joined by line segments, point data
    ``radius`` [m] (its needle's, for a tube filter) and ``displacement`` [m] from its nodes at t = 0.

    Raises
    ------
    ValueError
        Naming the file and the step when the step is not recorded (listing the recorded ones).
    """
    import meshio

    from refsim.io.reader import read_results
    from refsim.io.xdmf import nodal_constraint_forces

    results_path = Path(results_path)
    results = read_results(results_path)
    indices = _tissue_step_indices(results, step, results_path)
    folder = results_path.parent if folder is None else Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    stem = results_path.stem
    fixed = np.zeros(results.rest_positions.shape[0], dtype=np.int8)
    fixed[results.fixed_nodes] = 1
    cut = results.cut
    needles = _needle_series(results)
    written, series = [], {"tissue": [], "cut": [], **{name: [] for name in results.instrument_names}}
    for index in indices:
        number = int(results.tissue_steps[index])
        time = float(results.tissue_times[index])
        positions = results.tissue_positions[index]
        rows = results.constraints_at(number)
        tissue = meshio.Mesh(
            positions,
            [("tetra", results.tets)],
            point_data={
                "displacement": positions - results.rest_positions,
                "fixed": fixed,
                "constraint_force": nodal_constraint_forces(
                    positions, results.tets, rows.points, rows.directions, rows.forces
                ),
            },
        )
        path = folder / f"{stem}_tissue_{number:07d}.vtu"
        _write_whole(path, lambda temporary, mesh=tissue: meshio.write(temporary, mesh, file_format="vtu"))
        written.append(path)
        series["tissue"].append((time, path))
        for name, mesh in needles(number):
            path = folder / f"{stem}_{name}_{number:07d}.vtu"
            _write_whole(path, lambda temporary, mesh=mesh: meshio.write(temporary, mesh, file_format="vtu"))
            written.append(path)
            series[name].append((time, path))
        if cut is None or cut.tet_indices is None:
            continue
        existing = cut.triangle_step <= number
        if not np.any(existing):
            continue
        corners = results.tets[cut.tet_indices]
        points = np.einsum("pk,pki->pi", cut.barycentric, positions[corners])
        surface = meshio.Mesh(
            points,
            [("triangle", cut.triangles[existing])],
            point_data={"created_step": cut.point_step.astype(np.int64)},
        )
        path = folder / f"{stem}_cut_{number:07d}.vtu"
        _write_whole(path, lambda temporary, mesh=surface: meshio.write(temporary, mesh, file_format="vtu"))
        written.append(path)
        series["cut"].append((time, path))
    if str(step) == "all":
        for name, entries in series.items():
            if entries:
                written.append(_write_pvd(folder / f"{stem}_{name}.pvd", entries))
    return written


def _needle_radii(scene: dict, names: tuple) -> list[float]:
    """Each instrument's needle radius [m] from the scene dict: [needle]'s, or its [[instruments]] table's
    own ``radius`` (NaN when neither is stored)."""
    radius = float((scene.get("needle") or {}).get("radius", np.nan))
    tables = {table.get("name"): table for table in scene.get("instruments") or ()}
    return [float(tables.get(name, {}).get("radius", radius)) for name in names]


def _needle_series(results):
    """A function of a step number giving every instrument's needle at that step as (name, meshio.Mesh):
    its nodes (``steps/needle_positions`` of the step; at step 0, ``needle_rest_nodes``) joined by line
    segments."""
    import meshio

    views = results.instruments
    radii = _needle_radii(results.scene, results.instrument_names)

    def at(number: int) -> list:
        meshes = []
        where = np.flatnonzero(results.step == number)
        for view, radius in zip(views, radii, strict=True):
            rest = view.needle_rest_nodes
            nodes = view.needle_positions[int(where[0])] if where.size else rest
            segments = np.stack([np.arange(rest.shape[0] - 1), np.arange(1, rest.shape[0])], axis=1)
            meshes.append(
                (
                    view.instrument_names[0],
                    meshio.Mesh(
                        nodes,
                        [("line", segments)],
                        point_data={"radius": np.full(rest.shape[0], radius), "displacement": nodes - rest},
                    ),
                )
            )
        return meshes

    return at


def _write_pvd(path: Path, entries: list) -> Path:
    """A ParaView collection file: each (time [s], .vtu path) as one time step."""
    lines = ['<?xml version="1.0"?>', '<VTKFile type="Collection" version="0.1">', "  <Collection>"]
    lines += [f'    <DataSet timestep="{time!r}" part="0" file="{file.name}"/>' for time, file in entries]
    lines += ["  </Collection>", "</VTKFile>"]
    _write_whole(path, lambda temporary: temporary.write_text("\n".join(lines) + "\n", encoding="utf-8"))
    return path


@contextlib.contextmanager
def _renamed_when_complete(temporary: Path, path: Path):
    """The block writes ``temporary``; renamed onto ``path`` when the block completes, removed when it
    raises (an exception or an interrupt): no partial file is left at ``path``."""
    import os

    try:
        yield temporary
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def _write_whole(path: Path, write) -> None:
    """``write(temporary)`` beside ``path``, then renamed onto it: a failed write leaves no partial file."""
    import os

    temporary = path.with_name(f".{path.name}.partial")
    try:
        write(temporary)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
