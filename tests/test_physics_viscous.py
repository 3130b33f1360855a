"""Viscous liquid: the decay of a vortex against the Navier–Stokes (Taylor–Green) solution."""
import numpy as np

import fluidlab_core as fl
from fluidlab_core import materials as M
from tests.conftest import report


def _vortex_decay_rate(material, res=24, size=0.1, amplitude=0.1, duration=0.2):
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

    shape, (sx, cx, sz, cz) = mode(state["x"].astype(np.float64))
    state["v"][:] = amplitude * shape
    grad = np.zeros((len(sx), 3, 3))  # APIC affine velocity C = ∇v
    grad[:, 0, 0], grad[:, 0, 2] = amplitude * k * cx * cz, -amplitude * k * sx * sz
    grad[:, 2, 0], grad[:, 2, 2] = amplitude * k * sx * sz, -amplitude * k * cx * cz
    state["C"][:] = grad
    sim.set_state(state)
    times, amplitudes = [], []
    while sim.time <= duration:
        shape, _ = mode(sim.positions("liquid"))
        times.append(sim.time)
        amplitudes.append(float((sim.velocities("liquid") * shape).sum() / (shape * shape).sum()))
        sim.step(n=10)
    return -np.polyfit(times, np.log(amplitudes), 1)[0], k


def test_viscous_vortex_decays_faster_with_viscosity_at_about_the_navier_stokes_rate():
    """The vortex decays at 2νk² plus the scheme's own dissipation, which we measure with inviscid water in the
    same set-up (about 10 /s at 24 cells across: APIC transfers smooth the velocity a little every substep).

    Known result checked: the excess decay rate over that baseline grows with the viscosity and matches
    2νk² (9.9 and 39.5 /s for η = 5 and 20 Pa·s, ρ = 1000 kg/m³) to within a factor between 0.8 and 2.6.
    The bound is loose on purpose and says what we measure: at this resolution the discretised viscous
    stress over-damps by 2.4× (η = 5) and 1.7× (η = 20), and by 1.6× (η = 5) at twice the resolution, so
    the error shrinks with the grid but is not yet small. Tightening it is open work."""
    baseline, k = _vortex_decay_rate(M.WATER, duration=0.05)
    ratios, rates = [], [baseline]
    for eta in (5.0, 20.0):
        liquid = M.ViscousLiquid(f"viscous_{eta:g}", density=1000.0, viscosity_pas=eta)
        rate, _ = _vortex_decay_rate(liquid, duration=0.05 if eta < 10 else 0.03)
        expected = 2 * eta / liquid.density * k ** 2
        ratios.append((rate - baseline) / expected)
        rates.append(rate)
        report("viscous decay", viscosity_pas=eta, rate_per_s=rate, inviscid_baseline_per_s=baseline,
               navier_stokes_per_s=expected, excess_over_navier_stokes=ratios[-1])
    assert all(0.8 <= r <= 2.6 for r in ratios), ratios
    assert rates[0] < rates[1] < rates[2], rates
