"""Transporting and Pouring (the paper's "Transporting" and "Fine Grained Pouring").

Transporting: a water-jet bot moves in a 30 × 60 mm area at the near end of the tank of the Gathering tasks
(gathering.py: x 0.42…0.58, y −0.06…0.06, 25 mm of water) and injects water through a nozzle it carries (a
6 mm disc whose centre is 5 mm under the surface: its top millimetre is above it), pointing along its own x
axis. A foam cube (the Gathering tasks' floating foam, 24 mm)
floats at (0.50, 0.0); the goal is GOAL = (0.545, 0.03) at its floating height. Actions: vx, vy (m/s) and wz
(rad/s, turning the jet about the vertical). Loss (the paper's form, a norm, not its square): the mean over
the steps and over the cube's particles of |x_i − goal| (m).

Pouring: a glass (a cup 50 mm across, 60 mm tall, 2-cell walls) held above the table holds a heavy liquid
(ρ = 1.5, the paper's) under a light one (ρ = 0.8). The agent tilts the glass about the horizontal axis y
through the middle of its rim on the +x side (the tool origin): one action, wy (rad/s). The light liquid should
leave and land on the table around GROUND = (0.56, 0, 0) while the heavy one stays. Loss (the paper's): after
the last step, the mean squared distance of the light particles to GROUND plus that of the heavy particles to
their initial positions (m²): the glass must pour and come back upright. The glass is a tool that keeps particles out of its walls (tools.py, keep_out),
so liquid does not leak through them as they move.
"""
from __future__ import annotations

import numpy as np

from fluidlab_core import losses, materials as M
from fluidlab_core import shapes as S
from fluidlab_core.tasks import common
from fluidlab_core.tasks.base import SizeConfig, Task
from fluidlab_core.tasks.gathering import CUBE_SIDE, GATHERING_SIZES, TANK_LOWER, TANK_UPPER, TANK_WALL, \
    WATER_DEPTH
from fluidlab_core.tasks.losses import MeanDistance

# --- Transporting ------------------------------------------------------------------------------------------
JET_AREA = ((0.440, -0.03), (0.470, 0.03))  # the bot origin's (x, y) bounds (m)
JET_RATE = 4.0e-5  # m³/s
JET_RADIUS = 0.006
JET_DEPTH = 0.005  # the nozzle's exit under the water surface (m)
OBJECT_XY = (0.50, 0.0)
GOAL = (0.545, 0.03)
FLANGE_TO_BOT = (0.0, 0.0, 0.15, 1.0, 0.0, 0.0, 0.0)
SQ = np.sqrt(0.5)


