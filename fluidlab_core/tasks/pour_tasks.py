"""The FluidLab tasks whose fluid enters the scene while it runs: LatteArtPour, IceCreamStatic, IceCreamDynamic.

Each has an emitter (engine/emitters.py) and a Chamfer loss over a goal pattern that a scripted motion drew on
the reference physics (goal files, tasks/goals.py).

LatteArtPour (Xian et al. 2023, "Latte Art (Pour)"): the cup of coffee of the cup tasks (cup_tasks.py, its axis
at CUP_CENTER, 25 mm of coffee) and a milk jug above it, whose spout is a nozzle carried by the jug (the tool):
milk leaves it downwards at JUG_RATE. The agent moves the jug in the horizontal plane (vx, vy), within a 30 mm
square over the cup axis, JUG_Z above the table. Loss: Σ over goal steps (every 5th) of the Chamfer distance
between the milk that has been poured and the goal's (m²). The milk is the paper's: as dense as the coffee
(ρ = 1.0 in its table), so it plunges and spreads into the coffee rather than floating; the pattern is where
it goes.

IceCream (Static and Dynamic; "Ice Cream" in the paper): an ice-cream machine's nozzle and a cone (a hollow
cone standing on its tip, CONE_*). Static: the cone stands on the table and the agent moves the nozzle in x, y
and z. Dynamic: the nozzle is fixed and the agent moves the cone (the arm holds it), in x, y and z; the ice
cream moves with the cone through friction with its wall. Loss: Σ over goal steps of the Chamfer distance
between the ice cream and the goal's: a spiral drawn by the scripted motion (the nozzle, or the cone,
circling while it rises).
"""
from __future__ import annotations

import numpy as np

from fluidlab_core import materials as M
from fluidlab_core import shapes as S
from fluidlab_core.tasks import common
from fluidlab_core.tasks.base import PatternTask, SizeConfig
from fluidlab_core.tasks.cup_tasks import CUP_CENTER, CUP_HEIGHT, CUP_OUTER_RADIUS, CUP_SIZES, CUP_WALL

# --- LatteArtPour ----------------------------------------------------------------------------------------
POUR_TOP = 0.09  # m, the domain's height: room for the jug above the cup
JUG_Z = 0.075  # tool origin (the spout's exit centre) above the table
JUG_REACH = 0.015  # half side of the square the spout moves in (m)
JUG_RADIUS = 0.004  # spout (nozzle disc) radius
JUG_RATE = 1.6e-5  # m³/s of milk (16 ml/s)
# the jug is held spout down: the tool frame is the flange frame (z down), 0.15 m along its z axis
FLANGE_TO_JUG = (0.0, 0.0, 0.15, 0.0, 0.0, 0.0, 1.0)
# the paper's milk: the coffee's density (weakly compressible as every task liquid, common.py)
TASK_MILK = M.NewtonianLiquid("task_milk", density=1000.0, bulk_modulus=1000.0 * common.SOUND_SPEED ** 2,
                              color=M.MILK.color)


def scripted_goal(task, body: str, actions, every: int, points: int):
    """Snapshots of a body every `every` steps of a scripted motion on the reference physics: a fixed-size random
    subset (seed 0) of the particles present at that step (a body still being emitted is resampled with
    repetition to the fixed size; steps before any particle is present are left out). Returns steps (K,) and
    points (K, points, 3)."""
    sim = task.simulator()
    task.reset(sim)
    rng = np.random.default_rng(0)
    steps, snaps = [], []
    for k, tw in enumerate(task.twists(actions), start=1):
        sim.step(tw)
        if k % every == 0:
            x = sim.positions(body)
            if len(x) == 0:
                continue
            pick = rng.permutation(len(x))[:points]
            steps.append(k)
            snaps.append(x[np.resize(np.sort(pick), points)])
    task.reset(sim)
    return np.array(steps), np.array(snaps)


class EmittingTask(PatternTask):
    """A pattern task (base.PatternTask) whose body comes from an emitter: no DP attraction (the tool does not
    touch the fluid it moves: its nozzle, or a container, carries it)."""

    emitted_body = ""

    @property
    def pattern_body(self) -> str:
        return self.emitted_body

    def attraction(self, weight: float):
        return None

    def goal_from_script(self):
        steps, points = scripted_goal(self, self.emitted_body, self.scripted_actions(), self.goal_every,
                                      self.goal_points)
        script = dict(self.SCRIPT, dt=self.dt, horizon=self.horizon, every=self.goal_every,
                      points=f"{self.emitted_body} particles present at the step, a fixed-size random subset "
                             f"(seed 0), resampled with repetition while fewer", contact="hard")
        return steps, points, script


