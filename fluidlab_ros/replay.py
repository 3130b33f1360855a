"""Replay a recording into the twin's fluid and compare it with the plan: `replay(recording, out_dir)`.

What is compared (docs/replay.md):
- the *planned* rollout: the task's fluid simulated with the tool following the plan (the plan's joint
  positions at each command, through forward kinematics), on the wall-clock timing of the execution;
- the *replayed* rollout: the same with the *measured* joint positions of the recording (the twin's in twin
  mode, the arm's in robot mode), optionally disturbed (delay, scale, noise) to show what a gap looks like.
Both drive the simulator the way sim_node's fluid twin does: from the tool pose p_j, R_j at the start of
step j (task dt of wall time) the tool gets the twist that reaches the recorded pose at the end of the step,
    v = (p_{j+1} - p_sim) / dt,   w = rotvec(R_{j+1} R_sim^T) / dt.
The task loss is evaluated on the trajectory's own steps: trajectory step k (time k dt) was executed at the
wall time where the plan's time map reaches k dt (the recording holds that map), and the loss term of step
k is evaluated on the simulator's state at the nearest wall-time step. So the planned rollout's loss is the
optimiser's loss on the executed (time-scaled, corner-rounded) motion, and the replayed one differs from it
only by how the arm moved.

Outputs in out_dir: report.json, joint_tracking.png, tool_path.png, loss.png, final_planned.png,
final_replayed.png. Units: m, s, rad.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from fluidlab_core.files import write_atomic
from fluidlab_ros.recording import RecordingError, read_recording


def tracking_twist(current_pose: np.ndarray, target_pose: np.ndarray, dt: float) -> np.ndarray:
    """The constant twist (world frame) that moves a tool from current_pose to target_pose in dt."""
    v = (target_pose[:3] - current_pose[:3]) / dt
    w = (Rotation.from_quat(target_pose[3:]) * Rotation.from_quat(current_pose[3:]).inv()).as_rotvec() / dt
    return np.concatenate([v, w])


def parse_disturbance(text: str) -> dict:
    """"delay=0.05,scale=1.1,noise=0.002" -> {"delay": 0.05, ...}: delay s (the arm moves later), scale
    (joint displacement from the start posture times this), noise rad (Gaussian, seeded)."""
    out = {}
    for part in filter(None, (p.strip() for p in (text or "").split(","))):
        key, _, value = part.partition("=")
        if key not in ("delay", "scale", "noise", "seed"):
            raise ValueError(f"unknown disturbance {key!r}: use delay=<s>, scale=<factor>, noise=<rad>, seed=<int>")
        try:
            out[key] = float(value)
        except ValueError:
            raise ValueError(f"disturbance {key} needs a number, got {value!r}") from None
    return out


def disturb(times: np.ndarray, q: np.ndarray, d: dict) -> np.ndarray:
    q = q.copy()
    if d.get("delay"):
        q = np.stack([np.interp(times - d["delay"], times, q[:, j]) for j in range(q.shape[1])], axis=1)
    if d.get("scale"):
        q = q[0] + d["scale"] * (q - q[0])
    if d.get("noise"):
        q = q + np.random.default_rng(int(d.get("seed", 0))).normal(0.0, d["noise"], q.shape)
    return q


def _poses_at(times: np.ndarray, poses: np.ndarray, t: np.ndarray) -> np.ndarray:
    t = np.clip(t, times[0], times[-1])
    pos = np.stack([np.interp(t, times, poses[:, i]) for i in range(3)], axis=1)
    rot = Slerp(times, Rotation.from_quat(poses[:, 3:]))(t)
    return np.hstack([pos, rot.as_quat()])


def _unique(times, values):
    keep = np.concatenate([[True], np.diff(times) > 0])
    return times[keep], values[keep]


def _drive(task, sim, wall_poses: np.ndarray, dt: float, step_of_k: np.ndarray, horizon: int, progress=None):
    """Reset, then step the simulator to follow wall_poses[j] (j = 0..J); evaluate loss term k at step
    step_of_k[k-1]. Returns (loss, per-k loss values, tool poses of the sim, final particle positions)."""
    task.reset(sim, tool_position=wall_poses[0][:3])
    tool = task.tool_name
    task_loss = task.loss(horizon)
    values = np.zeros(horizon)
    by_step: dict[int, list[int]] = {}
    for k, j in enumerate(step_of_k, start=1):
        by_step.setdefault(int(j), []).append(k)
    sim_poses = [sim.tool_pose(tool)]
    for j in range(1, len(wall_poses)):
        sim.step(tracking_twist(sim.tool_pose(tool), wall_poses[j], dt))
        sim_poses.append(sim.tool_pose(tool))
        for k in by_step.get(j, ()):
            if task_loss.active(k, horizon):
                st = dataclasses.replace(task.step_state(sim), step=k)
                values[k - 1] = task_loss(st, horizon)[0]
        if progress:
            progress(j, len(wall_poses) - 1)
    return float(values.sum()), values, np.array(sim_poses), sim.positions()


def replay(path, out_dir, disturbance: dict | str | None = None, progress=None, render: bool = True) -> dict:
    """Replay a recording; write the report and plots into out_dir; return the report (dict)."""
    from fluidlab_core import tasks
    from fluidlab_core.trajectory import Trajectory
    from fluidlab_ros.robot import Robot

    t_begin = time.perf_counter()
    d = parse_disturbance(disturbance) if isinstance(disturbance, str) else dict(disturbance or {})
    rec = read_recording(path)
    meta = rec.metadata
    traj = Trajectory.from_dict(meta["trajectory_document"])
    size = traj.metadata.get("size", "small")
    task = tasks.make(traj.task, size=size)
    if abs(task.dt - traj.dt) > 1e-12:
        raise RecordingError(f"the recorded trajectory's dt {traj.dt} s is not {traj.task} ({size})'s {task.dt} s")
    robot = Robot(meta["robot"], meta["mounting"]["flange_to_tool"])
    t_m, q_m = _unique(*rec.measured)
    t_p, q_p = _unique(*rec.planned)
    if len(t_m) < 2 or len(t_p) < 2:
        raise RecordingError(f"{path} holds too few joint states to replay ({len(t_m)} measured, {len(t_p)} planned)")
    q_m = disturb(t_m, q_m, d)

    # the task segment in wall time, and where each trajectory step was executed
    plan_t = np.asarray(meta["plan_times"], dtype=float)
    plan_r = np.array([np.nan if v is None else v for v in meta["plan_traj_times"]], dtype=float)
    seg = np.isfinite(plan_r)
    t_a, t_b = float(meta["task_start_time"]), float(meta["task_end_time"])
    if t_m[-1] < t_b - 0.05:  # states are recorded every few commands; the last one may be a little early
        raise RecordingError(f"the recording ends at {t_m[-1]:.3f} s, before the task segment ends ({t_b:.3f} s): "
                             f"the execution was stopped, nothing to compare")
    dt = task.dt
    J = int(np.floor((t_b - t_a) / dt + 1e-9))
    wall = t_a + dt * np.arange(J + 1)
    N = traj.n_steps
    r_seg, t_seg = plan_r[seg], plan_t[seg]
    t_of_k = np.interp(np.arange(1, N + 1) * traj.dt, r_seg, t_seg)  # wall time of trajectory step k
    step_of_k = np.clip(np.round((t_of_k - t_a) / dt), 1, J).astype(int)

    def tool_poses(qs):
        pos, rot = robot.tool_positions_rotations(qs)
        return np.hstack([pos, Rotation.from_matrix(rot).as_quat()])

    pose_m = tool_poses(q_m)
    pose_p = tool_poses(q_p)
    sim = task.simulator()
    results = {}
    finals = {}
    for name, (tt, pp) in (("planned", (t_p, pose_p)), ("replayed", (t_m, pose_m))):
        wall_poses = _poses_at(tt, pp, wall)
        loss, values, sim_poses, x = _drive(task, sim, wall_poses, dt, step_of_k, N,
                                            (lambda j, n, nm=name: progress(nm, j, n)) if progress else None)
        results[name] = {"loss": loss, "values": values, "sim_poses": sim_poses}
        finals[name] = x
        if render:
            out = Path(out_dir)
            out.mkdir(parents=True, exist_ok=True)
            sim.render(str(out / f"final_{name}.png"), view="iso", size=(480, 360), title=f"{traj.task}: {name}")

    # tool path and joint tracking over the whole recording, at the measured times
    common = (t_m >= max(t_m[0], t_p[0])) & (t_m <= min(t_m[-1], t_p[-1]))
    tc = t_m[common]
    p_plan_c = _poses_at(t_p, pose_p, tc)[:, :3]
    path_err = np.linalg.norm(pose_m[common, :3] - p_plan_c, axis=1)
    q_plan_c = np.stack([np.interp(tc, t_p, q_p[:, j]) for j in range(q_p.shape[1])], axis=1)
    joint_err = np.abs(q_m[common] - q_plan_c)
    in_task = (tc >= t_a) & (tc <= t_b)
    lp, lr = results["planned"]["loss"], results["replayed"]["loss"]
    dx = np.linalg.norm(finals["replayed"] - finals["planned"], axis=1)
    report = {
        "recording": str(Path(path)), "closed": rec.closed, "trajectory": meta["trajectory_name"],
        "trajectory_sha256": meta["trajectory_sha256"], "task": traj.task, "size": size, "robot": meta["robot"],
        "mode": meta["mode"], "disturbance": d, "task_steps_wall": J, "trajectory_steps": N,
        "time_scale": meta.get("plan_report", {}).get("time_scale"),
        "loss_optimised": traj.metadata.get("final_loss"), "loss_planned": lp, "loss_replayed": lr,
        "loss_gap": lr - lp, "loss_gap_relative": (lr - lp) / abs(lp) if lp else None,
        "tool_path_error_max": float(path_err.max()), "tool_path_error_rms": float(np.sqrt(np.mean(path_err ** 2))),
        "tool_path_error_task_max": float(path_err[in_task].max()) if in_task.any() else 0.0,
        "joint_error_max": float(joint_err.max()), "final_particle_displacement_mean": float(dx.mean()),
        "final_particle_displacement_max": float(dx.max()), "seconds": round(time.perf_counter() - t_begin, 2),
        "counts": rec.counts,
        "fluid_clouds_recorded": len(rec.particles),
        "fluid_recorded_until": float(rec.particles[-1][0]) if rec.particles else None,
    }
    report["notes"] = report_notes(report)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    _plots(out, tc, q_m[common], q_plan_c, pose_m[common], p_plan_c, path_err, results, traj.dt, meta, report)
    write_atomic(out / "report.json", json.dumps(report, indent=1, default=float))
    return report


def report_notes(report: dict) -> list[str]:
    """What a reader of the report must know to read its numbers: how the executed timing relates to the
    optimised one (and what that does to the loss), and whether the recording holds the twin's fluid."""
    notes = []
    ts, lo, lp = report.get("time_scale"), report.get("loss_optimised"), report.get("loss_planned")
    if ts and abs(ts - 1.0) > 0.01:
        text = (f"the execution ran {ts:.3g}x {'slower' if ts > 1 else 'faster'} than the optimised trajectory "
                f"(time_scale: the arm's velocity, acceleration and jerk limits), so the fluid had {ts:.3g}x as long "
                f"to respond to each tool motion")
        if lo is not None and lp is not None and lo != 0:
            text += (f"; this timing, with the jerk-limited rounding of the trajectory's corners, moves the task loss "
                     f"from the optimised {lo:.4g} to the planned {lp:.4g} ({100 * (lp - lo) / abs(lo):+.0f} %)")
        notes.append(text + ". Judge the execution by loss_replayed against loss_planned (the same timing), "
                            "not against loss_optimised.")
    if not report.get("fluid_clouds_recorded"):
        notes.append("the recording holds no particle cloud of the twin's fluid (fluid_twin off, or the twin did "
                     "not run); the replay simulated the fluid from the recorded motion alone")
    return notes


