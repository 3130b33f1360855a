"""Timing of sim_node's command stream under load, measured by a separate process on the ROS graph.

Starts sim_node (twin mode) and command_monitor as separate processes through their console scripts, on an
isolated graph (a private ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST), sends one ~/execute goal
for the 10 s stirring trajectory of bench_planning.py and reports what the monitor saw: commands received
against sent, the rate from the arrival span, inter-arrival p50 / p99 / p99.9 / max, the gaps between the
stream process's own send stamps (from the execution's recording), and what the node reported (late ticks, the
largest lateness against its timeline, the twin's tracking error). Loads:

  quiet    the stream alone (fluid twin off)
  fluid    the fluid twin (a Taichi process stepping the Mixing fluid with the tool) beside the stream
  loaded   the fluid twin, an ~/optimise goal (CMA-ES on LatteArtStir, in its worker process) and two
           processes that each burn a core, all started before the stream

at 500 Hz and at 1 kHz. The goal for (loaded, 500 Hz): p99.9 <= 3 ms and max <= 10 ms. The inter-arrival
figures include the monitor's own delays (a Python process under the same load; it asks for SCHED_FIFO so that
they stay small where that is allowed), so they bound the stream's jitter from above.

    python bench/bench_stream.py [--rates 500 1000] [--loads quiet fluid loaded] [--out bench/results/stream_cpu.txt]
"""
import argparse
import datetime
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.bench_planning import stirring  # noqa: E402

BURN = "import time\nwhile True:\n    pass\n"
MONITOR_PRIORITY = 20  # the monitor at real-time priority where allowed: it measures the stream, not itself


