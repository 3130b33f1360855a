"""Air Circulation (FluidLab, Xian et al. 2023): turn an air conditioner so that it cools two rooms of a house and
keeps the third warm.

Scene (base frame fr3_link0, metres): a model house on the table, its inside HOUSE_LOWER…HOUSE_UPPER (56 × 38 cm,
4 cm high; closed walls, floor and ceiling), warm at T_WARM = 30 °C. Inner walls 31 mm thick split it into
three rooms and a hall, with doors, as in the paper's house (its `room.obj`, scaled and laid on the table with y
= −(the paper's z)):

    y ↑    +-----------+---+-----------+---+-----------+
           | upper-left|   |           |   |           |
           |  (cool)   door     hall   |   |   right   |
           +----  -----+   |    AC     door  (cool)    |
           | lower-left|   |           |   |           |
           |  (warm)   door            |   |           |
           +-----------+---+-----------+---+-----------+ → x

The air conditioner is a tool (a 24 × 70 × 24 mm box, a solid the air flows around) at the hall's centre, held
by the arm from above and turned about the vertical (the action: its yaw rate ω_z in rad/s, |ω_z| ≤ 1.5). Its vent
(a gas source carried by the tool, 60 mm wide and the house's height, in front of it along the tool's +x) blows
cool air, T_COOL = 18 °C, at 1 m/s. Air: ν = 1.5e-5 m²/s, Boussinesq buoyancy; gas solver
fluidlab_core/engine/gas.py. An episode is 6 s at every size (small 240 steps of 25 ms on a 40-cell grid,
medium 400 of 15 ms on 64 cells, paper 800 of 7.5 ms on 128 × 87 × 9 cells. The paper's grid is
128 × 9 × 128 in its y-up frame (x, height, depth) over a square domain; ours has its 128 cells along the house's
length and its 9 cells of height, and covers only the house's depth (87 cells), not the square around it).

Loss: 27 sensors at mid-height, 9 per room on a 3 × 3 grid. After each step k,

    ℓ_k = (1/27) [ Σ_upper-left |T − T_COOL| + Σ_right |T − T_COOL| + Σ_lower-left |T − T_WARM| ]   (K)

and the task loss is its mean over the horizon, L = (1/N) Σ_k ℓ_k (the paper's Σ over steps and sensors, in
kelvin per sensor and step). At the start ℓ = 8 K (18 sensors 12 K off). Reward r = 1 − ℓ/8 per step.

Observation: the temperature (K) and velocity (m/s) sampled at 8 × 6 points at mid-height (a fixed, downsampled
grid), the tool pose and twist: 8·6·4 + 13 = 205 numbers at every size.
"""
from __future__ import annotations

import numpy as np

from fluidlab_core import losses, shapes as S
from fluidlab_core.tasks.base import SizeConfig, Task

HOUSE_LOWER = (0.30, -0.19, 0.0)
HOUSE_UPPER = (0.86, 0.19, 0.04)
T_WARM = 303.15  # K, the house at the start, and what the lower-left room should stay at
T_COOL = 291.15  # K, the air conditioner's outlet, and what the upper-left and right rooms should reach
VENT_SPEED = 1.0  # m/s
AIR_VISCOSITY = 1.5e-5  # m²/s
AC_HALF = (0.012, 0.035, 0.012)  # the air conditioner's body, half extents in its frame (m)
VENT_HALF = (0.02, 0.03, 0.006)  # the vent's region in its own frame (z along the flow)
FLANGE_TO_AC = (0.0, 0.0, 0.15, 1.0, 0.0, 0.0, 0.0)
OBSERVED_GRID = (8, 6)  # observation points along x and y at mid-height

