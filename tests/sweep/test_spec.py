"""Study specifications: --sweep parsing, product and zip, cases, the reference, study files and their
errors."""

from __future__ import annotations

import pytest

from refsim.sweep import load_study, parse_sweep, study_from_options
from refsim.sweep.spec import toml_value


def test_parse_sweep_values_and_lists():
    sweep = parse_sweep("insertion.spacing=2e-3,1e-3,5e-4")
    assert sweep.values == (2e-3, 1e-3, 5e-4) and sweep.measure == "value"
    cells = parse_sweep("mesh.cells=4,[6, 6, 8],8")
    assert cells.values == ([4, 4, 4], [6, 6, 8], [8, 8, 8])  # a scalar is repeated for a 3-vector key
    assert cells.measure == "inverse" and cells.spacing([8, 8, 8]) == pytest.approx(1 / 8)
    assert parse_sweep("solver.method=exact,gauss_seidel").values == ("exact", "gauss_seidel")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("insertion.spacing", "expected section.key=v1"),
        ("insertion.nope=1,2", "has no key 'nope'"),
        ("nosection.key=1", "expected section.key"),
        ("insertion.spacing=", "no values"),
    ],
)
def test_bad_sweep_is_named(text, message):
    with pytest.raises(ValueError, match=message):
        parse_sweep(text)


def test_product_and_zip():
    sweeps = ["insertion.spacing=1e-3,5e-4", "cutting.point_spacing=1e-3,5e-4"]
    product = study_from_options("cube", sweeps).runs()
    assert len(product) == 4
    zipped = study_from_options("cube", sweeps, combine="zip").runs()
    assert [run.values for run in zipped] == [
        {"insertion.spacing": 1e-3, "cutting.point_spacing": 1e-3},
        {"insertion.spacing": 5e-4, "cutting.point_spacing": 5e-4},
    ]
    assert zipped[0].overrides == ("insertion.spacing=0.001", "cutting.point_spacing=0.001")
    with pytest.raises(ValueError, match="equal length"):
        study_from_options("cube", ["insertion.spacing=1,2", "cutting.point_spacing=1"], combine="zip")


def test_run_ids_are_stable_and_distinct():
    first = study_from_options(
        "cube", ["insertion.spacing=1e-3,5e-4"], overrides=["mesh.cells=[4, 4, 4]"]
    ).runs()
    again = study_from_options(
        "cube", ["insertion.spacing=1e-3,5e-4"], overrides=["mesh.cells=[4, 4, 4]"]
    ).runs()
    assert [r.id for r in first] == [r.id for r in again]
    assert len({r.id for r in first}) == 2
    other = study_from_options("cube", ["insertion.spacing=1e-3,5e-4"]).runs()
    assert {r.id for r in other}.isdisjoint(r.id for r in first)
    other_scene = study_from_options(
        "cube_cut", ["insertion.spacing=1e-3,5e-4"], overrides=["mesh.cells=[4, 4, 4]"]
    ).runs()
    assert {r.id for r in other_scene}.isdisjoint(r.id for r in first)  # a changed scene is never reused


def test_toml_values():
    assert toml_value([4, 4, 4]) == "[4, 4, 4]"
    assert toml_value("exact") == '"exact"'
    assert toml_value(True) == "true"


def test_study_file(tmp_path):
    path = tmp_path / "pareto.toml"
    path.write_text("""
scene = "cube"
set = ["mesh.cells=[3, 3, 3]"]
quantities = ["needle_force@end", "displacement@0,0,0.09"]
[[sweep]]
key = "solver.tolerance"
values = [1e-4, 1e-6]
measure = "none"
[[case]]
label = "cap 10"
set = ["solver.max_iterations=10"]
[reference]
label = "exact"
set = ['solver.method="exact"']
""")
    spec = load_study(path)
    assert spec.name == "pareto" and spec.scene == "cube"
    runs = spec.runs()
    assert [r.label for r in runs] == ["solver.tolerance=0.0001", "solver.tolerance=1e-06", "cap 10"]
    assert runs[2].overrides == ("mesh.cells=[3, 3, 3]", "solver.max_iterations=10")
    reference = spec.reference_run()
    assert reference.label == "exact" and reference.overrides[-1] == 'solver.method="exact"'


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('scene = "cube"\nfoo = 1\n[[sweep]]\nkey="insertion.spacing"\nvalues=[1]', "unknown key 'foo'"),
        ('[[sweep]]\nkey="insertion.spacing"\nvalues=[1]', "missing key 'scene'"),
        ('scene = "cube"', "at least one sweep or case"),
        ('scene = "cube"\nquantities=["bogus"]\n[[case]]\nset=[]', "quantity 'bogus': unknown"),
        ('scene = "cube"\ncombine="cross"\n[[case]]\nset=[]', "combine = 'cross'"),
        ('scene = "cube"\n[[sweep]]\nkey="insertion.spacing"', "needs key and values"),
        ('name = "x"\n[mesh]\ngenerator = "box"', "a scene file, not a study file"),
    ],
)
def test_bad_study_file_is_named(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as error:
        load_study(path)
    assert str(path) in str(error.value)
