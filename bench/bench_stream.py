"""Rate and jitter of sim_node's command stream, measured by a separate process on the ROS graph.

Starts sim_node (twin mode) and command_monitor as separate processes through their console scripts, on an
isolated graph (a private ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST), sends one ~/execute goal
for the 10 s stirring trajectory of bench_planning.py, and reports what the monitor saw: commands received
against commands sent, rate from the arrival span, inter-arrival p50 / p99 / max, and the peak fractions of
the FR3's limits of the stream as received (held 1 ms per tick). Runs twice: with the fluid twin off (the
stream alone) and on (a Taichi process stepping the fluid beside the stream), the second as a ratio against
the first, on the same machine in the same run.

    python bench/bench_stream.py [--out bench/results/stream_cpu.txt]
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


def run_once(tmp: Path, fluid: bool, env: dict, arch: str = "cpu") -> dict:
    import rclpy
    from action_msgs.msg import GoalStatus
    from rclpy.action import ActionClient

    from fluidlab_msgs.action import Execute

    bindir = Path(sys.executable).parent
    folder = tmp / "trajectories"
    log = open(tmp / f"node_{fluid}.log", "w")
    node = subprocess.Popen([str(bindir / "sim_node"), "--ros-args", "-p", f"trajectory_folder:={folder}", "-p",
                             f"fluid_twin:={'true' if fluid else 'false'}", "-p", f"recording_folder:={tmp / 'recordings'}",
                             "-p", f"arch:={arch}"], env=env, stdout=log,
                            stderr=subprocess.STDOUT)
    ready = tmp / f"mon_{fluid}.ready"
    out = tmp / f"mon_{fluid}.npz"
    mon = subprocess.Popen([str(bindir / "command_monitor"), "--topic", "/sim_node/commands", "--out", str(out),
                            "--ready-file", str(ready)], env=env, stdout=subprocess.PIPE, text=True)
    try:
        while not ready.exists():
            time.sleep(0.1)
        cl = rclpy.create_node("bench_client")
        act = ActionClient(cl, Execute, "/sim_node/execute")
        assert act.wait_for_server(timeout_sec=60), "sim_node did not come up"
        fut = act.send_goal_async(Execute.Goal(trajectory_name="bench_stir", target="twin"))
        rclpy.spin_until_future_complete(cl, fut)
        res_fut = fut.result().get_result_async()
        rclpy.spin_until_future_complete(cl, res_fut, timeout_sec=600)
        res = res_fut.result()
        assert res.status == GoalStatus.STATUS_SUCCEEDED, res.result.message
        time.sleep(0.5)
        cl.destroy_node()
    finally:
        mon.send_signal(signal.SIGINT)
        stats = json.loads(mon.communicate(timeout=30)[0].strip().splitlines()[-1])
        node.send_signal(signal.SIGINT)
        node.wait(30)
        log.close()
    stats["sent"] = int(round(res.result.duration * 500))  # the plan's commands (the feedback may add a ramp-out)
    stats["result"] = res.result.message
    return stats


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "stream_cpu.txt"))
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"],
                    help="Taichi backend of the node's fluid twin (default cpu)")
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
        for fluid in (False, True):
            s = run_once(tmp, fluid, env, args.arch)
            rows.append((fluid, s))
            print(json.dumps({"fluid_twin": fluid, **s}), flush=True)
    rclpy.shutdown()
    base = rows[0][1]
    lines = [f"# sim_node command stream, 500 Hz, measured by command_monitor in another process "
             f"({datetime.date.today()}, {platform.node()}, {os.cpu_count()} cores, {platform.processor() or platform.machine()})",
             "# trajectory: 10 s stirring (bench_planning.py) from the ready posture, twin mode",
             f"{'fluid twin':<11} {'sent':>6} {'recv':>6} {'rate Hz':>8} {'median':>8} {'p50 ms':>7} {'p99 ms':>7} {'max ms':>7} "
             f"{'p99/base':>8} {'peak v':>7} {'peak a':>7} {'peak j':>7}"]
    for fluid, s in rows:
        pk = s["peak_fraction"]
        lines.append(f"{'on' if fluid else 'off':<11} {s['sent']:>6} {s['count']:>6} {s['rate']:>8.2f} {s['rate_median']:>8.2f} "
                     f"{s['gap_p50_ms']:>7.3f} {s['gap_p99_ms']:>7.3f} {s['gap_max_ms']:>7.2f} "
                     f"{s['gap_p99_ms'] / base['gap_p99_ms']:>8.2f} {pk['velocity']:>7.2f} {pk['acceleration']:>7.2f} "
                     f"{pk['jerk']:>7.2f}")
    text = "\n".join(lines) + "\n"
    print(text)
    Path(args.out).write_text(text)


if __name__ == "__main__":
    main()
