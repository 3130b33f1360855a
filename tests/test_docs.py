"""Every code block in the README and docs/ runs, or is checked against the program it documents.

- `python` blocks run, the blocks of one file in order in one fresh interpreter (later blocks use what earlier
  ones defined, as a reader would), in a scratch folder that sees the repository's shipped trajectories/.
- `bash` blocks: each command is checked against what it calls. `fluidlab ...` commands are parsed by the
  `fluidlab` argument parser (a misspelt option or sub-command fails), and `fluidlab list` / `materials` run;
  `python <script> --options` must name a script in the repository whose --help lists every option used;
  `sim_node` / `ros2 run fluidlab_ros sim_node` (or a colcon-installed `.../lib/fluidlab_ros/sim_node`) may only set
  parameters (-p name:=value) that the node declares; `ros2 launch fluidlab_ros sim_node.launch.py` may only set
  arguments (name:=value) that launch/sim_node.launch.py declares.
  Set-up commands (venv, pip, colcon, rosdep, source) are not run here: the README's test command is what `.ci/run`
  runs (checked below, to the character), and its install command is the first half of that.
- `yaml` blocks parse; `text` blocks are diagrams and listings. A block without a language is refused, so that
  a new block is never silently skipped.
"""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
LANGUAGES = ("python", "bash", "yaml", "text")
SETUP = {"python3", "pip", "source", "colcon", "rosdep", "git", "cd", "export", "rm", "mkdir"}


def doc_files() -> list[Path]:
    skip = {".venv", "venv", "out", "build", "install", "log", ".git", "recordings"}
    return sorted(p for p in ROOT.rglob("*.md") if not skip & set(p.relative_to(ROOT).parts))


def blocks(path: Path) -> list[tuple[int, str, str]]:
    """(line, language, text) of every fenced block of a Markdown file."""
    out, lang, start, body = [], None, 0, []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if line.startswith("```"):
            if lang is None:
                lang, start, body = line[3:].strip(), i, []
            else:
                out.append((start, lang, "\n".join(body)))
                lang = None
        elif lang is not None:
            body.append(line)
    assert lang is None, f"{path}: the block opened at line {start} is never closed"
    return out


ALL = [(p, *b) for p in doc_files() for b in blocks(p)]


def test_every_block_has_a_known_language():
    bad = [f"{p.relative_to(ROOT)}:{line} ({lang or 'none'})" for p, line, lang, _ in ALL if lang not in LANGUAGES]
    assert not bad, f"code blocks need one of the languages {LANGUAGES}: {bad}"
    assert len(ALL) >= 20  # the README and docs/ hold about two dozen


def test_ci_runs_the_readmes_test_command():
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text()
    commands = [b for _, lang, b in blocks(ROOT / "README.md") if lang == "bash" and "pytest" in b]
    assert len(commands) == 1, "the README holds one test command"
    assert commands[0].strip() in ci.splitlines(), f"{commands[0]!r} is not a line of .ci/run"
    assert "python3 -m venv .venv" in readme


# --- bash ------------------------------------------------------------------------------------------------
def commands(text: str) -> list[list[str]]:
    """The command lines of a bash block as argument lists: continuations joined, comments and `&&` chains
    split, environment assignments and a `.venv/bin/` prefix dropped."""
    out = []
    for line in text.replace("\\\n", " ").splitlines():
        lexer = shlex.shlex(line, posix=True, punctuation_chars="&;|")
        lexer.whitespace_split, lexer.commenters = True, "#"
        words: list[str] = []
        for word in [*lexer, "&&"]:
            if word in ("&&", ";", "||", "|"):
                while words and re.match(r"^[A-Z_]+=", words[0]):
                    words = words[1:]
                if words:
                    words[0] = words[0].removeprefix(".venv/bin/")
                    out.append(words)
                words = []
            else:
                words.append(word)
    return out


BASH = [(p, line, cmd) for p, line, lang, text in ALL if lang == "bash" for cmd in commands(text)]


def _id(item):
    p, line, cmd = item
    return f"{p.relative_to(ROOT)}:{line}:{cmd[0]}"


