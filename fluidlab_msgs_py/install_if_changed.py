"""Install fluidlab_msgs into this Python's environment with `pip install ./fluidlab_msgs_py`, but only when needed.

Run it with the virtual environment's Python, from anywhere:

    .venv/bin/python fluidlab_msgs_py/install_if_changed.py [--force] [pip install options]

pip builds a local folder again on every `pip install` (a minute or two: an isolated build environment with
~30 build requirements, CMake, the rosidl generators and their C/C++ compilation). This script builds only when
one of these holds, and otherwise reuses what is installed:

- the environment has no fluidlab-msgs distribution, or `fluidlab_msgs.msg/.srv/.action` or the package's C
  typesupport module do not import;
- the files of this folder (the interfaces, CMakeLists.txt, cmake/, package.xml, pyproject.toml, ...) differ from
  those of the last build this script installed: a SHA-256 over every file's path and content;
- the installed distribution is not the one this script installed (its RECORD changed: another
  `pip install ./fluidlab_msgs_py`, an uninstall, a reinstall).

The stamp (both hashes) lives in the environment, <sys.prefix>/share/fluidlab_msgs_py/install_stamp.json, so a
fresh virtual environment always builds. It prints one line (built or reused); pip runs with -q and its errors show
as usual; a failed build or an install that does not import exits non-zero.
--force builds regardless; other options go to `pip install` (e.g. --no-cache-dir, -v).
This script takes no part in the build itself: colcon and a plain `pip install ./fluidlab_msgs_py` never read it.
"""
import argparse
import hashlib
import importlib.metadata
import json
import os
import subprocess
import sys
import time
from pathlib import Path

SOURCE = Path(__file__).resolve().parent
DIST = "fluidlab-msgs"
STAMP = Path(sys.prefix) / "share" / "fluidlab_msgs_py" / "install_stamp.json"
# What a build or an editor may leave in the folder; none of it is an input of the build.
SKIP_DIRS = {"build", "dist", "_skbuild", "__pycache__", ".git", ".pytest_cache"}
SKIP_SUFFIXES = (".pyc", ".swp", "~")
# The Python package and its C typesupport extension (which loads the package's lib/*.so).
IMPORT_CHECK = ("import fluidlab_msgs.msg, fluidlab_msgs.srv, fluidlab_msgs.action; "
                "from rosidl_generator_py import import_type_support; import_type_support('fluidlab_msgs')")


def source_hash() -> str:
    digest = hashlib.sha256()
    for root, dirs, files in os.walk(SOURCE):
        dirs[:] = sorted(d for d in dirs if d not in SKIP_DIRS and not d.endswith(".egg-info"))
        for name in sorted(files):
            if name.endswith(SKIP_SUFFIXES):
                continue
            path = Path(root, name)
            digest.update(path.relative_to(SOURCE).as_posix().encode() + b"\0")
            digest.update(hashlib.sha256(path.read_bytes()).digest())
    return digest.hexdigest()


def record_hash() -> str | None:
    """SHA-256 of the installed distribution's RECORD (its file list with each file's hash), None if not installed."""
    try:
        record = importlib.metadata.distribution(DIST).read_text("RECORD")
    except importlib.metadata.PackageNotFoundError:
        return None
    return hashlib.sha256(record.encode()).hexdigest() if record else None


def imports() -> bool:
    # A separate interpreter: the same start-up (the ros wheels' .pth hook) as the tests and the node get.
    return subprocess.run([sys.executable, "-c", IMPORT_CHECK], capture_output=True).returncode == 0


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        description="pip install ./fluidlab_msgs_py into this Python's environment unless the installed build "
                    "is that of the folder's current files. Other options go to pip install (e.g. --no-cache-dir).")
    parser.add_argument("--force", action="store_true", help="build and install even if nothing changed")
    args, pip_args = parser.parse_known_args(argv)
    force = args.force
    wanted = source_hash()
    try:
        stamp = json.loads(STAMP.read_text())
    except (OSError, ValueError):
        stamp = {}
    installed = record_hash()
    if force:
        reason = "--force"
    elif installed is None:
        reason = "not installed"
    elif stamp.get("source") != wanted:
        reason = "sources changed" if stamp else "no stamp from an earlier build"
    elif stamp.get("record") != installed:
        reason = "the installed one is not the stamped build"
    elif not imports():
        reason = "the installed one does not import"
    else:
        print(f"fluidlab_msgs: reused the installed build (sources unchanged, source hash {wanted[:12]})")
        return 0

    start = time.monotonic()
    cmd = [sys.executable, "-m", "pip", "install", "-q", *pip_args, str(SOURCE)]
    if subprocess.run(cmd).returncode != 0:
        print(f"fluidlab_msgs: BUILD FAILED ({reason}; pip's error above): {' '.join(cmd)}", file=sys.stderr)
        return 1
    if not imports():
        check = subprocess.run([sys.executable, "-c", IMPORT_CHECK], capture_output=True, text=True)
        print(f"fluidlab_msgs: built and installed, but this fails: {IMPORT_CHECK}\n{check.stderr}", file=sys.stderr)
        return 1
    installed = record_hash()
    if installed:
        STAMP.parent.mkdir(parents=True, exist_ok=True)
        STAMP.write_text(json.dumps({"source": wanted, "record": installed}) + "\n")
    took = time.monotonic() - start
    print(f"fluidlab_msgs: built and installed in {took:.0f} s ({reason}; source hash {wanted[:12]})")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
