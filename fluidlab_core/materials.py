"""Materials: small typed objects with SI parameters, and the catalogue.

Each material names one constitutive model (``model``) implemented in
``fluidlab_core.engine.constitutive``; the solver unrolls the models present in a scene statically and
never branches on material names.

Similarity with the FluidLab paper
----------------------------------
The paper's material table is in unit-cube units: density 1, Lamé λ = 277.78 for every material and
shear modulus μ = 0 (liquids), 208.33 or 416.67 (solids), with gravity of about 10. We map it to SI by

    1 paper length unit  = 1 m            (L* = 1 m)
    1 paper density unit = 1000 kg/m³     (ρ* = water)
    gravity              = 9.81 m/s²      (the paper's g, so the Froude number g·T²/L is unchanged)

hence the time unit is T* = 1 s and velocities map 1:1, while stresses (Lamé constants, yield stresses)
scale by ρ*·(L*/T*)² = 1000 Pa and viscosities by 1000 Pa·s. Every dimensionless group of the paper
(Cauchy number ρ g L / λ, density ratios, μ/λ, Reynolds number) is then the same in our SI scenes at the
same size in metres, so behaviour carries over. The liquids are weakly compressible: sound speed
sqrt(λ/ρ) ≈ 16.7 m/s for water, far above the ~1 m/s flows of the tasks (Mach < 0.1), which keeps density
changes under 1 % at the depths of a cup or tank.

Users define their own materials by constructing these classes, e.g.
``NewtonianLiquid("honey-ish", density=1400, bulk_modulus=4e5)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

STRESS_UNIT_PA = 1000.0  # 1 paper stress unit in Pa (see the module docstring)
VISCOSITY_UNIT_PAS = 1000.0  # 1 paper viscosity unit in Pa·s
DENSITY_UNIT = 1000.0  # 1 paper density unit in kg/m³


def lame_from_young(youngs_modulus: float, poisson_ratio: float) -> tuple[float, float]:
    """(μ, λ) in Pa from Young's modulus E (Pa) and Poisson's ratio ν."""
    mu = youngs_modulus / (2.0 * (1.0 + poisson_ratio))
    lam = youngs_modulus * poisson_ratio / ((1.0 + poisson_ratio) * (1.0 - 2.0 * poisson_ratio))
    return mu, lam


def _check_positive(obj, **values):
    for key, value in values.items():
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{type(obj).__name__} {obj.name!r}: {key} must be a positive finite number, got {value!r}")


@dataclass(frozen=True)
class Material:
    """Base class. density in kg/m³; color is RGB in [0, 1] for pictures."""

    name: str
    density: float
    color: tuple[float, float, float] = (0.5, 0.5, 0.5)
    model: ClassVar[str] = ""
    is_liquid: ClassVar[bool] = False
    is_rigid: ClassVar[bool] = False

    def kernel_params(self) -> dict[str, float]:
        """The parameters the kernels read, by the names the model declares (engine/constitutive.py), in SI
        units. A material of a new model returns that model's names."""
        raise NotImplementedError

    @property
    def mu(self) -> float:
        """Shear modulus (Pa), 0 for materials without one."""
        return float(self.kernel_params().get("mu", 0.0))

    @property
    def lam(self) -> float:
        """Lamé's first parameter (Pa); for liquids and rigid bodies the bulk modulus of their pressure law."""
        return float(self.kernel_params().get("lam", 0.0))

    @property
    def viscosity(self) -> float:
        """Dynamic viscosity η (Pa·s), 0 for inviscid materials; sets the explicit viscous time-step limit."""
        return float(self.kernel_params().get("eta", 0.0))

    @property
    def bulk_viscosity(self) -> float:
        """Bulk viscosity ζ (Pa·s), 0 for materials without one; it too limits the explicit time step."""
        return float(self.kernel_params().get("zeta", 0.0))

    def wave_speed(self) -> float:
        """P-wave speed sqrt((λ + 2μ)/ρ) in m/s: the fastest signal the explicit solver must resolve. A material
        of a model without μ and λ overrides this (the build's stability check calls it)."""
        params = self.kernel_params()
        if "lam" not in params and "mu" not in params:
            raise NotImplementedError(f"{type(self).__name__} has no 'mu' or 'lam' parameter: override wave_speed() "
                                      f"so that the stability check knows its fastest wave (m/s)")
        return math.sqrt((self.lam + 2.0 * self.mu) / self.density)


@dataclass(frozen=True)
class Elastic(Material):
    """Fixed-corotated hyperelastic solid (Stomakhin et al. 2012). shear_modulus μ and lame_lambda λ in Pa."""

    shear_modulus: float = 2.0833e5
    lame_lambda: float = 2.7778e5
    model: ClassVar[str] = "fixed_corotated"

    def __post_init__(self):
        _check_positive(self, density=self.density, shear_modulus=self.shear_modulus, lame_lambda=self.lame_lambda)

    def kernel_params(self):
        return {"mu": self.shear_modulus, "lam": self.lame_lambda}


