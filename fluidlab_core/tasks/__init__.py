"""The task registry: `names()`, `make(name, size)` and `register(...)` for tasks of your own.

Each task is a class in a module of its family (cup_tasks: LatteArtStir, Mixing; gathering: GatheringEasy,
GatheringHard; pour_tasks, jet_and_glass; air_circulation: AirCirculation, the gas task); variants of a family are the same class with a parameter. Making a task compiles nothing: its
simulators are built on first use (`Task.simulator()`).

Tasks of your own (docs/extending.md) join the registry, and with it the Gymnasium ids
(`FluidLab/<name>-v0`), the `fluidlab` command and sim_node, without editing this package:

    from fluidlab_core import tasks

    @tasks.register
    class Stirring(tasks.Task): ...

A process that did not import your module (sim_node and its worker processes, `fluidlab optimise`) finds it
through either
  * the environment variable FLUIDLAB_TASKS, a comma-separated list of modules to import
    (FLUIDLAB_TASKS=my_lab.tasks), or
  * an entry point in the group `fluidlab.tasks` of an installed package (its value: a module, imported, or a
    function, called), e.g. in setup.py: entry_points={"fluidlab.tasks": ["my_lab = my_lab.tasks"]}.
Both are read the first time the registry is asked for a task (never at import).
"""
from __future__ import annotations

import importlib
import os
import sys
import threading

from fluidlab_core.tasks.base import SIZES, Task

PLUGIN_GROUP = "fluidlab.tasks"
PLUGIN_ENV = "FLUIDLAB_TASKS"

_registry: dict[str, type] = {}
_plugins_loaded = False
_plugins_lock = threading.RLock()
_loading: list = []  # non-empty while this process loads the plug-ins (a re-entrant call returns at once)


def register(cls=None, *, name: str | None = None):
    """Register a Task subclass under `name` (default: the class's `name` attribute). Usable as a decorator,
    with or without arguments. Registering the same class twice is a no-op; another class under a name in
    use is refused."""
    def add(task_cls):
        if not (isinstance(task_cls, type) and issubclass(task_cls, Task)):
            raise TypeError(f"only subclasses of fluidlab_core.tasks.Task can be registered, got {task_cls!r}")
        key = name or task_cls.name
        if not isinstance(key, str) or not key.isidentifier():
            raise ValueError(f"a task needs a name that is an identifier (class attribute `name` or name=...), "
                             f"got {key!r} for {task_cls.__name__}")
        old = _registry.get(key)
        if old is not None and old is not task_cls:
            raise ValueError(f"a task named {key!r} is already registered ({old.__module__}.{old.__qualname__})")
        _registry[key] = task_cls
        if "fluidlab_core.envs" in sys.modules:  # already imported: give the new task its Gymnasium id too
            from fluidlab_core import envs

            envs.register()
        return task_cls

    return add if cls is None else add(cls)


def unregister(name: str):
    """Take a task out of the registry (and its Gymnasium id out of Gymnasium's), e.g. to register an edited
    class again in a notebook. Unknown names are refused."""
    _load_plugins()
    if name not in _registry:
        raise KeyError(f"unknown task {name!r}; known tasks: {', '.join(_registry)}")
    del _registry[name]
    if "fluidlab_core.envs" in sys.modules:
        sys.modules["fluidlab_core.envs"].unregister(name)


def _builtin():
    from fluidlab_core.tasks import air_circulation, cup_tasks, gathering, jet_and_glass, pour_tasks

    for cls in (cup_tasks.LatteArtStir, cup_tasks.Mixing, gathering.GatheringEasy, gathering.GatheringHard,
                pour_tasks.LatteArtPour, pour_tasks.IceCreamStatic, pour_tasks.IceCreamDynamic,
                jet_and_glass.Transporting, jet_and_glass.Pouring, air_circulation.AirCirculation):
        register(cls)


def _load_plugins():
    """Built-in tasks, then FLUIDLAB_TASKS modules and `fluidlab.tasks` entry points (once per process). Under a
    lock, and marked done only when done: a second thread asking meanwhile waits instead of seeing an empty
    registry (sim_node's executor and the benchmarks ask from several threads)."""
    global _plugins_loaded
    if _plugins_loaded:
        return
    with _plugins_lock:
        if _plugins_loaded or _loading:
            return  # loaded meanwhile, or a plug-in registering a task calls back in while we load
        _loading.append(True)
        try:
            _builtin()
            for module in filter(None, (m.strip() for m in os.environ.get(PLUGIN_ENV, "").split(","))):
                try:
                    importlib.import_module(module)
                except ImportError as err:
                    raise ImportError(f"{PLUGIN_ENV} names module {module!r}, which cannot be imported: {err}") \
                        from err
            from importlib.metadata import entry_points

            for ep in entry_points(group=PLUGIN_GROUP):
                loaded = ep.load()
                if callable(loaded) and not isinstance(loaded, type):
                    loaded()
            _plugins_loaded = True
        finally:
            _loading.clear()


def names() -> list[str]:
    """The registered task names (the paper's, then your own)."""
    _load_plugins()
    return list(_registry)


def task_class(name: str) -> type:
    """The class registered under `name`; unknown names list the known ones."""
    _load_plugins()
    if name not in _registry:
        raise KeyError(f"unknown task {name!r}; known tasks: {', '.join(_registry)}")
    return _registry[name]


def make(name: str, size: str = "small", pressure: str = "state") -> Task:
    """A task by name; size "small" (tests, laptops) or "paper" (the paper's 64³ grid, about 100k particles);
    pressure "state" (the default) or "projection" (forward only: Task.__init__)."""
    cls = task_class(name)
    if size not in SIZES:
        raise ValueError(f"size must be one of {', '.join(SIZES)}, got {size!r}")
    return cls(size) if pressure == "state" else cls(size, pressure=pressure)


__all__ = ["names", "make", "register", "unregister", "task_class", "Task", "SIZES"]
