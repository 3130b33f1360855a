"""sim_node with a task of the user's own (tests/extension/toy_task.py), named by FLUIDLAB_TASKS: the node
(a separate process) optimises it in its worker process, saves and lists the trajectory, and plans an
execution of it on the twin arm with the tool offset the task declares (docs/extending.md)."""
from __future__ import annotations

import math
import os

from action_msgs.msg import GoalStatus

from .conftest import ROOT, start_node

from fluidlab_msgs.action import Execute, Optimise  # noqa: E402
from fluidlab_msgs.srv import ListTrajectories  # noqa: E402

from fluidlab_core.trajectory import Trajectory  # noqa: E402


def test_sim_node_optimises_lists_and_plans_a_task_of_our_own(ros_env, client, tmp_path):
    env = dict(ros_env, FLUIDLAB_TASKS="tests.extension.toy_task",
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    folder = tmp_path / "trajectories"
    node = start_node(env, tmp_path, f"trajectory_folder:={folder}", "fluid_twin:=false")
    try:
        act = client.action(Optimise, "/sim_node/optimise")
        goal = Optimise.Goal(task="ToyPush", size="small", method="cma-es", budget=4 * 6, seed=0, name="toy_opt")
        accepted, status, result = client.run_goal(act, goal, timeout=600)
        assert accepted and status == GoalStatus.STATUS_SUCCEEDED, (result.message if result else None, node.text())
        assert result.trajectory_name == "toy_opt" and math.isfinite(result.final_loss)
        saved = Trajectory.load(folder / "ToyPush" / "toy_opt.json")
        assert saved.task == "ToyPush" and saved.tool == "pusher"
        assert saved.metadata["flange_to_tool"] == [0.0, 0.0, 0.12, 1.0, 0.0, 0.0, 0.0]
        listed = client.call(client.service(ListTrajectories, "/sim_node/list_trajectories"),
                             ListTrajectories.Request(task="ToyPush"))
        assert [t.name for t in listed.trajectories] == ["toy_opt"]
        # a dry run plans the execution through IK with the task's own tool offset, and sends nothing
        ex = client.action(Execute, "/sim_node/execute")
        goal = Execute.Goal(trajectory_name="toy_opt", target="twin", speed_scale=1.0, dry_run=True)
        accepted, status, res = client.run_goal(ex, goal, timeout=120)
        assert accepted and status == GoalStatus.STATUS_SUCCEEDED, (res.message, node.text())
    finally:
        assert node.stop() == 0, node.text()
