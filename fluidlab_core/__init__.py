"""FluidLab-ROS engine: differentiable multi-material MLS-MPM in SI units, scenes, tasks and optimisers.

Importing this package does no work: no Taichi initialisation, no file I/O. Call `fluidlab_core.init()` to
choose the backend (CPU and float32 by default), or let `Scene.build()` do it with the defaults.
"""
from __future__ import annotations

__version__ = "0.1.0"

from fluidlab_core import materials, optim, tasks
from fluidlab_core.runtime import init
from fluidlab_core.scene import ParticleHandle, Scene, UnstableTimeStepError
from fluidlab_core.shapes import Box, Cup, Cylinder, Mesh, Sphere, Tank

__all__ = ["init", "materials", "tasks", "optim", "Scene", "ParticleHandle", "UnstableTimeStepError", "Box", "Cylinder", "Sphere",
           "Mesh", "Cup", "Tank", "__version__"]
