"""A task defined outside the package: a sphere pushes a block of the toy gel (toy_material.py) across a box
towards a goal. It registers itself on import, which is all a user's task needs:

    FLUIDLAB_TASKS=tests.extension.toy_task fluidlab list        # any process: the CLI, sim_node, workers

Scene (metres, base frame): a 6 cm × 4 cm × 4 cm box from (0.47, −0.02, 0); a 16 × 16 × 12 mm gel block
on its floor at x = 0.485…0.501; a sphere of radius 8 mm behind it, moving in x and y. Loss: squared distance
of the block's centre of mass to GOAL after the last step (m²).
"""
import numpy as np

from fluidlab_core import losses, shapes as S
from fluidlab_core.tasks import Task, register
from fluidlab_core.tasks.base import SizeConfig
from tests.extension.toy_material import GEL

LOWER, UPPER = (0.47, -0.02, 0.0), (0.53, 0.02, 0.04)
GOAL = (0.515, 0.0, 0.006)


@register
class ToyPush(Task):
    """Push a gel block to a goal with a sphere."""

    name = "ToyPush"
    tool_name = "pusher"
    action_axes = (0, 1)
    max_tool_speed = 0.1
    observed_bodies = ("gel",)
    target_body = "gel"
    reward_c1, reward_c2 = 1.0, 1e4
    flange_to_tool = (0.0, 0.0, 0.12, 1.0, 0.0, 0.0, 0.0)
    sizes = {"small": SizeConfig(grid_res=10, dt=2e-3, horizon=6, particles_per_body=16),
             "paper": SizeConfig(grid_res=48, dt=2e-3, horizon=100, particles_per_body=500)}

    def _domain(self):
        return LOWER, UPPER

    def workspace(self):
        return np.array([0.472, -0.01, 0.008]), np.array([0.51, 0.01, 0.008])

    def initial_tool_pose(self):
        return np.array([0.475, 0.0, 0.008, 0.0, 0.0, 0.0, 1.0])

    def _populate(self, scene, contact):
        scene.add_particles(S.Box((0.485, -0.008, 0.0), (0.501, 0.008, 0.012)), GEL, name="gel")
        scene.add_tool(S.Sphere((0, 0, 0), 0.008), pose=self.initial_tool_pose(), name=self.tool_name,
                       softness=self.softness if contact == "soft" else None, action_mask=(1, 1, 0, 0, 0, 0),
                       workspace=self.workspace(), max_speed=self.max_tool_speed)

    def loss(self, horizon=None):
        return losses.CenterOfMassDistance(GOAL, particles=self.body_slice("gel"), steps="final")

    def step_term(self):
        return losses.CenterOfMassDistance(GOAL, particles=self.body_slice("gel"), steps="all")