@dataclass(frozen=True)
class Rigid(Material):
    """A rigid body made of particles, projected every substep to the best rigid motion of its body (shape
    matching, Müller et al. 2005); each `add_particles` call with a rigid material makes one body.

    Between projections the body responds elastically to compression only: Kirchhoff stress
    τ = λ J (J − 1) I with J the volume change the grid flow imposes (bulk_modulus λ in Pa). That pressure is
    what keeps liquid out of the body; shear stiffness would be projected away and only tighten the time
    step, so there is none. The stability check uses the body's wave speed sqrt(λ/ρ)."""

    bulk_modulus: float = 2.7778e5
    model: ClassVar[str] = "rigid"
    is_rigid: ClassVar[bool] = True

    def __post_init__(self):
        _check_positive(self, density=self.density, bulk_modulus=self.bulk_modulus)

    def kernel_params(self):
        return {"lam": self.bulk_modulus}


@dataclass(frozen=True)
class Plastic(Material):
    """Corotated elastoplastic solid with a box yield on the principal stretches (Stomakhin et al. 2013):
    singular values of F are clamped to [1 - yield_compression, 1 + yield_stretch] (dimensionless)."""

    shear_modulus: float = 2.0833e5
    lame_lambda: float = 2.7778e5
    yield_compression: float = 0.02
    yield_stretch: float = 0.005
    model: ClassVar[str] = "corotated_box_yield"

    def __post_init__(self):
        _check_positive(self, density=self.density, shear_modulus=self.shear_modulus, lame_lambda=self.lame_lambda,
                        yield_compression=self.yield_compression, yield_stretch=self.yield_stretch)
        if self.yield_compression >= 1.0:
            raise ValueError(f"Plastic {self.name!r}: yield_compression must be < 1, got {self.yield_compression}")

    def kernel_params(self):
        return {"mu": self.shear_modulus, "lam": self.lame_lambda, "yield_compression": self.yield_compression,
                "yield_stretch": self.yield_stretch}


@dataclass(frozen=True)
class VonMisesPlastic(Material):
    """St. Venant–Kirchhoff in Hencky (log) strain with a von Mises yield surface and perfect plasticity
    (return mapping of Klár et al. 2016, as in PlasticineLab). yield_stress in Pa: the deviatoric Kirchhoff
    stress norm sqrt(3/2)·|dev τ| is capped at it, so the material flows once sheared past it. Flow lowers the
    effective viscosity as the shear rate grows: shear-thinning in effect (ice cream, plasticine)."""

    shear_modulus: float = 2.0833e5
    lame_lambda: float = 2.7778e5
    yield_stress: float = 1.0e3
    model: ClassVar[str] = "von_mises"

    def __post_init__(self):
        _check_positive(self, density=self.density, shear_modulus=self.shear_modulus, lame_lambda=self.lame_lambda,
                        yield_stress=self.yield_stress)

    def kernel_params(self):
        return {"mu": self.shear_modulus, "lam": self.lame_lambda, "yield_stress": self.yield_stress}


@dataclass(frozen=True)
class NewtonianLiquid(Material):
    """Weakly compressible liquid: pressure p = -λ (J - 1) with J = det F (Tait-like, linearised); F is reset
    to its volume part J^(1/3)·I every substep, so shear never accumulates. bulk_modulus λ in Pa."""

    bulk_modulus: float = 2.7778e5
    model: ClassVar[str] = "liquid"
    is_liquid: ClassVar[bool] = True

    def __post_init__(self):
        _check_positive(self, density=self.density, bulk_modulus=self.bulk_modulus)

    def kernel_params(self):
        return {"lam": self.bulk_modulus}


@dataclass(frozen=True)
class ViscousLiquid(NewtonianLiquid):
    """Newtonian liquid plus the deviatoric viscous stress τ_v = 2 η J dev(sym ∇v). viscosity η in Pa·s."""

    viscosity_pas: float = 1.0
    model: ClassVar[str] = "viscous_liquid"

    def __post_init__(self):
        super().__post_init__()
        _check_positive(self, viscosity_pas=self.viscosity_pas)

    def kernel_params(self):
        return {"lam": self.bulk_modulus, "eta": self.viscosity_pas}


@dataclass(frozen=True)
class DampedLiquid(NewtonianLiquid):
    """Newtonian liquid plus a bulk viscosity ζ (Pa·s): τ_b = ζ J (∇·v) I. It damps the sound waves that the
    weakly compressible liquid otherwise keeps (a standing wave of wavenumber k decays at ζ k²/(2ρ); the ring
    of a column of depth H, k = π/2H) and does nothing to a divergence-free flow. A resolution-aware choice is
    ζ = α ρ c Δx (c the sound speed): its time-step limit ρΔx²/(6ζ) = Δx/(6αc) then stays above the
    sound-speed limit 0.5 Δx/c at every resolution for α ≤ 1/3. bench/sound_ring.py measures it."""

    bulk_viscosity_pas: float = 10.0
    model: ClassVar[str] = "damped_liquid"

    def __post_init__(self):
        super().__post_init__()
        _check_positive(self, bulk_viscosity_pas=self.bulk_viscosity_pas)

    def kernel_params(self):
        return {"lam": self.bulk_modulus, "zeta": self.bulk_viscosity_pas}


