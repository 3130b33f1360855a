"""The demo scene the README's first command runs: a water column collapses in a tank around a floating
block while an elastic ball and a lump of plastic drop into it. Written as PNG frames.

Sizes: "small" (default; about 30k particles on a 40-cell grid, a minute or two on a laptop CPU) and
"paper" (64-cell grid, about 8 particles per cell).
"""
from __future__ import annotations

import time
from pathlib import Path

from fluidlab_core import materials as M
from fluidlab_core.scene import Scene
from fluidlab_core.shapes import Box, Sphere, Tank

SIZES = {"small": 40, "paper": 64}


def build_scene(size: str = "small", seed: int = 0) -> Scene:
    """A tank 0.40 × 0.20 m standing at x = 0.35..0.75 m in front of the robot base (world frame fr3_link0)."""
    if size not in SIZES:
        raise ValueError(f"unknown size {size!r}; choose one of {', '.join(SIZES)}")
    lower, upper = (0.35, -0.12, 0.0), (0.75, 0.12, 0.28)
    scene = Scene(lower=lower, upper=upper, grid_res=SIZES[size], dt=2e-3, substeps=16, seed=seed)
    wall = 2.0 * scene.dx
    tank = Tank((0.35, -0.12, 0.0), (0.75, 0.12, 0.22), wall_thickness=wall)
    scene.add_static(tank, friction=0.2, name="tank")
    inner = tank.interior(0.06)
    lo, hi = inner.lower, inner.upper
    scene.add_particles(Box(lo, (lo[0] + 0.10, hi[1], lo[2] + 0.12)), M.WATER, name="water_column")
    scene.add_particles(Box((lo[0] + 0.10, lo[1], lo[2]), (hi[0], hi[1], lo[2] + 0.03)), M.WATER, name="water_layer")
    scene.add_particles(Box((0.60, -0.03, lo[2] + 0.035), (0.66, 0.03, lo[2] + 0.065)), M.RIGID_LIGHT, name="block")
    scene.add_particles(Sphere((0.52, 0.04, 0.20), 0.025), M.ELASTIC, name="ball")
    scene.add_particles(Box((0.60, -0.07, 0.17), (0.64, -0.03, 0.21)), M.PLASTIC, name="plastic")
    scene.substeps = scene.stable_substeps()  # finer grids need shorter substeps
    return scene


def run(out_dir: str | Path = "out/demo", size: str = "small", duration: float = 1.0, frames: int = 10,
        view: str = "iso", seed: int = 0, log=None) -> list[Path]:
    """Simulate `duration` seconds and write `frames` + 1 PNG pictures to out_dir; returns their paths."""
    if duration <= 0 or frames < 1:
        raise ValueError("duration must be positive and frames at least 1")
    log = log or (lambda text: print(text, flush=True))
    out = Path(out_dir)
    scene = build_scene(size, seed)
    log(f"building the demo scene ({size}: grid {scene.grid_res}, dx = {scene.dx * 1000:.1f} mm, "
        f"{scene.substeps} substeps per {scene.dt * 1000:.0f} ms step) ...")
    t0 = time.perf_counter()
    sim = scene.build()
    log(f"{sim.n_particles} particles, fields allocated in {time.perf_counter() - t0:.1f} s; the first step "
        f"compiles the solver's kernels (about a minute on two cores the first time, seconds once Taichi has "
        f"cached them)")
    steps = max(1, round(duration / scene.dt))
    every = max(1, steps // frames)
    def picture():
        path = out / f"frame_{sim.step_count:04d}.png"
        sim.render(path, view=view, title=f"t = {sim.time:.3f} s")
        return path

    paths = [picture()]
    t0 = time.perf_counter()
    while sim.step_count < steps:
        sim.step(n=min(every, steps - sim.step_count))
        paths.append(picture())
        rate = sim.step_count * scene.substeps * sim.n_particles / (time.perf_counter() - t0)
        log(f"  step {sim.step_count}/{steps}  t = {sim.time:.3f} s  ({rate / 1e6:.2f} M particle-substeps/s)"
            f"  -> {paths[-1]}")
    return paths
