"""The task registry: `names()` and `make(name, size)`.

Each task is a class in a module of its family (cup_tasks: LatteArtStir, Mixing; gathering: GatheringEasy,
GatheringHard); variants of a family are the same class with a parameter. Making a task compiles nothing: its
simulators are built on first use (`Task.simulator()`).
"""
from __future__ import annotations

from fluidlab_core.tasks.base import SIZES, Task


def _registry() -> dict:
    from fluidlab_core.tasks import cup_tasks, gathering

    return {
        "LatteArtStir": cup_tasks.LatteArtStir,
        "Mixing": cup_tasks.Mixing,
        "GatheringEasy": gathering.GatheringEasy,
        "GatheringHard": gathering.GatheringHard,
    }


def names() -> list[str]:
    """The registered task names."""
    return list(_registry())


def make(name: str, size: str = "small") -> Task:
    """A task by name; size "small" (tests, laptops) or "paper" (the paper's 64³ grid, about 100k particles)."""
    registry = _registry()
    if name not in registry:
        raise KeyError(f"unknown task {name!r}; known tasks: {', '.join(registry)}")
    if size not in SIZES:
        raise ValueError(f"size must be one of {', '.join(SIZES)}, got {size!r}")
    return registry[name](size)


__all__ = ["names", "make", "Task"]