def run_once(tmp: Path, load: str, rate: float, env: dict) -> dict:
    import rclpy
    from action_msgs.msg import GoalStatus
    from rclpy.action import ActionClient

    from fluidlab_msgs.action import Execute, Optimise

    bindir = Path(sys.executable).parent
    folder = tmp / "trajectories"
    tag = f"{load}_{int(rate)}"
    log = open(tmp / f"node_{tag}.log", "w")
    fluid = load != "quiet"
    node = subprocess.Popen([str(bindir / "sim_node"), "--ros-args", "-p", f"trajectory_folder:={folder}",
                             "-p", f"fluid_twin:={'true' if fluid else 'false'}", "-p",
                             f"recording_folder:={tmp / 'recordings'}", "-p", f"control_rate:={rate}"],
                            env=env, stdout=log, stderr=subprocess.STDOUT)
    ready, out = tmp / f"mon_{tag}.ready", tmp / f"mon_{tag}.npz"
    mon = subprocess.Popen([str(bindir / "command_monitor"), "--topic", "/sim_node/commands", "--out", str(out),
                            "--ready-file", str(ready), "--rate", str(rate), "--realtime-priority", str(MONITOR_PRIORITY)],
                           env=env, stdout=subprocess.PIPE, text=True)
    burners = []
    cl = None
    try:
        while not ready.exists():
            time.sleep(0.1)
        cl = rclpy.create_node("bench_client")
        act = ActionClient(cl, Execute, "/sim_node/execute")
        assert act.wait_for_server(timeout_sec=60), "sim_node did not come up"
        if fluid:  # a dry run starts nothing; a first short execution compiles (or loads) the fluid's kernels
            warm = act.send_goal_async(Execute.Goal(trajectory_name="bench_stir", target="twin", speed_scale=1.0))
            rclpy.spin_until_future_complete(cl, warm)
            f = warm.result().get_result_async()
            rclpy.spin_until_future_complete(cl, f, timeout_sec=600)
            time.sleep(1.0)
        if load == "loaded":
            opt = ActionClient(cl, Optimise, "/sim_node/optimise")
            assert opt.wait_for_server(timeout_sec=30)
            og = opt.send_goal_async(Optimise.Goal(task="LatteArtStir", size="small", method="cma-es",
                                                   budget=1000 * 75, seed=0, name="bench_load"))
            rclpy.spin_until_future_complete(cl, og)
            opt_handle = og.result()
            burners = [subprocess.Popen([sys.executable, "-c", BURN]) for _ in range(2)]
            time.sleep(5.0)  # the optimiser's worker is up and iterating
        mon_t0 = time.monotonic()
        fut = act.send_goal_async(Execute.Goal(trajectory_name="bench_stir", target="twin"))
        rclpy.spin_until_future_complete(cl, fut)
        res_fut = fut.result().get_result_async()
        rclpy.spin_until_future_complete(cl, res_fut, timeout_sec=600)
        res = res_fut.result()
        failed = "" if res.status == GoalStatus.STATUS_SUCCEEDED else res.result.message  # a row all the same
        if load == "loaded":
            c = opt_handle.cancel_goal_async()
            rclpy.spin_until_future_complete(cl, c, timeout_sec=10)
        time.sleep(0.5)
    finally:
        for b in burners:
            b.kill()
            b.wait()
        if cl is not None:
            cl.destroy_node()
        mon.send_signal(signal.SIGINT)
        mon.communicate(timeout=30)
        node.send_signal(signal.SIGINT)
        node.wait(30)
        log.close()
    import numpy as np

    from fluidlab_ros.limits import JointLimits
    from fluidlab_ros.monitor import stream_stats

    d = np.load(out)
    t, c = d["times"], d["commands"]
    keep = t >= mon_t0  # the measured execution only (not the warm-up one)
    stats = stream_stats(t[keep], c[keep], rate, JointLimits.load("fr3"))
    stats["sent"] = int(round(res.result.duration * rate))  # the plan's commands (the feedback may add a ramp-out)
    msg = res.result.message
    import re
    m = re.search(r"(\d+) late ticks \(max ([0-9.e+-]+) ms\)", msg)
    stats["late_ticks"], stats["node_max_late_ms"] = (int(m.group(1)), float(m.group(2))) if m else (-1, float("nan"))
    stats["tracking_mm"] = res.result.max_tracking_error * 1e3
    # the sender's own view: the stamps the stream process wrote as each command went out (the recording)
    from fluidlab_ros.recording import read_recording
    sent_t = read_recording(res.result.recording_path).commands[0] if res.result.recording_path else []
    if len(sent_t) > 1:
        gaps = np.diff(sent_t) * 1e3
        stats.update(send_p999_ms=float(np.percentile(gaps, 99.9)), send_max_ms=float(gaps.max()))
    else:  # refused, or stopped, before a second command was sent
        stats.update(send_p999_ms=float("nan"), send_max_ms=float("nan"))
        print(f"the execution was refused: {msg}", file=sys.stderr)
    stats["result"] = msg
    stats["failed"] = failed
    return stats


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "stream_cpu.txt"))
    ap.add_argument("--rates", type=float, nargs="+", default=[500.0, 1000.0])
    ap.add_argument("--loads", nargs="+", default=["quiet", "fluid", "loaded"], choices=["quiet", "fluid", "loaded"])
    args = ap.parse_args()
    env = dict(os.environ, ROS_DOMAIN_ID=str(150 + os.getpid() % 50), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               RMW_IMPLEMENTATION="rmw_fastrtps_cpp")
    os.environ.update({k: env[k] for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "RMW_IMPLEMENTATION")})
    import rclpy

    rclpy.init()
    rows = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        stirring().save(tmp / "trajectories" / "Mixing" / "bench_stir.json")
        for rate in args.rates:
            for load in args.loads:
                s = run_once(tmp, load, rate, env)
                rows.append((rate, load, s))
                print(json.dumps({"rate": rate, "load": load, **s}), flush=True)
    rclpy.shutdown()
    lines = [f"# sim_node command stream (its own process), measured by command_monitor in another process "
             f"({datetime.date.today()}, {platform.node()}, {os.cpu_count()} cores, {platform.processor() or platform.machine()})",
             "# trajectory: 10 s stirring (bench_planning.py) from the ready posture, twin mode; inter-arrival in ms;",
             "# late/max late: the node's own count of ticks later than half a period and the largest lateness;",
             "# loaded = fluid twin + an optimise goal + two processes burning a core each; the monitor runs at SCHED_FIFO",
             f"# {MONITOR_PRIORITY} where allowed; sent p99.9/max: gaps between the stream process's own send stamps (the recording)",
             f"{'rate':>5} {'load':<7} {'sent':>6} {'recv':>6} {'rate Hz':>8} {'p50':>6} {'p99':>6} {'p99.9':>6} "
             f"{'max':>6} {'late':>5} {'max late':>8} {'track mm':>8} {'peak j':>6} {'sent p99.9':>10} {'sent max':>8}"]
    for rate, load, s in rows:
        lines.append(f"{rate:>5.0f} {load:<7} {s['sent']:>6} {s['count']:>6} {s['rate']:>8.2f} {s['gap_p50_ms']:>6.2f} "
                     f"{s['gap_p99_ms']:>6.2f} {s['gap_p999_ms']:>6.2f} {s['gap_max_ms']:>6.2f} {s['late_ticks']:>5} "
                     f"{s['node_max_late_ms']:>8.2f} {s['tracking_mm']:>8.2f} {s['peak_fraction']['jerk']:>6.2f} "
                     f"{s['send_p999_ms']:>10.2f} {s['send_max_ms']:>8.2f}")
    for rate, load, s in rows:
        if s["failed"]:
            lines.append(f"# {rate:.0f} Hz {load}: the stream STOPPED: {s['failed']}")
    text = "\n".join(lines) + "\n"
    print(text)
    Path(args.out).write_text(text)


if __name__ == "__main__":
    main()
