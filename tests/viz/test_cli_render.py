"""The render and plot subcommands: framing options, the animation, and errors that name the option."""

from __future__ import annotations

import numpy as np

from refsim.cli import main


def test_render_with_camera_options_writes_the_picture(insertion_file, tmp_path, capsys):
    output = tmp_path / "fig.png"
    code = main(
        [
            "render",
            str(insertion_file),
            "-o",
            str(output),
            "--camera",
            "1,-1,0.5",
            "--view-up",
            "0,0,1",
            "--zoom",
            "1.5",
            "--focus",
            "0.001,0.002,0.09",
            "--step",
            "30",
        ]
    )
    assert code == 0 and output.is_file()
    assert str(output) in capsys.readouterr().out


def test_render_animation_has_steps_over_k_frames(insertion_file, tmp_path):
    import imageio.v3 as iio

    output = tmp_path / "run.gif"
    assert main(["render", str(insertion_file), "--animate", str(output), "--every", "10"]) == 0
    assert iio.imread(output, index=None).shape[0] == 5  # 50 steps, K = 10


def test_render_errors_name_the_option(insertion_file, tmp_path, capsys):
    assert main(["render", str(insertion_file), "-o", str(tmp_path / "x.png"), "--camera", "top"]) == 2
    assert "camera = 'top'" in capsys.readouterr().err
    assert main(["render", str(insertion_file), "-o", str(tmp_path / "x.png"), "--zoom", "-1"]) == 2
    assert "zoom = -1" in capsys.readouterr().err
    assert main(["render", str(insertion_file)]) == 2
    assert "--animate" in capsys.readouterr().err
    assert main(["render", str(insertion_file), "--animate", str(tmp_path / "x.gif"), "--every", "0"]) == 2
    assert "every = 0" in capsys.readouterr().err


def test_plot_of_a_lateral_motion(lateral_file, tmp_path):
    import matplotlib.image

    output = tmp_path / "forces.png"
    assert main(["plot", str(lateral_file), "-o", str(output)]) == 0
    height, width = matplotlib.image.imread(str(output)).shape[:2]
    assert np.isclose(width / height, (2 * 5.2 + 3.6) / 4.8, rtol=0.02)  # two panels and the event table
