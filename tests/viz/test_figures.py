"""Figures: the off-screen picture and the force plot are real images of the run."""

from __future__ import annotations

import numpy as np
import pytest

from refsim.io import ResultWriter
from refsim.simulation import Simulation


@pytest.fixture(scope="module")
def result_file(tmp_path_factory):
    from refsim.scene import load_scene

    scene = load_scene("cube", ["mesh.cells=[4, 4, 4]", "time.duration=0.5"])
    simulation = Simulation(scene)
    path = tmp_path_factory.mktemp("fig") / "run.h5"
    with ResultWriter(path, scene, simulation.models) as writer:
        simulation.run(on_step=lambda state, record: writer.append(record))
    return path


def _image(path):
    import matplotlib.image

    image = matplotlib.image.imread(str(path))
    assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100
    return image


def test_render_is_a_picture(result_file, tmp_path):
    from refsim.viz import render_result

    output = tmp_path / "render.png"
    render_result(result_file, output)
    image = _image(output)
    # Not one colour: tissue, needle and background differ.
    assert len(np.unique(image.reshape(-1, image.shape[2]).round(2), axis=0)) > 20


def test_render_of_a_missing_step_names_it(result_file, tmp_path):
    from refsim.viz import render_result

    with pytest.raises(ValueError, match="9999"):
        render_result(result_file, tmp_path / "x.png", step=9999)


def test_plot_shows_the_forces(result_file, tmp_path):
    from refsim.viz import plot_result

    output = tmp_path / "forces.png"
    plot_result(result_file, output)
    image = _image(output)
    assert len(np.unique(image.reshape(-1, image.shape[2]).round(2), axis=0)) > 10
