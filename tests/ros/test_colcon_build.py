"""`colcon build` of the repository, and sim_node run from colcon's install tree as `ros2 run` would run it.

What a ROS 2 Jazzy machine does, with the `ros-jazzy-*` wheels of this virtual environment standing in for
/opt/ros/jazzy (the environment's prefix is an ament prefix: AMENT_PREFIX_PATH=<prefix> is what sourcing
/opt/ros/jazzy/setup.bash would set):

- `colcon build` from the repository root, into temporary build/install/log bases (nothing is written into the
  repository): the root is the ament_python package fluidlab_ros. The installed tree must hold the executables
  `ros2 run` looks for (lib/fluidlab_ros/sim_node), share/fluidlab_ros/package.xml, the ament index marker and
  the launch file;
- `source install/setup.bash` in bash, then the package is looked up through the ament index (as `ros2 run`
  does) and its sim_node started as a separate process: it must import the colcon-installed fluidlab_ros, not
  this environment's own (editable or pip) copy, and serve ~/list_trajectories on a real rclpy graph;
- the launch file (launch/sim_node.launch.py) cannot run here (launch and launch_ros have no wheels): it is
  read with ast, and every argument must be a sim_node parameter with the node's default and type.

fluidlab_msgs is not rebuilt here: it comes from the environment (pip install ./fluidlab_msgs_py), as it would
from an underlay. Building it with colcon too costs a minute or more of compiling and needs the rosidl build
wheels; FLUIDLAB_COLCON_MSGS=1 runs that variant (test_colcon_build_with_interfaces, docs/ros-build.md).
"""
from __future__ import annotations

import ast
import importlib.metadata
import importlib.util
import json
import os
import re
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from .conftest import LATE_TICK_LIMIT, ROOT, Client, Proc

from fluidlab_msgs.srv import ListTrajectories  # noqa: E402

from fluidlab_ros.sim_node import PARAMETERS  # noqa: E402

LAUNCH_FILE = ROOT / "launch" / "sim_node.launch.py"
PACKAGE = "fluidlab_ros"

needs_colcon = pytest.mark.skipif(
    importlib.util.find_spec("colcon_core") is None or importlib.util.find_spec("colcon_ros") is None
    or importlib.util.find_spec("colcon_bash") is None,
    reason="colcon is not installed (colcon-core, colcon-ros, colcon-bash: setup.py's test extra)")


def colcon_build(tmp: Path, base_paths: list[Path], *extra: str, timeout: float = 300) -> tuple[Path, float]:
    """`colcon build` of base_paths into tmp/build, tmp/install, tmp/log; returns (install base, seconds)."""
    env = dict(os.environ,
               AMENT_PREFIX_PATH=sys.prefix,  # what `source /opt/ros/jazzy/setup.bash` sets on a ROS machine
               COLCON_HOME=str(tmp / "colcon_home"))  # no user configuration (defaults, mixins) takes part
    env.pop("COLCON_PREFIX_PATH", None)  # no other colcon workspace is chained into this one's setup.bash
    args = [sys.executable, "-m", "colcon", "--log-base", str(tmp / "log"), "build",
            "--build-base", str(tmp / "build"), "--install-base", str(tmp / "install"),
            "--base-paths", *map(str, base_paths), *extra]
    t0 = time.monotonic()
    out = subprocess.run(args, cwd=tmp, env=env, capture_output=True, text=True, timeout=timeout)
    took = time.monotonic() - t0
    assert out.returncode == 0, f"colcon build failed ({' '.join(args)}):\n{out.stdout[-6000:]}\n{out.stderr[-4000:]}"
    return tmp / "install", took


def sourced(install: Path, command: list[str]) -> list[str]:
    """command run by bash after `source <install>/setup.bash`, exec'd so that signals reach it."""
    return ["bash", "-c", 'source "$0/setup.bash" && exec "${@}"', str(install), *command]


# What `ros2 run fluidlab_ros sim_node` does to find the executable (ros2run: the package's prefix from the ament
# index, then lib/<package>/<executable>), and where the installed Python code comes from.
PROBE = r"""
import importlib.metadata, json, sys
from ament_index_python.packages import get_package_prefix, get_package_share_directory
import fluidlab_core, fluidlab_msgs, fluidlab_ros, robot_models
print(json.dumps({
    "prefix": get_package_prefix("fluidlab_ros"),
    "share": get_package_share_directory("fluidlab_ros"),
    "msgs_prefix": get_package_prefix("fluidlab_msgs"),
    "fluidlab_ros": fluidlab_ros.__file__, "fluidlab_core": fluidlab_core.__file__,
    "robot_models": robot_models.__file__, "fluidlab_msgs": fluidlab_msgs.__file__,
    # the console script loads its entry point from the first fluidlab-ros distribution on sys.path
    "distribution": str(importlib.metadata.distribution("fluidlab-ros").locate_file("")),
}))
"""


