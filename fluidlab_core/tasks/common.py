"""Materials and parts the task scenes share.

Explicit MPM needs a substep under the CFL limit 0.5·Δx/(c + v) of the fastest wave c. The catalogue's
liquids (fluidlab_core.materials) carry the paper's bulk modulus, a sound speed of 17–24 m/s, which at the
paper's 1.4 mm cells needs about 40 substeps per 2 ms step. The tasks use weakly compressible versions
instead: the same densities, with the bulk modulus set for a sound speed of c = 4 m/s,

    K = ρ c²,   Mach number v/c ≤ 0.08 for the tool's 0.15 m/s and the flows it makes,

so that density varies by under 2 % (hydrostatic compression gH/c² = 1.8 % at 3 cm depth), which is the
usual weakly compressible choice (Monaghan 1994: c ≥ 10 v_max). Viscous liquids keep their viscosity within
the explicit viscous limit ρΔx²/(6η) at paper resolution. The floating objects of Gathering are a soft foam
(400 kg/m³, E = 4.8 kPa, ν = 0.3) whose pressure-wave speed is also 4 m/s.
"""
from __future__ import annotations

import numpy as np

from fluidlab_core import materials as M, shapes as S

SOUND_SPEED = 4.0  # m/s, of every task liquid


def _bulk(density: float) -> float:
    return density * SOUND_SPEED ** 2


COFFEE = M.NewtonianLiquid("task_coffee", density=1000.0, bulk_modulus=_bulk(1000.0), color=M.COFFEE.color)
WATER = M.NewtonianLiquid("task_water", density=1000.0, bulk_modulus=_bulk(1000.0), color=M.WATER.color)
# frothed milk foam: floats on coffee; viscosity of a microfoam (0.5 Pa·s)
MILK_FOAM = M.ViscousLiquid("task_milk_foam", density=500.0, bulk_modulus=_bulk(500.0), viscosity_pas=0.5,
                            color=M.FROTHED_MILK.color)
# the paper's "sugar cube": a viscous, denser body (2 Pa·s, 1200 kg/m³) that stirring spreads
SUGAR = M.ViscousLiquid("task_sugar", density=1200.0, bulk_modulus=_bulk(1200.0), viscosity_pas=2.0,
                        color=(0.97, 0.92, 0.78))
_FOAM_MU, _FOAM_LAMBDA = M.lame_from_young(4.75e3, 0.3)
FLOAT_FOAM = M.Elastic("task_float_foam", density=400.0, shear_modulus=_FOAM_MU, lame_lambda=_FOAM_LAMBDA,
                       color=(0.9, 0.3, 0.25))
FLOAT_FOAM_B = M.Elastic("task_float_foam_b", density=400.0, shear_modulus=_FOAM_MU, lame_lambda=_FOAM_LAMBDA,
                         color=(0.3, 0.75, 0.3))


class Posed(S.Shape):
    """A shape given in its own frame (a tool's), placed at pose (x, y, z, qx, qy, qz, qw): its signed distance
    in the world. For the tools' initial poses, which the liquid is sampled around (`Without`)."""

    def __init__(self, shape: S.Shape, pose):
        from scipy.spatial.transform import Rotation

        pose = np.asarray(pose, dtype=float)
        self.shape, self.position = shape, pose[:3]
        self.rotation = Rotation.from_quat(pose[3:] / np.linalg.norm(pose[3:]))

    def bounds(self):
        lo, hi = self.shape.bounds()
        corners = np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]]
                            for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        world = self.rotation.apply(corners) + self.position
        return world.min(axis=0), world.max(axis=0)

    def sdf(self, points):
        return self.shape.sdf(self.rotation.inv().apply(np.asarray(points, dtype=float) - self.position))


class Without(S.Shape):
    """A box of liquid minus solids (floating objects, a post, a sugar cube, the tool at its initial pose): its
    signed distance excludes them, so that no liquid particle starts inside one. Sampled on the box's lattice."""

    def __init__(self, shape: S.Shape, solids):
        self.shape = shape
        self.solids = list(solids)

    def bounds(self):
        return self.shape.bounds()

    def sdf(self, points):
        d = self.shape.sdf(points)
        for s in self.solids:
            d = np.maximum(d, -s.sdf(points))
        return d

    def volume(self):
        raise NotImplementedError

    def _lattice_steps(self, spacing):
        return self.shape._lattice_steps(spacing)
