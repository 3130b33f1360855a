"""The Gathering tasks on the default liquid and on the projection (issue 19: the tasks' physics).

    python bench/gathering_projection.py [--tasks GatheringEasy GatheringHard] [--size small]
        [--pressures state projection] [--out bench/results/gathering_projection_small.txt]
        [--float-seconds S]

For each task and liquid pressure ("state": the default weakly compressible liquid the tasks were optimised on;
"projection": engine/projection.py, which floats bodies at Archimedes' depth):
- rest: the paddle held still over the horizon; the share of each foam object's particles below the water's
  surface (the tank's fill height, 41 mm: the water was filled around the objects at their Archimedes depth, so
  its level stays there), as the mean over the horizon's second half (Archimedes 0.40: 400 kg/m³ foam);
- shipped: the shipped trajectory (trajectories/<task>/<task>_dp_seed0_<size>.json, optimised by DP on the
  default), its task loss (m², lower is better) and return (the sum of the per-step rewards), and the same for the
  paddle held still (what the trajectory gains over doing nothing);
- the wall time per simulated step of the shipped rollout (after its first, compiling, call).
With --float-seconds S, instead: the paddle held still for S seconds, each second's mean share under (both objects)
and the water's fastest and rms particle speeds at each second's end (the still water's spurious currents).
Appends its table to the output file.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def submerged_share(task, sim, body: str) -> float:
    from fluidlab_core.tasks import gathering

    z = sim.positions(body)[:, 2]
    return float((z < gathering.TANK_WALL + gathering.WATER_DEPTH).mean())


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
    shares = {b: [] for b in ("object_a", "object_b")}
    for k in range(n):
        sim.step(action=np.zeros(6))
        if k >= n // 2:
            for b in shares:
                shares[b].append(submerged_share(task, sim, b))
    out = {"task": task_name, "size": size, "pressure": pressure, "substeps": sim.scene.substeps
           if hasattr(sim, "scene") else None}
    out["rest_share"] = {b: float(np.mean(v)) for b, v in shares.items()}
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
            shares.append([submerged_share(task, sim, b) for b in ("object_a", "object_b")])
        a, b = np.mean(shares, axis=0)
        speed = np.linalg.norm(sim.velocities("water"), axis=1)
        rows.append(f"{task_name} | {pressure} | {second}-{second + 1} s | {a:.3f}, {b:.3f} | "
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
             "# task | pressure | substeps | rest: share under (a, b; Archimedes 0.40) | still: loss, return | "
             "shipped: loss, return | s per step"]
    if args.float_seconds:
        lines[1] = ("# task | pressure | second | share under (a, b; Archimedes 0.40) | water's max, rms speed at its "
                    "end (m/s) | wall time")
    print("\n".join(lines), flush=True)
    for name in args.tasks if args.float_seconds else ():
        for pressure in args.pressures:
            lines += floating(name, args.size, pressure, args.float_seconds)
    for name in args.tasks if not args.float_seconds else ():
        for pressure in args.pressures:
            r = run(name, args.size, pressure)
            line = (f"{name} | {pressure} | {r['substeps']} | {r['rest_share']['object_a']:.3f}, "
                    f"{r['rest_share']['object_b']:.3f} | {r['still_loss']:.3e}, {r['still_return']:.2f} | "
                    f"{r['loss']:.3e}, {r['return']:.2f} | {r['step_s']:.3f}")
            print(line, flush=True)
            lines.append(line)
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "a") as f:
        f.write("\n".join(lines) + "\n\n")
    print(f"appended to {out}")


if __name__ == "__main__":
    main()
