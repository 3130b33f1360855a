"""Tasks with an emitter and a tool that turns, through sim_node on the twin: the shipped IceCreamDynamic
trajectory (the arm moves the cone under the machine's fixed nozzle; the paper ran this task on a real Franka)
and the shipped Pouring trajectory (the arm tilts the glass about its rim). Each is planned, streamed within
the arm's limits (the twin applies libfranka's checks and would stop on a reflex) and recorded with the twin's
fluid: the ice cream appears and grows in the recording, and the glass pours its light liquid out."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from action_msgs.msg import GoalStatus

from .conftest import start_node

from fluidlab_msgs.action import Execute  # noqa: E402

from fluidlab_ros.recording import read_recording  # noqa: E402


# the shipped pour, optimised at its own speed: 86 % of the light liquid and 3 % of the heavy one end below the
# glass; on the twin (time scale 1.0 on the FR3), measured 79 % and 0 %. The bounds leave room for the twin's
# stream under load (a late tick holds the arm's last velocity) and would still catch a glass that does not
# pour (under 10 % at 1.45 rad of tilt) or tips both out.
LIGHT_OUT, HEAVY_OUT = 0.5, 0.2


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
            if task == "Pouring":
                pour_scale = result.time_scale

        # the ice cream: nothing at the start, then a growing body that ends in the cone (it moved with the cone)
        clouds = results["IceCreamDynamic"].particles
        sizes = [len(p) for _, p in clouds]
        assert sizes[0] == 0 and sizes[-1] > 100 and sizes == sorted(sizes), sizes
        final = clouds[-1][1]
        assert np.all(final[:, 2] > 0.0) and abs(float(np.median(final[:, 0])) - 0.5) < 0.03

        # the pour: the arm tilts the glass past 75° about its rim and back, at about the speed it was optimised
        # for (Pouring's tilt is bounded so that the FR3 follows it with little slow-down, docs/tasks.md), and the
        # twin's light liquid ends on the table while most of the heavy one stays in the glass
        rec = results["Pouring"]
        from scipy.spatial.transform import Rotation

        from fluidlab_core import tasks
        from fluidlab_core.tasks.jet_and_glass import GLASS_BASE_Z

        assert pour_scale <= 1.5, pour_scale
        tilt = Rotation.from_quat(rec.tool[1][:, 3:]).magnitude()
        assert tilt.max() > 1.3 and tilt[-1] < 0.2, (tilt.max(), tilt[-1])
        bodies = {b.handle.name: b.handle.slice for b in tasks.make("Pouring", "small").scene().bodies}
        start, end = rec.particles[0][1], rec.particles[-1][1]
        assert len(start) == len(end) == bodies["light"].stop
        light_out = float(np.mean(end[bodies["light"], 2] < GLASS_BASE_Z))
        heavy_out = float(np.mean(end[bodies["heavy"], 2] < GLASS_BASE_Z))
        print(f"[Pouring] time scale {pour_scale:.3g}: {light_out:.0%} of the light liquid and {heavy_out:.0%} of "
              f"the heavy one ended below the glass")
        assert light_out > LIGHT_OUT and heavy_out < HEAVY_OUT, (light_out, heavy_out)
    finally:
        assert node.stop() == 0, node.text()
