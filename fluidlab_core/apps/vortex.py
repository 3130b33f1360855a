"""The cellular (Taylor–Green) vortex between free-slip walls: the engine's check on viscous decay and on its
own numerical dissipation (tests/test_physics_viscous.py, bench/numerical_dissipation.py).

A square slab of side L, two cells thick, without gravity, holds the mode of stream function
    ψ = (U/k) sin(kx) sin(kz),  k = π/L,   v = (sin kx cos kz, 0, −cos kx sin kz) U,
whose affine velocity C = ∇v the particles start with. The mode satisfies the free-slip walls exactly and its
inertial term is a pure gradient, so in a Newtonian liquid it decays as exp(−2νk²t), ν = η/ρ; in an inviscid
one it keeps its amplitude, and any decay is the scheme's. The amplitude is the projection of the particle
velocities onto the mode at their current positions, fitted with an exponential over the run.
"""
from __future__ import annotations

import math

import numpy as np


def mode_shape(x, k: float):
    """The mode's velocity shape at positions x (N, 3) and its sines and cosines (sx, cx, sz, cz)."""
    sx, cx, sz, cz = np.sin(k * x[:, 0]), np.cos(k * x[:, 0]), np.sin(k * x[:, 2]), np.cos(k * x[:, 2])
    return np.stack([sx * cz, np.zeros_like(sx), -cx * sz], axis=1), (sx, cx, sz, cz)


def vortex_simulator(material, res: int = 24, size: float = 0.1, amplitude: float = 0.1,
                     substeps: int | None = None, substep_factor: float = 1.0, flip: float = 0.0,
                     jbar: bool = False):
    """(simulator, k 1/m) of the slab started on the mode: velocities and their gradient C = ∇v. flip: the
    Scene's AFLIP share, jbar its J-bar (engine/transfer.py)."""
    import fluidlab_core as fl

    dx = size / res
    scene = fl.Scene(lower=(0, 0, 0), upper=(size, 2 * dx, size), grid_res=res, dt=1e-3, substeps=substeps or 1,
                     gravity=(0.0, 0.0, 0.0), max_speed=amplitude, flip=flip, jbar=jbar)
    scene.add_particles(fl.Box((0, 0, 0), (size, 2 * dx, size)), material, name="liquid")
    if substeps is None:
        scene.substeps = max(1, int(round(scene.stable_substeps() * substep_factor)))
    sim = scene.build()
    k = math.pi / size
    state = sim.get_state()
    shape, (sx, cx, sz, cz) = mode_shape(state.x.astype(np.float64), k)
    state.v[:] = amplitude * shape
    grad = np.zeros((len(sx), 3, 3))  # APIC affine velocity C = ∇v
    grad[:, 0, 0], grad[:, 0, 2] = amplitude * k * cx * cz, -amplitude * k * sx * sz
    grad[:, 2, 0], grad[:, 2, 2] = amplitude * k * sx * sz, -amplitude * k * cx * cz
    state.C[:] = grad
    sim.set_state(state)
    return sim, k


def decay_rate(material, res: int = 24, size: float = 0.1, amplitude: float = 0.1, duration: float = 0.2,
               every: int = 10, substeps: int | None = None, substep_factor: float = 1.0, flip: float = 0.0,
               jbar: bool = False):
    """(fitted decay rate 1/s, k 1/m, substeps per 1 ms step) of the vortex in `material`. substeps: per 1 ms
    step (default: the stable count × substep_factor); flip: the AFLIP share (0: APIC); jbar: the Scene's J-bar."""
    sim, k = vortex_simulator(material, res, size, amplitude, substeps, substep_factor, flip, jbar)
    times, amps = [], []
    while sim.time <= duration:
        shape, _ = mode_shape(sim.positions("liquid"), k)
        times.append(sim.time)
        amps.append(float((sim.velocities("liquid") * shape).sum() / (shape * shape).sum()))
        sim.step(n=every)
    return -np.polyfit(times, np.log(amps), 1)[0], k, sim.model.substeps
