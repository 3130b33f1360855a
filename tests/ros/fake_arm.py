"""A stand-in for franka_ros2 in robot-mode tests: integrates the velocity commands it receives on
--command-topic into joint positions and publishes sensor_msgs/JointState on --joint-state-topic at --rate Hz.
With --drop-after N it stops publishing joint states once N commands have arrived (lost feedback), but keeps
recording commands. On SIGINT it writes the commands with their arrival times to --out (npz)."""
import argparse
import signal
import threading
import time

import numpy as np
import rclpy
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from fluidlab_ros.monitor import wait_quiet

READY_Q = [0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--command-topic", required=True)
    ap.add_argument("--joint-state-topic", required=True)
    ap.add_argument("--rate", type=float, default=250.0)
    ap.add_argument("--drop-after", type=int, default=-1)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    node = rclpy.create_node("fake_arm")
    names = [f"fr3_joint{i}" for i in range(1, 8)]
    lock = threading.Lock()
    state = {"q": np.array(READY_Q), "v": np.zeros(7), "t": time.monotonic()}
    times, cmds = [], []

    def advance(now):
        state["q"] = state["q"] + state["v"] * (now - state["t"])
        state["t"] = now

    def on_command(msg):
        now = time.monotonic()
        with lock:
            advance(now)
            state["v"] = np.array(msg.data)
            times.append(now)
            cmds.append(list(msg.data))

    node.create_subscription(Float64MultiArray, args.command_topic, on_command, 1000)
    pub = node.create_publisher(JointState, args.joint_state_topic, 10)

    def publish():
        with lock:
            if 0 <= args.drop_after <= len(cmds):
                return
            advance(time.monotonic())
            msg = JointState(name=names, position=state["q"].tolist(), velocity=state["v"].tolist())
        msg.header.stamp = node.get_clock().now().to_msg()
        pub.publish(msg)

    node.create_timer(1.0 / args.rate, publish)
    spin = threading.Thread(target=rclpy.spin, args=(node,), daemon=True)
    spin.start()
    stop.wait()
    wait_quiet(cmds)  # what is still on its way
    rclpy.shutdown()
    spin.join(2.0)
    np.savez(args.out, times=np.array(times), commands=np.array(cmds, dtype=float) if cmds else np.zeros((0, 7)))


if __name__ == "__main__":
    main()
