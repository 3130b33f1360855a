"""What Scene(pressure="projection") costs against the default liquid, in one process (issue 19).

    python bench/projection_cost.py [--scene cube|gathering] [--res 16] [--seconds 0.2] [--rounds 3] [--threads N]

--scene cube (the default) is the scene of tests/test_projection.py: a 4 cm rigid cube of 500 kg/m³ dropped from 1 cm onto 6 cm of water in a
closed 12 cm tank, `--res` cells across, float32 on the CPU. Each pressure model's scene is built and stepped once
for 0.1 s to compile and to let the cube land, then timed over `--seconds` of simulated time, the two alternating
for `--rounds` rounds (the median is reported), each at its own substep count: the stable one for the default
(the water's sound speed sets it) and twice the flow's CFL count for the projection (as bench/buoyancy_3d.py's
runs and the test). Then the projection's substep split by stage (one more timed stretch, with a sync after each
stage, which adds a little). Writes bench/results/projection_cost_cpu.txt. --scene gathering: GatheringEasy at its
small size (its static tank, paddle held still and two elastic foam cubes; --res is ignored) at the task's substep
count for both (the foam's sound speed sets it), from 0.1 s on; writes bench/results/projection_cost_gathering_cpu.txt.
"""
from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", choices=("cube", "gathering"), default="cube")
    ap.add_argument("--res", type=int, default=16)
    ap.add_argument("--seconds", type=float, default=0.2, help="simulated seconds timed per round")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None, help="CPU threads (default: the runtime's)")
    args = ap.parse_args()
    import taichi as ti

    import fluidlab_core as fl
    from fluidlab_core import materials as M
    from fluidlab_core.apps import validation

    fl.init("cpu", cpu_threads=args.threads)
    body = M.Rigid("rigid_500", density=500.0)
    sims = {}
    for pressure, factor in (("state", 1.0), ("projection", 2.0)):
        if args.scene == "gathering":
            from fluidlab_core import tasks

            task = tasks.make("GatheringEasy", "small", pressure=pressure)
            sim = task.simulator()
            task.reset(sim)
            scene = sim.scene
        else:
            sim, scene = validation.floating_cube_sim(args.res, body, M.WATER, drop=0.01, substep_factor=factor,
                                                      pressure=pressure)
        t0 = time.perf_counter()
        sim.step(n=int(round(0.1 / scene.dt)))
        print(f"{pressure}: {scene.substeps} substeps per {scene.dt * 1e3:g} ms step, {sim.n_particles} particles; "
              f"compile and the first 0.1 s {time.perf_counter() - t0:.1f} s", flush=True)
        sims[pressure] = (sim, scene)
    times = {k: [] for k in sims}
    for r in range(args.rounds):
        for pressure, (sim, scene) in sims.items():
            n = int(round(args.seconds / scene.dt))
            ti.sync()
            t0 = time.perf_counter()
            sim.step(n=n)
            ti.sync()
            times[pressure].append((time.perf_counter() - t0) / (n * scene.dt))
            print(f"round {r + 1}: {pressure} {times[pressure][-1]:.2f} s per simulated second", flush=True)
    med = {k: statistics.median(v) for k, v in times.items()}
    sub = {k: s.substeps / s.dt for k, (_, s) in sims.items()}  # substeps per simulated second
    lines = [f"# bench/projection_cost.py --scene {args.scene} --res {args.res} --seconds {args.seconds:g} --rounds {args.rounds}; "
             f"{platform.processor() or platform.machine()}, CPU, {args.threads or 'default'} threads, "
             f"{time.strftime('%Y-%m-%d')}",
             f"{'pressure':<11} {'substeps/s':>10} {'s per sim s':>11} {'ms/substep':>10}"]
    for k in sims:
        lines.append(f"{k:<11} {sub[k]:>10.0f} {med[k]:>11.2f} {1e3 * med[k] / sub[k]:>10.2f}")
    lines.append(f"projection / state: {med['projection'] / med['state']:.2f}x the wall time per simulated second, "
                 f"{(med['projection'] / sub['projection']) / (med['state'] / sub['state']):.2f}x per substep")
    # the projection's substep by stage
    sim, scene = sims["projection"]
    solver = sim.solver
    proj = solver.proj
    still = np.zeros((max(solver.model.n_tools, 1), 6))  # the tools held still
    p2g = (lambda st: solver.projection_p2g_kernel_tools(st, still)) if solver.model.n_tools \
        else (lambda st: solver.projection_p2g_kernel(st))
    stages = [("P2G and grid update", p2g)]
    if proj.has_kin:
        stages.append(("projection: statics and tools", lambda st: proj.kinematic(st)))
    stages += [("projection: classify", lambda st: proj.classify()),
              ("projection: enclosed air (host labels)", lambda st: proj.enclose_air()),
              ("projection: right-hand side, MIC(0)", lambda st: (proj.rhs(), proj.factor())),
              ("projection: pressure CG", lambda st: proj.solve(proj.iterations)),
              ("projection: correction and faces", lambda st: (proj.body_impulse(st), proj.correct(st), proj.faces())),
              ("projection: position correction", lambda st: proj.position_correction()),
              ("G2P", lambda st: solver.projection_g2p_kernel(st)),
              ("displace, rigid projection, push", lambda st: (proj.displace(st), solver.rigid.forward(st, 0),
                                                               proj.push(st)) if solver.rigid is not None
               else proj.displace(st))]
    acc = {name: 0.0 for name, _ in stages}
    n_sub = int(round(args.seconds / scene.dt)) * scene.substeps
    it0, pc0 = len(proj.iterations), len(proj.correction_iterations)
    for _ in range(n_sub):
        for name, run in stages:
            ti.sync()
            t0 = time.perf_counter()
            run(sim.state)
            ti.sync()
            acc[name] += time.perf_counter() - t0
    total = sum(acc.values())
    lines.append(f"projection substep by stage ({n_sub} substeps, synced after each stage: {1e3 * total / n_sub:.2f} ms "
                 f"per substep; CG iterations per substep: pressure {statistics.mean(proj.iterations[it0:]):.1f}, "
                 f"position correction {statistics.mean(proj.correction_iterations[pc0:]):.1f})")
    for name, _ in stages:
        lines.append(f"  {name:<40} {1e3 * acc[name] / n_sub:>7.2f} ms  {100 * acc[name] / total:>5.1f} %")
    text = "\n".join(lines) + "\n"
    print(text, flush=True)
    name = "projection_cost_cpu.txt" if args.scene == "cube" else "projection_cost_gathering_cpu.txt"
    out = Path(__file__).resolve().parent / "results" / name
    out.write_text(text)


if __name__ == "__main__":
    main()
