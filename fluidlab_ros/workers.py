"""Work that sim_node runs in child processes, off its executor: the optimiser and the fluid twin.

Both run fluidlab_core (Taichi) in a process of their own, started with the "spawn" method (a fork of a
process with DDS threads is unsafe), so the node's executor and its 500 Hz command stream never wait on a
simulation. They talk to the node through multiprocessing queues of plain dicts and numpy arrays; the node
holds no physics (docs/design.md §2).

optimise_worker: runs fluidlab_core.optim.optimise and puts {"kind": "feedback", ...} per iteration and one
  {"kind": "result", ...} or {"kind": "error", ...}. A set `stop` event ends it at the next iteration (the
  node also terminates the process if that takes longer than it allows for a cancel).
fluid_worker: the twin's fluid. On start it puts {"kind": "compiling"}, runs one step to compile the
  simulator's kernels (and restores the state), then puts {"kind": "ready", "compile_seconds": ...}. It
  receives {"kind": "reset"}, {"kind": "pose", "pose": (7,), "stamp": ns} and {"kind": "final", "stamp": ns}
  messages; each pose is where the executed tool is one task step (dt) after the previous one, and the worker
  steps the task's simulator with the twist that takes its tool there:
      v = (p_target - p_sim) / dt,   w = rotvec(R_target R_sim^T) / dt
  (tracking the executed pose, so the simulated tool does not drift from the arm's). It puts
  {"kind": "particles", "positions": (N, 3) float32, "step": k, "stamp": ns or None, "epoch": e} after the
  reset (stamp None), every `publish_every` steps and after the last pose (stamp: the wall time the arm was at
  the pose the fluid was stepped to), and once more, with "final": True, when it reaches the "final" message:
  by then it has stepped every pose sent before it, however far behind real time it ran, so a recording that
  waits for it holds the fluid of the whole execution.
"""
from __future__ import annotations

import os
import queue
import time
import traceback


FINAL_SETTLE = 1.0  # s: the most the fluid twin simulates after the last pose, with the tool still


def _init_core(arch: str, precision: str):
    import signal

    import fluidlab_core

    # Ctrl-C in a terminal reaches the whole process group: the node, not its workers, decides when they end
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    fluidlab_core.init(arch=arch, precision=precision)


def optimise_worker(request: dict, out, stop, folder: str, arch: str = "cpu", precision: str = "f32"):
    """request: task, size, method, budget, seed, name, path (where to save, decided by the node)."""
    from pathlib import Path

    try:
        _init_core(arch, precision)
        from fluidlab_core import optim, tasks

        task = tasks.make(request["task"], size=request["size"])
        t0 = time.monotonic()

        def callback(p):
            out.put({"kind": "feedback", "iteration": int(p.iteration), "loss": float(p.loss),
                     "best_loss": float(p.best_loss), "steps": int(p.steps), "elapsed": time.monotonic() - t0})
            return stop.is_set()

        traj = optim.optimise(task, request["method"], int(request["budget"]), seed=int(request["seed"]),
                              callback=callback)
        if stop.is_set():
            out.put({"kind": "cancelled"})
            return
        path = Path(request["path"])
        traj.save(path)  # atomic: a complete file or none
        out.put({"kind": "result", "name": path.stem, "path": str(path),
                 "final_loss": float(traj.metadata["final_loss"]), "iterations": traj.metadata["iterations"]})
    except BaseException as err:  # noqa: BLE001 - reported to the node, which fails the goal with it
        out.put({"kind": "error", "message": f"{type(err).__name__}: {err}", "traceback": traceback.format_exc()})


def scene_description(sim) -> dict:
    """What a viewer needs to draw the scene: per-particle colours (N, 3) uint8 by body material, the
    statics as point samples in the world frame, each tool's shape as points in its own frame, and colours
    (0..1). Point samples keep this generic over primitives, containers and meshes."""
    import numpy as np

    colors = sim.particle_colors()
    dx = sim.scene.dx
    statics = [(st.name, st.shape.sample(dx).astype(np.float32)) for st in sim.scene.statics]
    tools = [(spec.name, spec.shape.sample(0.5 * dx).astype(np.float32), tuple(spec.color)) for spec in sim.tool_specs]
    return {"colors": colors, "statics": statics, "tools": tools, "dx": float(dx)}