@pytest.fixture(scope="module")
def sim_node_parameters() -> set[str]:
    out = subprocess.run([str(BIN / "sim_node"), "--help"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return set(re.findall(r"^\s+([a-z_]+)\s", out.stdout, re.M))


@pytest.mark.parametrize("item", BASH, ids=[_id(i) for i in BASH])
def test_documented_command(item, sim_node_parameters):
    path, line, cmd = item
    where = f"{path.relative_to(ROOT)}:{line}: {' '.join(cmd)}"
    prog = cmd[0]
    if prog in SETUP or (prog == "python3" and cmd[1:3] == ["-m", "venv"]):
        return  # set-up commands: .ci/run runs the README's (test above); the others need a ROS machine
    if (prog == "fluidlab" and cmd[1:2] == ["benchmark"]) or (prog in ("python", "python3") and
                                                           cmd[1:3] == ["-m", "fluidlab_core.benchmark"]):
        from fluidlab_core import benchmark  # its own parser (fluidlab_core/cli.py hands it the options)

        try:
            benchmark.build_parser().parse_args(cmd[2:] if prog == "fluidlab" else cmd[3:])
        except SystemExit:
            pytest.fail(f"{where}: the benchmark refuses these arguments")
        return
    if prog == "fluidlab":
        from fluidlab_core.cli import build_parser

        try:
            build_parser().parse_args(cmd[1:])
        except SystemExit:
            pytest.fail(f"{where}: the fluidlab command refuses these arguments")
        if cmd[1] in ("list", "materials"):
            env = dict(os.environ, **dict(a.split("=", 1) for a in _env(path, line)))
            env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")  # tests.extension
            out = subprocess.run([str(BIN / "fluidlab"), *cmd[1:]], capture_output=True, text=True, env=env,
                                 cwd=ROOT, timeout=300)
            assert out.returncode == 0, f"{where}: {out.stderr}"
            if "FLUIDLAB_TASKS" in env:
                assert "ToyPush" in out.stdout, out.stdout
        return
    if prog == "ros2" and cmd[1] == "launch":
        assert cmd[2:4] == ["fluidlab_ros", "sim_node.launch.py"], f"{where}: unknown launch file"
        declared = launch_arguments()
        unknown = [w.split(":=")[0] for w in cmd[4:] if ":=" in w and w.split(":=")[0] not in declared]
        assert not unknown, f"{where}: launch/sim_node.launch.py declares no argument {unknown}"
        options = [w for w in cmd[4:] if ":=" not in w]
        assert set(options) <= {"--show-args", "-s", "--debug", "-d"}, f"{where}: unknown ros2 launch options"
        return
    if prog.endswith("/lib/fluidlab_ros/sim_node"):
        prog = "sim_node"  # the colcon-installed executable that `ros2 run fluidlab_ros sim_node` starts
    if prog in ("sim_node", "ros2"):
        if prog == "ros2":
            assert cmd[1:4] == ["run", "fluidlab_ros", "sim_node"], f"{where}: unknown ros2 use"
        params = [cmd[i + 1].split(":=")[0] for i, w in enumerate(cmd) if w == "-p"]
        unknown = [p for p in params if p not in sim_node_parameters]
        assert not unknown, f"{where}: sim_node declares no parameter {unknown}"
        return
    if prog in ("python", "python3") and cmd[1] == "-m":
        import importlib.util

        assert importlib.util.find_spec(cmd[2]) is not None, f"{where}: no module {cmd[2]}"
        return
    if prog in ("python", "python3"):
        script = ROOT / cmd[1]
        assert script.is_file(), f"{where}: no script {cmd[1]} in the repository"
        out = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, cwd=ROOT,
                             timeout=300)
        assert out.returncode == 0, f"{where}: --help failed: {out.stderr[-2000:]}"
        missing = [w.split("=")[0] for w in cmd[2:] if w.startswith("--") and w.split("=")[0] not in out.stdout]
        assert not missing, f"{where}: {cmd[1]} --help lists no {missing}"
        return
    if prog in ("sim_node", "command_monitor"):
        assert (BIN / prog).exists()
        return
    pytest.fail(f"{where}: the docs test does not know how to check {prog!r}; teach it (tests/test_docs.py)")


def launch_arguments() -> set[str]:
    """The arguments launch/sim_node.launch.py declares: its ARGUMENTS table and DeclareLaunchArgument calls with a
    literal name (read with ast: launch has no wheel)."""
    import ast

    tree = ast.parse((ROOT / "launch" / "sim_node.launch.py").read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and [getattr(t, "id", None) for t in node.targets] == ["ARGUMENTS"]:
            names |= set(ast.literal_eval(node.value))
        if (isinstance(node, ast.Call) and getattr(node.func, "id", None) == "DeclareLaunchArgument"
                and node.args and isinstance(node.args[0], ast.Constant)):
            names.add(node.args[0].value)
    return names


def _env(path: Path, line: int) -> list[str]:
    """Environment assignments in front of the fluidlab command of that block."""
    text = next(t for p, l, lang, t in ALL if p == path and l == line)
    return re.findall(r"\b([A-Z_]+=[^\s]+)\s+fluidlab\b", text)


# --- yaml ------------------------------------------------------------------------------------------------
YAML = [(p, line, text) for p, line, lang, text in ALL if lang == "yaml"]


@pytest.mark.parametrize("item", YAML, ids=[f"{p.relative_to(ROOT)}:{line}" for p, line, _ in YAML])
def test_yaml_block_parses(item):
    import yaml

    assert isinstance(yaml.safe_load(item[2]), dict)


# --- python ----------------------------------------------------------------------------------------------
PYTHON_FILES = sorted({p for p, _, lang, _ in ALL if lang == "python"})


@pytest.mark.parametrize("path", PYTHON_FILES, ids=[str(p.relative_to(ROOT)) for p in PYTHON_FILES])
def test_python_blocks_run(path, tmp_path):
    code = [f"# --- {path.relative_to(ROOT)}:{line}\n{text}" for p, line, lang, text in ALL
            if p == path and lang == "python"]
    script = tmp_path / "doc_blocks.py"
    script.write_text("\n\n".join(code) + "\n")
    (tmp_path / "trajectories").symlink_to(ROOT / "trajectories")
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               MPLBACKEND="Agg")
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=tmp_path, env=env,
                         timeout=1200)
    assert out.returncode == 0, f"the Python blocks of {path.relative_to(ROOT)} fail:\n{out.stderr[-4000:]}"
