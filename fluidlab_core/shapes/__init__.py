"""Geometry without Taichi: shapes in the world frame and meshes.

* `primitives`: `Shape` and the primitives (`Box`, `Sphere`, `Cylinder`, `Frustum`), the open containers (`Cup`,
  `Tank`, `Cone`)
  and `Mesh`: bounds, numpy signed distance (negative inside), lattice sampling.
* `mesh_sdf`: loading meshes with a pose and a scale (trimesh), signed distance grids (cached on disk) and
  volume sampling.

The engine's Taichi side of statics and tools (`fluidlab_core.engine.statics`) evaluates the same distances
inside kernels.
"""
from fluidlab_core.shapes.primitives import Box, Cone, Cup, Cylinder, Frustum, Mesh, Shape, Sphere, Tank

CONTAINERS = (Cup, Tank, Cone)  # open containers: statics or tools, never particle bodies

__all__ = ["Shape", "Box", "Sphere", "Cylinder", "Frustum", "Cup", "Tank", "Cone", "Mesh", "CONTAINERS"]
