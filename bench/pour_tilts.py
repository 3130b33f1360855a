"""Pouring's slow pours: how much of each liquid a tilt to θ pours (a trapezoidal tilt rate accelerating at α up
to 0.8 rad/s, a hold, and back), the task loss, and the time scale the execution pipeline needs to run it on
the FR3 and the Panda at 500 Hz.

    python bench/pour_tilts.py

Writes bench/results/pour_tilts_small.txt. These figures set the task's bounds and DP's starting pour
(fluidlab_core/tasks/jet_and_glass.py, docs/tasks.md).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

CASES = [  # (tilt rad, acceleration rad/s², hold s)
    (1.45, 0.6, 1.5), (1.5, 0.6, 1.5), (1.55, 0.6, 1.2), (1.6, 0.6, 1.2), (1.5, 1.0, 1.5), (1.5, 1.5, 1.5)]


def main():
    import fluidlab_core
    from fluidlab_core import tasks
    from fluidlab_core.tasks.jet_and_glass import GLASS_BASE_Z, POUR_MAX_RATE, tilt_profile
    from fluidlab_ros.pipeline import plan

    fluidlab_core.init("cpu")
    task = tasks.make("Pouring", "small")
    sim = task.simulator()
    lines = [f"Pouring (small, {task.horizon} steps of {task.dt * 1e3:g} ms): a tilt to θ at acceleration α up to "
             f"{POUR_MAX_RATE} rad/s, a hold and back; shares of each liquid below the glass's base at the end, "
             "the task loss (m), and the time scale the pipeline needs at 500 Hz (1 = none).",
             f"{'θ rad':>6} {'α rad/s²':>9} {'hold s':>7} {'light out':>10} {'heavy out':>10} {'loss m':>9} "
             f"{'FR3 scale':>10} {'Panda scale':>12}"]
    for tilt, accel, hold in CASES:
        rates = tilt_profile(task.dt, task.horizon, tilt, accel, POUR_MAX_RATE, hold)[:, None]
        loss = task.evaluate(rates, rewards=False)["loss"]
        x = sim.get_state().x
        light = np.mean(x[task.body_slice("light"), 2] < GLASS_BASE_Z)
        heavy = np.mean(x[task.body_slice("heavy"), 2] < GLASS_BASE_Z)
        traj = task.trajectory(rates)
        scales = [plan(traj, robot).report.time_scale for robot in ("fr3", "panda")]
        lines.append(f"{tilt:>6.2f} {accel:>9.2f} {hold:>7.1f} {light:>10.0%} {heavy:>10.0%} {loss:>9.4f} "
                     f"{scales[0]:>10.3g} {scales[1]:>12.3g}")
        print(lines[-1], flush=True)
    out = Path(__file__).resolve().parent / "results" / "pour_tilts_small.txt"
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
