"""A constitutive model with six parameters, defined outside the package: a compressible neo-Hookean solid that
stiffens with stretch, with Kelvin–Voigt damping.

With b = F Fᵀ, I₁ = tr b, J = max(det F, J_min):
    μ_eff = μ (1 + k (I₁ − 3))                                     (strain stiffening, k ≥ 0)
    τ = μ_eff (b − I) + λ ln(J) I                                  (compressible neo-Hookean, Kirchhoff)
      + η J (C + Cᵀ − ⅔ tr(C) I) + ζ J tr(C) I                    (shear and bulk viscosity, C ≈ ∇v)
Parameters: mu, lam (Pa), stiffening k (dimensionless), eta, zeta (Pa·s), j_min (dimensionless).
"""
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import taichi as ti

from fluidlab_core import materials
from fluidlab_core.engine import constitutive


@constitutive.register("stiffening_kelvin_voigt", params=("mu", "lam", "stiffening", "eta", "zeta", "j_min"),
                       needs_svd=False)
@ti.func
def stiffening_kelvin_voigt(F, C, prm, U, sig, V):
    I = ti.Matrix.identity(float, 3)
    b = F @ F.transpose()
    J = ti.max(F.determinant(), prm.j_min)
    mu_eff = prm.mu * (1.0 + prm.stiffening * (b.trace() - 3.0))
    tau = mu_eff * (b - I) + prm.lam * ti.log(J) * I
    tau += prm.eta * J * (C + C.transpose() - (2.0 / 3.0) * C.trace() * I) + prm.zeta * J * C.trace() * I
    return F, tau


def kirchhoff_stress(F, C, p: dict) -> np.ndarray:
    """The same law in numpy, for checks: τ of each (F, C) in (N, 3, 3) arrays."""
    eye = np.eye(3)
    b = F @ np.swapaxes(F, 1, 2)
    J = np.maximum(np.linalg.det(F), p["j_min"])[:, None, None]
    mu_eff = p["mu"] * (1.0 + p["stiffening"] * (np.trace(b, axis1=1, axis2=2)[:, None, None] - 3.0))
    trC = np.trace(C, axis1=1, axis2=2)[:, None, None]
    return (mu_eff * (b - eye) + p["lam"] * np.log(J) * eye
            + p["eta"] * J * (C + np.swapaxes(C, 1, 2) - 2.0 / 3.0 * trC * eye) + p["zeta"] * J * trC * eye)


@dataclass(frozen=True)
class StiffeningGel(materials.Material):
    """The toy material: parameters in SI units (see the module docstring)."""

    shear_modulus: float = 2.0e4
    lame_lambda: float = 8.0e4
    stiffening: float = 0.5
    shear_viscosity: float = 2.0
    bulk_viscosity: float = 1.0
    min_volume_ratio: float = 0.2
    model: ClassVar[str] = "stiffening_kelvin_voigt"

    def kernel_params(self):
        return {"mu": self.shear_modulus, "lam": self.lame_lambda, "stiffening": self.stiffening,
                "eta": self.shear_viscosity, "zeta": self.bulk_viscosity, "j_min": self.min_volume_ratio}

    @property
    def viscosity(self) -> float:
        # the explicit viscous limit: the stiffest viscous response, (4/3) η + ζ for a normal strain rate
        return 4.0 / 3.0 * self.shear_viscosity + self.bulk_viscosity

    def wave_speed(self) -> float:
        # stiffening raises the shear modulus; allow for stretches up to I₁ − 3 = 1
        return math.sqrt((self.lame_lambda + 2.0 * self.shear_modulus * (1.0 + self.stiffening)) / self.density)


GEL = StiffeningGel("toy_gel", density=1100.0, color=(0.5, 0.8, 0.9))
