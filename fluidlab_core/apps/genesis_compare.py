"""The benchmark's liquid scene in Genesis (`genesis-world`), timed like ours, for the ours/Genesis ratio.

What is compared: forward MLS-MPM throughput in particle-substeps per second on the CPU backend, float32,
for the same grid, particle density and substep as `fluidlab_core.apps.throughput`:

* domain: the cube [0, domain]^3 (0.4 m); `MPMOptions(lower_bound=(0,0,0), upper_bound=(domain,)*3,
  grid_density=grid_res / domain)`, i.e. 64 cells across (Genesis allocates 65 nodes per axis and keeps
  particles 3 cells inside the walls);
* particles: `particle_size = 0.5 * dx` (Genesis gives each particle the volume particle_size^3), i.e. 8 per
  cell, sampled with the `regular` sampler (a lattice, like ours, and a deterministic count);
* material: `gs.materials.MPM.Liquid(rho=1000)` with its defaults E = 1e6 Pa, nu = 0.2, i.e.
  lambda = 2.78e5 Pa, the same bulk modulus as our `WATER`; inviscid (no SVD);
* time: `SimOptions(dt=dt, substeps=substeps)`: Genesis integrates dt / substeps per substep (2e-4 s in the
  bench), which is our substep; one `scene.step()` is one of our `sim.step()`. Genesis warns that this is
  above its rule of thumb 2e-2 * dx (1.25e-4 s); the liquid block stays stable over the timed steps;
* scene: one water block resting on the floor, centred, with the fewest whole lattice layers that hold
  `n_particles` inside Genesis's safety padding and a square footprint sized to match the count (e.g. 20000
  -> 100 x 100 x 2; the count actually sampled is returned); no viewer, no rigid bodies.

Differences that remain: our bench scene also holds a 5 % elastic cube and a static tank (SDF collision),
which Genesis's liquid-only scene does not; Genesis's walls are the grid boundary condition. The ratio is
therefore a like-for-like measure of the P2G / grid / G2P pipeline for liquid, not of identical scenes.

Genesis ships its own Taichi fork (`quadrants`), so it can share a process with `taichi`; `time_liquid` still
runs Genesis in a child process (`python -m fluidlab_core.apps.genesis_compare ...`, which prints one JSON line),
so that its threads, memory and one-shot `gs.init` do not disturb our timings and peak-RSS figures. Pass
`in_process=True` to run it in the caller's process instead. Nothing here imports genesis at module import.
Written against genesis-world 1.4.5 (quadrants 1.3.3) with torch 2.13.0+cpu; `gs.init(backend=gs.cpu,
precision="32", logging_level="warning")`. The first run compiles Genesis's kernels (~25 s here); later runs
load them from quadrants' offline cache (~5-10 s), and are reported under "compile", outside the timing.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def liquid_block(n_particles: int, grid_res: int, domain: float):
    """(lower, upper, spacing) of a water block of about n_particles on the lattice Genesis samples.

    The block is centred in x, y inside Genesis's safety padding and rests one spacing above it; it has the
    fewest whole layers that fit n_particles in that footprint, and a square footprint sized to match the count.
    """
    dx = domain / grid_res
    spacing = 0.5 * dx
    pad = 3 * dx  # Genesis's MPM boundary padding
    n_xy_max = int((domain - 2 * pad - 2 * spacing) / spacing + 1e-9)
    n_z = max(1, -(-n_particles // n_xy_max ** 2))
    n_xy = min(n_xy_max, max(1, round((n_particles / n_z) ** 0.5)))
    if pad + spacing + n_z * spacing > domain - pad:
        raise ValueError(f"{n_particles} particles do not fit in a {domain} m cube at {grid_res}^3")
    side = n_xy * spacing  # whole lattice cells, so the regular sampler gives n_xy^2 * n_z
    lo_xy = 0.5 * (domain - side)
    z0 = pad + spacing
    return (lo_xy, lo_xy, z0), (lo_xy + side, lo_xy + side, z0 + n_z * spacing), spacing


def _run_in_process(n_particles: int, steps: int, grid_res: int, domain: float, dt: float,
                    substeps: int) -> dict:
    import genesis as gs

    if not getattr(gs, "_initialized", False):
        gs.init(backend=gs.cpu, precision="32", logging_level="warning")
    import quadrants as qd

    dx = domain / grid_res
    lower, upper, spacing = liquid_block(n_particles, grid_res, domain)
    t0 = time.perf_counter()
    scene = gs.Scene(
        sim_options=gs.options.SimOptions(dt=dt, substeps=substeps),
        mpm_options=gs.options.MPMOptions(lower_bound=(0.0, 0.0, 0.0), upper_bound=(domain,) * 3,
                                          grid_density=1.0 / dx, particle_size=spacing),
        show_viewer=False,
    )
    water = scene.add_entity(
        material=gs.materials.MPM.Liquid(rho=1000.0, sampler="regular"),
        morph=gs.morphs.Box(lower=lower, upper=upper),
    )
    scene.build()
    scene.step()  # compile
    qd.sync()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(steps):
        scene.step()
    qd.sync()
    elapsed = time.perf_counter() - t0
    n = int(water.n_particles)
    pos = water.get_particles_pos()
    pos = pos.cpu().numpy() if hasattr(pos, "cpu") else pos
    finite = bool(np.isfinite(pos).all())
    solver = scene.sim.mpm_solver
    return {"rate": n * substeps * steps / elapsed, "particles": n, "elapsed": elapsed, "compile": compile_s,
            "steps": steps, "substeps": substeps, "substep_dt": float(solver.substep_dt),
            "grid_res": [int(r) for r in solver.grid_res], "dx": float(solver.dx),
            "finite": finite, "z_max": float(pos[..., 2].max()), "genesis": str(gs.__version__)}


def time_liquid(n_particles: int, steps: int, grid_res: int, domain: float, dt: float, substeps: int,
                in_process: bool = False, timeout: float = 1800.0) -> dict:
    """Time `steps` Genesis steps of the liquid scene (after one warm-up step that compiles).

    Returns {"rate": particle-substeps per second, "particles", "elapsed" (s, the timed steps), "compile" (s,
    build and first step), ...}. Runs in a child process of the same interpreter unless in_process.
    """
    if in_process:
        return _run_in_process(n_particles, steps, grid_res, domain, dt, substeps)
    root = str(Path(__file__).resolve().parents[1])
    env = dict(os.environ)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    cmd = [sys.executable, "-m", "fluidlab_core.apps.genesis_compare", "--particles", str(n_particles),
           "--steps", str(steps), "--grid-res", str(grid_res), "--domain", repr(domain), "--dt", repr(dt),
           "--substeps", str(substeps)]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=root, env=env, timeout=timeout)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr or proc.stdout)[-2000:]
        raise RuntimeError(f"Genesis run failed (exit {proc.returncode}):\n{tail}")
    return json.loads(lines[-1])


def main(argv=None):
    parser = argparse.ArgumentParser(description="Time the benchmark's liquid scene in Genesis (CPU); "
                                                 "prints one JSON line.")
    parser.add_argument("--particles", type=int, default=20_000)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--grid-res", type=int, default=64)
    parser.add_argument("--domain", type=float, default=0.4)
    parser.add_argument("--dt", type=float, default=2e-3)
    parser.add_argument("--substeps", type=int, default=10)
    args = parser.parse_args(argv)
    result = _run_in_process(args.particles, args.steps, args.grid_res, args.domain, args.dt, args.substeps)
    print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