class LatteArtPour(EmittingTask):
    """Pour milk from a moving jug into a cup of coffee to form a goal pattern."""

    name = "LatteArtPour"
    tool_name = "jug"
    action_axes = (0, 1)
    max_tool_speed = 0.15
    flange_to_tool = FLANGE_TO_JUG
    sizes = CUP_SIZES
    observed_bodies = ("coffee", "milk")
    target_body = "milk"
    emitted_body = "milk"
    camera = (30.0, 55.0)
    fill_height = 0.025
    # reward r = c1 − c2·ℓ with ℓ the Chamfer distance (m²) at a step: 1 mm² earns 0.8
    reward_c1 = 1.0
    reward_c2 = 2e5
    SCRIPT = {"description": "a forward pour with a sideways wiggle (a rosetta)", "vx": "0.06 m/s",
              "vy": "0.12·sin(2π t / 0.15 s) m/s", "start": "the task's initial jug pose"}

    def _domain(self):
        r = CUP_OUTER_RADIUS
        return (CUP_CENTER[0] - r, CUP_CENTER[1] - r, 0.0), (CUP_CENTER[0] + r, CUP_CENTER[1] + r, POUR_TOP)

    def workspace(self):
        lo = np.array([CUP_CENTER[0] - JUG_REACH, CUP_CENTER[1] - JUG_REACH, JUG_Z])
        hi = np.array([CUP_CENTER[0] + JUG_REACH, CUP_CENTER[1] + JUG_REACH, JUG_Z])
        return lo, hi

    def initial_tool_pose(self):
        return np.array([CUP_CENTER[0] - 0.01, CUP_CENTER[1], JUG_Z, 1.0, 0.0, 0.0, 0.0])  # spout down

    def _populate(self, scene, contact):
        cup = S.Cup(base_center=(*CUP_CENTER, 0.0), outer_radius=CUP_OUTER_RADIUS, height=CUP_HEIGHT,
                    wall_thickness=CUP_WALL)
        scene.add_static(cup, friction=0.3, name="cup")
        scene.add_particles(cup.interior(self.fill_height), common.COFFEE, name="coffee")
        # the jug: a spout tube above its exit (tool frame z down, the exit at the origin); it never touches
        # the fluid, so it has hard contact whatever `contact` asks
        scene.add_tool(S.Cylinder((0.0, 0.0, -0.008), JUG_RADIUS + 0.002, 0.01), pose=self.initial_tool_pose(),
                       name=self.tool_name, action_mask=(1, 1, 0, 0, 0, 0), workspace=self.workspace(),
                       max_speed=self.max_tool_speed)
        scene.add_emitter(TASK_MILK, rate=JUG_RATE, nozzle="disc", size=JUG_RADIUS, pose=(0, 0, 0, 0, 0, 0, 1),
                          tool=self.tool_name, duration=self.horizon * self.dt, name="milk")

    def scripted_actions(self) -> np.ndarray:
        t = np.arange(self.horizon) * self.dt
        return np.stack([np.full_like(t, 0.06), 0.12 * np.sin(2.0 * np.pi * t / 0.15)], axis=1)


# --- IceCream ----------------------------------------------------------------------------------------------
ICE_LOWER, ICE_UPPER = (0.45, -0.05, 0.0), (0.55, 0.05, 0.12)  # the domain (m)
CONE_TIP = (0.50, 0.0, 0.01)  # the fixed cone's tip (Static)
CONE_START = (0.50, 0.0, 0.025)  # the held cone's tip at the start (Dynamic): it may go down 15 mm
CONE_TOP_RADIUS = 0.03
CONE_HEIGHT = 0.07  # rim 80 mm above the table
NOZZLE_TIP = (0.50, 0.0, 0.10)  # the machine's nozzle exit (Dynamic; Static's start)
NOZZLE_RADIUS = 0.006
ICE_RATE = 2.0e-5  # m³/s (20 ml/s)
ICE_REACH = (0.012, 0.012, 0.015)  # half extents of the box the moving part's origin may move in (m)
# the arm holds the nozzle (Static) pointing down, or the cone (Dynamic) upright: tool frame = flange frame
# turned by π about x, 0.15 m along its z axis (Static); the cone upright, its tip 0.10 m below the flange
# and 0.06 m beside it (Dynamic)
FLANGE_TO_NOZZLE = (0.0, 0.0, 0.15, 0.0, 0.0, 0.0, 1.0)
# from the side, 100 mm off the cone's axis: at 60 mm the arm's wrist (fr3_link7) passed 1.9 mm from the nozzle above
# (the collision check, fluidlab_ros/collision.py, wants 10 mm); at 100 mm it keeps 32 mm
FLANGE_TO_CONE = (0.10, 0.0, 0.12, 1.0, 0.0, 0.0, 0.0)
# soft serve: the paper's ice cream density (0.5); moduli set for a 4 m/s wave speed like every task material
# (λ + 2μ = ρ c²), and a yield stress of 200 Pa, which a pile reaches at about 4 cm (ρ g h ≈ 200 Pa): the cone's
# spiral holds, and the nozzle's stream flows
TASK_ICE_CREAM = M.VonMisesPlastic("task_ice_cream", density=500.0, shear_modulus=2000.0, lame_lambda=4000.0,
                                   yield_stress=200.0, color=M.ICE_CREAM.color)
