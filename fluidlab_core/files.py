"""Writing files so that a reader never sees half of one, with the permissions the user's umask gives.

Every file the project writes for people to read (trajectories, reports, pictures, videos, goal files, caches)
goes through `atomic_path`: the data goes into a temporary file in the target folder, which is renamed over the
target only when complete, so a crash or an error leaves the old file or none, never a partial one. The
temporary file is made by `tempfile.mkstemp`, which creates it readable by its owner only; before the rename
it gets the mode a plain `open(path, "w")` would give (0o666 less the umask), as every other file does.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


def umask() -> int:
    """The process's umask, read without changing it where the system tells it (Linux /proc), else by setting
    and restoring it."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def user_mode() -> int:
    """The mode of a new regular file: 0o666 less the umask."""
    return 0o666 & ~umask()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None):
    """Yield a temporary path beside `path` to write to; on success give it the user's file mode and rename it
    over `path`; on an error remove it. `suffix` (default: the target's) matters to writers that pick the
    format from the extension (numpy's savez, ffmpeg)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + (path.suffix if suffix is None else suffix),
                               dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, user_mode())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_atomic(path: str | os.PathLike, data: bytes | str, fsync: bool = True) -> Path:
    """Write `data` to `path` atomically (see the module docstring); returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
            if fsync:
                f.flush()
                os.fsync(f.fileno())
    return path
