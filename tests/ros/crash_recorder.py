"""Writes a recording with fluidlab_ros.recording.Recorder at 500 Hz and then dies by SIGKILL (no close), or
closes it normally with --close: the crash-safety test's subject."""
import argparse
import os
import signal
import time

from std_msgs.msg import Float64MultiArray

from fluidlab_ros.recording import Recorder

ap = argparse.ArgumentParser()
ap.add_argument("folder")
ap.add_argument("--seconds", type=float, default=1.5)
ap.add_argument("--close", action="store_true")
args = ap.parse_args()
rec = Recorder(args.folder, {"format": "fluidlab-recording", "version": 1, "trajectory_name": "crash_test",
                             "start_time": time.time()})
t0 = time.monotonic()
k = 0
while time.monotonic() - t0 < args.seconds:
    rec.put("/sim_node/commands", Float64MultiArray(data=[0.001 * k] * 7), time.time_ns())
    k += 1
    time.sleep(0.002)
print(k, flush=True)
if args.close:
    rec.close()
else:
    time.sleep(0.1)  # let the writer take the queue, as a live node would
    os.kill(os.getpid(), signal.SIGKILL)
