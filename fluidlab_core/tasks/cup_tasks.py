"""The cup tasks of FluidLab: LatteArtStir and Mixing. A stirring stick, held vertically by the robot, moves
in the horizontal plane inside a cup of coffee.

Scene (base frame fr3_link0, metres): a cup standing on the table plane z = 0 with its axis at
CUP_CENTER = (0.50, 0.00), outer radius 45 mm, height 60 mm, walls 12 mm (inner radius 33 mm), holding 25 mm
(LatteArtStir) or 30 mm (Mixing) of coffee. The stick is a cylinder of radius 6 mm and length 50 mm whose tool
frame sits at its lower tip (z axis up the stick), 8 mm above the cup's inner bottom, held from the flange
by FLANGE_TO_STICK (tip 0.15 m below the flange along the flange's z axis, the flange pointing down, so the
tool frame is the flange frame turned by π about x and offset). The stick's origin moves in a 36 mm square
centred on the cup axis, which keeps the stick off the walls.

LatteArtStir (Xian et al. 2023, §4 and appendix): a disc of frothed milk foam (radius 15 mm, 6 mm thick)
floats on the coffee; the goal is a pattern drawn by a scripted stroke (a forward pass with a sideways
wiggle, the motion of a rosetta). Loss: Σ over goal steps k (every 5th step) of the Chamfer distance between
the milk particles and the goal's milk particles at step k (m², tasks/losses.py).

Mixing: a 12 mm cube of a viscous, denser "sugar" rests on the cup's bottom; stirring should spread it
through the coffee. Loss: minus the spatial spread of the sugar particles after the last step (m²).
"""
from __future__ import annotations

import numpy as np

from fluidlab_core import shapes as S
from fluidlab_core.tasks import common
from fluidlab_core.tasks.base import PatternTask, SizeConfig, Task
from fluidlab_core.tasks.losses import NegativeSpread

CUP_CENTER = (0.50, 0.00)  # m, cup axis in the base frame
CUP_OUTER_RADIUS = 0.045
CUP_HEIGHT = 0.06
CUP_WALL = 0.012
STICK_RADIUS = 0.006
STICK_LENGTH = 0.05
STICK_TIP_Z = 0.020  # tool origin: the stick's lower tip, 8 mm above the inner bottom (base 12 mm)
STICK_REACH = 0.018  # half side of the square the stick's axis may move in (m)
# tool frame in the flange frame: the flange's z axis points down in the stirring posture; the stick hangs
# along it with its tip 0.15 m from the flange, and the tool frame's z axis points up the stick
FLANGE_TO_STICK = (0.0, 0.0, 0.15, 1.0, 0.0, 0.0, 0.0)

CUP_SIZES = {
    "small": SizeConfig(grid_res=16, dt=4e-3, horizon=75, particles_per_body=64, spacing_cells=0.5),
    "medium": SizeConfig(grid_res=24, dt=3e-3, horizon=100, particles_per_body=250, spacing_cells=0.5),
    "paper": SizeConfig(grid_res=64, dt=2e-3, horizon=150, particles_per_body=1000, spacing_cells=0.75),
}


class CupTask(Task):
    tool_name = "stick"
    action_axes = (0, 1)
    max_tool_speed = 0.15
    flange_to_tool = FLANGE_TO_STICK
    camera = (30.0, 55.0)
    sizes = CUP_SIZES
    fill_height = 0.025
    start_xy = (CUP_CENTER[0] - 0.015, CUP_CENTER[1])

    def _domain(self):
        r = CUP_OUTER_RADIUS
        return (CUP_CENTER[0] - r, CUP_CENTER[1] - r, 0.0), (CUP_CENTER[0] + r, CUP_CENTER[1] + r, CUP_HEIGHT)

    def cup(self) -> S.Cup:
        return S.Cup(base_center=(*CUP_CENTER, 0.0), outer_radius=CUP_OUTER_RADIUS, height=CUP_HEIGHT,
                     wall_thickness=CUP_WALL)

    def workspace(self):
        lo = np.array([CUP_CENTER[0] - STICK_REACH, CUP_CENTER[1] - STICK_REACH, STICK_TIP_Z])
        hi = np.array([CUP_CENTER[0] + STICK_REACH, CUP_CENTER[1] + STICK_REACH, STICK_TIP_Z])
        return lo, hi

    def initial_tool_pose(self):
        return np.array([*self.start_xy, STICK_TIP_Z, 0.0, 0.0, 0.0, 1.0])

    def stick(self) -> S.Shape:
        """The stick in its own frame (origin at its lower tip)."""
        return S.Cylinder((0.0, 0.0, 0.5 * STICK_LENGTH), STICK_RADIUS, STICK_LENGTH)

    def stick_at_start(self) -> S.Shape:
        return common.Posed(self.stick(), self.initial_tool_pose())

    def solids(self) -> list:
        """Bodies that sit inside the coffee (the coffee is sampled around them)."""
        return []

    def _add_cup_and_stick(self, scene, contact):
        cup = self.cup()
        scene.add_static(cup, friction=0.3, name="cup")
        # the coffee fills the cup round the stick as it starts (2026-12-07: 2.7 % of it started inside the stick,
        # docs/tasks.md)
        around = self.solids() + [self.stick_at_start()]
        coffee = scene.add_particles(common.Without(cup.interior(self.fill_height), around), common.COFFEE,
                                     name="coffee")
        scene.add_tool(self.stick(), pose=self.initial_tool_pose(), name=self.tool_name, friction=self.tool_friction,
                       softness=self.softness if contact == "soft" else None, action_mask=(1, 1, 0, 0, 0, 0),
                       workspace=self.workspace(), max_speed=self.max_tool_speed)
        return cup, coffee


