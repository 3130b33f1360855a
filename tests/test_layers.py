"""The layering of docs/design.md §2, and facts about a task kept in one place.

* fluidlab_core never imports fluidlab_ros or rclpy (the `fluidlab replay` sub-command comes from fluidlab_ros
  through an entry point), and only the applications import fluidlab_core.apps.
* The Gymnasium ids, the robot mounting's tool offset and the task sizes come from the task registry, so they
  cannot disagree with it.
"""
import ast
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _imports(path: Path) -> set[str]:
    """Every module a file imports (absolute names; relative imports resolved against the package)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                out.add(".".join(base + ([node.module] if node.module else [])))
            elif node.module:
                out.add(node.module)
                out.update(f"{node.module}.{alias.name}" for alias in node.names)
    return out


def _core_files():
    return sorted((ROOT / "fluidlab_core").rglob("*.py"))


def test_core_never_imports_the_ros_side():
    ros_side = ("fluidlab_ros", "rclpy")
    offenders = {str(f.relative_to(ROOT)): sorted(m for m in _imports(f) if m.split(".")[0] in ros_side)
                 for f in _core_files()}
    offenders = {f: m for f, m in offenders.items() if m}
    assert not offenders, f"fluidlab_core imports the ROS side: {offenders}"
    assert len(_core_files()) > 30  # the scan saw the package


def test_only_applications_import_the_applications():
    allowed = {"fluidlab_core/cli.py"}
    offenders = [str(f.relative_to(ROOT)) for f in _core_files()
                 if "apps" not in f.parts and str(f.relative_to(ROOT)) not in allowed
                 and any(m.startswith("fluidlab_core.apps") for m in _imports(f))]
    assert not offenders, f"library modules import applications: {offenders}"


def test_the_replay_command_comes_from_an_entry_point():
    """`fluidlab --help` lists `replay` (registered by fluidlab_ros), and fluidlab_core's CLI module does not
    import fluidlab_ros to get it (checked in a fresh interpreter)."""
    code = ("import sys, fluidlab_core.cli as c; "
            "assert not any(m.startswith('fluidlab_ros') for m in sys.modules), 'imported at import'; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr
    help_text = subprocess.run([sys.executable, "-m", "fluidlab_core.cli", "--help"], capture_output=True, text=True,
                               timeout=120).stdout
    assert "replay" in help_text


def test_gym_ids_and_mountings_follow_the_task_registry():
    import gymnasium as gym

    import fluidlab_core.envs  # noqa: F401 - registers the ids
    from fluidlab_core import tasks
    from fluidlab_ros.mounting import load_mounting

    names = tasks.names()
    assert {"LatteArtStir", "Mixing", "GatheringEasy", "GatheringHard"} <= set(names)
    for name in names:
        assert f"FluidLab/{name}-v0" in gym.registry
        task = tasks.make(name, "small")
        m = load_mounting(name)
        np.testing.assert_allclose(m.flange_to_tool[:3], task.flange_to_tool[:3])
        q = np.asarray(task.flange_to_tool[3:]) / np.linalg.norm(task.flange_to_tool[3:])
        assert abs(abs(np.dot(m.flange_to_tool[3:], q)) - 1.0) < 1e-12
        assert m.tool == task.tool_name
    # the mounting file holds only the lab's calibration, for registered tasks
    doc = json.loads((ROOT / "robot_models" / "mounting.json").read_text())
    assert set(doc["tasks"]) <= set(names)
    assert not any("flange_to_tool" in entry or "tool" in entry for entry in doc["tasks"].values())


def test_task_sizes_are_defined_once():
    from fluidlab_core import tasks

    sources = {f.relative_to(ROOT).as_posix(): f.read_text() for f in (ROOT / "fluidlab_ros").glob("*.py")}
    redefined = [f for f, text in sources.items() if "SIZES = (" in text or "SIZES=(" in text]
    assert not redefined, f"task sizes redefined outside fluidlab_core.tasks: {redefined}"
    for name in tasks.names():
        assert set(tasks.task_class(name).sizes) == set(tasks.SIZES), name
