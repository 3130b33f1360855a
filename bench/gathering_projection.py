"""The floating-object tasks (Gathering, Transporting) on the default liquid and on the projection (issue 19: the
tasks' physics).

    python bench/gathering_projection.py [--tasks GatheringEasy GatheringHard Transporting] [--size small]
        [--pressures state projection] [--out bench/results/gathering_projection_small.txt]
        [--float-seconds S]

For each task and liquid pressure ("state": the default weakly compressible liquid the tasks were optimised on;
"projection": engine/projection.py, which floats bodies at Archimedes' depth):
- rest: the tool held still over the horizon (Transporting's jet runs, as in every rollout of that task); the share
  of each foam object's particles below the water's level, as the mean over the horizon's second half (Archimedes
  0.40: 400 kg/m³ foam). The level is the tank's fill height (41 mm: the water was filled around the objects at
  their Archimedes depth) raised by the jet's emitted volume over the tank's inner area (Transporting: 7 mm over
  its 0.5 s), the level an incompressible liquid would have;
- the water's level at the horizon's end, measured: the median over the tank's inner columns away from the objects
  and the jet of the highest water particle's height plus half the particle spacing, beside the level above
  (Transporting; Gathering's has no inflow);
- shipped: the shipped trajectory (trajectories/<task>/<task>_dp_seed0_<size>.json, optimised by DP on the
  default), its task loss and return (the sum of the per-step rewards), and the same for the tool held still (what
  the trajectory gains over doing nothing);
- the wall time per simulated step of the shipped rollout (after its first, compiling, call).
With --float-seconds S, instead: the tool held still for S seconds, each second's mean share under (both objects)
and the water's fastest and rms particle speeds at each second's end (the still water's spurious currents).
Appends its table to the output file.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from results_file import append_table  # bench/results_file.py (this script's folder is on the path)

ROOT = Path(__file__).resolve().parents[1]


def objects(task) -> list[str]:
    """The task's floating objects (its observed bodies named object*)."""
    return [b for b in task.observed_bodies if b.startswith("object")]


def inner_area() -> float:
    """The tank's inner floor area (m²): the Gathering tank's, which Transporting shares."""
    from fluidlab_core.tasks import gathering as g

    return (g.TANK_UPPER[0] - g.TANK_LOWER[0] - 2 * g.TANK_WALL) * (g.TANK_UPPER[1] - g.TANK_LOWER[1] - 2 * g.TANK_WALL)


def level(task, sim) -> float:
    """The water's level (m) an incompressible liquid would have: the fill height raised by the emitted volume."""
    from fluidlab_core.tasks import gathering as g

    emitted = sum(sim.masses(e.name).sum() / e.material.density for e in sim.emitter_specs)
    return g.TANK_WALL + g.WATER_DEPTH + emitted / inner_area()


def measured_level(task, sim) -> float:
    """The water's surface (m) as its particles show it: the median, over the tank's inner columns of 2 x 2 particle
    spacings more than a cube's side from every object and the tool, of the highest water particle plus half a
    spacing."""
    from fluidlab_core.tasks import gathering as g

    s = sim.scene.particle_spacing
    x = np.concatenate([sim.positions(b) for b in ("water", *[e.name for e in sim.emitter_specs])])
    far = np.ones(len(x), bool)
    for c in [sim.positions(b).mean(axis=0) for b in objects(task)] + [sim.tool_pose(task.tool_name)[:3]]:
        far &= np.abs(x[:, :2] - c[:2]).max(axis=1) > g.CUBE_SIDE
    cols = np.floor(x[far, :2] / (2 * s)).astype(np.int64)
    _, inverse = np.unique(cols, axis=0, return_inverse=True)
    top = np.full(inverse.max() + 1, -np.inf)
    np.maximum.at(top, inverse.ravel(), x[far, 2])
    return float(np.median(top) + 0.5 * s)


def submerged_share(task, sim, body: str) -> float:
    z = sim.positions(body)[:, 2]
    return float((z < level(task, sim)).mean())


