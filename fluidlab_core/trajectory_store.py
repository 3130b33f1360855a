"""A folder of trajectories: names, listing, lookup and where a new one goes (the `fluidlab` CLI and sim_node).

Layout (the same as the `fluidlab` CLI writes and trajectories/ ships): <folder>/<Task>/<name>.json, with an
optional <name>.report.json and <name>.mp4 beside it. A trajectory's *name* is its file name without
".json"; names are unique across the whole folder (a second file with the same name is an error that names
both paths), contain no path separators (fluidlab_core.trajectory.check_name), and never point outside the
folder.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from fluidlab_core.trajectory import Trajectory, TrajectoryError, check_name


def report_path(path) -> Path:
    """The optimiser's report beside the trajectory file `path`: <name>.report.json next to <name>.json."""
    path = Path(path)
    return path.with_name(path.stem + ".report.json")


class StoreError(ValueError):
    """A request the trajectory folder cannot serve, with the reason."""


@dataclass
class Info:
    name: str
    task: str
    method: str
    seed: int
    steps: int
    dt: float
    final_loss: float
    path: Path

    @property
    def duration(self) -> float:
        return self.steps * self.dt


@dataclass
class Loaded:
    path: Path
    data: bytes
    trajectory: Trajectory


# A paper-size trajectory (hundreds of steps of 6 twists, with metadata) is under 1 MB; a file far larger is not a
# trajectory this project wrote, and parsing it would hold the node for as long as it takes.
MAX_FILE_BYTES = 32_000_000


class TrajectoryStore:
    def __init__(self, folder: str | Path):
        self.folder = Path(folder).expanduser().resolve()

    def _files(self) -> list[Path]:
        if not self.folder.is_dir():
            return []
        return sorted(p for p in self.folder.glob("*/*.json") if not p.name.endswith(".report.json")
                      and not p.name.startswith("."))

    def find(self, name: str) -> Path:
        try:
            check_name(name)
        except TrajectoryError as err:
            raise StoreError(str(err)) from None
        hits = [p for p in self._files() if p.stem == name]
        if not hits:
            raise StoreError(f"no trajectory named {name!r} in {self.folder} (see ~/list_trajectories)")
        if len(hits) > 1:
            raise StoreError(f"trajectory name {name!r} is ambiguous: {', '.join(str(h) for h in hits)}")
        return hits[0]

    def read(self, name: str) -> "Loaded":
        """The file of trajectory `name`: its path, its bytes and the Trajectory they hold, from one read (so
        that what is planned, hashed and recorded is the same document). Refuses a file that is a link (or in a
        linked folder) leading out of the folder, and one larger than MAX_FILE_BYTES."""
        path = self.find(name)
        real = path.resolve()
        if not real.is_relative_to(self.folder):
            raise StoreError(f"trajectory {name!r} cannot be used: {path} leads out of the trajectory folder "
                             f"{self.folder} (to {real}); copy the file into the folder instead of linking it")
        try:
            size = real.stat().st_size
            if size > MAX_FILE_BYTES:
                raise StoreError(f"trajectory {name!r} cannot be used: {path} has {size / 1e6:.1f} MB, more than "
                                 f"the {MAX_FILE_BYTES / 1e6:g} MB a trajectory file may have")
            data = real.read_bytes()
            return Loaded(path, data, Trajectory.loads(data, str(path)))
        except (TrajectoryError, OSError) as err:
            raise StoreError(f"trajectory {name!r} cannot be used: {err}") from None

    def load(self, name: str) -> Trajectory:
        return self.read(name).trajectory

    def info(self, path: Path, traj: Trajectory | None = None) -> Info:
        traj = traj or Trajectory.load(path)
        loss = traj.metadata.get("final_loss") if isinstance(traj.metadata, dict) else None
        return Info(name=path.stem, task=traj.task, method=traj.method or "", seed=int(traj.seed or 0),
                    steps=traj.n_steps, dt=float(traj.dt), final_loss=float(loss) if loss is not None else math.nan,
                    path=path)

    def list(self, task: str = "") -> tuple[list[Info], list[str]]:
        """Infos of the loadable trajectories (optionally of one task), and one line per file that is not."""
        infos, problems = [], []
        for path in self._files():
            if task and path.parent.name != task:
                continue
            try:
                infos.append(self.info(path))
            except (TrajectoryError, OSError, ValueError) as err:
                problems.append(f"{path}: {err}")
        return infos, problems

    def new_path(self, task: str, name: str, overwrite: bool = False) -> Path:
        """Where a new trajectory `name` of `task` goes. Refuses a name already used anywhere in the folder;
        with `overwrite`, the file of the same task and name may be replaced, but a name used by another task's
        file is still refused (the name would then be ambiguous)."""
        try:
            check_name(name)
            check_name(task, "task name")
        except TrajectoryError as err:
            raise StoreError(str(err)) from None
        path = self.folder / task / f"{name}.json"
        taken = [p for p in self._files() if p.stem == name and not (overwrite and p == path)]
        if taken:
            hint = "choose another name" + ("" if overwrite or taken[0] != path else ", or overwrite it (--force)")
            raise StoreError(f"a trajectory named {name!r} exists already ({taken[0]}); {hint}")
        return path