ICE_SIZES = {
    "small": SizeConfig(grid_res=24, dt=5e-3, horizon=100, particles_per_body=64, spacing_cells=0.5),
    "medium": SizeConfig(grid_res=32, dt=4e-3, horizon=125, particles_per_body=250, spacing_cells=0.5),
    "paper": SizeConfig(grid_res=64, dt=2e-3, horizon=250, particles_per_body=500, spacing_cells=0.5),
}


class IceCream(EmittingTask):
    """Fill a cone with ice cream from a machine's nozzle to a goal spiral: Static moves the nozzle, Dynamic
    (the task the paper ran on a real Franka) moves the cone under a fixed nozzle."""

    dynamic = False
    paper_particles = (5_000, 140_000)  # what the nozzle emits over the horizon: about 12k
    action_axes = (0, 1, 2)
    max_tool_speed = 0.1
    sizes = ICE_SIZES
    observed_bodies = ("ice_cream",)
    target_body = "ice_cream"
    emitted_body = "ice_cream"
    camera = (30.0, 35.0)
    goal_every = 10
    goal_points = 1000
    # reward r = c1 − c2·ℓ with ℓ the Chamfer distance (m²) at a step: 1 mm² earns 0.8
    reward_c1 = 1.0
    reward_c2 = 2e5
    SCRIPT = {"description": "a spiral: the moving part circles (radius 6 mm, one turn in 0.25 s) while the nozzle "
                             "rises relative to the cone at 0.035 m/s after the first 0.1 s",
              "start": "the task's initial pose"}

    def _domain(self):
        return ICE_LOWER, ICE_UPPER

    def workspace(self):
        start = self.initial_tool_pose()[:3]
        reach = np.array(ICE_REACH)
        return start - reach, start + reach

    def cone(self, dx: float) -> S.Cone:
        """The cone with 2-cell walls, its tip at the origin of the tool frame (Dynamic) or at CONE_TIP."""
        tip = (0.0, 0.0, 0.0) if self.dynamic else CONE_TIP
        return S.Cone(tip, CONE_TOP_RADIUS, CONE_HEIGHT, wall_thickness=2.0 * dx)

    def _populate(self, scene, contact):
        up = (0.0, 0.0, 0.0, 1.0)
        if self.dynamic:  # the cone is the tool; the nozzle is fixed and points down
            scene.add_tool(self.cone(scene.dx), pose=self.initial_tool_pose(), name=self.tool_name, friction=0.5,
                           action_mask=(1, 1, 1, 0, 0, 0), workspace=self.workspace(), max_speed=self.max_tool_speed,
                           keep_out=True, softness=None)
            scene.add_emitter(TASK_ICE_CREAM, rate=ICE_RATE, size=NOZZLE_RADIUS, pose=(*NOZZLE_TIP, 1.0, 0.0, 0.0, 0.0),
                              duration=self.horizon * self.dt, name="ice_cream")
        else:  # the cone is fixed; the nozzle is the tool (its tube above the exit, tool z pointing down)
            scene.add_static(self.cone(scene.dx), friction=0.5, name="cone")
            scene.add_tool(S.Cylinder((0.0, 0.0, -0.01), NOZZLE_RADIUS + 0.003, 0.012), pose=self.initial_tool_pose(),
                           name=self.tool_name, action_mask=(1, 1, 1, 0, 0, 0), workspace=self.workspace(),
                           max_speed=self.max_tool_speed)
            scene.add_emitter(TASK_ICE_CREAM, rate=ICE_RATE, size=NOZZLE_RADIUS, pose=(0, 0, 0, *up),
                              tool=self.tool_name, duration=self.horizon * self.dt, name="ice_cream")

    def scripted_actions(self) -> np.ndarray:
        t = np.arange(self.horizon) * self.dt
        w = 2.0 * np.pi / 0.25
        vx, vy = -0.006 * w * np.sin(w * t), 0.006 * w * np.cos(w * t)
        rise = np.where(t > 0.1, 0.035, 0.0) * (-1.0 if self.dynamic else 1.0)  # the cone goes down instead
        return np.stack([vx, vy, rise], axis=1)


class IceCreamStatic(IceCream):
    name = "IceCreamStatic"
    dynamic = False
    tool_name = "nozzle"
    flange_to_tool = FLANGE_TO_NOZZLE

    def initial_tool_pose(self):
        return np.array([*NOZZLE_TIP, 1.0, 0.0, 0.0, 0.0])


class IceCreamDynamic(IceCream):
    name = "IceCreamDynamic"
    dynamic = True
    tool_name = "cone"
    flange_to_tool = FLANGE_TO_CONE

    def initial_tool_pose(self):
        return np.array([*CONE_START, 0.0, 0.0, 0.0, 1.0])