def probe(install: Path, env: dict, cwd: Path) -> dict:
    # cwd outside the repository: `python -c` puts the working directory first on sys.path, the installed
    # sim_node script puts its own folder (lib/fluidlab_ros) there instead
    out = subprocess.run(sourced(install, [sys.executable, "-c", PROBE]), env=env, cwd=cwd, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-4000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_installed_node(install: Path, env: dict, tmp: Path, trajectories: Path) -> float:
    """Start the installed sim_node found through the ament index; call ~/list_trajectories. Returns the seconds
    from the start to the first answer."""
    found = probe(install, env, tmp)
    prefix = install / PACKAGE
    assert Path(found["prefix"]) == prefix, found
    assert Path(found["share"]) == prefix / "share" / PACKAGE, found
    site = prefix / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    for module in ("fluidlab_ros", "fluidlab_core", "robot_models"):
        assert Path(found[module]).is_relative_to(site), f"{module} imported from {found[module]}, not from {site}"
    assert Path(found["distribution"]) == site, found

    executable = Path(found["prefix"]) / "lib" / PACKAGE / "sim_node"
    args = [str(executable), "--ros-args", "-p", LATE_TICK_LIMIT, "-p", f"trajectory_folder:={trajectories}",
            "-p", "fluid_twin:=false", "-p", f"recording_folder:={tmp / 'recordings'}"]
    t0 = time.monotonic()
    node = Proc(sourced(install, args), env, tmp / "installed_sim_node.log")
    client = Client()
    try:
        service = client.service(ListTrajectories, "/sim_node/list_trajectories")
        listed = client.call(service, ListTrajectories.Request(task=""))
        took = time.monotonic() - t0
        names = {t.name for t in listed.trajectories}
        shipped = {p.stem for p in trajectories.glob("*/*.json") if not p.name.endswith(".report.json")}
        assert shipped and names == shipped, (names, shipped)
        assert node.p.poll() is None, node.text()
    except BaseException:
        print(node.text()[-6000:])
        raise
    finally:
        client.close()
        code = node.stop()
    assert code == 0, f"the installed sim_node ended with {code}:\n{node.text()[-4000:]}"
    return took


def _untouched_repository():
    """Names colcon writes by default; none of them may appear in the repository."""
    return {name for name in ("build", "install", "log") if (ROOT / name).exists()}


@needs_colcon
def test_colcon_build_installs_and_runs_sim_node(ros_env, tmp_path, trajectories):
    before = _untouched_repository()
    t0 = time.monotonic()
    install, build_s = colcon_build(tmp_path, [ROOT])
    assert _untouched_repository() == before, "colcon wrote build/, install/ or log/ into the repository"

    prefix = install / PACKAGE
    script = prefix / "lib" / PACKAGE / "sim_node"
    assert script.is_file() and os.access(script, os.X_OK), sorted(p.name for p in script.parent.glob("*"))
    assert (prefix / "lib" / PACKAGE / "command_monitor").is_file()
    assert (prefix / "share" / PACKAGE / "package.xml").read_text() == (ROOT / "package.xml").read_text()
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / PACKAGE).is_file()
    installed_launch = prefix / "share" / PACKAGE / "launch" / LAUNCH_FILE.name
    assert installed_launch.read_text() == LAUNCH_FILE.read_text()
    assert (install / "setup.bash").is_file()
    # only fluidlab_ros is in this workspace: colcon does not look inside a package (the root) for others
    assert sorted(p.name for p in install.iterdir() if p.is_dir()) == [PACKAGE]

    env = dict(ros_env, AMENT_PREFIX_PATH=sys.prefix)  # the underlay: this environment, with fluidlab_msgs
    env.pop("COLCON_PREFIX_PATH", None)
    found = probe(install, env, tmp_path)
    assert Path(found["msgs_prefix"]) == Path(sys.prefix), found

    served_s = run_installed_node(install, env, tmp_path, trajectories)
    print(f"\ncolcon build {build_s:.1f} s; installed sim_node answered ~/list_trajectories {served_s:.1f} s after "
          f"its start; whole test {time.monotonic() - t0:.1f} s")


# --- both packages, fluidlab_msgs compiled by colcon (opt-in) ---------------------------------------------------
def _build_requirements() -> list[str]:
    """fluidlab_msgs_py's pinned build requirements that a colcon build needs: all but the pip build backend and
    setuptools (colcon-core 0.21.3 requires setuptools<80; ament_cmake_python's `setup.py egg_info` works with the
    environment's own)."""
    requires = tomllib.loads((ROOT / "fluidlab_msgs_py" / "pyproject.toml").read_text())["build-system"]["requires"]
    return [r for r in requires if not r.startswith(("scikit-build-core", "setuptools"))]


def _missing(requirements: list[str]) -> list[str]:
    missing = []
    for req in requirements:
        name, _, version = req.partition("==")
        try:
            if importlib.metadata.version(name) != version:
                missing.append(req)
        except importlib.metadata.PackageNotFoundError:
            missing.append(req)
    return missing


