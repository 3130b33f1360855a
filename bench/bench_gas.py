"""Gas solver throughput: a smoke plume at 64³ and 128³, forward and forward + backward, beside PhiFlow solving the
same plume to the same pressure tolerance in the same process.

    python bench/bench_gas.py [--sizes 64 128] [--steps 8 3] [--arch cpu|cuda] [--threads 1] [--no-phiflow]
        [--report-only]

The plume (both solvers): a closed cube of side 0.5 m, a heater centred 0.05 m above the floor that sets the
temperature excess to 30 K inside it every step (ours: a disc source of radius 0.05 m and half thickness 0.05 m, a
soft-edged upright cylinder; PhiFlow: a soft sphere of radius 0.05 m, its nearest shape: the heated volumes differ
by about a third, the grids and what a step computes do not), Boussinesq buoyancy a = g β ΔT with β = 1/293.15 K,
MacCormack advection of the temperature and of the velocity, a pressure projection to a relative residual of 1e-6,
dt = 0.02 s. Ours also carries a smoke density (its second scalar); PhiFlow carries one scalar.
Ours: fluidlab_core's GasSimulator (MGPCG; fields float32, the solve float64). PhiFlow: `phiflow` (3.4) on its
torch backend in float64 (its float32 CG does not reach 1e-6: it stalled at 2e-5 after 2000 iterations at 64³),
`Solve('CG', 1e-6, 0)` for the pressure (unpreconditioned CG on an explicit sparse matrix). At 128³ a PhiFlow step
takes minutes, so it is timed over fewer steps (--phiflow-steps) and its gradient only at 64³ by default.

Forward + backward: the gradient of a linear functional of the final temperature with respect to the initial
velocity over the same steps (ours: rollout(grad=True); PhiFlow: math.gradient on the torch backend).

Also measured: the projection's cost against one V-cycle of our multigrid per digit of residual reduction (the
issue's bar: within 3×), i.e. (seconds per pressure solve) / (seconds per V-cycle × 6 digits).

Each figure is the median over the timed steps after one warm-up step (which compiles); both solvers run with
`--threads` CPU threads. Results: bench/results/gas_<arch>.txt and .json.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

L = 0.5
DT = 0.02
T_AMB = 293.15
HEAT = 30.0
TOL = 1e-6


def ours(n: int, steps: int, grad_steps: int, arch: str, threads: int) -> dict:
    import fluidlab_core as fl
    from fluidlab_core import losses

    fl.init(arch=arch, precision="f32", cpu_threads=threads)
    import taichi as ti

    sync = ti.sync  # CUDA launches are asynchronous: a timer reads the clock after the device has finished
    out = {}
    for grad in (False, True):
        scene = fl.Scene(lower=(0, 0, 0), upper=(L, L, L), grid_res=n, dt=DT)
        scene.add_gas(resolution=n, tolerance=TOL, max_iterations=500)
        scene.add_gas_source("heater", "disc", (0.05, 0.05), pose=(L / 2, L / 2, 0.05, 0, 0, 0, 1),
                             temperature=T_AMB + HEAT, smoke=0.01)
        sim = scene.build(requires_grad=grad)
        if not grad:
            sim.step()  # compiles
            sync()
            times = []
            for _ in range(steps):
                t0 = time.perf_counter()
                sim.step()
                sync()
                times.append(time.perf_counter() - t0)
            rep = sim.solver.poisson.last
            # the projection against one V-cycle: time both on the current state
            s = sim.solver
            s.prepare_boundaries()
            s.forward_stages(DT)
            sync()
            t0 = time.perf_counter()
            s.project(DT, 0)
            sync()
            t_solve = time.perf_counter() - t0
            p = s.poisson
            for _ in range(2):
                p._vcycle()
            sync()
            t0 = time.perf_counter()
            for _ in range(5):
                p._vcycle()
            sync()
            t_v = (time.perf_counter() - t0) / 5
            out.update(forward_s=float(np.median(times)), iterations=rep["iterations"], residual=rep["residual"],
                       solve_s=t_solve, vcycle_s=t_v, solve_per_vcycle_digit=t_solve / (t_v * 6))
        else:
            w = np.random.default_rng(0).standard_normal(sim.solver.shape)
            loss = losses.GasLinear({"temperature": w})
            start = sim.get_state()
            sim.rollout(1, loss, grad=True)  # compiles forward and backward
            sim.set_state(start)
            sync()
            t0 = time.perf_counter()
            sim.rollout(grad_steps, loss, grad=True)
            sync()
            out["forward_backward_s"] = (time.perf_counter() - t0) / grad_steps
    return out


def phiflow(n: int, steps: int, grad_steps: int, threads: int, gpu: bool = False) -> dict:
    """PhiFlow's plume on its torch backend in float64 (float32 CG stalled at a max residual of 2e-5 after 2000
    iterations at 64³, short of 1e-6). `steps` 0 or `grad_steps` 0 skip that part. gpu: torch on the GPU (what
    PhiFlow would use on a GPU machine; with --arch cuda), synchronised before each clock reading."""
    import torch

    torch.set_num_threads(threads)
    from phi.torch import flow as pf

    if gpu:
        from phiml.backend.torch import TORCH

        if not TORCH.set_default_device("GPU"):
            raise RuntimeError("PhiFlow: torch finds no GPU")

    def sync():
        if gpu:
            torch.cuda.synchronize()
    from phiml.backend._numpy_backend import NumPyBackend

    # phiml 1.16.1 casts the flat indices of its sparse Poisson matrix back to int32: from 64³ cells (2^36
    # entries) they overflow ("index -2147479552 is out of bounds"); keep them int64
    if not getattr(NumPyBackend, "_ravel_int64", False):
        orig = NumPyBackend.ravel_multi_index
        NumPyBackend.ravel_multi_index = lambda self, mi, shape, mode="undefined": orig(
            self, np.asarray(mi, dtype=np.int64), shape, mode)
        NumPyBackend._ravel_int64 = True
    pf.math.set_global_precision(64)
    out = {}
    g_beta = 9.81 / T_AMB
    box = pf.Box(x=L, y=L, z=L)
    heater = pf.Sphere(x=L / 2, y=L / 2, z=0.05, radius=0.05)
    mask = pf.resample(heater, to=pf.CenteredGrid(0, pf.ZERO_GRADIENT, x=n, y=n, z=n, bounds=box), soft=True)

    def step(v, t, p):
        t = pf.advect.mac_cormack(t, v, DT)
        t = t * (1 - mask) + HEAT * mask
        buoyancy = pf.resample(t * (0, 0, g_beta), to=v)
        v = pf.advect.mac_cormack(v, v, DT) + buoyancy * DT
        v, p = pf.fluid.make_incompressible(v, (), pf.Solve("CG", TOL, 0, x0=p, max_iterations=5000))
        return v, t, p

    def fresh():
        return (pf.StaggeredGrid(0, 0, x=n, y=n, z=n, bounds=box),
                pf.CenteredGrid(0, pf.ZERO_GRADIENT, x=n, y=n, z=n, bounds=box), None)

    if steps:
        v, t, p = fresh()
        v, t, p = step(v, t, p)  # warm-up
        sync()
        times = []
        for _ in range(steps):
            t0 = time.perf_counter()
            v, t, p = step(v, t, p)
            sync()
            times.append(time.perf_counter() - t0)
        out["forward_s"] = float(np.median(times))
    if grad_steps:
        w = pf.math.random_normal(pf.CenteredGrid(0, pf.ZERO_GRADIENT, x=n, y=n, z=n, bounds=box).values.shape)

        def loss_of(v0):
            vv, tt, pp = v0, fresh()[1], None
            for _ in range(grad_steps):
                vv, tt, pp = step(vv, tt, pp)
            return pf.math.sum(tt.values * w)

        grad_fn = pf.math.gradient(loss_of, "v0", get_output=False)
        sync()
        t0 = time.perf_counter()
        grad_fn(fresh()[0])
        sync()
        out["forward_backward_s"] = (time.perf_counter() - t0) / grad_steps
    return out


def table(rows: list, arch: str, threads: int) -> str:
    """The results table; a ratio is '-' where PhiFlow was not timed."""
    lines = [f"Smoke plume, {L} m cube, dt {DT} s, pressure to a relative residual of {TOL:g}; {arch}, "
             f"{threads} thread(s); seconds per step (median), steps/s in brackets; ratio = PhiFlow / ours "
             f"(above 1: ours faster); PhiFlow on {'the GPU (torch CUDA)' if arch == 'cuda' else 'the CPU'}.", ""]
    lines.append(f"{'grid':>6} {'ours fwd':>16} {'PhiFlow fwd':>16} {'ratio':>6} {'ours fwd+bwd':>16} "
                 f"{'PhiFlow fwd+bwd':>16} {'ratio':>6} {'MGPCG iters':>11} {'solve / (V-cycle x 6)':>22}")
    for r in rows:
        o, p = r["ours"], r.get("phiflow", {})

        def cell(x):
            return f"{x:8.3f} ({1 / x:5.2f})" if x else f"{'-':>16}"

        def ratio(key):
            return f"{p[key] / o[key]:6.2f}" if p.get(key) else f"{'-':>6}"

        lines.append(f"{r['n']:>5}³ {cell(o['forward_s'])} {cell(p.get('forward_s'))} {ratio('forward_s')} "
                     f"{cell(o['forward_backward_s'])} {cell(p.get('forward_backward_s'))} "
                     f"{ratio('forward_backward_s')} "
                     f"{o['iterations']:>11} {o['solve_per_vcycle_digit']:>22.2f}")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128])
    ap.add_argument("--steps", type=int, nargs="+", default=[8, 3], help="timed forward steps per size")
    ap.add_argument("--grad-steps", type=int, nargs="+", default=[4, 2], help="steps of the gradient rollout per size")
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--no-phiflow", action="store_true")
    ap.add_argument("--phiflow-steps", type=int, nargs="+", default=[2, 1],
                    help="PhiFlow's timed forward steps per size (0 skips; at 128³ a step takes minutes)")
    ap.add_argument("--phiflow-grad-steps", type=int, nargs="+", default=[2, 0],
                    help="PhiFlow's gradient rollout steps per size (0 skips)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--report-only", action="store_true", help="rewrite the .txt table from the .json of a run")
    args = ap.parse_args(argv)
    out = Path(args.out or ROOT / "bench" / "results" / f"gas_{args.arch}")
    if args.report_only:
        text = table(json.loads(out.with_suffix(".json").read_text()), args.arch, args.threads)
        print(text)
        out.with_suffix(".txt").write_text(text + "\n")
        return
    rows = []
    for i, n in enumerate(args.sizes):
        steps = args.steps[min(i, len(args.steps) - 1)]
        gsteps = args.grad_steps[min(i, len(args.grad_steps) - 1)]
        row = {"n": n, "ours": ours(n, steps, gsteps, args.arch, args.threads)}
        print(f"{n}³ ours: {row['ours']}", flush=True)
        rows.append(row)
        write(out, rows, args)  # after each solver, so that a run cut short keeps what it measured
        if not args.no_phiflow:
            try:
                row["phiflow"] = phiflow(n, args.phiflow_steps[min(i, len(args.phiflow_steps) - 1)],
                                         args.phiflow_grad_steps[min(i, len(args.phiflow_grad_steps) - 1)],
                                         args.threads, gpu=args.arch == "cuda")
            except Exception as e:  # noqa: BLE001 - a failing comparison must not lose our own figures
                row["phiflow"] = {"error": f"{type(e).__name__}: {e}"[:300]}
            print(f"{n}³ PhiFlow: {row['phiflow']}", flush=True)
            write(out, rows, args)
    print(table(rows, args.arch, args.threads))


def write(out: Path, rows: list, args) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".txt").write_text(table(rows, args.arch, args.threads) + "\n")
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
