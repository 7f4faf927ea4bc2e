"""docs/scenes.md is generated from the scene dataclasses: it must be current."""

from pathlib import Path

from refsim.scene.spec import scene_reference


def test_scene_reference_is_current():
    page = Path(__file__).resolve().parents[2] / "docs" / "scenes.md"
    assert page.read_text(encoding="utf-8") == scene_reference() + "\n", (
        "docs/scenes.md is stale: regenerate it with "
        'python -c "from refsim.scene.spec import scene_reference; print(scene_reference())" > docs/scenes.md'
    )
