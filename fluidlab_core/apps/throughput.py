"""Forward throughput of the MPM engine, in particle-substeps per second, with peak memory.

Scene (the issue's benchmark): a cube of water and an elastic cube in an open tank, 64³ grid over a 1 m cube
(the paper's unit domain), 8 particles per cell, substep 2e-4 s; the water is sized for the requested
particle count. Each size is warmed up (compilation) and then timed over a few steps. When `genesis-world`
is installed, the Genesis MPM liquid scene with the same grid, particle count and substep runs right after
ours (fluidlab_core/apps/genesis_compare.py) and the ratio is printed.

Figures are ratios against runs in the same process, so they compare like with like on one machine.
"""
from __future__ import annotations

import resource
import time

from fluidlab_core import materials as M
from fluidlab_core.scene import Scene
from fluidlab_core.shapes import Box, Tank

GRID_RES = 64
DOMAIN = 1.0  # m, cube side: the paper's unit cube, Δx = 15.6 mm
DT, SUBSTEPS = 2e-3, 10


def benchmark_scene(n_particles: int, elastic: bool = True) -> Scene:
    """Water (and a 5 % elastic cube) in a tank, sized to about n_particles particles."""
    scene = Scene(lower=(0, 0, 0), upper=(DOMAIN,) * 3, grid_res=GRID_RES, dt=DT, substeps=SUBSTEPS,
                  max_speed=1.0)
    dx = scene.dx
    wall = 2 * dx
    scene.add_static(Tank((0, 0, 0), (DOMAIN, DOMAIN, 0.75 * DOMAIN), wall), friction=0.1, name="tank")
    spacing = scene.particle_spacing
    volume = n_particles * spacing ** 3
    # a cube of water standing in the middle of the tank (it collapses while we time it), an elastic cube above
    side = ((0.95 if elastic else 1.0) * volume) ** (1 / 3)
    c, z0 = DOMAIN / 2, wall + spacing
    scene.add_particles(Box((c - side / 2, c - side / 2, z0), (c + side / 2, c + side / 2, z0 + side)), M.WATER,
                        name="water")
    if elastic:
        e = (0.05 * volume) ** (1 / 3)
        scene.add_particles(Box((c - e / 2, c - e / 2, z0 + side + dx), (c + e / 2, c + e / 2, z0 + side + dx + e)),
                            M.ELASTIC, name="elastic")
    return scene


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def time_ours(n_particles: int, steps: int) -> dict:
    scene = benchmark_scene(n_particles)
    t0 = time.perf_counter()
    sim = scene.build()
    sim.check_finite_every = 0  # time the physics alone
    sim.step()
    compile_s = time.perf_counter() - t0
    sim.solver.grid_m.to_numpy()  # synchronise
    t0 = time.perf_counter()
    sim.step(n=steps)
    sim.solver.grid_m.to_numpy()
    elapsed = time.perf_counter() - t0
    n = sim.n_particles
    return {"particles": n, "rate": n * SUBSTEPS * steps / elapsed, "elapsed": elapsed, "compile": compile_s,
            "peak_rss_mb": _peak_rss_mb()}


def time_genesis(n_particles: int, steps: int):
    """The liquid scene in Genesis (CPU), or None when genesis-world is not installed.

    Genesis runs in a child process (see genesis_compare); it is only looked up here, not imported, so that its
    ~0.5 GB of imports (torch) do not count in our peak RSS."""
    import importlib.util

    if importlib.util.find_spec("genesis") is None:
        return None
    from fluidlab_core.apps import genesis_compare

    return genesis_compare.time_liquid(n_particles, steps, GRID_RES, DOMAIN, DT, SUBSTEPS)


def main(particles=(20_000, 50_000, 100_000), steps: int = 5, genesis: bool = True, log=print):
    from fluidlab_core import runtime

    cfg = runtime.ensure_init()
    log(f"MPM forward throughput: {GRID_RES}^3 grid, water + elastic in a tank, substep {DT / SUBSTEPS:.0e} s, "
        f"backend {cfg.backend}/{cfg.precision}")
    log(f"{'particles':>10} {'M p-substeps/s':>15} {'s/step':>8} {'compile s':>10} {'peak RSS MB':>12} "
        f"{'Genesis M/s':>12} {'ours/Genesis':>13}")
    rows = []
    for n in particles:
        ours = time_ours(n, steps)
        theirs = time_genesis(ours["particles"], steps) if genesis else None
        ratio = f"{ours['rate'] / theirs['rate']:.2f}" if theirs else "-"
        g_rate = f"{theirs['rate'] / 1e6:.2f}" if theirs else "-"
        log(f"{ours['particles']:>10} {ours['rate'] / 1e6:>15.2f} {ours['elapsed'] / steps:>8.3f} "
            f"{ours['compile']:>10.1f} {ours['peak_rss_mb']:>12.0f} {g_rate:>12} {ratio:>13}")
        rows.append((ours, theirs))
    if genesis and rows and rows[0][1] is None:
        log("(genesis-world is not installed: no comparison)")
    return rows


if __name__ == "__main__":
    main()
