"""The `fluidlab` command: the demo (the README's main job) writes pictures; bad options fail clearly."""
import subprocess
import sys

import numpy as np
from PIL import Image

from fluidlab_core import cli


def test_demo_writes_pictures_of_the_scene(tmp_path):
    """A short demo run in a separate process writes the first and last frames as PNGs that show the scene
    (not a blank picture)."""
    out = tmp_path / "demo"
    run = subprocess.run([sys.executable, "-m", "fluidlab_core.cli", "demo", "--out", str(out), "--duration", "0.02",
                          "--frames", "1", "--view", "front"], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    frames = sorted(out.glob("frame_*.png"))
    assert [f.name for f in frames] == ["frame_0000.png", "frame_0010.png"]
    image = np.asarray(Image.open(frames[-1]).convert("RGB")).astype(int)
    assert image.shape == (600, 800, 3)
    water_blue = (image[..., 2] > 150) & (image[..., 0] < 120)  # the water's colour, (0.25, 0.55, 0.95)
    assert water_blue.mean() > 0.01
    assert "wrote 2 pictures" in run.stdout


def test_materials_lists_the_catalogue(capsys):
    assert cli.main(["materials"]) == 0
    out = capsys.readouterr().out
    assert "water" in out and "frothed_milk" in out and "von_mises" in out


def test_bad_options_fail_with_a_message(capsys):
    assert cli.main(["demo", "--duration", "-1"]) == 2
    assert "duration must be positive" in capsys.readouterr().err
