"""command_monitor: a separate process that watches a joint velocity command stream and judges it.

    command_monitor --topic /sim_node/commands --out stream.npz [--robot fr3]

Records every std_msgs/Float64MultiArray on the topic with its arrival time (time.monotonic, s) until SIGINT
or SIGTERM (and the topic has then been quiet for 0.5 s), then writes `out` (npz: times (K,), commands (K, dof)) atomically and prints one JSON line:
count, rate (Hz, from the arrival span, and the median over windows of 50 commands), inter-arrival p50/p99/p99.9/max (ms), and whether the commands, held for
1 ms ticks at the nominal rate from rest, stay within the arm's official limits (velocity, acceleration,
jerk; the FR3's position-based velocity limits need a start posture and are left to the node's verifier).
Tests and bench/bench_stream.py use it, so what they report is what another process on the graph saw.
"""
from __future__ import annotations

import argparse
import json
import signal
import threading
import time

import numpy as np

from fluidlab_core.files import atomic_path


def wait_quiet(received: list, quiet: float = 0.5):
    """Return once `received` (a list a subscription appends to) has not grown for `quiet` s: a subscriber on
    a loaded machine may still be behind the stream when it is asked to stop."""
    while True:
        n = len(received)
        time.sleep(quiet)
        if len(received) == n:
            return


def stream_stats(times: np.ndarray, commands: np.ndarray, rate: float, limits) -> dict:
    out = {"count": int(len(times))}
    if len(times) >= 2:
        gaps = np.diff(times) * 1e3
        # rate over the whole span, and the median over windows of 50 commands (robust to a subscriber that
        # was itself descheduled for a while, which stretches the span it sees)
        w = min(50, len(times) - 1)
        out.update(rate=(len(times) - 1) / (times[-1] - times[0]),
                   rate_median=float(w / np.median(times[w:] - times[:-w])), gap_p50_ms=float(np.percentile(gaps, 50)),
                   gap_p99_ms=float(np.percentile(gaps, 99)), gap_p999_ms=float(np.percentile(gaps, 99.9)),
                   gap_max_ms=float(gaps.max()))
    if len(commands):
        n = int(round(1.0 / (rate * limits.check_period)))
        v = np.repeat(commands, n, axis=0)
        v_ext = np.vstack([np.zeros((2, v.shape[1])), v, np.zeros((2, v.shape[1]))])
        acc = np.diff(v_ext, axis=0) / limits.check_period
        jerk = np.diff(acc, axis=0) / limits.check_period
        peaks = {"velocity": np.abs(v).max(axis=0) / limits.velocity,
                 "acceleration": np.abs(acc).max(axis=0) / limits.acceleration,
                 "jerk": np.abs(jerk).max(axis=0) / limits.jerk}
        out["peak_fraction"] = {k: float(p.max()) for k, p in peaks.items()}
        out["within_limits"] = bool(all(p.max() <= 1.0 for p in peaks.values()))
        out["ends_at_rest"] = bool(not np.any(commands[-1]))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(prog="command_monitor", description=__doc__.split("\n\n")[0])
    ap.add_argument("--topic", default="/sim_node/commands")
    ap.add_argument("--out", required=True, help="npz file to write on exit")
    ap.add_argument("--rate", type=float, default=500.0, help="nominal stream rate (Hz) for the hold model")
    ap.add_argument("--robot", default="fr3")
    ap.add_argument("--ready-file", default=None, help="touch this file once subscribed (for scripts)")
    ap.add_argument("--realtime-priority", type=int, default=0,
                    help="SCHED_FIFO priority for this process (0: normal), so that what it measures is the stream's "
                         "timing and not its own scheduling; needs rtprio / CAP_SYS_NICE")
    args = ap.parse_args(argv)
    if args.realtime_priority > 0:
        import os
        import sys
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.realtime_priority))
        except (OSError, AttributeError) as err:
            print(f"command_monitor: SCHED_FIFO {args.realtime_priority} refused ({err}); normal scheduling",
                  file=sys.stderr)

    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import Float64MultiArray

    from fluidlab_ros.limits import JointLimits

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    node = rclpy.create_node("command_monitor")
    times, data = [], []

    def on_command(msg):
        times.append(time.monotonic())
        data.append(list(msg.data))

    node.create_subscription(Float64MultiArray, args.topic, on_command, 1000)
    spin = threading.Thread(target=rclpy.spin, args=(node,), daemon=True)
    spin.start()
    if args.ready_file:
        open(args.ready_file, "w").close()
    stop.wait()
    wait_quiet(times)
    rclpy.shutdown()
    spin.join(2.0)
    limits = JointLimits.load(args.robot)
    t = np.array(times)
    c = np.array(data, dtype=float) if data else np.zeros((0, limits.dof))
    with atomic_path(args.out, suffix=".npz") as tmp:
        np.savez(tmp, times=t, commands=c)
    print(json.dumps(stream_stats(t, c, args.rate, limits)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