# --- catalogue (paper values mapped by the similarity above) -------------------------------------------
_LAMBDA = 277.78 * STRESS_UNIT_PA  # 2.7778e5 Pa, every material in the paper's table
_MU_SOFT = 208.33 * STRESS_UNIT_PA
_MU_STIFF = 416.67 * STRESS_UNIT_PA

WATER = NewtonianLiquid("water", density=1000.0, bulk_modulus=_LAMBDA, color=(0.25, 0.55, 0.95))
COFFEE = NewtonianLiquid("coffee", density=1000.0, bulk_modulus=_LAMBDA, color=(0.36, 0.22, 0.12))
# The paper's milk has the density of water and coffee (ρ = 1.0).
MILK = NewtonianLiquid("milk", density=1000.0, bulk_modulus=_LAMBDA, color=(0.96, 0.96, 0.92))
# The project's own: a milk foam half as dense as coffee, which floats (LatteArtStir's milk layer needs to float
# to keep a pattern on the surface; the paper's milk, as dense as coffee, would sink into it).
MILK_FOAM = NewtonianLiquid("milk_foam", density=500.0, bulk_modulus=_LAMBDA, color=(0.98, 0.97, 0.93))
# The paper's viscous liquids keep μ = 200 in a liquid model with F reset every 2e-4 s substep, i.e. an
# effective viscosity η ≈ μ·dt = 0.04 paper units = 40 Pa·s; we state it as a real viscosity instead.
FROTHED_MILK = ViscousLiquid("frothed_milk", density=500.0, bulk_modulus=_LAMBDA, viscosity_pas=40.0,
                             color=(0.98, 0.94, 0.85))
# The paper's light and heavy liquids (ρ = 0.8 and 1.5), those of its Fine Grained Pouring task.
LIGHT_LIQUID = NewtonianLiquid("light_liquid", density=800.0, bulk_modulus=_LAMBDA, color=(0.95, 0.75, 0.2))
HEAVY_LIQUID = NewtonianLiquid("heavy_liquid", density=1500.0, bulk_modulus=_LAMBDA, color=(0.6, 0.15, 0.55))
# The project's own pair for the Rayleigh–Taylor validation (ρ = 1 and 3): an Atwood number of 0.5 grows the
# interface fast enough to measure in a short run (tests/test_physics_solids.py).
RT_LIGHT = NewtonianLiquid("rt_light", density=1000.0, bulk_modulus=_LAMBDA, color=(0.95, 0.75, 0.2))
RT_HEAVY = NewtonianLiquid("rt_heavy", density=3000.0, bulk_modulus=_LAMBDA, color=(0.6, 0.15, 0.55))
# Paper: ρ = 0.5, μ = 416.67 with a yield of about 2.5e-3 strain, i.e. a yield stress ≈ 2μ·ε ≈ 2 kPa.
ICE_CREAM = VonMisesPlastic("ice_cream", density=500.0, shear_modulus=_MU_STIFF, lame_lambda=_LAMBDA,
                            yield_stress=2.0e3, color=(0.98, 0.88, 0.9))
ELASTIC = Elastic("elastic", density=1000.0, shear_modulus=_MU_STIFF, lame_lambda=_LAMBDA, color=(0.9, 0.3, 0.25))
# Paper: singular values clamped to [1 - 2e-3, 1 + 3e-3].
PLASTIC = Plastic("plastic", density=1000.0, shear_modulus=_MU_SOFT, lame_lambda=_LAMBDA, yield_compression=2e-3,
                  yield_stretch=3e-3, color=(0.55, 0.8, 0.35))
PLASTIC_VON_MISES = VonMisesPlastic("plastic_von_mises", density=1000.0, shear_modulus=_MU_SOFT,
                                    lame_lambda=_LAMBDA, yield_stress=1.0e3, color=(0.45, 0.7, 0.3))
# Paper: rigid bodies with ρ = 1, 0.5 (light) and 10 (heavy), λ = 277.78.
RIGID = Rigid("rigid", density=1000.0, bulk_modulus=_LAMBDA, color=(0.85, 0.65, 0.3))
RIGID_LIGHT = Rigid("rigid_light", density=500.0, bulk_modulus=_LAMBDA, color=(0.95, 0.8, 0.4))
RIGID_HEAVY = Rigid("rigid_heavy", density=10000.0, bulk_modulus=_LAMBDA, color=(0.4, 0.4, 0.45))

CATALOGUE: dict[str, Material] = {m.name: m for m in (
    WATER, MILK, MILK_FOAM, COFFEE, FROTHED_MILK, LIGHT_LIQUID, HEAVY_LIQUID, RT_LIGHT, RT_HEAVY, ICE_CREAM,
    ELASTIC, PLASTIC,
    PLASTIC_VON_MISES, RIGID, RIGID_LIGHT, RIGID_HEAVY)}


def get(name: str) -> Material:
    """A catalogue material by name; unknown names list the known ones."""
    try:
        return CATALOGUE[name.lower()]
    except KeyError:
        raise KeyError(f"unknown material {name!r}; known: {', '.join(sorted(CATALOGUE))}") from None
