"""What blocking a gas by face fractions costs against whole cells, side by side in one process.

    python bench/bench_gas_fractions.py [--sizes 32 48] [--steps 10] [--grad-steps 4] [--repeats 2] [--threads 1]
        [--arch cpu|cuda] [--solids tool static particles]

The scene: a box room of n³ cells (0.5 m across), air blown in through the x− wall at 1 m/s and out through the open
x+ wall, MacCormack advection, a pressure projection to a relative residual of 1e-6, dt = 0.4 Δx / (1 m/s). The
solid is one of
- "tool": a box paddle (0.12 × 0.08 × 0.2 m) in mid-room, moving across the stream at 0.1 m/s and turning about
  the vertical at 1 rad/s (so its faces' shares change every step);
- "static": a fixed cylinder (radius 0.06 m, axis vertical, centred at (0.25, 0.25, 0) so that it stands in the
  lower half of the room, up to z = 0.25 m; its shares are computed once, on the host);
- "particles": a water blob (0.1 m cube, MPM on a 16³ grid, gravity off) crossing the stream at 0.1 m/s; its
  steps include the particles' own MPM step, the same in both modes.
Each solid is run with `tool_faces` / `static_faces` / `particle_faces` "cells" and "fractions", alternating (cells,
fractions, cells, fractions, … for `--repeats` rounds) so that a drift of the machine's speed falls on both.

Measured per mode (medians over the timed steps after a warm-up that compiles):
- forward s/step: `sim.step` with the solid moving;
- boundaries s/step: the step's boundary stage alone (solid cells, face shares, the solver's flags and the
  closed-region labelling), timed over the same number of calls on the last state;
- MGPCG iterations per projection (mean over the timed steps);
- forward + backward s/step: `rollout(grad=True)` over `--grad-steps` steps with a linear loss on the final
  velocity (the fractional backward pass solves the projection once more per step, for the shares' gradient).
The ratio column is fractions / cells (above 1: fractions cost more). Results: bench/results/gas_fractions_<arch>.txt
and .json.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

L = 0.5
U = 1.0
TOL = 1e-6
MODES = ("cells", "fractions")


def build(fl, n: int, solid: str, mode: str, grad: bool):
    dx = L / n
    if solid == "particles":
        from fluidlab_core import materials as M

        scene = fl.Scene(lower=(0, 0, 0), upper=(L, L, L), grid_res=16, dt=0.4 * dx / U, gravity=(0, 0, 0))
        scene.add_gas(resolution=n, walls={"x-": (U, 0.0, 0.0), "x+": "open"}, tolerance=TOL, max_iterations=500,
                      particles_block=True, particle_faces=mode)
        scene.add_particles(fl.Box((0.2, 0.15, 0.2), (0.3, 0.25, 0.3)), M.WATER, name="blob", velocity=(0, 0.1, 0))
        scene.substeps = scene.stable_substeps()
        sim = scene.build(requires_grad=grad)
        start = sim.get_state(), sim.gas_state()
        start[1].velocity[0][:] = U
        return sim, start
    scene = fl.Scene(lower=(0, 0, 0), upper=(L, L, L), grid_res=n, dt=0.4 * dx / U)
    faces = {"tool_faces": mode} if solid == "tool" else {"static_faces": mode}
    scene.add_gas(resolution=n, walls={"x-": (U, 0.0, 0.0), "x+": "open"}, tolerance=TOL, max_iterations=500,
                  **faces)
    if solid == "tool":
        scene.add_tool(fl.Box((-0.06, -0.04, -0.1), (0.06, 0.04, 0.1)), pose=(0.25, 0.22, 0.25, 0, 0, 0, 1),
                       name="paddle", action_mask=(1, 1, 0, 0, 0, 1), max_speed=0.5)
    else:
        scene.add_static(fl.Cylinder((0.25, 0.25, 0.0), 0.06, L), name="post")
    sim = scene.build(requires_grad=grad)
    start = sim.get_state()
    start.gas.velocity[0][:] = U
    return sim, start


def actions(solid: str, steps: int):
    """The paddle's twist per step (m/s, rad/s): across the stream at 0.1 m/s, turning at 1 rad/s (None without
    tools)."""
    if solid != "tool":
        return [None] * steps
    a = np.zeros((steps, 6))
    a[:, 1] = 0.1
    a[:, 5] = 1.0
    return a


def set_start(sim, start):
    if isinstance(start, tuple):  # particles and gas
        sim.set_state(start[0])
        sim.set_gas_state(start[1])
    else:
        sim.set_state(start)


def measure(fl, n: int, solid: str, mode: str, steps: int, grad_steps: int, sync) -> dict:
    from fluidlab_core import losses

    sim, start = build(fl, n, solid, mode, grad=False)
    acts = actions(solid, steps + 1)
    set_start(sim, start)
    sim.step(acts[0])  # compiles
    sync()
    times, iters = [], []
    for k in range(steps):
        t0 = time.perf_counter()
        sim.step(acts[k + 1])
        sync()
        times.append(time.perf_counter() - t0)
        iters.append((sim.gas if solid == "particles" else sim.solver).poisson.last["iterations"])
    if solid == "particles":
        s = sim.gas
        coupling = sim.gas_coupling

        def particles():
            coupling.particles_to_gas(sim.state, 0)
    else:
        s = sim.solver
        particles = None
    s.prepare_boundaries(particles)
    sync()
    bt = []
    for _ in range(steps):
        t0 = time.perf_counter()
        s.prepare_boundaries(particles)
        sync()
        bt.append(time.perf_counter() - t0)
    out = {"forward_s": float(np.median(times)), "boundaries_s": float(np.median(bt)),
           "iterations": float(np.mean(iters))}
    if grad_steps > 0:
        gsim, gstart = build(fl, n, solid, mode, grad=True)
        # a linear functional of the final velocity (random weights): the wake depends on the solid's shares
        # (particles: a linear loss on the particles' final velocities, which the gas reaches through nothing here:
        # the backward pass still goes through the gas and its coupling)
        if solid == "particles":
            loss = losses.Linear(a=np.zeros((gsim.n_particles, 3)),
                                 b=np.random.default_rng(0).standard_normal((gsim.n_particles, 3)))
        else:
            loss = losses.GasLinear({"velocity": np.random.default_rng(0).standard_normal((n, n, n, 3))})
        ga = actions(solid, grad_steps) if solid == "tool" else grad_steps
        set_start(gsim, gstart)
        gsim.rollout(ga[:1] if solid == "tool" else 1, loss, grad=True)  # compiles forward and backward
        set_start(gsim, gstart)
        sync()
        t0 = time.perf_counter()
        gsim.rollout(ga, loss, grad=True)
        sync()
        out["forward_backward_s"] = (time.perf_counter() - t0) / grad_steps
    return out


def table(rows: list, arch: str, threads: int) -> str:
    lines = [f"Gas blocked by whole cells against face fractions, side by side ({arch}, {threads} thread(s)); "
             "stream at 1 m/s through a 0.5 m room, pressure to 1e-6; seconds per step (median over the timed "
             "steps, then over the rounds); ratio = fractions / cells.", "",
             f"{'solid':>9} {'grid':>5} {'what':>22} {'cells':>10} {'fractions':>10} {'ratio':>6}"]
    for r in rows:
        for key, what in (("forward_s", "forward s/step"), ("boundaries_s", "boundaries s/step"),
                          ("iterations", "MGPCG iterations"), ("forward_backward_s", "fwd+bwd s/step")):
            vals = [np.median([rnd[m][key] for rnd in r["rounds"] if key in rnd[m]]) if
                    any(key in rnd[m] for rnd in r["rounds"]) else float("nan") for m in MODES]
            fmt = ".1f" if key == "iterations" else ".4f"
            ratio = vals[1] / vals[0] if vals[0] else float("nan")
            lines.append(f"{r['solid']:>9} {r['n']:>4}³ {what:>22} {vals[0]:>10{fmt}} {vals[1]:>10{fmt}} "
                         f"{ratio:>6.2f}")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[32, 48])
    ap.add_argument("--steps", type=int, default=10, help="timed forward steps per mode and round")
    ap.add_argument("--grad-steps", type=int, default=4, help="steps of the timed gradient rollout (0 skips it)")
    ap.add_argument("--repeats", type=int, default=2, help="rounds of (cells, fractions)")
    ap.add_argument("--solids", nargs="+", default=["tool", "static", "particles"],
                    choices=["tool", "static", "particles"])
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    import fluidlab_core as fl

    fl.init(arch=args.arch, precision="f32", cpu_threads=args.threads)
    import taichi as ti

    out = Path(args.out or ROOT / "bench" / "results" / f"gas_fractions_{args.arch}")
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    for solid in args.solids:
        for n in args.sizes:
            row = {"solid": solid, "n": n, "rounds": []}
            rows.append(row)
            for rnd in range(args.repeats):
                res = {}
                for mode in MODES:
                    # the gradient rollout only in the first round: it compiles a new scene's kernels each time
                    res[mode] = measure(fl, n, solid, mode, args.steps, args.grad_steps if rnd == 0 else 0, ti.sync)
                    print(f"{solid} {n}³ round {rnd} {mode}: {res[mode]}", flush=True)
                row["rounds"].append(res)
                out.with_suffix(".json").write_text(json.dumps(rows, indent=1) + "\n")
                out.with_suffix(".txt").write_text(table(rows, args.arch, args.threads) + "\n")
    print(table(rows, args.arch, args.threads))


if __name__ == "__main__":
    main()
