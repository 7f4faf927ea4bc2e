"""The reference set end to end at the coarse level: the build through the study machinery (a one-worker
LocalCluster), the package (manifest, checksums, HDF5, CSV), ``refsim compare`` on refsim's own runs, on a
coarse run, and on runs made 2 % stiffer on purpose, and its errors for bad input."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from refsim.cli import EXIT_FAILED, EXIT_INPUT, main
from refsim.io.export import read_problem_set
from refsim.reference import (
    build_reference,
    case_names,
    case_values,
    check_manifest,
    compare,
    load_case,
    read_case_reference,
    read_their_csv,
    reference_value,
    write_their_csv,
)
from refsim.reference.page import write_page
from refsim.scene import load_scene
from refsim.solvers import natural_residual
from refsim.sweep.convergence import ROUNDOFF

CASES = ["cantilever", "puncture"]


@pytest.fixture(scope="module")
def package(tmp_path_factory):
    folder = tmp_path_factory.mktemp("reference") / "package"
    manifest = build_reference(folder, level="coarse", cases=CASES, workers=1, command="test")
    return folder, manifest


def _run_files(folder, case: str) -> list:
    import h5py

    with h5py.File(folder / "cases" / case / "reference.h5", "r") as handle:
        return [folder / "cases" / case / name.decode() for name in handle["runs"][()]]


# ---------------------------------------------------------------------- the uncertainty


def test_reference_value_on_manufactured_sequences():
    h = np.array([0.5, 0.25, 0.125])
    f1, f2 = 1.0 + h[2] ** 2, 1.0 + h[1] ** 2
    # monotone at the formal order 2: f = 1 + h²; Richardson recovers 1, U = 1.25 |f1 - f2| / (2² - 1)
    answer = reference_value(h, 1.0 + h**2, formal_order=2.0)
    assert answer["method"] == "richardson" and answer["safety_factor"] == 1.25
    assert answer["value"] == pytest.approx(1.0, abs=1e-12)
    assert answer["order"] == pytest.approx(2.0, abs=1e-9)
    assert answer["uncertainty"] == pytest.approx(1.25 * abs(f1 - f2) / 3.0, rel=1e-12)
    # the same sequence against a formal order of 1 (Roy's rule): Fs = 3 and p = 1, U = 3 |f1 - f2| / (2 - 1)
    answer = reference_value(h, 1.0 + h**2, formal_order=1.0)
    assert answer["safety_factor"] == 3.0 and answer["order_used"] == 1.0
    assert answer["uncertainty"] == pytest.approx(3.0 * abs(f1 - f2), rel=1e-12)
    # an order below 0.5 is used as 0.5: f = 1 + h^0.2
    answer = reference_value(h, 1.0 + h**0.2, formal_order=1.0)
    assert answer["order"] == pytest.approx(0.2, abs=1e-9) and answer["order_used"] == 0.5
    # oscillatory: the finest value, no order claimed, Roache's GCI at the formal order with Fs = 3:
    # f(h) = 1 + (-1)^k h² at h = 1/2, 1/4, 1/8 → f1 = 1 + 1/64, f2 = 1 - 1/16, U = 3 |f1 - f2| / (2² - 1)
    signs = np.array([1.0, -1.0, 1.0])
    oscillating = 1.0 + signs * h**2
    answer = reference_value(h, oscillating, formal_order=2.0)
    assert answer["method"] == "oscillatory" and math.isnan(answer["order"])
    assert answer["value"] == oscillating[2] and answer["safety_factor"] == 3.0
    assert answer["order_used"] == 2.0
    assert answer["uncertainty"] == pytest.approx(3.0 * (1.0 / 64 + 1.0 / 16) / 3.0, rel=1e-12)
    assert abs(answer["value"] - 1.0) <= answer["uncertainty"]  # the band holds the limit 1
    # divergent (differences growing under refinement): the same rule
    answer = reference_value(h, np.array([1.0, 1.1, 1.5]), formal_order=1.0)
    assert answer["method"] == "divergent" and math.isnan(answer["order"])
    assert answer["uncertainty"] == pytest.approx(3.0 * 0.4 / (2.0 - 1.0), rel=1e-12)
    # converged to round-off: the finest two levels of f = 1 + h² made equal to within 2 ulp; the value is f1,
    # its uncertainty the round-off floor δ = ROUNDOFF · scale, and no order (it would be ≈ 48 from the ulps)
    rounded = 1.0 + h**2
    rounded[2] = rounded[1] - 2.0 * np.spacing(rounded[1])
    answer = reference_value(h, rounded, formal_order=2.0)
    assert answer["method"] == "converged" and math.isnan(answer["order"])
    assert answer["value"] == rounded[2] and answer["uncertainty"] == ROUNDOFF * rounded[0]
    # against a curve's scale: a sample near zero judged against the curve's magnitude
    answer = reference_value(h, np.array([3e-13, 1e-13, 2e-13]), formal_order=1.0, scale=1.0)
    assert answer["method"] == "converged" and answer["uncertainty"] == ROUNDOFF
    assert reference_value(h, np.array([2.0, 1.0, 1.0]), formal_order=1.0)["method"] == "converged"
    assert reference_value(h, np.array([2.0, np.nan, 1.0]), formal_order=1.0)["method"] == "missing"


def test_convergence_status_says_what_the_levels_show():
    """Per sample: asymptotic only when the observed order is the formal one (Roy's Fs = 1.25), pre-asymptotic
    for a monotone sequence at another order (Fs = 3), not converged without an order, converged at round-off;
    a quantity is as converged as its least converged sample."""
    from refsim.reference.build import convergence_status, worst_status

    h = np.array([0.5, 0.25, 0.125])

    def status(values, order):
        answer = reference_value(h, np.asarray(values, dtype=float), formal_order=order)
        return convergence_status(answer["method"], answer["safety_factor"])

    assert status(1.0 + h, 1.0) == "asymptotic"
    assert status(1.0 + h**0.5, 1.0) == "pre-asymptotic"  # the puncture's kind: monotone at the wrong order
    assert status(1.0 + np.array([1.0, -1.0, 1.0]) * h, 1.0) == "not converged"
    assert status([1.0, 1.1, 1.5], 1.0) == "not converged"
    assert status([2.0, 1.0, 1.0], 1.0) == "converged"
    assert status([2.0, np.nan, 1.0], 1.0) == "missing"
    assert worst_status(["converged", "not converged", "asymptotic"]) == "not converged"
    assert worst_status(["asymptotic", "pre-asymptotic"]) == "pre-asymptotic"


# ---------------------------------------------------------------------- the package


def test_manifest_records_version_levels_and_checksums(package):
    folder, manifest = package
    written = json.loads((folder / "manifest.json").read_text())
    assert written["format"] == "refsim-reference" and written["level"] == "coarse"
    assert written["refsim_version"] and written["git_commit"] and written["command"] == "test"
    from refsim.sweep.worker import numerics_digest

    assert written["numerics_digest"] == numerics_digest()  # what the runs are keyed by
    assert set(written["cases"]) == set(CASES)
    assert written["cases"]["puncture"]["levels"]["mesh.cells"] == [2, 3, 4]
    for case in CASES:
        for name in ("reference.h5", "reference.csv", "case.toml"):
            assert f"cases/{case}/{name}" in written["files"]
    assert (
        "cases/puncture/scene.toml" in written["files"] and "cases/puncture/problems.h5" in written["files"]
    )
    problems = written["cases"]["puncture"]["problems"]
    assert problems["count"] == 20 and problems["recorded"] > 20
    problem_set = read_problem_set(folder / "cases" / "puncture" / "problems.h5")
    assert len(problem_set) == problems["count"]
    for (
        _,
        problem,
        multipliers,
    ) in problem_set:  # each stored solution solves its problem (solve_exact, 1e-10)
        assert natural_residual(problem, multipliers) <= 1e-8
    assert check_manifest(folder) == []
    target = folder / "cases" / "puncture" / "reference.csv"
    original = target.read_bytes()
    try:
        target.write_bytes(original + b"\n")
        assert check_manifest(folder) == ["cases/puncture/reference.csv"]
    finally:
        target.write_bytes(original)


def test_package_holds_fclib_problems_of_the_tip_contact(package):
    """The puncture case's finest run: its loaded tip contacts before puncture are FCLib problems (Coulomb's
    cone on the step's W, q, mu), kept evenly spaced; each reads back with its stored solution meeting FCLib's
    error measure (Siconos' normalised natural map, which is refsim's natural_residual) to the export's
    tolerance, 1e-10 (export_problems' default, solve_exact stops at it)."""
    import h5py

    from refsim.io.export import coulomb_contacts
    from refsim.solvers.readers import read_fclib

    folder, manifest = package
    problems = manifest["cases"]["puncture"]["problems"]
    assert problems["fclib"] == min(10, problems["fclib_holdable"]) > 0
    files = sorted((folder / "cases" / "puncture" / "fclib").glob("*.hdf5"))
    assert [int(p.stem.split("_")[1]) for p in files] == problems["fclib_steps"]
    for path in files:
        assert f"cases/puncture/fclib/{path.name}" in manifest["files"]
        back = read_fclib(path)
        with h5py.File(path, "r") as handle:
            r = handle["solution/r"][()]
        assert back.contacts.shape == (1, 3) and r[0] > 0.0
        assert natural_residual(back, r) <= 1e-10
        assert coulomb_contacts(back) is not None  # already pure contact: taken as is


def test_answers_come_from_the_runs(package):
    folder, _ = package
    case = load_case("puncture")
    reference = read_case_reference(folder, "puncture")
    files = _run_files(folder, "puncture")
    assert len(files) == 3
    for level, path in enumerate(files):  # coarsest first; each level's stored values are its run's
        values = case_values(case, path)
        for name, stored in reference["quantities"].items():
            np.testing.assert_allclose(stored["levels"][level], np.atleast_1d(values[name]), rtol=1e-12)
    # the puncture force is f_p by the event rule at every level (scene: insertion.puncture_force = 0.8 N)
    puncture = reference["quantities"]["puncture_force"]
    assert puncture["method"] == ["converged"] and puncture["value"][0] == pytest.approx(0.8, rel=1e-9)


def test_cantilever_answers_bracket_the_closed_forms(package):
    folder, _ = package
    reference = read_case_reference(folder, "cantilever")
    for name, entry in reference["quantities"].items():
        # The elastica (Reissner's rod, the continuum the Timoshenko elements discretise) lies within the GCI
        # band of the Richardson value: the band bounds the discretisation error (Fs = 1.25 or 3), and the
        # elastica BVP is solved to 1e-10.
        assert entry["method"] == ["richardson"], name
        assert abs(entry["value"][0] - entry["closed_form"]) <= entry["uncertainty"][0] + 1e-9 * abs(
            entry["closed_form"]
        ), name


def test_whether_an_event_happens_is_read_from_the_run(package, tmp_path):
    """A scalar of an event alone is 1 when the run has the event, 0 when not: the puncture case's finest
    coarse run punctures (its travel_at_puncture is finite) and never cuts (no cutting in its scene)."""
    folder, _ = package
    finest = _run_files(folder, "puncture")[-1]
    scene = load_case("puncture").scene_path
    path = tmp_path / "events.toml"
    path.write_text(
        f'[case]\ntitle = "t"\nwhy = "w"\nsetup = "s"\nscene = "{scene}"\nrefine = "mesh.cells"\n'
        'formal_order = 1\n[levels]\ncoarse = { "mesh.cells" = [2, 3, 4] }\n'
        '[[quantity]]\nname = "punctures"\nunit = "1"\nevent = "puncture"\n'
        '[[quantity]]\nname = "cuts"\nunit = "1"\nevent = "cut_start"\n'
    )
    values = case_values(load_case(path), finest)
    assert math.isfinite(float(case_values(load_case("puncture"), finest)["travel_at_puncture"]))
    assert float(values["punctures"]) == 1.0 and float(values["cuts"]) == 0.0


def test_csv_round_trip(package, tmp_path):
    folder, _ = package
    for name in CASES:
        case = load_case(name)
        reference = read_case_reference(folder, name)
        # the package's own CSV is in the comparison format (extra columns ignored)
        values = read_their_csv(folder / "cases" / name / "reference.csv", case)
        for quantity, entry in reference["quantities"].items():
            np.testing.assert_allclose(values[quantity], np.atleast_1d(entry["value"]), rtol=1e-11)
        written = write_their_csv(
            case, {q: reference["quantities"][q]["value"] for q in values}, tmp_path / "x.csv"
        )
        again = read_their_csv(written, case)
        for quantity in values:
            np.testing.assert_allclose(again[quantity], values[quantity], rtol=1e-11)
        assert all(item.all_passed for item in compare(name, written, folder))


def test_page_is_written_from_the_package(package, tmp_path):
    folder, _ = package
    page = write_page(folder, tmp_path / "docs" / "reference.md")
    text = page.read_text()
    reference = read_case_reference(folder, "cantilever")
    value = reference["quantities"]["deflection_small"]["value"][0]
    assert "## cantilever:" in text and "## puncture:" in text and f"{value:.5g}" in text
    # every quantity's convergence is stated in the summary, and the digest the runs are keyed by
    manifest = json.loads((folder / "manifest.json").read_text())
    for name, case in manifest["cases"].items():
        for quantity, row in case["quantities"].items():
            assert (
                f"| {name} | {case['level']} | {quantity} | {', '.join(row['methods'])} | {row['status']} |"
                in text
            )
    assert manifest["numerics_digest"] in text and manifest["git_commit"] in text
    assert (tmp_path / "docs" / "figures" / "reference" / "puncture.png").is_file()


# ---------------------------------------------------------------------- compare


def test_refsim_finest_run_passes(package, tmp_path):
    folder, _ = package
    finest = _run_files(folder, "puncture")[-1]
    # The reference is f1 (converged, oscillatory, divergent) or f1's Richardson value with |f1 - ref| = U/Fs
    # (richardson, Fs >= 1.25): the finest run lies inside U.
    results = compare("puncture", finest, folder)
    assert all(item.all_passed for item in results)
    csv = write_their_csv(
        load_case("puncture"), case_values(load_case("puncture"), finest), tmp_path / "own.csv"
    )
    assert (
        main(["compare", "puncture", str(csv), "--reference", str(folder), "-o", str(tmp_path / "f.png")])
        == 0
    )
    assert (tmp_path / "f.png").stat().st_size > 0


def test_coarsest_run_as_another_implementation(package):
    folder, _ = package
    reference = read_case_reference(folder, "puncture")
    coarsest = _run_files(folder, "puncture")[0]
    for item in compare("puncture", coarsest, folder):
        stored = reference["quantities"][item.quantity]
        np.testing.assert_allclose(item.theirs, stored["levels"][0], rtol=1e-12)
        expected = np.abs(stored["levels"][0] - stored["value"]) <= stored["band"]
        np.testing.assert_array_equal(item.passed, expected)


def _predicted(reference, their, margin: float = 0.25):
    """Verdicts the band predicts for a perturbation of known size, and a mask of the samples not within
    ``margin`` of the band's edge (where a small departure from the prediction could flip it)."""
    difference = np.abs(their - reference["value"])
    clear = np.abs(difference - reference["band"]) > margin * reference["band"]
    return difference <= reference["band"], clear


def test_two_percent_stiffer_tissue_against_the_band(package, tmp_path):
    """Tissue E x 1.02 on the finest coarse level. Before the puncture the indentation force is linear in E
    (linear quasi-static elasticity; the stiffness damping scales with E too, only the tissue's inertia does
    not), so theirs = 1.02 f1; the band predicts the verdict of each sample."""
    from refsim.sweep.worker import run_scene

    folder, _ = package
    case = load_case("puncture")
    levels = case.level("coarse")
    scene = load_scene(
        case.scene_path,
        [
            f"mesh.cells={[levels['mesh.cells'][-1]] * 3}",
            f"time.dt={levels['time.dt'][-1]}",
            "tissue.youngs_modulus=51000.0",  # 50 kPa x 1.02
            "output.tissue_every=1000000",
        ],
    )
    stiffer = tmp_path / "stiffer.h5"
    run_scene(scene, stiffer)
    reference = read_case_reference(folder, "puncture")["quantities"]["indentation_force"]
    finest = reference["levels"][-1]
    measured = np.atleast_1d(case_values(case, stiffer)["indentation_force"])
    np.testing.assert_allclose(measured / finest, 1.02, atol=2e-3)  # the inertia's share is below 0.2 %
    item = next(c for c in compare("puncture", stiffer, folder) if c.quantity == "indentation_force")
    predicted, clear = _predicted(reference, 1.02 * finest)
    assert np.any(clear)
    np.testing.assert_array_equal(item.passed[clear], predicted[clear])


def test_two_percent_stiffer_needle_fails(package, tmp_path):
    """Needle E x 1.02 on the finest coarse level: the small-load deflection is P L³/(3 E I) + P L/(κ G A), so
    1/1.02 of the reference, 2 % off, against a band of U (about 1e-6 relative) + T (0.1 %): it must fail."""
    from refsim.verification.needle import needle_cantilever

    folder, _ = package
    case = load_case("cantilever")
    spec = case.cantilever
    count = case.level("coarse")["needle.element_count"][-1]
    reference = read_case_reference(folder, "cantilever")["quantities"]
    values = {}
    from refsim.fem.needle import NeedleModel

    section = NeedleModel(
        length=spec["length"],
        radius=spec["radius"],
        element_count=1,
        youngs_modulus=spec["youngs_modulus"],
        poisson_ratio=spec["poisson_ratio"],
        density=1.0,
    ).section
    # the loads are P = k E I / L² with the specified E: the stiffer needle carries the same forces
    for name, parameter in spec["load_parameters"].items():
        force = parameter * spec["youngs_modulus"] * section.second_moment / spec["length"] ** 2
        tip = needle_cantilever(
            [0.0, -force, 0.0],
            length=spec["length"],
            radius=spec["radius"],
            youngs_modulus=1.02 * spec["youngs_modulus"],
            poisson_ratio=spec["poisson_ratio"],
            element_count=count,
        ).tip_displacement
        values[f"deflection_{name}"] = -tip[1]
        values[f"shortening_{name}"] = -tip[0]
    csv = write_their_csv(case, {q.name: values[q.name] for q in case.quantities}, tmp_path / "stiff.csv")
    results = {item.quantity: item for item in compare("cantilever", csv, folder)}
    small = reference["deflection_small"]["value"][0]
    # linear: δ ∝ 1/E for the bending and shear parts alike (G = E/(2(1 + ν))); the geometric non-linearity at
    # P L²/(E I) = 0.1 is O(1e-3) of δ and nearly the same for both moduli
    assert values["deflection_small"] == pytest.approx(small / 1.02, rel=1e-4)
    for name, item in results.items():
        predicted, clear = _predicted(reference[name], np.atleast_1d(values[name]))
        assert clear.all() and not predicted.any(), name
        assert not item.all_passed, name
    assert main(["compare", "cantilever", str(csv), "--reference", str(folder)]) == EXIT_FAILED


# ---------------------------------------------------------------------- bad input


def test_bad_input_exits_2_naming_what_is_wrong(package, tmp_path, capsys):
    folder, _ = package
    bad = tmp_path / "bad.csv"
    bad.write_text("name,depth,force\nx,1,2\n")
    assert main(["compare", "puncture", str(bad), "--reference", str(folder)]) == EXIT_INPUT
    assert "missing column 'quantity'" in capsys.readouterr().err
    bad.write_text("quantity,x,value\npuncture_force,,0.8\n")
    assert main(["compare", "puncture", str(bad), "--reference", str(folder)]) == EXIT_INPUT
    assert "no rows for quantity 'indentation_force'" in capsys.readouterr().err
    bad.write_text("quantity,x,value\nstiffness,,1\n")
    assert main(["compare", "puncture", str(bad), "--reference", str(folder)]) == EXIT_INPUT
    assert "line 2, column quantity: 'stiffness'" in capsys.readouterr().err
    bad.write_text("quantity,x,value\npuncture_force,,abc\n")
    assert main(["compare", "puncture", str(bad), "--reference", str(folder)]) == EXIT_INPUT
    assert "line 2" in capsys.readouterr().err
    assert main(["compare", "nope", str(bad), "--reference", str(folder)]) == EXIT_INPUT
    assert "unknown reference case 'nope'" in capsys.readouterr().err
    assert main(["compare", "insertion", str(bad), "--reference", str(folder)]) == EXIT_INPUT
    assert "no reference for case 'insertion'" in capsys.readouterr().err
    short = tmp_path / "short.csv"
    at = load_case("puncture").quantity("indentation_force").at
    write_their_csv(
        load_case("puncture"),
        {"indentation_force": np.arange(1.0, len(at) + 1), "travel_at_puncture": 1e-3, "puncture_force": 0.8},
        short,
    )
    # their curve stops before the reference's last sampling point
    lines = short.read_text().splitlines(keepends=True)
    last = max(i for i, line in enumerate(lines) if line.startswith("indentation_force,"))
    short.write_text("".join(lines[:last] + lines[last + 1 :]))
    assert main(["compare", "puncture", str(short), "--reference", str(folder)]) == EXIT_INPUT
    assert "the reference samples it at" in capsys.readouterr().err
    assert main(["reference", "build", "--cases", "nope", "-o", str(tmp_path / "p")]) == EXIT_INPUT
    assert "unknown reference case 'nope'" in capsys.readouterr().err
    assert main(["reference", "build", "--level", "finest", "-o", str(tmp_path / "p")]) == EXIT_INPUT
    assert "has no level 'finest' (levels: coarse, standard, fine)" in capsys.readouterr().err
    assert not (tmp_path / "p").exists()


def test_case_files_are_validated(tmp_path):
    assert set(CASES) <= set(case_names())
    for name in case_names():
        case = load_case(name)
        assert len(case.level("coarse")[case.refine]) >= 3
    # a variant of a scene: the paper's cut law on the laceration scene, an override of every run
    variant = load_case("laceration_paper_law")
    assert variant.overrides == ('cutting.law="paper"',)
    assert load_scene(variant.scene_path, list(variant.overrides)).cutting.law == "paper"
    path = tmp_path / "broken.toml"
    path.write_text(
        '[case]\ntitle = "t"\nwhy = "w"\nsetup = "s"\nrefine = "mesh.cells"\nformal_order = 1\n'
        'runner = "cantilever"\n'
        '[levels]\ncoarse = { "mesh.cells" = [2, 3] }\n'
    )
    with pytest.raises(ValueError, match=r"broken.toml: \[levels\] coarse: expected at least three"):
        load_case(path)
    path.write_text(
        '[case]\ntitle = "t"\nwhy = "w"\nsetup = "s"\nrefine = "mesh.cells"\nformal_order = 1\n'
        'runner = "cantilever"\n'
        '[levels]\ncoarse = { "mesh.cells" = [2, 3, 4] }\n[[quantity]]\nname = "q"\nunit = "N"\n'
        'y = "force"\nx = "time"\nat = [1.0]\n'
    )
    with pytest.raises(ValueError, match=r"\[\[quantity\]\] 1: y = 'force'"):
        load_case(path)
    path.write_text(path.read_text().replace("formal_order = 1", "formal_order = -1"))
    with pytest.raises(ValueError, match=r"\[case\] formal_order: -1: expected a number in \(0, 4\]"):
        load_case(path)
    path.write_text(path.read_text().replace("formal_order = -1", "formal_order = 1\nset = 3"))
    with pytest.raises(ValueError, match=r"\[case\] set: 3: expected a list of 'section.key=value' strings"):
        load_case(path)
    with pytest.raises(ValueError, match="has no level 'finest'"):
        load_case("puncture").level("finest")


@pytest.mark.parametrize("name", case_names())
def test_every_run_of_every_level_is_a_valid_scene(name):
    """Each run of each level (the level's values of its keys over the case's scene) loads: the scene's
    validation (a duration that is a whole number of steps, keys in range) holds before any cluster starts."""
    case = load_case(name)
    if case.runner != "scene":
        return
    for level in case.levels:
        keys = case.level(level)
        for index in range(len(keys[case.refine])):
            overrides = [
                f"{key}={[values[index]] * 3 if key == 'mesh.cells' else values[index]}"
                for key, values in keys.items()
            ]
            scene = load_scene(case.scene_path, [*case.overrides, *overrides])
            assert scene.time.dt == pytest.approx(keys["time.dt"][index], rel=1e-15)


def test_the_published_page_is_generated_by_this_code():
    """docs/reference.md is written by refsim.reference.page: its fixed text is the generator's (an edit to
    either without regenerating fails here), and it names the commit and the numerics digest of its build."""
    import re

    from refsim.reference.page import INTRODUCTION

    text = (Path(__file__).parents[2] / "docs" / "reference.md").read_text(encoding="utf-8")
    assert text.startswith(INTRODUCTION)
    assert re.search(r"commit `[0-9a-f]{40}`, numerics digest `[0-9a-f]{64}`", text)


def test_a_build_over_complete_runs_reuses_them_and_their_problems(package, tmp_path):
    """Built again in the same folder, the case's runs are reused (same content key) and so is the export of
    the finest run's problems (the longest part of a build over complete runs): problems.h5 is not written
    again and the manifest says the same of it; the answers are the same."""
    folder, manifest = package
    problems = folder / "cases" / "puncture" / "problems.h5"
    written = problems.stat().st_mtime_ns
    again = build_reference(folder, level="coarse", cases=CASES, workers=1, command="test")
    assert problems.stat().st_mtime_ns == written
    assert again["cases"]["puncture"]["problems"] == manifest["cases"]["puncture"]["problems"]
    for case in CASES:
        assert again["cases"][case]["quantities"] == manifest["cases"][case]["quantities"]


def test_a_build_into_a_package_adds_its_cases_and_keeps_the_others(package, tmp_path):
    """A package grows case by case: a build of one case at another level into it replaces that case (its
    level and provenance recorded per case) and keeps the others with their own build's provenance; the page
    says each case's level and the checksums cover every file."""
    folder, manifest = package
    grown = tmp_path / "package"
    shutil.copytree(folder, grown)
    again = build_reference(grown, level="standard", cases=["cantilever"], workers=1, command="grow")
    assert list(again["cases"]) == CASES  # the set's order, not the build's
    assert again["cases"]["cantilever"]["level"] == "standard"
    assert again["cases"]["cantilever"]["build"]["command"] == "grow"
    assert again["cases"]["cantilever"]["levels"]["needle.element_count"] == [8, 16, 32]
    kept = again["cases"]["puncture"]
    assert kept["level"] == "coarse" and kept["build"]["command"] == "test"
    assert kept["quantities"] == manifest["cases"]["puncture"]["quantities"]
    assert check_manifest(grown) == []
    assert read_case_reference(grown, "cantilever")["attributes"]["level"] == "standard"
    text = write_page(grown, tmp_path / "docs" / "reference.md").read_text()
    assert "built by 2 invocations" in text and "with `grow`" in text and "with `test`" in text
    assert "| cantilever | standard | deflection_small |" in text
    assert "| puncture | coarse | indentation_force |" in text
    assert "Built at the `standard` level" in text and "Built at the `coarse` level" in text
    # a case built over its study file of another level replaces that file and reuses the complete runs
    study = grown / "cases" / "puncture" / "study.h5"
    with h5py.File(study, "a") as handle:
        handle.attrs["name"] = "puncture_fine"
    runs = sorted((grown / "cases" / "puncture" / "study_runs").glob("*.h5"))
    stamps = [path.stat().st_mtime_ns for path in runs]
    build_reference(grown, level="coarse", cases=["puncture"], workers=1, command="again")
    assert [path.stat().st_mtime_ns for path in runs] == stamps
    with h5py.File(study, "r") as handle:
        assert handle.attrs["name"] == "puncture_coarse"


def test_a_folder_with_another_manifest_is_refused_before_anything_runs(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(ValueError, match="not a reference package|something-else"):
        build_reference(tmp_path, level="coarse", cases=["cantilever"], workers=1)
    assert not (tmp_path / "cases").exists()
