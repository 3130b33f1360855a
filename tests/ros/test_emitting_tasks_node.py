"""Tasks with an emitter and a tool that turns, through sim_node on the twin: the shipped IceCreamDynamic
trajectory (the arm moves the cone under the machine's fixed nozzle; the paper ran this task on a real Franka)
and the shipped Pouring trajectory (the arm tilts the glass about its rim). Each is planned, streamed within
the arm's limits (the twin applies libfranka's checks and would stop on a reflex) and recorded with the twin's
fluid: the ice cream appears and grows in the recording, and the glass tilts and its liquid moves."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from action_msgs.msg import GoalStatus

from .conftest import start_node

from fluidlab_msgs.action import Execute  # noqa: E402

from fluidlab_ros.recording import read_recording  # noqa: E402


def shipped(trajectories: Path, task: str) -> str:
    (path,) = sorted((trajectories / task).glob("*_small.json"))
    return path.stem


def test_ice_cream_and_pouring_execute_on_the_twin_with_their_fluid(ros_env, client, tmp_path, trajectories):
    node = start_node(ros_env, tmp_path, f"trajectory_folder:={trajectories}")
    try:
        act = client.action(Execute, "/sim_node/execute")
        results = {}
        for task in ("IceCreamDynamic", "Pouring"):
            name = shipped(trajectories, task)
            accepted, status, result = client.run_goal(act, Execute.Goal(trajectory_name=name), timeout=600)
            assert accepted and status == GoalStatus.STATUS_SUCCEEDED, (task, result.message, node.text())
            assert "to the end of the motion" in result.message, result.message
            print(f"\n[{task}] {result.message}")
            results[task] = read_recording(Path(result.recording_path))

        # the ice cream: nothing at the start, then a growing body that ends in the cone (it moved with the cone)
        clouds = results["IceCreamDynamic"].particles
        sizes = [len(p) for _, p in clouds]
        assert sizes[0] == 0 and sizes[-1] > 100 and sizes == sorted(sizes), sizes
        final = clouds[-1][1]
        assert np.all(final[:, 2] > 0.0) and abs(float(np.median(final[:, 0])) - 0.5) < 0.03

        # the pour: the arm tilts the glass past 75° about its rim and back, and the twin's liquid moves with it.
        # The shipped pour was optimised at the simulation's speed (the glass at 86° within 0.4 s); the arm runs it
        # about 9.5x slower (joint 7's acceleration), and the slow tilt pours far less: measured 0.7 % of the
        # liquid below the glass at the end in the twin, against 76 % of the light liquid at the optimised speed
        # (docs/tasks.md: a pour that an arm can run is an open problem).
        rec = results["Pouring"]
        from scipy.spatial.transform import Rotation

        tilt = Rotation.from_quat(rec.tool[1][:, 3:]).magnitude()
        assert tilt.max() > 1.3 and tilt[-1] < 0.2, (tilt.max(), tilt[-1])
        clouds = rec.particles
        start, end = clouds[0][1], clouds[-1][1]
        assert len(start) == len(end) > 500
        moved = np.linalg.norm(end - start, axis=1)
        assert np.median(moved) > 0.002, np.median(moved)
    finally:
        assert node.stop() == 0, node.text()
