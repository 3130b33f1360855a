"""Liquid validation against known physics: dam break (Martin & Moyce 1952), hydrostatics, and the damping of
sound waves by a bulk viscosity.

Quasi-2-D set-ups: a slab two cells thick between frictionless walls, which behaves as the 2-D experiments
and keeps the tests within CI's time. The scenes are fluidlab_core/apps/validation.py's, which
bench/convergence.py runs at three resolutions.
"""
import numpy as np
import pytest

import fluidlab_core as fl
from fluidlab_core import materials as M
from fluidlab_core.apps import validation
from fluidlab_core.apps.validation import MARTIN_MOYCE_N2
from tests.conftest import report


def test_dam_break_surge_front_matches_martin_moyce():
    """The surge front of a collapsing water column against Martin & Moyce's measurements.

    Tolerance: the simulated Z may lead the measurement by up to 25 % and lag it by up to 10 % for
    0.8 ≤ T ≤ 3.4. Frictionless, inviscid simulations (SPH, MPS and MPM alike) run ahead of this experiment by
    10-20 %: the gate took a finite time to lift and the floor was not frictionless. The front speed dZ/dT
    over 1.5 ≤ T ≤ 3 must lie between the experiment's (≈1.3) and the shallow-water (Ritter) limit of 2
    (front speed 2·sqrt(g·2a)). A wrong gravity, density, time step or boundary fails both.
    """
    r = validation.dam_break(res=64, substeps=10)
    ratio, speed = r["ratio"], r["speed"]
    report("dam break", dx_m=r["dx"], particles=r["particles"], min_ratio=ratio.min(), max_ratio=ratio.max(),
           front_speed_dZdT=speed)
    z_sim = r["z_sim"]
    for (T, Z), zs in zip(MARTIN_MOYCE_N2, z_sim):
        print(f"  T={T:.3f}  Z_exp={Z:.3f}  Z_sim={zs:.3f}")
    assert np.all(ratio <= 1.25) and np.all(ratio >= 0.90), ratio
    assert speed >= 1.2 and speed <= 2.0, speed


def test_water_at_rest_keeps_volume_and_hydrostatic_pressure():
    """10,000 substeps of water at rest in a box: volume Σ V⁰ det F within 1 % all along, the free surface
    where it started, and the time-averaged pressure linear in depth with slope ρ g within 5 %.

    The weakly compressible liquid rings with sound waves (period 4H/c ≈ 30 ms) that APIC barely damps, so
    pressure is averaged over the last 0.2 s (≈ 7 periods). Particles within 1.5 cells of the floor are left
    out of the fit: their B-spline support reaches into the wall nodes, which lowers their pressure.
    """
    height = 0.12
    r = validation.water_column(res=16, height=height, steps=1000, average=100, substeps=10)
    worst, surface, slope, rho_g, r2, intercept = (r[k] for k in ("worst_volume_error", "surface", "slope", "rho_g",
                                                                  "r2", "intercept"))
    dx = r["dx"]
    report("hydrostatics", substeps=r["substeps"], worst_volume_error=worst, surface_m=surface, slope_Pa_per_m=slope,
           rho_g=rho_g, slope_ratio=slope / rho_g, r2=r2, intercept_Pa=intercept)
    assert worst < 0.01
    assert abs(surface - height) < 0.5 * dx
    assert abs(slope / rho_g - 1.0) < 0.05
    assert r2 > 0.99
    assert abs(intercept) < 0.05 * rho_g * height  # zero pressure at the free surface


def test_cup_holds_water_for_two_seconds():
    """Water in a cup whose walls are the minimum 2 cells thick, given a gentle 0.1 m/s push so that it sloshes
    against the wall, stands for 2 simulated seconds: no particle enters the wall or gets outside the cavity,
    and the volume is kept within 1 %."""
    res, size = 20, 0.1
    dx = size / res
    cup = fl.Cup((0.05, 0.05, 0.0), outer_radius=0.035, height=0.06, wall_thickness=2 * dx)
    scene = fl.Scene(lower=(0, 0, 0), upper=(size, size, 0.08), grid_res=res, dt=2e-3, substeps=15)
    scene.add_static(cup, friction=0.2)
    scene.add_particles(cup.interior(0.03), M.WATER, name="water", velocity=(0.1, 0.0, 0.0))
    sim = scene.build()
    v0 = sim.volumes("water").sum()
    worst_out, worst_in_wall, worst_volume = -1.0, 0, 0.0
    while sim.time < 2.0:
        sim.step(n=10)
        x = sim.positions("water")
        worst_out = max(worst_out, float(cup._hollow().sdf(x).max()))  # > 0: outside the cavity
        worst_in_wall = max(worst_in_wall, int((cup.sdf(x) < -1e-4).sum()))
        worst_volume = max(worst_volume, abs(sim.volumes("water").sum() / v0 - 1))
    report("cup", dx_m=dx, wall_m=cup.wall_thickness, particles=sim.n_particles,
           farthest_outside_cavity_m=worst_out, particles_in_wall=worst_in_wall, worst_volume_error=worst_volume)
    assert worst_in_wall == 0
    assert worst_out <= 1e-4
    assert worst_volume < 0.01


