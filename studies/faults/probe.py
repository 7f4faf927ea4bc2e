"""Probe of bad inputs and faults (issues 10, 24, 25): run every kind, classify what refsim did, print it.

Each kind runs `refsim run` (or a small Python harness that injects a fault and then calls it) in a child
process, on the paper's cube reduced to 3³ cells and a few steps, and is classified:

- **well**: the expected exit code (2 bad input, 3 numerical problem or failed write, 130 SIGINT, 143 SIGTERM,
  0 with the expected warning for inputs refsim repairs or only warns about), a message naming what the case
  expects (the key, the file, the cause), no file after exit 2, a readable file with ``complete = false`` and
  a stored reason after 3, 130 and 143;
- **poorly**: reported, but with another exit code, a message that misses the key, or a file left in a wrong
  state;
- **crashed**: a traceback, an "internal error", or a death by a signal (a segfault);
- **silent**: exit 0 without the expected error or warning (a wrong answer given as a right one), or exit 0
  with a result that fails the case's check of what the file must hold (e.g. the nodes it fixed).

    python studies/faults/probe.py [--markdown table.md] [--only NAME ...] [--tree CHECKOUT]

``--tree`` probes another checkout of refsim (e.g. the issue's 132aab8, unpacked with ``git archive``) with
the same cases, for a before/after comparison.

The table and the counts in docs/faults.md come from this script.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SMALL = ["--set", "mesh.cells=[3, 3, 3]", "--set", "time.duration=0.1", "--set", "output.tissue_every=5"]
FAR = "[[0.00123, 0.00231, 0.39], [0.00123, 0.00231, 0.39], [0.00123, 0.00231, 0.39]]"


@dataclass
class Case:
    """One kind of bad input or fault.

    Attributes
    ----------
    name : Short identifier.
    kind : What is wrong, in words (the table's first column).
    args : Arguments of `refsim run` after the scene ("{dir}" is replaced by the case's folder).
    code : Expected exit code.
    fragments : Texts the message must contain (any case).
    warning : For code 0: a text the warning must contain (a repaired or doubtful input).
    scene : Scene name or path ("{dir}" replaced); cube by default.
    setup : Python code run first with ``folder`` (a pathlib.Path) defined: writes files for the case.
    harness : Python code run instead of the plain command line: it must call ``run(argv)`` (defined for it),
        after injecting its fault.
    signal_after : Send this signal once the results file holds steps (SIGINT, SIGTERM).
    needs_root : Skipped unless run as root (a tmpfs is mounted).
    small : Add the 3³-cell, 10-step overrides.
    argv : The whole command line after ``refsim`` ("{dir}" replaced), instead of ``run SCENE ...``; no
        results file of the case's own is then expected.
    verify : For code 0: a Python expression on ``results`` (the results file read), ``folder`` and ``np``
        that must be true (what the file must hold, e.g. the nodes it fixed).
    keeps_output : The output exists and belongs to another run (a second writer): not "left by bad input".
    no_file : The expected outcome leaves no results file at all (a full disk before the first step).
    tmpfs_size : Size of the tmpfs a needs_root case writes to.
    close_stdout : Close the child's standard output at once (a reader that went away: `| head`).
    """

    name: str
    kind: str
    args: list = field(default_factory=list)
    code: int = 2
    fragments: tuple = ()
    warning: str = ""
    scene: str = "cube"
    setup: str = ""
    harness: str = ""
    signal_after: int | None = None
    needs_root: bool = False
    small: bool = True
    argv: list | None = None
    verify: str = ""
    keeps_output: bool = False
    no_file: bool = False
    tmpfs_size: str = "1m"
    close_stdout: bool = False


def s(text: str) -> list[str]:
    """--set arguments from 'a=b; c=d'."""
    out = []
    for item in text.split(";"):
        out += ["--set", item.strip()]
    return out


MESH_SETUP = textwrap.dedent("""
    import numpy as np, meshio
    from refsim.mesh import box_mesh, write_mesh
    cube = box_mesh(size=(0.1, 0.1, 0.1), cells=(3, 3, 3), origin=(-0.05, -0.05, 0.0))
    positions, tets = np.array(cube.rest_positions), np.array(cube.tets)
    def save(name, positions, tets, fmt=None, cells="tetra"):
        meshio.write(folder / name, meshio.Mesh(positions, [(cells, tets)]), file_format=fmt)
    def truncate(name, fraction=0.6):
        data = (folder / name).read_bytes(); (folder / name).write_bytes(data[: int(len(data) * fraction)])
""")
SCENE_WITH_MESH = textwrap.dedent("""
    text = (Path(refsim.__file__).parent / "scenes" / "cube.toml").read_text()
    (folder / "scene.toml").write_text(text.replace('generator = "box"', f'file = "{folder / MESH}"'))
""")


def mesh_case(
    name: str, kind: str, make: str, code: int = 2, fragments=(), warning: str = "", **extra
) -> Case:
    setup = (
        MESH_SETUP + make + f"\nMESH = {name!r}\nimport refsim\nfrom pathlib import Path\n" + SCENE_WITH_MESH
    )
    return Case(
        name,
        kind,
        code=code,
        fragments=fragments,
        warning=warning,
        scene="{dir}/scene.toml",
        setup=setup,
        **extra,
    )


INJECT = textwrap.dedent("""
    import numpy as np, dataclasses
    from refsim.simulation import Simulation
    original = Simulation.step
    def poisoned(self, state, **kwargs):
        new_state, record = original(self, state, **kwargs)
        if state.step + 1 == 4:
            new_state, record = POISON(self, new_state, record)
        return new_state, record
    Simulation.step = poisoned
""")


RUN_FIRST = textwrap.dedent("""
    import subprocess, sys
    out = folder / 'out.h5'
    subprocess.run([sys.executable, '-m', 'refsim', 'run', 'cube', '--set', 'mesh.cells=[3, 3, 3]', '--set',
                    'time.duration=0.1', '-q', '-o', str(out)], check=True, stdout=subprocess.DEVNULL)
""")


def inject_case(name: str, kind: str, poison: str, fragments=()) -> Case:
    return Case(name, kind, code=3, fragments=fragments, harness=poison + INJECT + "run(ARGV)\n")


CASES = [
    # ---------------------------------------------------------------- scene values (--set)
    Case(
        "string_rigid_modulus",
        "string in a numeric key (rigid needle's modulus)",
        s('needle.youngs_modulus="soft"'),
        fragments=("override --set", "needle.youngs_modulus"),
    ),
    Case(
        "string_spacing",
        "bare word in a numeric key (insertion.spacing=abc)",
        s("insertion.spacing=abc"),
        fragments=("override --set", "insertion.spacing"),
    ),
    Case("string_dt", 'quoted number (time.dt = "0.01")', s('time.dt="0.01"'), fragments=("time.dt",)),
    Case(
        "string_flexible_modulus",
        "string modulus on a flexible needle",
        s('needle.rigid=false; needle.youngs_modulus="soft"'),
        fragments=("needle.youngs_modulus",),
    ),
    Case("negative_radius", "negative needle radius", s("needle.radius=-1"), fragments=("needle.radius",)),
    Case(
        "poisson_half",
        "Poisson's ratio 0.5 (incompressible)",
        s("tissue.poisson_ratio=0.5"),
        fragments=("tissue.poisson_ratio",),
    ),
    Case(
        "density_overflow",
        "tissue density 1e300 (overflow)",
        s("tissue.density=1e300"),
        fragments=("tissue.density",),
    ),
    Case(
        "modulus_overflow",
        "tissue Young's modulus 1e308",
        s("tissue.youngs_modulus=1e308"),
        fragments=("tissue.youngs_modulus",),
    ),
    Case(
        "modulus_zero",
        "tissue Young's modulus 0",
        s("tissue.youngs_modulus=0"),
        fragments=("tissue.youngs_modulus",),
    ),
    Case(
        "element_count_float",
        "non-integer element count",
        s("needle.element_count=16.5"),
        fragments=("needle.element_count",),
    ),
    Case(
        "element_count_zero",
        "zero beam elements",
        s("needle.element_count=0"),
        fragments=("needle.element_count",),
    ),
    Case(
        "cells_two",
        "mesh.cells with 2 numbers",
        s("mesh.cells=[8, 8]"),
        fragments=("mesh.cells",),
        small=False,
    ),
    Case(
        "cells_zero",
        "zero cells along an axis",
        s("mesh.cells=[0, 4, 4]"),
        fragments=("mesh.cells",),
        small=False,
    ),
    Case("rigid_int", "1 for a boolean key", s("needle.rigid=1"), fragments=("needle.rigid",)),
    Case("dt_zero", "dt = 0", s("time.dt=0"), fragments=("time.dt",)),
    Case("dt_nan", "dt = nan", s("time.dt=nan"), fragments=("time.dt",)),
    Case(
        "duration_not_multiple",
        "duration not a multiple of dt",
        s("time.duration=0.105"),
        fragments=("time.duration", "whole number"),
    ),
    Case(
        "duration_short", "duration shorter than dt", s("time.duration=0.001"), fragments=("time.duration",)
    ),
    Case(
        "puncture_zero",
        "f_p = 0 (puncture in the air)",
        s("insertion.puncture_force=0"),
        fragments=("insertion.puncture_force",),
    ),
    Case(
        "puncture_negative",
        "negative f_p",
        s("insertion.puncture_force=-1"),
        fragments=("insertion.puncture_force",),
    ),
    Case(
        "spacing_longer_than_needle",
        "d_i = 1 m for a 0.32 m needle",
        s("insertion.spacing=1"),
        fragments=("insertion.spacing", "needle.length"),
    ),
    Case(
        "radius_wider_than_tissue",
        "needle radius wider than the tissue",
        s("needle.radius=0.06"),
        fragments=("needle.radius",),
    ),
    Case(
        "dt_too_coarse",
        "dt = 0.5 s: the tip jumps the contact zone",
        s("time.dt=0.5; time.duration=2.0"),
        fragments=("time.dt", "contact_distance"),
    ),
    Case(
        "dt_beyond_spacing",
        "dt = 0.1 s: several insertion points per step (warning)",
        s("time.dt=0.1; time.duration=0.3"),
        code=0,
        warning="several insertion points",
    ),
    Case(
        "antiparallel_directions",
        "antiparallel consecutive directions",
        s("trajectory.directions=[[0, 0, -1], [0, 0, 1], [0, 0, 1]]"),
        fragments=("trajectory.directions", "180"),
    ),
    Case(
        "obtuse_directions",
        "directions 95 degrees apart",
        s("trajectory.directions=[[0, 0, -1], [1, 0, 0.1], [1, 0, 0.1]]"),
        fragments=("trajectory.directions",),
    ),
    Case(
        "zero_direction",
        "zero direction",
        s("trajectory.directions=[[0, 0, 0], [0, 0, -1], [0, 0, -1]]"),
        fragments=("trajectory.directions",),
    ),
    Case(
        "times_decreasing",
        "waypoint times not increasing",
        s("trajectory.times=[0, 2, 1]"),
        fragments=("trajectory.times",),
    ),
    Case(
        "positions_rows",
        "base_positions with a missing row",
        s("trajectory.base_positions=[[0, 0, 0.422], [0, 0, 0.403]]"),
        fragments=("trajectory.base_positions",),
    ),
    Case(
        "needle_inside",
        "needle inside the tissue at t = 0",
        s(f"trajectory.base_positions={FAR}"),
        fragments=("inside the tissue",),
    ),
    Case(
        "needle_never_reaches",
        "the needle never comes near the tissue (warning)",
        s("trajectory.base_positions=[[1, 1, 1.5], [1, 1, 1.5], [1, 1, 1.5]]"),
        code=0,
        warning="never comes",
    ),
    Case(
        "unknown_backend",
        "unknown QP backend",
        s('solver.method="exact"; solver.backend="nosuch"'),
        fragments=("solver.backend",),
    ),
    Case(
        "unknown_method", "unknown solver method", s('solver.method="newton"'), fragments=("solver.method",)
    ),
    Case("tolerance_large", "solver tolerance 2", s("solver.tolerance=2"), fragments=("solver.tolerance",)),
    Case(
        "max_iterations_zero",
        "zero solver iterations",
        s("solver.max_iterations=0"),
        fragments=("solver.max_iterations",),
    ),
    Case(
        "unknown_key",
        "unknown key (blamed on the override)",
        s("needle.colour=1"),
        fragments=("override --set", "needle.colour"),
    ),
    Case("unknown_section", "unknown section in an override", s("foo.bar=1"), fragments=("foo",)),
    Case(
        "malformed_override",
        "override without section.key=",
        ["--set", "nonsense"],
        fragments=("section.key=value",),
    ),
    Case(
        "tissue_every_zero",
        "output.tissue_every = 0",
        s("output.tissue_every=0"),
        fragments=("output.tissue_every",),
    ),
    Case(
        "radius_not_below_length",
        "needle radius not below its length",
        s("needle.length=1e-3; needle.radius=1e-3"),
        fragments=("needle.radius",),
    ),
    Case("bad_face", "unknown fixed face", s('mesh.fixed_faces=["top"]'), fragments=("mesh.fixed_faces",)),
    Case("no_fixed_nodes", "no fixed nodes", s("mesh.fixed_faces=[]"), fragments=("fixed",)),
    Case(
        "all_fixed",
        "face tolerance that fixes every node",
        s("mesh.face_tolerance=1"),
        fragments=("mesh.face_tolerance", "every node"),
    ),
    Case(
        "gravity_overflow",
        "gravity 1e300 m/s²",
        s("tissue.gravity=[0, 0, -1e300]"),
        fragments=("tissue.gravity",),
    ),
    Case(
        "mesh_in_millimetres",
        "a tissue 1000 times too large (mesh in mm read as m: warning)",
        s("mesh.size=[100, 100, 100]; mesh.origin=[-50, -50, -100.3]"),
        code=0,
        warning="millimetres",
    ),
    # ---------------------------------------------------------------- scene files
    Case(
        "scene_missing", "scene file missing", scene="{dir}/none.toml", fragments=("none.toml", "not found")
    ),
    Case(
        "scene_unknown_name",
        "neither a file nor a built-in scene",
        scene="no_such_scene",
        fragments=("neither a scene file",),
    ),
    Case(
        "scene_bad_toml",
        "invalid TOML",
        scene="{dir}/bad.toml",
        setup="(folder / 'bad.toml').write_text('[mesh\\n')",
        fragments=("bad.toml", "not valid TOML"),
    ),
    Case(
        "scene_missing_key",
        "required key missing in the file",
        scene="{dir}/scene.toml",
        setup="import refsim\nfrom pathlib import Path\n(folder / "
        "'scene.toml').write_text((Path(refsim.__file__).parent"
        " / 'scenes' / 'cube.toml').read_text().replace('puncture_force = 0.8', ''))",
        fragments=("scene.toml", "insertion.puncture_force"),
    ),
    Case(
        "scene_missing_section",
        "section missing in the file",
        scene="{dir}/scene.toml",
        setup="import refsim, re\nfrom pathlib import Path\ntext = (Path(refsim.__file__).parent / 'scenes' "
        "/ "
        "'cube.toml').read_text()\n(folder / 'scene.toml').write_text(text.split('[solver]')[0])",
        fragments=("missing section [solver]",),
    ),
    Case(
        "string_in_file",
        "a string in a numeric key of the file",
        scene="{dir}/scene.toml",
        setup="import refsim\nfrom pathlib import Path\n(folder / "
        "'scene.toml').write_text((Path(refsim.__file__)."
        "parent / 'scenes' / 'cube.toml').read_text().replace('dt = 0.01', 'dt = \"0.01\"'))",
        fragments=("scene.toml", "time.dt"),
    ),
    # ---------------------------------------------------------------- meshes
    mesh_case("missing.vtu", "mesh file missing", "", fragments=("missing.vtu", "does not exist")),
    mesh_case(
        "cut.vtu",
        "truncated .vtu",
        "save('cut.vtu', positions, tets); truncate('cut.vtu')",
        fragments=("cut.vtu", "truncated"),
    ),
    mesh_case(
        "cut22.msh",
        "truncated Gmsh 2.2",
        "save('cut22.msh', positions, tets, 'gmsh22'); truncate('cut22.msh')",
        fragments=("cut22.msh", "truncated"),
    ),
    mesh_case(
        "cut41.msh",
        "truncated Gmsh 4.1",
        "save('cut41.msh', positions, tets, 'gmsh'); truncate('cut41.msh', 0.9)",
        fragments=("cut41.msh", "truncated"),
    ),
    mesh_case(
        "garbage.vtk",
        "random bytes as a mesh",
        "(folder / 'garbage.vtk').write_bytes(np.random.default_rng(0).integers(0, 256, 999, "
        "dtype=np.uint8).tobytes())",
        fragments=("garbage.vtk",),
    ),
    mesh_case(
        "empty.vtu", "empty mesh file", "(folder / 'empty.vtu').write_bytes(b'')", fragments=("empty",)
    ),
    mesh_case(
        "loose.vtu",
        "unmerged duplicate nodes (merged: warning)",
        "p = positions[tets].reshape(-1, 3); save('loose.vtu', p, np.arange(len(p)).reshape(-1, 4))",
        code=0,
        warning="merged",
    ),
    mesh_case(
        "inverted.vtu",
        "inverted tetrahedra (fixed: warning)",
        "t = tets.copy(); t[::2] = t[::2][:, [0, 1, 3, 2]]; save('inverted.vtu', positions, t)",
        code=0,
        warning="orientation",
    ),
    mesh_case(
        "flat.vtu",
        "a degenerate (zero-volume) tetrahedron",
        "save('flat.vtu', positions, np.vstack([tets, [[0, 1, 2, 2]]]))",
        fragments=("degenerate",),
    ),
    mesh_case(
        "nan.vtu",
        "NaN node coordinate",
        "p = positions.copy(); p[3, 1] = np.nan; save('nan.vtu', p, tets)",
        fragments=("non-finite",),
    ),
    mesh_case(
        "index.vtu",
        "node index out of range",
        "t = tets.copy(); t[0, 0] = len(positions) + 3; save('index.vtu', positions, t)",
        fragments=("out of range",),
    ),
    mesh_case(
        "surface.vtu",
        "surface mesh only (no tetrahedra)",
        "save('surface.vtu', positions, tets[:, :3], cells='triangle')",
        fragments=("no tetrahedra",),
    ),
    mesh_case(
        "overlap.vtu",
        "duplicated elements (a face shared by 3 tets)",
        "save('overlap.vtu', positions, np.vstack([tets, tets[:1]]))",
        fragments=("more than two",),
    ),
    # ---------------------------------------------------------------- trajectory files
    Case(
        "csv_missing",
        "trajectory CSV missing",
        scene="{dir}/scene.toml",
        setup="import refsim\nfrom pathlib import Path\nt = (Path(refsim.__file__).parent / 'scenes' / "
        "'cube.toml')"
        ".read_text()\nimport re\nt = re.sub(r'times = .*?\\ndirections = [^\\n]*\\n', 'file = "
        '"none.csv"\\n\', t,'
        " flags=re.S)\n(folder / 'scene.toml').write_text(t)",
        fragments=("none.csv",),
    ),
    Case(
        "csv_antiparallel",
        "trajectory CSV with antiparallel directions",
        scene="{dir}/scene.toml",
        setup="import refsim\nfrom pathlib import Path\nt = (Path(refsim.__file__).parent / 'scenes' / "
        "'cube.toml')"
        ".read_text()\nimport re\nt = re.sub(r'times = .*?\\ndirections = [^\\n]*\\n', 'file = "
        '"robot.csv"\\n\', t,'
        " flags=re.S)\n(folder / 'scene.toml').write_text(t)\n(folder / 'robot.csv').write_text("
        "'0,0.00123,0.00231,0.422,0,0,-1\\n1,0.00123,0.00231,0.41,0,0,1\\n')",
        fragments=("robot.csv", "180"),
    ),
    Case(
        "csv_text",
        "trajectory CSV with text",
        scene="{dir}/scene.toml",
        setup="import refsim\nfrom pathlib import Path\nt = (Path(refsim.__file__).parent / 'scenes' / "
        "'cube.toml')"
        ".read_text()\nimport re\nt = re.sub(r'times = .*?\\ndirections = [^\\n]*\\n', 'file = "
        '"robot.csv"\\n\', t,'
        " flags=re.S)\n(folder / 'scene.toml').write_text(t)\n(folder / "
        "'robot.csv').write_text('a,b\\nc,d\\n')",
        fragments=("robot.csv",),
    ),
    # ---------------------------------------------------------------- output paths
    Case(
        "output_exists",
        "results file exists, no --overwrite",
        setup="(folder / 'out.h5').write_bytes(b'keep')",
        fragments=("--overwrite",),
    ),
    Case(
        "output_parent_file",
        "parent of -o is a file",
        args=["-o", "{dir}/afile/out.h5"],
        setup="(folder / 'afile').write_text('x')",
        fragments=("afile is a file, not a folder",),
    ),
    Case("output_directory", "-o is a directory", args=["-o", "{dir}"], fragments=("is a directory",)),
    Case(
        "figure_suffix",
        "--figure that is not a picture",
        args=["--figure", "{dir}/plot.txt"],
        fragments=("--figure",),
    ),
    Case(
        "figure_parent_file",
        "--figure in a folder that is a file",
        args=["--figure", "{dir}/afile/p.png"],
        setup="(folder / 'afile').write_text('x')",
        fragments=("afile is a file",),
    ),
    # ---------------------------------------------------------------- during the run
    Case(
        "sigint",
        "Ctrl-C (SIGINT) during the run",
        s("time.duration=20.0"),
        code=130,
        signal_after=signal.SIGINT,
        fragments=("SIGINT",),
    ),
    Case(
        "sigterm",
        "SIGTERM during the run",
        s("time.duration=20.0"),
        code=143,
        signal_after=signal.SIGTERM,
        fragments=("SIGTERM",),
    ),
    Case(
        "disk_full",
        "full disk (a 1 MiB tmpfs)",
        s("mesh.cells=[4, 4, 4]; time.duration=2.2; output.tissue_every=1"),
        code=3,
        fragments=("space",),
        needs_root=True,
        small=False,
    ),
    Case(
        "write_error",
        "a write error from HDF5 (injected OSError)",
        code=3,
        fragments=("Input/output",),
        harness="from refsim.io.writer import ResultWriter\noriginal = ResultWriter._append\n"
        "def failing(self, path, values):\n    if self._steps_completed >= 4 and path == 'steps/time':\n"
        "        raise OSError(5, 'Input/output error')\n    return original(self, path, values)\n"
        "ResultWriter._append = failing\nfrom refsim.io import writer\nwriter.DEFAULT_BUFFER_STEPS = 2\n"
        "run(ARGV)\n",
    ),
    inject_case(
        "singular",
        "singular factorisation (scipy: Factor is exactly singular)",
        "def POISON(self, state, record):\n    raise RuntimeError('Factor is exactly singular')\n",
        fragments=("singular",),
    ),
    inject_case(
        "nan_tissue",
        "NaN in the tissue positions",
        "def POISON(self, state, record):\n    t = dataclasses.replace(state.tissue, "
        "positions=state.tissue.positions"
        " * np.nan)\n    return dataclasses.replace(state, tissue=t), record\n",
        fragments=("non-finite",),
    ),
    inject_case(
        "inf_force",
        "infinite force on the needle",
        "def POISON(self, state, record):\n    return state, dataclasses.replace(record, "
        "needle_force=np.array("
        "[np.inf, 0, 0]))\n",
        fragments=("non-finite",),
    ),
    inject_case(
        "overflow_positions",
        "overflowing (finite, 1e200) needle positions",
        "def POISON(self, state, record):\n    return state, dataclasses.replace(record, needle_positions="
        "record.needle_positions * 1e200)\n",
        fragments=("overflowing",),
    ),
    inject_case(
        "diverging_tissue",
        "a tissue thrown 1000 times its size (finite)",
        "def POISON(self, state, record):\n    t = dataclasses.replace(state.tissue, "
        "positions=state.tissue.positions"
        " * 1e3)\n    return dataclasses.replace(state, tissue=t), record\n",
        fragments=("diverges",),
    ),
    inject_case(
        "diverged_report",
        "a solver report that says diverged",
        "class R:\n    iterations, residual, converged, seconds, diverged, message = 5, 1e30, False, 0.0, "
        "True, 'x'\n"
        "def POISON(self, state, record):\n    return state, dataclasses.replace(record, solver=R())\n",
        fragments=("diverged",),
    ),
    Case(
        "gauss_seidel_infeasible",
        "Gauss–Seidel on an infeasible problem (W = ones(2, 2), δ_free = (1, −1))",
        code=3,
        fragments=("diverge",),
        harness="import numpy as np, sys\nfrom refsim.solvers import ConstraintProblem, solve_gauss_seidel\n"
        "p = ConstraintProblem(compliance=np.ones((2, 2)), free_gap=np.array([1.0, -1.0]), bilateral="
        "np.array([0, 1]))\nlam, report = solve_gauss_seidel(p, tolerance=1e-8, max_iterations=100000)\n"
        "if report.converged:\n    print('converged', report.residual)\n    sys.exit(0)\n"
        "print('refsim: not converged:', getattr(report, 'message', ''), 'diverged' if getattr(report, "
        "'diverged', False) else '', file=sys.stderr)\nsys.exit(3)\n",
    ),
    # ================================================================ issue 25
    # ---------------------------------------------------------------- boundary conditions
    Case(
        "fixed_nodes_negative",
        "a negative fixed-node index (Python's indexing pinned the last node)",
        s("mesh.fixed_faces=[]; mesh.fixed_nodes=[-1, 0, 1, 4]"),
        fragments=("mesh.fixed_nodes", "-1"),
    ),
    Case(
        "fixed_nodes_float",
        "a non-integer fixed-node index (was truncated)",
        s("mesh.fixed_faces=[]; mesh.fixed_nodes=[1.5, 0, 4, 16]"),
        fragments=("mesh.fixed_nodes", "1.5"),
    ),
    mesh_case(
        "renumbered.vtu",
        "mesh.fixed_nodes in the file's numbering, the reader drops an unused node and renumbers",
        "p = np.vstack([[[1.0, 1.0, 1.0]], positions]); save('renumbered.vtu', p, tets + 1)",
        code=0,
        warning="renumbered",
        args=s("mesh.fixed_faces=[]; mesh.fixed_nodes=[" + ", ".join(str(i) for i in range(1, 17)) + "]"),
        verify="np.all(results.rest_positions[results.fixed_nodes][:, 2] == 0.0) and "
        "results.fixed_nodes.size == 16",
    ),
    mesh_case(
        "loose_part.vtu",
        "a second tissue part that nothing holds (it floats or falls)",
        "c = box_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2), origin=(-0.05, -0.05, 0.0)); "
        "p = np.vstack([positions, np.asarray(c.rest_positions) + [0.2, 0.0, 0.05]]); "
        "save('loose_part.vtu', p, np.vstack([tets, np.asarray(c.tets) + len(positions)]))",
        fragments=("part 2", "no held node"),
    ),
    Case(
        "held_by_one_node",
        "the tissue held by one node (free to spin about it)",
        s("mesh.fixed_faces=[]; mesh.fixed_nodes=[0]"),
        fragments=("held node",),
    ),
    mesh_case(
        "tangled.vtu",
        "a tangled mesh (a node moved through a face) 'fixed' by swapping nodes",
        "p = positions.copy(); c = [-0.05 + 0.1 / 3, -0.05 + 0.1 / 3, 0.1 / 3]; "
        "i = int(np.flatnonzero(np.all(np.isclose(p, c), axis=1))[0]); p[i, 0] += 0.05; "
        "save('tangled.vtu', p, tets)",
        fragments=("tangled",),
    ),
    mesh_case(
        "one_tet.vtu",
        "a mesh of one tetrahedron whose lowest face is one node (held by that node only)",
        "save('one_tet.vtu', np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.05], [0.0, 0.1, 0.05], "
        "[0.05, 0.05, 0.1]]), np.array([[0, 1, 2, 3]]))",
        fragments=("held node",),
    ),
    Case(
        "cells_at_maximum",
        "mesh.cells at its documented maximum (256³ cells, 100 million tetrahedra)",
        s("mesh.cells=[256, 256, 256]"),
        fragments=("mesh.cells", "GiB"),
        small=False,
    ),
    Case(
        "spacing_below_memory",
        "insertion.spacing = 1e-9 m (a dense compliance of 10^14 rows squared)",
        s("insertion.spacing=1e-9"),
        fragments=("insertion.spacing", "GiB"),
    ),
    Case(
        "dt_below_roundoff",
        "time.dt = 1e-300 s (below round-off)",
        s("time.dt=1e-300; time.duration=1e-300"),
        fragments=("time.dt",),
        small=False,
    ),
    # ---------------------------------------------------------------- boundary motions
    Case(
        "boundary_jump",
        "a boundary CSV that moves the clamped face 5 cm in one step",
        s(
            'mesh.fixed_faces=[]; boundary.motion="file"; boundary.box=[[-1, -1, -1], [1, 1, 0.001]]; '
            'boundary.file="{dir}/motion.csv"'
        ),
        setup="(folder / 'motion.csv').write_text('t,dx,dy,dz\\n0,0,0,0\\n0.05,0,0,0\\n0.06,0,0,0.05\\n')",
        fragments=("boundary", "contact_distance"),
    ),
    Case(
        "boundary_oscillation",
        "a boundary CSV oscillating 2.5 cm faster than the steps",
        s(
            'mesh.fixed_faces=[]; boundary.motion="file"; boundary.box=[[-1, -1, -1], [1, 1, 0.001]]; '
            'boundary.file="{dir}/motion.csv"'
        ),
        setup="(folder / 'motion.csv').write_text('t,dx,dy,dz\\n' + ''.join(f'{0.005 * k},0,0,"
        "{0.0 if k % 2 == 0 else 0.025}\\n' for k in range(21)))",
        fragments=("boundary.file",),
    ),
    Case(
        "boundary_period_dt",
        "a periodic boundary motion whose period is dt (aliased to zero motion)",
        s(
            'mesh.fixed_faces=[]; boundary.motion="periodic"; boundary.box=[[-1, -1, -1], [1, 1, 0.001]]; '
            "boundary.amplitude=[0, 0, 0.01]; boundary.period=0.01"
        ),
        fragments=("boundary.period",),
    ),
    Case(
        "boundary_amplitude_huge",
        "a boundary amplitude of 1e300 m",
        s(
            'mesh.fixed_faces=[]; boundary.motion="periodic"; boundary.box=[[-1, -1, -1], [1, 1, 0.001]]; '
            "boundary.amplitude=[0, 0, 1e300]"
        ),
        fragments=("boundary.amplitude",),
    ),
    # ---------------------------------------------------------------- two writers, one file
    Case(
        "second_writer",
        "a second run with --overwrite on a file another run is writing",
        code=2,
        fragments=("is writing",),
        keeps_output=True,
        harness="import subprocess, time, h5py\nfrom pathlib import Path\n"
        "out = Path(ARGV[ARGV.index('-o') + 1])\n"
        "first = subprocess.Popen([sys.executable, '-m', 'refsim', 'run', 'cube', '--set', "
        "'mesh.cells=[3, 3, 3]', '--set', 'time.duration=4.0', '-q', '-o', str(out)], "
        "stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)\n"
        "for _ in range(600):\n    time.sleep(0.2)\n    try:\n"
        "        with h5py.File(out, 'r', locking=False) as f:\n"
        "            if int(f.attrs['steps_completed']) >= 32: break\n    except Exception: pass\n"
        "try:\n    code = main(ARGV + ['--overwrite'])\nexcept SystemExit as e:\n    code = e.code\n"
        "first_code = first.wait()\nfrom refsim.io import read_results\n"
        "try:\n    ok = read_results(out).complete and first_code == 0\nexcept Exception as e:\n"
        "    ok = False; print('the first run lost its file:', e, file=sys.stderr)\n"
        "if not ok:\n"
        "    print(f'the first run ended with exit {first_code} and a damaged file', file=sys.stderr)\n"
        "sys.exit(code if ok else 99)\n",
    ),
    Case(
        "study_replaces_file",
        "refsim study -o FILE on an existing results file, without --overwrite",
        argv=["study", "cube", "--sweep", "insertion.spacing=2e-3,1e-3", "-o", "{dir}/keep.h5", "-q"],
        setup="(folder / 'keep.h5').write_bytes(b'a results file')",
        fragments=("keep.h5", "--overwrite"),
        verify="(folder / 'keep.h5').read_bytes() == b'a results file'",
    ),
    # ---------------------------------------------------------------- a full disk, signals and pipes
    Case(
        "disk_full_before_first_step",
        "full disk before the first step (a 64 KiB tmpfs)",
        code=3,
        fragments=("out.h5", "space"),
        needs_root=True,
        no_file=True,
        tmpfs_size="64k",
    ),
    Case(
        "sighup",
        "SIGHUP during the run (a closed terminal, a dropped ssh)",
        s("time.duration=20.0"),
        code=129,
        signal_after=signal.SIGHUP,
        fragments=("SIGHUP",),
    ),
    Case(
        "broken_pipe",
        "refsim run ... | head: the reader closes the pipe",
        code=0,
        close_stdout=True,
        verify="results.complete and (folder / 'out.xdmf').is_file()",
    ),
    # ---------------------------------------------------------------- studies
    Case(
        "study_workers_negative",
        "refsim study --workers -1",
        argv=[
            "study",
            "cube",
            "--sweep",
            "insertion.spacing=2e-3,1e-3",
            "-o",
            "{dir}/s.h5",
            "--workers",
            "-1",
        ],
        fragments=("--workers",),
    ),
    Case(
        "study_unreachable_scheduler",
        "refsim study --scheduler that cannot be reached",
        argv=[
            "study",
            "cube",
            "--sweep",
            "insertion.spacing=2e-3,1e-3",
            "-o",
            "{dir}/s.h5",
            "--scheduler",
            "tcp://127.0.0.1:9",
            "-q",
        ],
        fragments=("--scheduler", "127.0.0.1:9"),
    ),
    Case(
        "study_name_absolute",
        "a study file whose name is an absolute path (writes anywhere)",
        argv=["study", "{dir}/study.toml", "--workers", "1", "-q", "--no-warm-up"],
        setup='(folder / \'study.toml\').write_text(f\'name = "{folder}/elsewhere/x"\\nscene = "cube"\\n'
        '[[case]]\\nlabel = "a"\\nset = ["mesh.cells=[2, 2, 2]"]\\n\')',
        fragments=("name",),
    ),
    Case(
        "study_failed_run",
        "a study whose one run fails (which one?)",
        argv=["study", "{dir}/study.toml", "-o", "{dir}/s.h5", "--workers", "1", "-q", "--no-warm-up"],
        setup='(folder / \'study.toml\').write_text(\'name = "small"\\nscene = "cube"\\nset = '
        '["mesh.cells=[2, 2, 2]", "time.duration=0.1"]\\n[[case]]\\nlabel = "bad spacing"\\n'
        'set = ["insertion.spacing=-1.0"]\\n\')',
        code=3,
        fragments=("bad spacing", "insertion.spacing"),
    ),
    # ---------------------------------------------------------------- results you cannot trust
    Case(
        "bit_flip",
        "a bit flip in a results file, exported",
        argv=["export", "{dir}/out.h5", "--csv", "{dir}/force.csv"],
        setup=RUN_FIRST + "import h5py\nwith h5py.File(out, 'r') as f:\n"
        "    offset = f['steps/needle_force'].id.get_chunk_info(0).byte_offset\n"
        "data = bytearray(out.read_bytes()); data[offset + 3] ^= 0x10; out.write_bytes(bytes(data))\n",
        fragments=("steps/needle_force", "damaged"),
    ),
    Case(
        "steps_completed_negative",
        "steps_completed = -3 in a results file",
        argv=["export", "{dir}/out.h5", "--csv", "{dir}/force.csv"],
        setup=RUN_FIRST
        + "import h5py\nwith h5py.File(out, 'r+') as f:\n    f.attrs['steps_completed'] = -3\n",
        fragments=("steps_completed",),
    ),
    Case(
        "truncated_results",
        "a truncated results file (a copy cut short)",
        argv=["export", "{dir}/out.h5", "--csv", "{dir}/force.csv"],
        setup=RUN_FIRST + "data = out.read_bytes(); out.write_bytes(data[: len(data) // 2])\n",
        fragments=("the file is truncated", "bytes of the"),
    ),
    # ---------------------------------------------------------------- lengths at the float edge, keys unused
    Case(
        "radius_underflow",
        "needle radius 1e-300 m (its section underflows)",
        s("needle.radius=1e-300; insertion.interference=0.0"),
        fragments=("needle.radius", "round-off"),
    ),
    Case(
        "radius_below_resolution",
        "needle radius 1e-14 m (below what the positions resolve)",
        s("needle.radius=1e-14; insertion.interference=0.0"),
        fragments=("needle.radius", "expected a length >="),
    ),
    Case(
        "cut_spacing_underflow",
        "cutting.point_spacing = 1e-300 m",
        s("cutting.point_spacing=1e-300"),
        scene="cube_cut",
        fragments=("cutting.point_spacing", "round-off"),
    ),
    Case(
        "cut_spacing_memory",
        "cutting.point_spacing = 1e-9 m (a cut of 1e5 samples per 0.1 mm)",
        s("cutting.point_spacing=1e-9"),
        scene="cube_cut",
        fragments=("cutting.point_spacing", "GiB"),
    ),
    Case(
        "contact_distance_overflow",
        "insertion.contact_distance = 1e300 m",
        s("insertion.contact_distance=1e300"),
        fragments=("insertion.contact_distance", "1000 m"),
    ),
    Case(
        "standoff_overflow",
        "trajectory.standoff = 1e300 m",
        s("trajectory.standoff=1e300"),
        fragments=("trajectory.standoff",),
    ),
    Case(
        "boundary_file_without_motion",
        "[boundary] file = ... without motion = 'file' (ran with no motion)",
        s('boundary.file="breathing.csv"'),
        fragments=("boundary.file", "motion = 'file'"),
    ),
    Case(
        "boundary_amplitude_without_motion",
        "[boundary] amplitude without a motion",
        s("boundary.amplitude=[0.0, 0.0, 0.01]"),
        fragments=("boundary.amplitude", "motion = 'periodic'"),
    ),
]


HARNESS_PREFIX = textwrap.dedent("""
    import sys
    from refsim.cli import main
    def run(argv):
        sys.exit(main(argv))
""")


def _command(case: Case, folder: Path) -> tuple[list[str], Path]:
    if case.argv is not None:
        argv = [a.replace("{dir}", str(folder)) for a in case.argv]
        return [sys.executable, "-m", "refsim", *argv], folder / "__no_results_file__.h5"
    output = folder / "out.h5"
    scene = case.scene.replace("{dir}", str(folder))
    args = [a.replace("{dir}", str(folder)) for a in case.args]
    argv = ["run", scene, *(SMALL if case.small else []), *args, "-q"]
    if "-o" not in args:
        argv += ["-o", str(output)]
    else:
        output = Path(args[args.index("-o") + 1])
    if case.harness:
        code = HARNESS_PREFIX + f"ARGV = {json.dumps(argv)}\n" + case.harness
        return [sys.executable, "-c", code], output
    return [sys.executable, "-m", "refsim", *argv], output


def _wait_for_steps(path: Path, count: int, process: subprocess.Popen, timeout: float = 300.0) -> None:
    import h5py

    start = time.monotonic()
    while time.monotonic() - start < timeout and process.poll() is None:
        if path.exists():
            try:
                with h5py.File(path, "r", locking=False) as handle:
                    if int(handle.attrs["steps_completed"]) >= count:
                        return
            except (OSError, KeyError):
                pass
        time.sleep(0.2)


def _file_state(path: Path) -> dict | None:
    """complete, stop_reason, steps of a results file (None when absent; 'unreadable' when it cannot be
    read)."""
    if not path.exists() or path.is_dir():
        return None
    try:
        from refsim.io import read_results

        results = read_results(path)
        return {"complete": results.complete, "reason": results.stop_reason, "steps": results.step_count}
    except Exception as error:  # noqa: BLE001
        return {"unreadable": f"{type(error).__name__}: {error}"}


def _terminal_signals() -> None:
    """In the child: SIGHUP as in a terminal session (its default action), also under a nohup probe."""
    signal.signal(signal.SIGHUP, signal.SIG_DFL)


def run_case(case: Case, folder: Path, tree: Path = ROOT) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree), "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    if case.setup:
        subprocess.run(
            [
                sys.executable,
                "-c",
                f"from pathlib import Path\nfolder = Path({str(folder)!r})\n" + case.setup,
            ],
            check=True,
            env=env,
            cwd=folder,
        )
    mounted = False
    if case.needs_root:
        if os.geteuid() != 0:
            return {"verdict": "not run", "code": None, "message": "needs root (a tmpfs)"}
        disk = folder / "disk"
        disk.mkdir()
        mount = ["mount", "-t", "tmpfs", "-o", f"size={case.tmpfs_size}", "tmpfs", str(disk)]
        if subprocess.run(mount).returncode != 0:
            return {"verdict": "not run", "code": None, "message": "cannot mount a tmpfs"}
        mounted = True
        case = Case(**{**case.__dict__, "args": [*case.args, "-o", str(disk / "out.h5")]})
    preexisting = {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}
    command, output = _command(case, folder)
    try:
        process = subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            cwd=folder,
            preexec_fn=_terminal_signals,
        )
        if case.close_stdout:
            process.stdout.close()  # the reader went away (`| head`): the child's writes meet a closed pipe
            error = process.stderr.read()
            process.wait(timeout=900)
            out = ""
        else:
            if case.signal_after is not None:
                _wait_for_steps(output, 32, process)
                process.send_signal(case.signal_after)
            out, error = process.communicate(timeout=900)
        state = _file_state(output)
        verified = _verify(case, output, folder)
        leftovers = (
            sorted(p.name for p in output.parent.iterdir() if p.name != "disk") if case.no_file else []
        )
    finally:
        if mounted:
            subprocess.run(["umount", str(folder / "disk")])
    code = process.returncode
    return {
        **classify(case, code, out, error, state, output, preexisting, verified, leftovers),
        "code": code,
        "message": _first_message(error, out),
    }


def _verify(case: Case, output: Path, folder: Path) -> bool | None:
    """The case's check of what the file holds (None when it has none); False when it fails or errors."""
    if not case.verify:
        return None
    import numpy as np

    try:
        from refsim.io import read_results

        results = read_results(output) if output.is_file() else None
        return bool(eval(case.verify, {"np": np, "results": results, "folder": folder}))  # noqa: S307
    except Exception:  # noqa: BLE001 - a check that cannot run is a failed check
        return False


def _first_message(error: str, out: str) -> str:
    lines = [line for line in error.splitlines() if line.strip() and not line.startswith("[")]
    important = [line for line in lines if "error" in line.lower() or "refsim" in line or "WARNING" in line]
    text = (important or lines or out.splitlines()[-1:] or [""])[0]
    return text.replace("|", "\\|").strip()[:240]


def _mentions(text: str, fragment: str) -> bool:
    """``fragment`` in ``text``; a key "section.key" also counts as named when written "[section] key"."""
    if fragment in text:
        return True
    section, dot, key = fragment.partition(".")
    return bool(dot) and " " not in fragment and f"[{section}] {key}" in text


def classify(
    case: Case,
    code: int,
    out: str,
    error: str,
    state,
    output: Path,
    preexisting: dict,
    verified: bool | None = None,
    leftovers: list | None = None,
) -> dict:
    text = error + out
    handled = (130, 143, 129) if case.code == 129 else (130, 143)
    if code < 0 or code >= 128 and code not in handled or "Traceback" in text or "internal error" in text:
        return {"verdict": "crashed"}
    if code == 0 and case.code != 0:
        return {"verdict": "silent"}
    if code == 0 and case.warning and case.warning not in text:
        return {"verdict": "silent"}
    if code == 0 and verified is False:
        return {"verdict": "silent", "problems": "exit 0, but the file fails the case's check"}
    problems = []
    if code != case.code:
        problems.append(f"exit {code}, expected {case.code}")
    missing = [f for f in case.fragments if not _mentions(text, f)]
    if missing:
        problems.append(f"message lacks {missing}")
    if code == 2 and output.name not in preexisting and state is not None and not case.keeps_output:
        problems.append("a results file was left after a bad input")
    if code != 0 and verified is False:
        problems.append("the case's check of the files failed")
    if case.no_file and leftovers:
        problems.append(f"files left: {', '.join(leftovers)}")
    if code == 2 and output.name in preexisting and output.read_bytes() != preexisting[output.name]:
        problems.append("an existing file was changed")
    file_expected = case.argv is None and not case.no_file and not case.keeps_output
    if (
        code in (3, 129, 130, 143)
        and file_expected
        and not case.harness.startswith("import numpy as np, sys")
    ):
        if state is None or "unreadable" in state:
            problems.append(f"results file missing or unreadable ({state})")
        elif state["complete"] or not state["reason"]:
            problems.append("the file says complete or gives no reason")
    return {"verdict": "poorly" if problems else "well", "problems": "; ".join(problems)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--markdown", help="also write the table as Markdown to this file")
    parser.add_argument("--only", nargs="*", help="run only these cases (names)")
    parser.add_argument("--tree", default=str(ROOT), help="the refsim checkout to probe (default: this one)")
    args = parser.parse_args(argv)
    cases = [c for c in CASES if not args.only or c.name in args.only]
    rows = []
    for index, case in enumerate(cases, 1):
        with tempfile.TemporaryDirectory(prefix=f"probe_{case.name}_") as folder:
            start = time.perf_counter()
            result = run_case(case, Path(folder), Path(args.tree))
            result["seconds"] = time.perf_counter() - start
        rows.append((case, result))
        print(
            f"{index:3d}/{len(cases)} {case.name:28s} exit {str(result['code']):>4s}  {result['verdict']:8s} "
            f"{result.get('problems', '')}  | {result['message'][:110]}",
            flush=True,
        )
    counts = {
        verdict: sum(1 for _, r in rows if r["verdict"] == verdict)
        for verdict in ("well", "poorly", "crashed", "silent", "not run")
    }
    summary = ", ".join(f"{count} {verdict}" for verdict, count in counts.items())
    print(f"{len(rows)} kinds: {summary}")
    if args.markdown:
        lines = [
            "| # | kind of bad input or fault | expected | exit | verdict | what refsim says |",
            "|---|---|---|---|---|---|",
        ]
        for index, (case, result) in enumerate(rows, 1):
            expected = f"{case.code}" + (" + warning" if case.warning else "")
            note = result["message"] + (f" ({result['problems']})" if result.get("problems") else "")
            lines.append(
                f"| {index} | {case.kind.replace('|', chr(92) + '|')} | {expected} | {result['code']} | "
                f"{result['verdict']} | {note} |"
            )
        lines += ["", f"**{len(rows)} kinds: {summary}.**"]
        Path(args.markdown).write_text("\n".join(lines) + "\n", encoding="utf-8")
    return 0 if counts["poorly"] + counts["crashed"] + counts["silent"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
