"""Planning time of the execution pipeline for a 10 s trajectory (fluidlab_ros.pipeline.plan), per stage.

Trajectory: a 10 s stirring motion for the Mixing task at dt = 2 ms (5000 twists): a 3 cm circle with a 4 s
period around the cup at (0.5, 0, 0.05) m, eased in and out over 1 s, with a 1 cm vertical bob. Each plan
starts from the ready posture, so it includes the approach segment to the first pose. Runs on the CPU in
one process; each configuration is planned `--repeat` times and the median and minimum are printed.

    python bench/bench_planning.py [--repeat 3] [--out bench/results/planning_cpu.txt]
"""
import argparse
import datetime
import os
import platform
import statistics
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from fluidlab_core.trajectory import Trajectory  # noqa: E402
from fluidlab_ros.pipeline import plan  # noqa: E402


def stirring(duration=10.0, dt=0.002):
    n = int(round(duration / dt))
    t = np.arange(n) * dt
    w, radius = 2 * np.pi / 4.0, 0.03
    env = np.clip(np.minimum(t, duration - t) / 1.0, 0, 1)
    env = env ** 2 * (3 - 2 * env)
    tw = np.zeros((n, 6))
    tw[:, 0] = -radius * w * np.sin(w * t) * env
    tw[:, 1] = radius * w * np.cos(w * t) * env
    tw[:, 2] = 0.01 * 2 * w * np.cos(2 * w * t) * env
    return Trajectory(task="Mixing", dt=dt, tool="stick", initial_pose=[0.53, 0.0, 0.05, 0, 0, 0, 1], twists=tw)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results",
                                                   "planning_cpu.txt"))
    args = ap.parse_args()
    traj = stirring()
    load = os.getloadavg()[0]  # other work on the machine slows planning: recorded with the figures
    plan(traj)  # warm-up: imports, URDF parsing, first allocations
    lines = [f"planning benchmark: {traj.duration:.0f} s trajectory ({traj.n_steps} twists at {traj.dt * 1e3:g} ms), "
             f"Mixing task, from the ready posture (approach included), {platform.processor() or platform.machine()}, "
             f"{os.cpu_count()} cores, {datetime.date.today().isoformat()}",
             "| robot | rate (Hz) | plan median (s) | plan min (s) | ik | time scaling | smoothing | verify | "
             "path error | commands | stream (s) | tool-path error (mm) | time scale |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for robot, rate in (("fr3", 500), ("fr3", 1000), ("panda", 500)):
        reports = [plan(traj, robot=robot, control_rate=rate).report for _ in range(args.repeat)]
        total = [r.planning_time for r in reports]
        stage = {k: statistics.median(r.stage_times[k] for r in reports) for k in reports[0].stage_times}
        r = reports[0]
        lines.append(f"| {robot} | {rate} | {statistics.median(total):.2f} | {min(total):.2f} | {stage['ik']:.2f} | "
                     f"{stage['time_scaling']:.3f} | {stage['smoothing']:.2f} | {stage['verify']:.2f} | "
                     f"{stage['path_error']:.2f} | {int(round(r.total_duration * rate))} | {r.total_duration:.2f} | "
                     f"{r.tool_path_error * 1e3:.2g} | {r.time_scale:.3g} |")
    lines.append("(stage columns: median seconds; 'stream' is the command stream's duration including the approach; "
                 f"1-minute load average at the start: {load:.2f} on {os.cpu_count()} cores)")
    text = "\n".join(lines)
    print(text)
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        f.write(text + "\n")


if __name__ == "__main__":
    main()