def test_bulk_viscosity_damps_the_sound_ring_at_the_viscous_rate():
    """A 6 cm water column released without its hydrostatic pressure rings with a quarter wave, period 4H/c
    (14.4 ms). The catalogue's water barely damps it (0.8 /s at these 16 cells, 0.4 /s at 24). With a bulk
    viscosity ζ = 50 Pa·s (materials.DampedLiquid) linear acoustics damps it at ζk²/(2ρ) = 17.1 /s, k = π/2H.

    Measured at 16 cells: 17.0 /s, period 15.0 ms (the discrete wave is 4 % slow), mean pressure 1.001 × ρgΔz.
    Tolerances: the rate within 15 % of the theory (the scheme's own 0.8 /s is 5 %), the period within 10 %, the
    mean within 3 %. bench/sound_ring.py shows what the damping leaves alone (vortex, dam break, surface)."""
    zeta, depth = 50.0, 0.06
    liquid = M.DampedLiquid("water_damped", density=1000.0, bulk_modulus=M.WATER.bulk_modulus, bulk_viscosity_pas=zeta)
    r = validation.sound_ring(res=16, depth=depth, seconds=0.3, liquid=liquid)
    theory = zeta * (np.pi / (2 * depth)) ** 2 / (2 * liquid.density)
    report("sound ring, bulk viscosity", zeta_Pas=zeta, decay_per_s=r["decay_rate"], theory_per_s=theory,
           period_ms=r["period"] * 1e3, period_theory_ms=r["period_theory"] * 1e3, mean_over_hydro=r["mean_over_hydro"])
    assert abs(r["decay_rate"] / theory - 1.0) < 0.15
    assert abs(r["period"] / r["period_theory"] - 1.0) < 0.1
    assert abs(r["mean_over_hydro"] - 1.0) < 0.03


def test_water_started_at_its_hydrostatic_compression_does_not_ring():
    """Simulator.start_hydrostatic gives each liquid particle the compression of the weight above it
    (J = 1 − p/λ). The same 6 cm column as above, 16 cells: released at J = 1 its mid-depth pressure swings by
    309 Pa about the hydrostatic 294 Pa; started hydrostatic it starts at 0.994 of it and stays within 20 Pa
    over 0.2 s (measured). Bounds: the start within 3 % of ρgΔz, the largest deviation under 0.15 ρgΔz (44 Pa)
    and under a quarter of the swing of the release from J = 1, run here beside it. Bad input is refused: gravity
    off the axes, and a liquid too soft for its depth (J < 0.5) named with its pressure and bulk modulus."""
    released = validation.sound_ring(res=16, seconds=0.2)
    settled = validation.sound_ring(res=16, seconds=0.2, hydrostatic=True)
    hydro = settled["hydro"]
    worst = float(np.abs(settled["pressures"] - hydro).max())
    report("hydrostatic start", hydrostatic_Pa=hydro, swing_from_J1_Pa=released["first_swing"],
           start_over_hydro=settled["pressures"][0] / hydro, worst_deviation_Pa=worst)
    assert abs(settled["pressures"][0] / hydro - 1.0) < 0.03
    assert worst < 0.15 * hydro and worst < 0.25 * released["first_swing"]

    for gravity, liquid, message in (((3.0, 0.0, -9.0), M.WATER, "gravity along one axis"),
                                     ((0.0, 0.0, -9.81), M.NewtonianLiquid("mud_soft", density=1000.0,
                                                                           bulk_modulus=500.0), "too soft")):
        scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.02, 0.1), grid_res=8, dt=1e-3, substeps=4, gravity=gravity)
        scene.add_particles(fl.Box((0, 0, 0), (0.1, 0.02, 0.06)), liquid, name="water")
        sim = scene.build()
        with pytest.raises(ValueError, match=message):
            sim.start_hydrostatic()