# the paper's house in its own unit square (x, z), FluidLab's assets/meshes/raw/room.obj: inside x 0.06…0.95,
# z 0.20…0.80, walls 0.05 thick, doors as gaps
_X0, _X1, _Z0, _Z1 = 0.06, 0.95, 0.20, 0.80
_WALLS = [  # (x range, z range) of inner wall pieces
    ((0.356, 0.406), (0.20, 0.27)), ((0.356, 0.406), (0.39, 0.58)), ((0.356, 0.406), (0.72, 0.80)),  # left | hall
    ((0.06, 0.356), (0.45, 0.50)),  # upper-left | lower-left
    ((0.66, 0.71), (0.20, 0.40)), ((0.66, 0.71), (0.58, 0.80)),  # hall | right
]
_ROOMS = {  # the rooms' (x range, z range), for the sensors
    "upper_left": ((0.06, 0.356), (0.20, 0.45)),
    "lower_left": ((0.06, 0.356), (0.50, 0.80)),
    "right": ((0.71, 0.95), (0.20, 0.80)),
}
_AC = (0.533, 0.50)

AIR_SIZES = {
    "small": SizeConfig(grid_res=40, dt=0.025, horizon=240, particles_per_body=0),
    "medium": SizeConfig(grid_res=64, dt=0.015, horizon=400, particles_per_body=0),
    "paper": SizeConfig(grid_res=128, dt=0.0075, horizon=800, particles_per_body=0),
}


def to_world(x, z) -> tuple[float, float]:
    """A point of the paper's unit-square house in the base frame (m): x scaled, the paper's z to −y."""
    lo, hi = np.asarray(HOUSE_LOWER), np.asarray(HOUSE_UPPER)
    wx = lo[0] + (x - _X0) / (_X1 - _X0) * (hi[0] - lo[0])
    wy = lo[1] + (_Z1 - z) / (_Z1 - _Z0) * (hi[1] - lo[1])
    return float(wx), float(wy)


WINDOW_SECONDS = 1.5  # DP over windows (optim/dp.py): the gradient window, in simulated seconds