class Transporting(Task):
    """Move a floating object to a goal with a water jet."""

    name = "Transporting"
    tool_name = "jet"
    action_axes = (0, 1, 5)
    max_tool_speed = 0.15  # m/s for vx, vy and rad/s for wz
    flange_to_tool = FLANGE_TO_BOT
    sizes = GATHERING_SIZES
    observed_bodies = ("water", "object")
    target_body = "object"
    camera = (-60.0, 50.0)
    # reward r = c1 − c2·ℓ with ℓ the mean distance of the object to the goal at a step (m): the start (about
    # 0.055 m) earns about −0.1, the object at its goal 1
    reward_c1 = 1.0
    reward_c2 = 20.0

    def _domain(self):
        return TANK_LOWER, TANK_UPPER

    def surface(self) -> float:
        return TANK_WALL + WATER_DEPTH

    def workspace(self):
        (x0, y0), (x1, y1) = JET_AREA
        z = self.surface() - JET_DEPTH
        return np.array([x0, y0, z]), np.array([x1, y1, z])

    def initial_tool_pose(self):
        (x0, _), (x1, _) = JET_AREA
        return np.array([0.5 * (x0 + x1), 0.0, self.surface() - JET_DEPTH, 0.0, 0.0, 0.0, 1.0])

    def goal_point(self) -> np.ndarray:
        bottom = self.surface() - common.FLOAT_FOAM.density / common.WATER.density * CUBE_SIDE
        return np.array([*GOAL, bottom + 0.5 * CUBE_SIDE])

    def _populate(self, scene, contact):
        tank = S.Tank(TANK_LOWER, TANK_UPPER, TANK_WALL)
        scene.add_static(tank, friction=0.2, name="tank")
        h = 0.5 * CUBE_SIDE
        z0 = self.surface() - common.FLOAT_FOAM.density / common.WATER.density * CUBE_SIDE
        cube = S.Box((OBJECT_XY[0] - h, OBJECT_XY[1] - h, z0), (OBJECT_XY[0] + h, OBJECT_XY[1] + h, z0 + CUBE_SIDE))
        scene.add_particles(cube, common.FLOAT_FOAM, name="object")
        scene.add_particles(common.Without(tank.interior(WATER_DEPTH), [cube]), common.WATER, name="water")
        # the bot: a small housing above and behind its nozzle (tool frame: the nozzle exit at the origin,
        # the jet along +x); it leaves the jet free and never touches the object
        scene.add_tool(S.Box((-0.02, -0.008, 0.004), (-0.004, 0.008, 0.02)), pose=self.initial_tool_pose(),
                       name=self.tool_name, action_mask=(1, 1, 0, 0, 0, 1), workspace=self.workspace(),
                       max_speed=self.max_tool_speed)
        scene.add_emitter(common.WATER, rate=JET_RATE, size=JET_RADIUS, pose=(0.0, 0.0, 0.0, 0.0, SQ, 0.0, SQ),
                          tool=self.tool_name, duration=self.horizon * self.dt, name="jet_water")

    def loss(self, horizon=None):
        return MeanDistance(self.goal_point(), self.body_slice("object"), steps="all", weight=1.0 / self.horizon)

    def step_term(self):
        return MeanDistance(self.goal_point(), self.body_slice("object"), steps="all")

    def attraction(self, weight: float):
        return None  # the jet moves the object from afar


# --- Pouring -----------------------------------------------------------------------------------------------
POUR_LOWER, POUR_UPPER = (0.43, -0.04, 0.0), (0.59, 0.04, 0.12)
GLASS_CENTER = (0.48, 0.0)
GLASS_BASE_Z = 0.03  # the glass is held 30 mm above the table
GLASS_RADIUS = 0.025
GLASS_HEIGHT = 0.06
LAYER = 0.012  # each liquid's depth in the upright glass (m)
GROUND = (0.56, 0.0, 0.0)
# the glass is held from its side (−y), the flange's z axis along the tilt axis (+y), 13 cm from the rim: tilting
# the glass turns the wrist (joint 7) while the hand circles the rim. (Held from above, the arm reached a
# singular posture at 80° of tilt; see docs/tasks.md.)
FLANGE_TO_GLASS = (0.025, -0.03, 0.13, 0.7071067811865476, 0.0, 0.0, 0.7071067811865476)
POURING_SIZES = {
    "small": SizeConfig(grid_res=32, dt=5e-3, horizon=200, particles_per_body=64, spacing_cells=0.5),
    "paper": SizeConfig(grid_res=64, dt=2e-3, horizon=500, particles_per_body=500, spacing_cells=0.5),
}
TASK_LIGHT = M.NewtonianLiquid("task_light_liquid", density=800.0, bulk_modulus=800.0 * common.SOUND_SPEED ** 2,
                               color=M.LIGHT_LIQUID.color)
TASK_HEAVY = M.NewtonianLiquid("task_heavy_liquid", density=1500.0, bulk_modulus=1500.0 * common.SOUND_SPEED ** 2,
                               color=M.HEAVY_LIQUID.color)