def run(task_name: str, size: str, pressure: str) -> dict:
    import fluidlab_core as fl
    from fluidlab_core import tasks
    from fluidlab_core.trajectory import Trajectory

    task = tasks.make(task_name, size, pressure=pressure)
    sim = task.simulator()
    n = task.horizon
    still = np.zeros((n, task.n_actions))
    # rest: the paddle still; the objects' shares over the second half
    task.reset(sim)
    shares = {b: [] for b in objects(task)}
    for k in range(n):
        sim.step(action=np.zeros(6))
        if k >= n // 2:
            for b in shares:
                shares[b].append(submerged_share(task, sim, b))
    out = {"task": task_name, "size": size, "pressure": pressure, "substeps": sim.substeps}
    out["rest_share"] = {b: float(np.mean(v)) for b, v in shares.items()}
    out["level"], out["measured_level"] = level(task, sim), measured_level(task, sim)
    rest = task.evaluate(still)
    out["still_loss"], out["still_return"] = rest["loss"], rest["return"]
    traj = Trajectory.load(ROOT / "trajectories" / task_name / f"{task_name}_dp_seed0_{size}.json")
    actions, position = task.actions_from_trajectory(traj)
    t0 = time.perf_counter()
    res = task.evaluate(actions, position)
    out["step_s"] = (time.perf_counter() - t0) / n
    out["loss"], out["return"] = res["loss"], res["return"]
    out["shipped_loss_recorded"] = float(traj.loss_history[-1]) if traj.loss_history else None
    fl.runtime.reset()  # the next build starts its fields' ids from zero (its kernels from the cache)
    return out


def floating(task_name: str, size: str, pressure: str, seconds: float) -> list[str]:
    """Per-second rows of the objects' share under and the water's speeds, the paddle held still."""
    import fluidlab_core as fl
    from fluidlab_core import tasks

    task = tasks.make(task_name, size, pressure=pressure)
    sim = task.simulator()
    task.reset(sim)
    per_second = int(round(1.0 / task.dt))
    rows = []
    t0 = time.perf_counter()
    for second in range(int(round(seconds))):
        shares = []
        for _ in range(per_second):
            sim.step(action=np.zeros(6))
            shares.append([submerged_share(task, sim, b) for b in objects(task)])
        mean = ", ".join(f"{v:.3f}" for v in np.mean(shares, axis=0))
        speed = np.linalg.norm(sim.velocities("water"), axis=1)
        rows.append(f"{task_name} | {pressure} | {second}-{second + 1} s | {mean} | "
                    f"{speed.max():.3f}, {np.sqrt((speed ** 2).mean()):.4f} | {time.perf_counter() - t0:.0f} s")
        print(rows[-1], flush=True)
    fl.runtime.reset()
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tasks", nargs="+", default=["GatheringEasy", "GatheringHard"])
    ap.add_argument("--size", default="small")
    ap.add_argument("--pressures", nargs="+", default=["state", "projection"])
    ap.add_argument("--out", default=None)
    ap.add_argument("--float-seconds", type=float, default=None, help="the objects' floating over this many seconds "
                    "instead (the paddle still)")
    args = ap.parse_args(argv)
    import fluidlab_core as fl

    fl.init(arch="cpu")
    out = Path(args.out or ROOT / "bench" / "results" / f"gathering_projection_{args.size}.txt")
    lines = [f"# bench/gathering_projection.py, {time.strftime('%Y-%m-%d %H:%M')}, size {args.size}, CPU, float32; the "
             f"tasks' liquid on the projection: APIC (Task.scene)",
             "# task | pressure | substeps | rest: share under (each object; Archimedes 0.40) | water level at the "
             "end: incompressible, measured (mm) | still: loss, return | shipped: loss, return | s per step"]
    if args.float_seconds:
        lines[1] = ("# task | pressure | second | share under (each object; Archimedes 0.40) | water's max, rms speed at its "
                    "end (m/s) | wall time")
    print("\n".join(lines), flush=True)
    for name in args.tasks if args.float_seconds else ():
        for pressure in args.pressures:
            lines += floating(name, args.size, pressure, args.float_seconds)
    for name in args.tasks if not args.float_seconds else ():
        for pressure in args.pressures:
            r = run(name, args.size, pressure)
            shares = ", ".join(f"{v:.3f}" for v in r["rest_share"].values())
            line = (f"{name} | {pressure} | {r['substeps']} | {shares} | {1e3 * r['level']:.1f}, "
                    f"{1e3 * r['measured_level']:.1f} | {r['still_loss']:.3e}, {r['still_return']:.2f} | "
                    f"{r['loss']:.3e}, {r['return']:.2f} | {r['step_s']:.3f}")
            print(line, flush=True)
            lines.append(line)
    append_table(out, lines)


if __name__ == "__main__":
    main()
