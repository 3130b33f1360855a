"""The floating-object tasks (Gathering, Transporting) on the default liquid and on the projection (issue 19: the
tasks' physics).

    python bench/gathering_projection.py [--tasks GatheringEasy GatheringHard Transporting] [--size small]
        [--pressures state projection] [--out bench/results/gathering_projection_small.txt]
        [--float-seconds S]

For each task and liquid pressure ("state": the default weakly compressible liquid the tasks were optimised on;
"projection": engine/projection.py, which floats bodies at Archimedes' depth):
- rest: the tool held still over the horizon (Transporting's jet runs, as in every rollout of that task); the share
  of each foam object's volume below the water's surface (submerged_shares), as the mean over the horizon's second
  half (Archimedes 0.40: 400 kg/m³ foam). The level in the next column is the tank's fill height (41 mm: the water
  was filled around the objects at their Archimedes depth) raised by the jet's emitted volume over the tank's inner
  area (Transporting: 7 mm over its 0.5 s), the level an incompressible liquid would have;
- the water's level at the horizon's end, measured: the median over the tank's inner columns away from the objects
  and the jet of the highest water particle's height plus half the particle spacing, beside the level above
  (Transporting; Gathering's has no inflow);
- shipped: the shipped trajectory (the one trajectories/<task>/<task>_*_<size>.json, optimised on the
  default), its task loss and return (the sum of the per-step rewards), and the same for the tool held still (what
  the trajectory gains over doing nothing, 1 − loss/still loss);
- the wall time per simulated step of the shipped rollout (after its first, compiling, call).
With --float-seconds S, instead: the tool held still for S seconds, each second's mean share under (both objects),
their tilt from upright at its end (a cube of density ratio s with s(1 − s) > 1/6, as the foam's 0.4, is unstable
upright and rolls), and the water's fastest and rms particle speeds at each second's end (the still water's
spurious currents).
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


def submerged_shares(task, sim) -> list[float]:
    """Each object's share of its volume below the water's surface (validation.gathering_submerged_shares: the height at
    which the water, emitted included, the objects' parts below it and the paddle's fill the tank). Until
    2026-12-07 this counted the particles below `level` (the fill height): a count that moves in steps of a particle
    layer (a sixth of a small-size cube), and that read the objects 1.1 mm (0.05) too high while the water that
    started inside the paddle raised the level (it now starts round it)."""
    from fluidlab_core.apps.validation import gathering_submerged_shares

    paddle = task.tool_name if task.tool_name == "paddle" else None  # Transporting's bot is above the water
    return gathering_submerged_shares(sim, objects(task), paddle=paddle)


def tilt_degrees(start: np.ndarray, now: np.ndarray) -> float:
    """The angle (degrees) of the rotation that best maps a body's particles at the start onto them now."""
    from fluidlab_core.apps.validation import best_rotation

    r = best_rotation(start, now)
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


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
    shares = []
    for k in range(n):
        sim.step(action=np.zeros(6))
        if k >= n // 2:
            shares.append(submerged_shares(task, sim))
    out = {"task": task_name, "size": size, "pressure": pressure, "substeps": sim.substeps}
    out["rest_share"] = dict(zip(objects(task), np.mean(shares, axis=0).tolist()))
    out["level"], out["measured_level"] = level(task, sim), measured_level(task, sim)
    rest = task.evaluate(still)
    out["still_loss"], out["still_return"] = rest["loss"], rest["return"]
    shipped = sorted(p for p in (ROOT / "trajectories" / task_name).glob(f"{task_name}_*_{size}.json")
                     if not p.name.endswith(".report.json"))
    if len(shipped) != 1:  # (the shipped one was named <task>_dp_seed0_<size>.json until 2026-12-06)
        raise SystemExit(f"expected one shipped trajectory for {task_name} at size {size} under trajectories/, "
                         f"found {[p.name for p in shipped]}")
    traj = Trajectory.load(shipped[0])
    out["shipped"] = shipped[0].name
    actions, position = task.actions_from_trajectory(traj)
    t0 = time.perf_counter()
    res = task.evaluate(actions, position)
    out["step_s"] = (time.perf_counter() - t0) / n
    out["loss"], out["return"] = res["loss"], res["return"]
    out["shipped_loss_recorded"] = float(traj.loss_history[-1]) if traj.loss_history else None
    fl.runtime.reset()  # the next build starts its fields' ids from zero (its kernels from the cache)
    return out


def floating(task_name: str, size: str, pressure: str, seconds: float) -> list[str]:
    """Per-second rows of the objects' share under, their tilt at the second's end and the water's speeds, the
    paddle held still."""
    import fluidlab_core as fl
    from fluidlab_core import tasks

    task = tasks.make(task_name, size, pressure=pressure)
    sim = task.simulator()
    task.reset(sim)
    start = {b: sim.positions(b) for b in objects(task)}
    per_second = int(round(1.0 / task.dt))
    rows = []
    t0 = time.perf_counter()
    for second in range(int(round(seconds))):
        shares = []
        for _ in range(per_second):
            sim.step(action=np.zeros(6))
            shares.append(submerged_shares(task, sim))
        mean = ", ".join(f"{v:.3f}" for v in np.mean(shares, axis=0))
        tilt = ", ".join(f"{tilt_degrees(x, sim.positions(b)):.1f}" for b, x in start.items())
        speed = np.linalg.norm(sim.velocities("water"), axis=1)
        rows.append(f"{task_name} | {size} | {pressure} | {second}-{second + 1} s | {mean} | {tilt} | "
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
             "# task | pressure | substeps | rest: share under, by volume (each object; Archimedes 0.40) | water level at the "
             "end: incompressible, measured (mm) | still: loss, return | shipped: loss, return | shipped's gain over still "
             "(1 − loss/still loss) | s per step | shipped file"]
    if args.float_seconds:
        lines[1] = ("# task | size | pressure | second | share under, by volume (each object; Archimedes 0.40) | tilt at "
                    "its end (degrees) | water's max, rms speed at its end (m/s) | wall time")
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
                    f"{r['loss']:.3e}, {r['return']:.2f} | {100 * (1 - r['loss'] / r['still_loss']):.1f} % | "
                    f"{r['step_s']:.3f} | {r['shipped']}")
            print(line, flush=True)
            lines.append(line)
    append_table(out, lines)


if __name__ == "__main__":
    main()