class Pouring(Task):
    """Tilt a glass to pour out the light liquid and keep the heavy one."""

    name = "Pouring"
    tool_name = "glass"
    paper_particles = (10_000, 140_000)  # a 50 mm glass holds about 15k at the paper's resolution
    action_axes = (4,)
    max_tool_speed = 4.0  # rad/s about y
    action_knots = 12  # a smooth tilt: per-step noise at 4 rad/s asked joint 7 for 137x its acceleration
    flange_to_tool = FLANGE_TO_GLASS
    sizes = POURING_SIZES
    observed_bodies = ("light", "heavy")
    target_body = "light"
    camera = (-90.0, 10.0)
    # reward r = c1 − c2·ℓ with ℓ the loss at a step (m²): standing still (about 9.4e-3 m²) earns about −0.9
    reward_c1 = 1.0
    reward_c2 = 200.0

    def _domain(self):
        return POUR_LOWER, POUR_UPPER

    def workspace(self):
        p = self.initial_tool_pose()[:3]
        return p.copy(), p.copy()  # the glass turns about its rim and does not move

    def initial_tool_pose(self):
        return np.array([GLASS_CENTER[0] + GLASS_RADIUS, GLASS_CENTER[1], GLASS_BASE_Z + GLASS_HEIGHT,
                         0.0, 0.0, 0.0, 1.0])

    def glass(self, dx: float) -> S.Cup:
        """In the tool frame (origin at the rim on the +x side, axes as the world's at the start)."""
        return S.Cup((-GLASS_RADIUS, 0.0, -GLASS_HEIGHT), GLASS_RADIUS, GLASS_HEIGHT, wall_thickness=2.0 * dx)

    def initial_actions(self):
        """DP starts from a pour: a steady tilt to 86° (1.5 rad) over the first 40 % of the horizon, a hold, and
        the way back upright over the last 40 % (the loss wants the heavy liquid back where it started). From
        rest the loss does not change with the tilt until the light liquid reaches the rim, so a gradient from
        rest sees nothing to pour."""
        a = np.zeros((self.horizon, 1))
        n = int(0.4 * self.horizon)
        a[:n] = 1.5 / (n * self.dt)
        a[-n:] = -1.5 / (n * self.dt)
        return a

    def _populate(self, scene, contact):
        glass_local = self.glass(scene.dx)
        pose = self.initial_tool_pose()
        world = S.Cup((GLASS_CENTER[0], GLASS_CENTER[1], GLASS_BASE_Z), GLASS_RADIUS, GLASS_HEIGHT, 2.0 * scene.dx)
        inner = world.interior(2 * LAYER)
        lo_z = inner.center[2] - LAYER
        scene.add_particles(S.Cylinder((*GLASS_CENTER, lo_z + 0.5 * LAYER), inner.radius, LAYER), TASK_HEAVY,
                            name="heavy")
        scene.add_particles(S.Cylinder((*GLASS_CENTER, lo_z + 1.5 * LAYER), inner.radius, LAYER), TASK_LIGHT,
                            name="light")
        scene.add_tool(glass_local, pose=pose, name=self.tool_name, friction=0.2, action_mask=(0, 0, 0, 0, 1, 0),
                       workspace=self.workspace(), max_speed=self.max_tool_speed * (2 * GLASS_RADIUS + GLASS_HEIGHT),
                       keep_out=True)

    def _terms(self, steps):
        """The light liquid to GROUND plus the heavy liquid to its starting places, at `steps`."""
        sim = next(iter(self._sims.values()), None) or self.simulator()
        heavy0 = self._initial_state[id(sim)].x[self.body_slice("heavy")].astype(np.float64)
        return losses.MeanSquaredDistance(np.array(GROUND), particles=self.body_slice("light"), steps=steps) + \
            losses.MeanSquaredDistance(heavy0, particles=self.body_slice("heavy"), steps=steps)

    def loss(self, horizon=None):
        return self._terms("final")

    def step_term(self):
        return self._terms("all")

    def attraction(self, weight: float):
        return None