@needs_colcon
@pytest.mark.skipif(os.environ.get("FLUIDLAB_COLCON_MSGS") != "1",
                    reason="set FLUIDLAB_COLCON_MSGS=1 to build fluidlab_msgs with colcon too (a minute or more)")
def test_colcon_build_with_interfaces(ros_env, tmp_path, trajectories):
    missing = _missing(_build_requirements())
    assert not missing, ("building fluidlab_msgs with colcon needs its build requirements in this environment: "
                         "pip install " + " ".join(f"'{m}'" for m in missing))
    # The same stand-in for /opt/ros/jazzy as pip's build uses (docs/ros-build.md): the rosidl wheels' exported
    # targets name include directories of the machine they were built on; a Jazzy installation needs neither.
    install, build_s = colcon_build(
        tmp_path, [ROOT, ROOT / "fluidlab_msgs_py"], "--cmake-args",
        f"-DCMAKE_PROJECT_fluidlab_msgs_INCLUDE={ROOT / 'fluidlab_msgs_py' / 'cmake' / 'pip_build.cmake'}",
        f"-DPython_EXECUTABLE={sys.executable}", "-DBUILD_TESTING=OFF", timeout=600)
    assert sorted(p.name for p in install.iterdir() if p.is_dir()) == ["fluidlab_msgs", PACKAGE]

    env = dict(ros_env, AMENT_PREFIX_PATH=sys.prefix)
    env.pop("COLCON_PREFIX_PATH", None)
    found = probe(install, env, tmp_path)
    msgs = install / "fluidlab_msgs"
    assert Path(found["msgs_prefix"]) == msgs, found
    assert Path(found["fluidlab_msgs"]).is_relative_to(msgs), found
    served_s = run_installed_node(install, env, tmp_path, trajectories)
    print(f"\ncolcon build of both packages {build_s:.1f} s; installed sim_node answered {served_s:.1f} s after start")


# --- the launch file -----------------------------------------------------------------------------------------
def _launch_arguments() -> dict[str, tuple[str, str, str]]:
    tree = ast.parse(LAUNCH_FILE.read_text(), filename=str(LAUNCH_FILE))
    for node in tree.body:
        if isinstance(node, ast.Assign) and [getattr(t, "id", None) for t in node.targets] == ["ARGUMENTS"]:
            return ast.literal_eval(node.value)
    raise AssertionError(f"{LAUNCH_FILE} defines no ARGUMENTS table")


def _as_launch_converts(text: str, kind: str):
    """A launch argument's text as launch_ros hands it to the node (ParameterValue(value_type=kind))."""
    if kind == "str":
        return text
    if kind in ("float", "int"):
        return {"float": float, "int": int}[kind](text)
    if kind == "bool":
        import yaml

        value = yaml.safe_load(text)
        assert isinstance(value, bool), f"{text!r} is no boolean"
        return value
    raise AssertionError(f"unknown launch argument type {kind!r}")


def test_launch_file_arguments_are_sim_node_parameters():
    arguments = _launch_arguments()
    python_type = {str: "str", float: "float", int: "int", bool: "bool"}
    problems = []
    for name, (default, kind, description) in arguments.items():
        if name not in PARAMETERS:
            problems.append(f"{name}: sim_node has no such parameter")
            continue
        node_default = PARAMETERS[name][0]
        if python_type.get(type(node_default)) != kind:
            problems.append(f"{name}: launch type {kind}, sim_node's default {node_default!r}")
        elif _as_launch_converts(default, kind) != node_default:
            problems.append(f"{name}: launch default {default!r}, sim_node's {node_default!r}")
        if not description:
            problems.append(f"{name}: no description")
    assert not problems, f"{LAUNCH_FILE.relative_to(ROOT)} disagrees with fluidlab_ros.sim_node.PARAMETERS: {problems}"
    # the ones left out are set through params_file, which the launch file documents
    left_out = sorted(set(PARAMETERS) - set(arguments))
    assert all(isinstance(PARAMETERS[n][0], list) for n in left_out), f"scalar parameters without an argument: {left_out}"
    text = LAUNCH_FILE.read_text()
    for name in left_out:
        assert name in text, f"the launch file's docstring does not mention {name}"

    tree = ast.parse(text)
    calls = {getattr(n.func, "id", None): n for n in ast.walk(tree) if isinstance(n, ast.Call)}
    node = calls.get("Node")
    assert node is not None, "no launch_ros.actions.Node in the launch file"
    keywords = {k.arg: k.value for k in node.keywords}
    assert ast.literal_eval(keywords["package"]) == PACKAGE
    assert ast.literal_eval(keywords["executable"]) == "sim_node"
    entry_points = re.findall(r'"(\w+) = ', (ROOT / "setup.py").read_text())
    assert "sim_node" in entry_points
    compile(text, str(LAUNCH_FILE), "exec")
