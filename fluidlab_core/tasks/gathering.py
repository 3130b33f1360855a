"""The Gathering tasks of FluidLab: a paddle, restricted to an area at one end of a tank of water, makes
currents that carry two floating foam objects to their goals.

Scene (base frame fr3_link0, metres): a tank on the table plane with outer bounds x 0.42…0.58, y −0.06…0.06,
z 0…0.07 and 16 mm walls, holding 25 mm of water (surface at z = 0.041). Two foam cubes (24 mm, 400 kg/m³)
float at (0.50, ±0.018). The paddle is a plate 16 mm thick (along x), 40 mm wide and 40 mm tall, whose tool
frame sits at the middle of its lower edge, 6 mm above the floor; it is held from the flange by
FLANGE_TO_PADDLE and may move only in the area x 0.450…0.475, y −0.02…0.02 (its workspace), behind the objects.

GatheringEasy: carry both objects to GOAL_EASY = (0.545, 0.0). GatheringHard: a post (16 mm square, x
0.515…0.531) stands between the objects' paths and they must part: object A (at +y) to (0.545, +0.03), object
B (at −y) to (0.545, −0.03).

Loss (Xian et al. 2023, appendix): the distance of the object particles to their goal, as the mean over the
horizon of the mean squared distance (m²):  L = (1/N) Σ_k Σ_objects mean_p |x_p(k) − g_object|².
The goals sit at the objects' floating height, so only the horizontal distance can go to zero.
"""
from __future__ import annotations

import numpy as np

from fluidlab_core import losses, shapes as S
from fluidlab_core.tasks import common
from fluidlab_core.tasks.base import SizeConfig, Task

TANK_LOWER = (0.42, -0.06, 0.0)
TANK_UPPER = (0.58, 0.06, 0.07)
TANK_WALL = 0.016
WATER_DEPTH = 0.025
CUBE_SIDE = 0.024
CUBE_Y = 0.018
CUBE_X = 0.50
PADDLE_SIZE = (0.016, 0.04, 0.04)  # thickness (x), width (y), height (z), metres
PADDLE_Z = TANK_WALL + 0.006
PADDLE_AREA = ((0.450, -0.02), (0.475, 0.02))  # the paddle origin's (x, y) bounds
GOAL_EASY = (0.545, 0.0)
GOAL_HARD = {"object_a": (0.545, 0.03), "object_b": (0.545, -0.03)}
POST = ((0.515, -0.008), (0.531, 0.008))  # GatheringHard's obstacle, x and y bounds (m)
FLANGE_TO_PADDLE = (0.0, 0.0, 0.15, 1.0, 0.0, 0.0, 0.0)

GATHERING_SIZES = {
    "small": SizeConfig(grid_res=20, dt=5e-3, horizon=100, particles_per_body=64, spacing_cells=0.5),
    "medium": SizeConfig(grid_res=32, dt=4e-3, horizon=125, particles_per_body=250, spacing_cells=0.5),
    "paper": SizeConfig(grid_res=64, dt=2e-3, horizon=250, particles_per_body=500, spacing_cells=0.6),
}


class Gathering(Task):
    """Move floating objects to goals with currents made by a paddle."""

    hard = False
    tool_name = "paddle"
    action_axes = (0, 1)
    max_tool_speed = 0.15
    flange_to_tool = FLANGE_TO_PADDLE
    sizes = GATHERING_SIZES
    observed_bodies = ("water", "object_a", "object_b")
    periodic = (10, 10)
    loss_is_step_mean = True
    camera = (-60.0, 50.0)
    # reward r = c1 − c2·ℓ with ℓ the summed mean squared distance of the objects to their goals at a step (m²):
    # the start (ℓ ≈ 4.7e-3 m²) earns about 0.06, both objects at their goals 1
    reward_c1 = 1.0
    reward_c2 = 200.0

    def _domain(self):
        return TANK_LOWER, TANK_UPPER

    def workspace(self):
        (x0, y0), (x1, y1) = PADDLE_AREA
        return np.array([x0, y0, PADDLE_Z]), np.array([x1, y1, PADDLE_Z])

    def initial_tool_pose(self):
        (x0, _), (x1, _) = PADDLE_AREA
        return np.array([0.5 * (x0 + x1), 0.0, PADDLE_Z, 0.0, 0.0, 0.0, 1.0])

    def water_surface(self) -> float:
        return TANK_WALL + WATER_DEPTH

    def float_bottom(self) -> float:
        """Height of a floating cube's bottom: it sinks by ρ_foam/ρ_water of its side (Archimedes)."""
        return self.water_surface() - common.FLOAT_FOAM.density / common.WATER.density * CUBE_SIDE

    def goals(self) -> dict:
        """{object body: goal point (m)} at the objects' floating height."""
        z = self.float_bottom() + 0.5 * CUBE_SIDE
        if self.hard:
            return {k: np.array([x, y, z]) for k, (x, y) in GOAL_HARD.items()}
        return {k: np.array([*GOAL_EASY, z]) for k in ("object_a", "object_b")}

    def _populate(self, scene, contact):
        tank = S.Tank(TANK_LOWER, TANK_UPPER, TANK_WALL)
        scene.add_static(tank, friction=0.2, name="tank")
        solids = []
        if self.hard:
            (x0, y0), (x1, y1) = POST
            post = S.Box((x0, y0, TANK_WALL), (x1, y1, TANK_UPPER[2]))
            scene.add_static(post, friction=0.2, name="post")
            solids.append(post)
        z0 = self.float_bottom()
        for name, y, mat in (("object_a", CUBE_Y, common.FLOAT_FOAM), ("object_b", -CUBE_Y, common.FLOAT_FOAM_B)):
            h = 0.5 * CUBE_SIDE
            cube = S.Box((CUBE_X - h, y - h, z0), (CUBE_X + h, y + h, z0 + CUBE_SIDE))
            scene.add_particles(cube, mat, name=name)
            solids.append(cube)
        tx, ty, tz = PADDLE_SIZE
        paddle = S.Box((-0.5 * tx, -0.5 * ty, 0.0), (0.5 * tx, 0.5 * ty, tz))
        # the water fills the tank round the paddle as it starts (2026-12-07: 5 % of it started inside the paddle,
        # which pushed it out in the first substeps and stirred the tank, docs/tasks.md)
        solids.append(common.Posed(paddle, self.initial_tool_pose()))
        scene.add_particles(common.Without(tank.interior(WATER_DEPTH), solids), common.WATER, name="water")
        scene.add_tool(paddle, pose=self.initial_tool_pose(),
                       name=self.tool_name, friction=self.tool_friction,
                       softness=self.softness if contact == "soft" else None, action_mask=(1, 1, 0, 0, 0, 0),
                       workspace=self.workspace(), max_speed=self.max_tool_speed)

    def loss(self, horizon=None):
        terms = [losses.MeanSquaredDistance(g, particles=self.body_slice(body), steps="all", weight=1.0 / self.horizon)
                 for body, g in self.goals().items()]
        return losses.Sum(terms)

    def step_term(self):
        return losses.Sum([losses.MeanSquaredDistance(g, particles=self.body_slice(body), steps="all")
                           for body, g in self.goals().items()])

    def attraction_particles(self):
        a, b = self.body_slice("object_a"), self.body_slice("object_b")
        return np.r_[a, b]


class GatheringEasy(Gathering):
    name = "GatheringEasy"
    hard = False


class GatheringHard(Gathering):
    name = "GatheringHard"
    hard = True