class AirCirculation(Task):
    """Cool two rooms and keep one warm by turning an air conditioner (see the module docstring)."""

    name = "AirCirculation"
    tool_name = "air_conditioner"
    action_axes = (5,)  # ω_z
    max_tool_speed = 1.5  # rad/s
    flange_to_tool = FLANGE_TO_AC
    sizes = AIR_SIZES
    observed_bodies = ()
    camera = "top"
    action_knots = 10  # an arm turns it: a smooth yaw rate
    start_noise = 0.1
    learning_rate = 0.03  # DP's Adam step: 0.045 rad/s per knot (0.15, the default, overshot: the loss rose 7.18 → 7.61)
    reward_c1 = 1.0
    reward_c2 = 1.0 / 8.0
    paper_particles = (0, 0)
    loss_is_step_mean = True

    @property
    def gradient_window(self) -> int:
        """DP over windows: 1.5 s of steps (60 at small size), the span over which bench/air_gradient.py found the
        loss's derivative to agree with finite differences (docs/tasks.md)."""
        return max(1, round(WINDOW_SECONDS / self.config.dt))

    def _domain(self):
        return HOUSE_LOWER, HOUSE_UPPER

    def workspace(self):
        p = self.initial_tool_pose()[:3]
        return p.copy(), p.copy()  # it turns in place

    def initial_tool_pose(self):
        x, y = to_world(*_AC)
        return np.array([x, y, 0.5 * HOUSE_UPPER[2], 0.0, 0.0, 0.0, 1.0])

    def walls(self) -> list:
        """The inner walls as boxes (m), the full height of the house."""
        out = []
        for (x0, x1), (z0, z1) in _WALLS:
            (ax, ay), (bx, by) = to_world(x0, z1), to_world(x1, z0)
            out.append(S.Box((ax, ay, HOUSE_LOWER[2] - 0.01), (bx, by, HOUSE_UPPER[2] + 0.01)))
        return out

    def sensors(self) -> dict:
        """{room: (9, 3) sensor points (m)}: a 3 × 3 grid at mid-height in each room, a quarter of the room in from
        its walls."""
        out = {}
        z = 0.5 * HOUSE_UPPER[2]
        for room, ((x0, x1), (z0, z1)) in _ROOMS.items():
            pts = [(*to_world(x0 + fx * (x1 - x0), z0 + fz * (z1 - z0)), z)
                   for fx in (0.25, 0.5, 0.75) for fz in (0.25, 0.5, 0.75)]
            out[room] = np.array(pts)
        return out

    def targets(self) -> dict:
        return {"upper_left": T_COOL, "right": T_COOL, "lower_left": T_WARM}

    def _populate(self, scene, contact):
        cfg = self.config
        # the jet runs at 1 m/s and speeds up a little round the body: max_cfl 3 (semi-Lagrangian advection is
        # stable at any CFL; the MacCormack clamp keeps it bounded)
        scene.add_gas(resolution=cfg.grid_res, initial_temperature=T_WARM, ambient_temperature=T_WARM,
                      viscosity=AIR_VISCOSITY, tolerance=1e-6, max_cfl=3.0)
        for i, wall in enumerate(self.walls()):
            scene.add_static(wall, name=f"wall_{i}")
        scene.add_tool(S.Box(tuple(-h for h in AC_HALF), AC_HALF), pose=self.initial_tool_pose(), name=self.tool_name,
                       action_mask=(0, 0, 0, 0, 0, 1), workspace=self.workspace(),
                       max_speed=self.max_tool_speed * 0.05)  # its corners' speed (m/s)
        s = float(np.sqrt(0.5))
        scene.add_gas_source("vent", "box", VENT_HALF, pose=(AC_HALF[0] + VENT_HALF[2] + 0.002, 0.0, 0.0, 0.0, s, 0.0, s),
                             tool=self.tool_name, speed=VENT_SPEED, temperature=T_COOL)

    def _sensor_terms(self, weight: float, steps="all"):
        n = sum(len(p) for p in self.sensors().values())
        return losses.Sum([losses.GasSensors(pts, "temperature", target=self.targets()[room], power=1, steps=steps,
                                             weight=weight / n)
                           for room, pts in self.sensors().items()])

    def loss(self, horizon=None):
        return self._sensor_terms(1.0 / (horizon or self.horizon))

    def step_term(self):
        return self._sensor_terms(1.0)

    def simulator(self, grad: bool = False, contact: str = "hard", grad_max_steps: int = 200):
        sim = super().simulator(grad, contact, grad_max_steps)
        sim.render_points = np.concatenate(list(self.sensors().values()))  # pictures show the sensors
        return sim

    def attraction(self, weight):
        return None  # nothing to pull the tool towards: it turns in place

    # --- observation ----------------------------------------------------------------------------------------------
    def _observation_points(self) -> np.ndarray:
        lo, hi = np.asarray(HOUSE_LOWER), np.asarray(HOUSE_UPPER)
        nx, ny = OBSERVED_GRID
        xs = lo[0] + (np.arange(nx) + 0.5) / nx * (hi[0] - lo[0])
        ys = lo[1] + (np.arange(ny) + 0.5) / ny * (hi[1] - lo[1])
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        return np.stack([X.ravel(), Y.ravel(), np.full(X.size, 0.5 * hi[2])], axis=1)

    def observation_size(self) -> int:
        return OBSERVED_GRID[0] * OBSERVED_GRID[1] * 4 + 13

    def observe(self, sim, tool_twist=None) -> np.ndarray:
        """Temperature (K) and velocity (m/s) at the observation points, then the tool pose and twist; float32."""
        view = sim.view()
        pts = self._observation_points()
        parts = [view.sample("temperature", pts), view.sample("velocity", pts).ravel(), sim.tool_pose(self.tool_name),
                 np.zeros(6) if tool_twist is None else np.asarray(tool_twist, dtype=np.float64)]
        return np.concatenate(parts).astype(np.float32)