def fluid_worker(task_name: str, size: str, inbox, out, arch: str = "cpu", precision: str = "f32",
                 publish_every: int = 5, nice: int = 10, stop=None, epoch=None):
    """stop (an Event) ends the worker at once; epoch (a shared integer) is raised by the node before each
    reset, and poses of an older epoch are skipped, so a worker that fell behind real time drops the rest of
    a finished execution instead of simulating it before the next one."""
    import numpy as np

    try:
        os.nice(nice)  # the command stream in the node comes first
    except OSError:
        pass
    try:
        _init_core(arch, precision)
        from fluidlab_core import tasks

        task = tasks.make(task_name, size=size)
        sim = task.simulator()
        dt = task.dt
        tool = task.tool_name
        # the first step compiles the kernels (about a minute on two cores with a cold cache): do it now, so the
        # node can say so, and executions are not kept waiting for it
        out.put({"kind": "compiling"})
        t0 = time.perf_counter()
        start = sim.get_state()
        sim.step()
        sim.set_state(start)
        out.put({"kind": "ready", "dt": dt, "n": int(len(sim.positions())),
                 "compile_seconds": time.perf_counter() - t0, **scene_description(sim)})
        step, stamp, current = 0, None, 0
        from fluidlab_ros.replay import tracking_twist

        colors = sim.particle_colors()
        changing = getattr(sim, "spec", None) is not None  # a gas scene: its points' colours are its temperature

        def publish(**extra):
            # the particles that take part (of a body being emitted: those that have left the nozzle), with
            # their colours; a gas scene's points and colours come from the simulator (GasSimulator.positions)
            nonlocal colors
            if changing:
                colors = sim.particle_colors()
            active = sim.active_rows()
            out.put({"kind": "particles", "positions": sim.positions().astype(np.float32), "step": step,
                     "stamp": stamp, "epoch": current,
                     "colors": colors if active is None else colors[active], **extra})

        while stop is None or not stop.is_set():
            try:
                msg = inbox.get(timeout=0.2)
            except queue.Empty:
                continue
            if msg is None or msg.get("kind") == "quit":
                return
            if epoch is not None and msg.get("epoch", epoch.value) < epoch.value:
                continue
            current = msg.get("epoch", current)
            if msg["kind"] == "reset":
                pos = msg.get("tool_position")
                task.reset(sim, tool_position=None if pos is None else np.asarray(pos, dtype=float))
                step, stamp = 0, None
                publish()
            elif msg["kind"] == "pose":
                sim.step(tracking_twist(sim.tool_pose(tool), np.asarray(msg["pose"], dtype=float), dt))
                step, stamp = step + 1, msg.get("stamp")
                if step % publish_every == 0 or msg.get("last"):
                    publish()
            elif msg["kind"] == "final":
                # the tool has held still since the last pose: the fluid goes on moving until the end (at most
                # FINAL_SETTLE seconds of it)
                end = msg.get("stamp")
                if stamp is not None and end is not None and end > stamp:
                    held = min(round((end - stamp) * 1e-9 / dt), int(FINAL_SETTLE / dt))
                    if held > 0:
                        sim.step(None, n=held)
                        step += held
                    stamp = end
                publish(final=True)
    except BaseException as err:  # noqa: BLE001
        out.put({"kind": "error", "message": f"{type(err).__name__}: {err}", "traceback": traceback.format_exc()})


def replay_worker(path: str, out_dir: str, disturbance: str, out, arch: str = "cpu", precision: str = "f32"):
    """Replay a recording (fluidlab_ros.replay) and put feedback and one result or error."""
    try:
        _init_core(arch, precision)
        from fluidlab_ros.replay import replay

        last = {}

        def progress(phase, j, n):
            if j == n or j - last.get(phase, 0) >= max(1, n // 20):
                last[phase] = j
                out.put({"kind": "feedback", "phase": phase, "progress": j / n})

        rep = replay(path, out_dir, disturbance, progress=progress)
        out.put({"kind": "result", "report": rep, "report_path": os.path.join(out_dir, "report.json")})
    except BaseException as err:  # noqa: BLE001
        out.put({"kind": "error", "message": f"{type(err).__name__}: {err}", "traceback": traceback.format_exc()})
