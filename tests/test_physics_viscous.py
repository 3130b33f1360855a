"""Viscous liquid: the decay of a vortex against the Navier–Stokes (Taylor–Green) solution."""
import numpy as np

import fluidlab_core as fl
from fluidlab_core import materials as M
from tests.conftest import report


def _vortex_decay_rate(material, res=24, size=0.1, amplitude=0.1, duration=0.2, every=10):
    """Fill a square slab between frictionless walls (no gravity) with the cellular vortex of stream function
    ψ = (U/k) sin(kx) sin(kz), k = π/L, and fit the decay rate (1/s) of that mode's amplitude.

    The mode satisfies the free-slip walls exactly and its inertial term is a pure gradient, so in a
    Newtonian liquid it decays as exp(−2 ν k² t), ν = η/ρ (the Taylor–Green solution)."""
    dx = size / res
    scene = fl.Scene(lower=(0, 0, 0), upper=(size, 2 * dx, size), grid_res=res, dt=1e-3, substeps=9 * max(1, res // 24),
                     gravity=(0.0, 0.0, 0.0), max_speed=amplitude)
    scene.add_particles(fl.Box((0, 0, 0), (size, 2 * dx, size)), material, name="liquid")
    sim = scene.build()
    state = sim.get_state()
    k = np.pi / size

    def mode(x):
        sx, cx, sz, cz = np.sin(k * x[:, 0]), np.cos(k * x[:, 0]), np.sin(k * x[:, 2]), np.cos(k * x[:, 2])
        return np.stack([sx * cz, np.zeros_like(sx), -cx * sz], axis=1), (sx, cx, sz, cz)

    shape, (sx, cx, sz, cz) = mode(state.x.astype(np.float64))
    state.v[:] = amplitude * shape
    grad = np.zeros((len(sx), 3, 3))  # APIC affine velocity C = ∇v
    grad[:, 0, 0], grad[:, 0, 2] = amplitude * k * cx * cz, -amplitude * k * sx * sz
    grad[:, 2, 0], grad[:, 2, 2] = amplitude * k * sx * sz, -amplitude * k * cx * cz
    state.C[:] = grad
    sim.set_state(state)
    times, amplitudes = [], []
    while sim.time <= duration:
        shape, _ = mode(sim.positions("liquid"))
        times.append(sim.time)
        amplitudes.append(float((sim.velocities("liquid") * shape).sum() / (shape * shape).sum()))
        sim.step(n=every)
    return -np.polyfit(times, np.log(amplitudes), 1)[0], k


def test_viscous_vortex_decays_at_the_navier_stokes_rate():
    """The vortex decays at 2νk² (9.87 and 39.5 /s for η = 5 and 20 Pa·s, ρ = 1000 kg/m³) on top of the scheme's
    own dissipation, which we measure with inviscid water in the same set-up. Over the first 10 ms the excess
    decay rate must match 2νk² within 10 %.

    Measured as well, and printed: over 50 ms the excess grows to 1.7-2.4× 2νk² (and the inviscid rate
    fluctuates between 7 and 15 /s), independently of the amplitude, so it is a linear coupling of the mode to
    others (the walls' half-cell treatment and sound waves), not the viscous stress itself. Closing that gap is
    open work."""
    baseline, k = _vortex_decay_rate(M.WATER, duration=0.01, every=1)
    baseline_50ms, _ = _vortex_decay_rate(M.WATER, duration=0.05)
    for eta in (5.0, 20.0):
        liquid = M.ViscousLiquid(f"viscous_{eta:g}", density=1000.0, viscosity_pas=eta)
        rate, _ = _vortex_decay_rate(liquid, duration=0.01, every=1)
        rate_50ms, _ = _vortex_decay_rate(liquid, duration=0.05 if eta < 10 else 0.03)
        expected = 2 * eta / liquid.density * k ** 2
        report("viscous decay", viscosity_pas=eta, navier_stokes_per_s=expected, rate_10ms=rate,
               inviscid_10ms=baseline, excess_ratio_10ms=(rate - baseline) / expected, rate_50ms=rate_50ms,
               inviscid_50ms=baseline_50ms, excess_ratio_50ms=(rate_50ms - baseline_50ms) / expected)
        assert abs((rate - baseline) / expected - 1.0) < 0.10