def _plots(out: Path, t, q_meas, q_plan, pose_meas, p_plan, path_err, results, traj_dt, meta, report):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = meta["joint_names"]
    fig, axes = plt.subplots(len(names), 1, figsize=(8, 1.4 * len(names)), sharex=True)
    for j, ax in enumerate(axes):
        ax.plot(t, q_plan[:, j], label="planned", lw=1.5)
        ax.plot(t, q_meas[:, j], "--", label="measured (replayed)", lw=1)
        ax.set_ylabel(f"{names[j]}\n(rad)", fontsize=7)
    axes[0].legend(fontsize=7, loc="upper right")
    axes[-1].set_xlabel("time since the stream's start (s)")
    fig.suptitle(f"joint tracking, max error {report['joint_error_max'] * 1e3:.3g} mrad")
    fig.tight_layout()
    fig.savefig(out / "joint_tracking.png", dpi=90)
    plt.close(fig)

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4.2))
    task = (t >= meta["task_start_time"]) & (t <= meta["task_end_time"])
    a1.plot(p_plan[task, 0], p_plan[task, 1], label="planned", lw=1.5)
    a1.plot(pose_meas[task, 0], pose_meas[task, 1], "--", label="measured", lw=1)
    a1.set_xlabel("x (m)")
    a1.set_ylabel("y (m)")
    a1.set_aspect("equal", adjustable="datalim")
    a1.legend(fontsize=8)
    a1.set_title("tool path in the task segment, top view (fr3_link0)", fontsize=9)
    a2.plot(t, path_err * 1e3)
    a2.axvspan(meta["task_start_time"], meta["task_end_time"], color="0.9", label="task segment")
    a2.set_xlabel("time (s)")
    a2.set_ylabel("tool position error (mm)")
    a2.legend(fontsize=8)
    a2.set_title("planned vs measured tool position")
    fig.tight_layout()
    fig.savefig(out / "tool_path.png", dpi=90)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 4))
    k = np.arange(1, len(results["planned"]["values"]) + 1) * traj_dt
    for name in ("planned", "replayed"):
        ax.plot(k, np.cumsum(results[name]["values"]), label=f"{name}: {results[name]['loss']:.4g}")
    ax.set_xlabel("trajectory time (s)")
    ax.set_ylabel("task loss, cumulative")
    ax.legend()
    ax.set_title(f"{report['task']}: loss planned vs replayed")
    fig.tight_layout()
    fig.savefig(out / "loss.png", dpi=90)
    plt.close(fig)