class LatteArtStir(PatternTask, CupTask):
    """Stir a floating layer of milk foam into a goal pattern."""

    name = "LatteArtStir"
    observed_bodies = ("coffee", "milk")
    target_body = "milk"
    milk_center = (CUP_CENTER[0], CUP_CENTER[1])
    milk_radius = 0.015
    milk_thickness = 0.006
    pattern_body = "milk"
    goal_every = 5  # steps between goal snapshots
    goal_points = 500  # goal points per snapshot (at most)
    # reward r = c1 − c2·ℓ with ℓ the Chamfer distance (m²) at a step: 1 mm² earns 0.8, 1 cm² earns −99
    reward_c1 = 1.0
    reward_c2 = 2e5

    def _populate(self, scene, contact):
        cup, _ = self._add_cup_and_stick(scene, contact)
        z0 = CUP_WALL + self.fill_height  # coffee surface
        milk = S.Cylinder((*self.milk_center, z0 + 0.5 * self.milk_thickness), self.milk_radius, self.milk_thickness)
        scene.add_particles(common.Without(milk, [self.stick_at_start()]), common.MILK_FOAM, name="milk")

    # --- the scripted goal ------------------------------------------------------------------------------
    SCRIPT = {"description": "forward stroke with a sideways wiggle (rosetta)",
              "vx": "0.08 m/s", "vy": "0.12·sin(2π t / 0.15 s) m/s", "start": "the task's initial tool pose"}

    def scripted_actions(self) -> np.ndarray:
        t = np.arange(self.horizon) * self.dt
        return np.stack([np.full_like(t, 0.08), 0.12 * np.sin(2.0 * np.pi * t / 0.15)], axis=1)

    def goal_from_script(self):
        sim = self.simulator()
        self.reset(sim)
        milk = sim.handle("milk")
        rng = np.random.default_rng(0)
        pick = np.sort(rng.choice(milk.count, min(self.goal_points, milk.count), replace=False))
        steps, points = [], []
        for k, tw in enumerate(self.twists(self.scripted_actions()), start=1):
            sim.step(tw)
            if k % self.goal_every == 0:
                steps.append(k)
                points.append(sim.positions(milk)[pick])
        self.reset(sim)
        script = dict(self.SCRIPT, dt=self.dt, horizon=self.horizon, every=self.goal_every,
                      points="milk particles, a fixed random subset (seed 0)", contact="hard")
        return np.array(steps), np.array(points), script


class Mixing(CupTask):
    """Stir a viscous sugar cube into the coffee (spread it as far as possible)."""

    name = "Mixing"
    observed_bodies = ("coffee", "sugar")
    target_body = "sugar"
    fill_height = 0.03
    cube_side = 0.012
    cube_center = (CUP_CENTER[0] + 0.01, CUP_CENTER[1])
    # Open loop, not the paper's periodic stroke-and-return policy. The sugar (2 Pa·s) is stirred at a Reynolds
    # number of about 1 (1200 kg/m³ · 0.15 m/s · 12 mm / 2 Pa·s), where viscous flow is nearly reversible: a stroke
    # followed by the motion that returns the tool undoes most of what the stroke did. Measured (small, reference
    # physics, spread relative to the still tool): back-and-forth strokes 0.98, one straight pass through the
    # cube 1.28; DP, DP-H and CMA-ES with the periodic policy reached 1.01-1.04 in 120 rollouts, and with an open
    # loop DP reached 1.16 and CMA-ES 1.10 in 40 (bench/results/benchmark_small, docs/benchmark.md).
    periodic = None
    # reward r = c1 − c2·ℓ with ℓ = −spread (m²): a spread of (5 mm)² earns 0.25
    reward_c1 = 0.0
    reward_c2 = 1e4

    def cube(self) -> S.Box:
        h = 0.5 * self.cube_side
        cx, cy = self.cube_center
        return S.Box((cx - h, cy - h, CUP_WALL), (cx + h, cy + h, CUP_WALL + self.cube_side))

    def solids(self):
        return [self.cube()]

    def _populate(self, scene, contact):
        self._add_cup_and_stick(scene, contact)
        scene.add_particles(self.cube(), common.SUGAR, name="sugar")

    def loss(self, horizon=None):
        return NegativeSpread(self.body_slice("sugar"), steps="final")

    def step_term(self):
        return NegativeSpread(self.body_slice("sugar"), steps="all")

