"""The `fluidlab` command: the demo (the README's main job) writes pictures; bad options fail clearly."""
import os
import stat
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
    # the first step compiles the kernels: said before it starts, and how long it took after
    assert "compiling the simulator's kernels" in run.stderr and "compiled, first run took" in run.stderr


def test_materials_lists_the_catalogue(capsys):
    assert cli.main(["materials"]) == 0
    out = capsys.readouterr().out
    assert "water" in out and "frothed_milk" in out and "von_mises" in out


def test_bad_options_fail_with_a_message(capsys):
    assert cli.main(["demo", "--duration", "-1"]) == 2
    assert "duration must be positive" in capsys.readouterr().err


def _fluidlab(*args, timeout=900, cwd=None, umask=None):
    return subprocess.run([sys.executable, "-m", "fluidlab_core.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd, preexec_fn=(lambda: os.umask(umask)) if umask is not None else None)


def test_list_shows_every_task(capsys):
    assert cli.main(["list"]) == 0
    out = capsys.readouterr().out
    for name in ("LatteArtStir", "Mixing", "GatheringEasy", "GatheringHard"):
        assert out.count(name) == 3  # small, medium and paper


def test_optimise_refuses_bad_requests_before_announcing_anything(capsys, tmp_path):
    """Nothing is printed as started for a request that is then refused; errors read as sentences (a KeyError's
    message unquoted); the installed package is no place for results."""
    import fluidlab_core

    assert cli.main(["optimise", "Mixing", "--budget", "-5", "--root", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "optimising" not in err and "budget must be a whole number" in err and "got -5" in err
    assert cli.main(["optimise", "GatheringEasy", "--pressure", "projection", "--root", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "optimising" not in err and "method 'dp' needs the simulator's gradients" in err, err
    assert cli.main(["optimise", "Nope", "--root", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fluidlab: error: unknown task 'Nope'; known tasks: LatteArtStir"), err
    inside = os.path.join(os.path.dirname(fluidlab_core.__file__), "trajectories")
    assert cli.main(["optimise", "Mixing", "--root", inside]) == 2
    assert "inside the installed package" in capsys.readouterr().err
    assert not os.path.exists(inside)


def test_optimise_evaluate_render_round_trip(tmp_path):
    """optimise writes a trajectory and a report atomically into ./out/trajectories by default, says where, and
    refuses to overwrite a name in use unless asked (--force); evaluate reproduces the report's loss; render
    writes PNG frames and an MP4; every file gets the mode the user's umask gives; a bad trajectory file is
    refused with the reason."""
    import json

    umask = 0o027  # group may read, others nothing: every file the command writes must say 0o640
    root = tmp_path / "out" / "trajectories"
    args = ("optimise", "GatheringEasy", "--method", "cma-es", "--budget", "200", "--seed", "1", "--name", "t1")
    run = _fluidlab(*args, cwd=tmp_path, umask=umask)
    assert run.returncode == 0, run.stderr
    assert "steps 200/200" in run.stderr  # the progress bar
    assert "compiling the simulator's kernels" in run.stderr and "compiled, first run took" in run.stderr
    traj_path = root / "GatheringEasy" / "t1.json"
    assert f"trajectory will be written to {traj_path}" in run.stderr and f"wrote {traj_path}" in run.stdout
    report = json.loads((root / "GatheringEasy" / "t1.report.json").read_text())
    assert report["steps_used"] == 200 and report["method"] == "cma-es"
    assert sorted(p.name for p in (root / "GatheringEasy").iterdir()) == ["t1.json", "t1.report.json"]  # no temp
    for p in (root / "GatheringEasy").iterdir():
        assert stat.S_IMODE(p.stat().st_mode) == 0o640, p

    # a name in use: refused (the file untouched) unless --force, and never across tasks
    before = traj_path.read_bytes()
    again = _fluidlab(*args, cwd=tmp_path)
    assert again.returncode == 2 and "exists already" in again.stderr and "--force" in again.stderr, again.stderr
    assert "optimising" not in again.stderr and traj_path.read_bytes() == before
    other = _fluidlab("optimise", "GatheringHard", "--budget", "200", "--name", "t1", "--force", cwd=tmp_path)
    assert other.returncode == 2 and str(traj_path) in other.stderr, other.stderr
    forced = _fluidlab(*args[:-4], "--seed", "2", "--name", "t1", "--force", cwd=tmp_path)
    assert forced.returncode == 0 and "replacing" in forced.stderr, forced.stderr
    assert json.loads(traj_path.read_text())["seed"] == 2

    ev = _fluidlab("evaluate", str(traj_path))
    assert ev.returncode == 0, ev.stderr
    report = json.loads((root / "GatheringEasy" / "t1.report.json").read_text())
    assert f"loss {report['final_loss']:.6g}" in ev.stdout
    out = tmp_path / "render"
    rn = _fluidlab("render", str(traj_path), "--out", str(out), "--every", "25", umask=umask)
    assert rn.returncode == 0, rn.stderr
    assert sorted(p.name for p in out.glob("frame_*.png")) == [f"frame_{k:04d}.png" for k in (0, 25, 50, 75, 100)]
    mp4 = (out / "episode.mp4").read_bytes()
    assert len(mp4) > 1000 and mp4[4:8] == b"ftyp"
    for p in out.iterdir():
        assert stat.S_IMODE(p.stat().st_mode) == 0o640, p
    bad = tmp_path / "bad.json"
    doc = json.loads(traj_path.read_text())
    doc["version"] = 99
    bad.write_text(json.dumps(doc))
    assert cli.main(["evaluate", str(bad)]) == 2
    doc["version"], doc["twists"][3][0] = 1, None
    bad.write_text(json.dumps(doc))
    rc = _fluidlab("evaluate", str(bad))
    assert rc.returncode == 2 and "twists" in rc.stderr
