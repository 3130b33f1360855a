"""The physics validation scenes, at any resolution: what the validation tests (tests/test_physics_*.py) run at
one size and the convergence study (bench/convergence.py) runs at three.

Each function builds its scene, runs it and returns what it measured as a dict; none asserts. Units SI, world
frame, z up, g = 9.81 m/s².

- `dam_break`: a water column of width a and height 2a collapses on a frictionless floor (Martin & Moyce
  1952, n² = 2). Reported: the surge front Z = x_front/a at the measured times T = t √(2g/a), its ratio to the
  measurement, and the front speed dZ/dT over 1.5 ≤ T ≤ 3.
- `water_column`: water at rest in a closed box. Hydrostatics: p = ρ g (h_s − z); reported: the fitted slope
  over ρg, r² of the fit, the intercept at the free surface (Pa) and the worst volume error Σ V⁰ det F / V − 1.
- `rayleigh_taylor`: a heavy liquid over a light one, the interface seeded with a cosine of wavelength W.
  Linear theory (inviscid, deep layers): the mode grows as exp(σt), σ = √(A k g), A = (ρ₁ − ρ₂)/(ρ₁ + ρ₂),
  k = 2π/W. Reported: the spike amplitude over time and its fitted rate over 0.04–0.2 s.
- `floating_cube`: a rigid cube of side b and density ρ_b dropped onto water in a closed 3-D tank. Archimedes:
  it floats with the fraction ρ_b/ρ_w of its side below the surface. Reported over time: its lowest face below
  the far-field surface over b (the submerged fraction), the share of its particles below that surface, and the
  share of its volume below the surface that the liquid's volume fills the tank to (the measure to judge by).

- `magnus`: a neutrally buoyant rigid disc (quasi-2-D, a slab one disc thick, no gravity) or ball (3-D tank,
  gravity, the ball at mid-depth), started at U along x with spin ω about z (spin ratio α = ω r / U) in water at
  rest. Magnus: it deflects along ω × U, here +y for α > 0 (towards the side where its surface moves with the
  oncoming flow); none without spin; more with more spin. Reported over time: its displacement, velocity and
  spin.
- `magnus_held`: the same disc (or a ball) held at U and ω as a hand would hold it: the water's force on it over
  each step, its lift along ω × U against Kutta–Joukowski.
- `static_tank`: a liquid at rest in a tank that is a static (its floor and walls an SDF, as in the tasks), its
  floor's surface `offset` cells above a node row (0: on one), beside the same liquid held by the domain's own
  walls. The depth it fills is V/A whatever the boundary (minus its hydrostatic compression, ρgh/(2K) on average);
  reported over time: the depth twice the particles' mean height shows and the share of particles on the floor.
- `sound_ring`: a water column of depth H released at rest without its hydrostatic pressure (J = 1) rings
  with a quarter wave, period 4H/c (c = √(λ/ρ)); a bulk viscosity ζ (materials.DampedLiquid) damps it at
  ζk²/(2ρ), k = π/(2H). Reported: the mid-depth pressure over time, its period, first swing, decay rate and mean
  against ρg(H − z).

The quasi-2-D scenes (dam break, water column, Rayleigh–Taylor) are slabs two cells thick between frictionless
walls, which behave as the 2-D experiments they are compared with (the sound ring too); the floating cube is
fully 3-D.
"""
from __future__ import annotations

import math

import numpy as np

G = 9.81

# Martin, J. C. & Moyce, W. J. (1952) "An experimental study of the collapse of liquid columns on a rigid
# horizontal plane", Phil. Trans. R. Soc. A 244, 312-324, Fig. 3: column of width a and height 2a (n² = 2).
# Surge front Z = x/a against T = t·sqrt(2g/a), as digitised in PySPH (pysph/examples/db_exp_data.py) for
# a = 1.125 in and a = 2.25 in.
MARTIN_MOYCE_N2 = np.array([
    (0.849, 1.245), (1.212, 1.443), (1.602, 1.884), (2.283, 2.689), (2.950, 3.728),  # a = 1.125 in
    (0.832, 1.217), (1.219, 1.474), (1.997, 2.292), (2.547, 2.995), (3.345, 4.134),  # a = 2.25 in
])


def _substeps(scene, substeps):
    scene.substeps = int(substeps) if substeps else scene.stable_substeps()


def dam_break(res: int = 64, a: float = 0.1, length: float = 0.5, substeps: int | None = 10, liquid=None,
              flip: float = 0.0, jbar: bool = False) -> dict:
    """The collapsing column of `liquid` (default the catalogue's water) in a tank `length` long, `res` cells
    along it (substeps None: the stable count; flip, jbar: the Scene's AFLIP share and J-bar)."""
    import fluidlab_core as fl
    from fluidlab_core import materials as M

    liquid = liquid or M.WATER
    dx = length / res
    thick = 2 * dx
    scene = fl.Scene(lower=(0, 0, 0), upper=(length, thick, 0.25), grid_res=res, dt=2e-3, substeps=1, flip=flip,
                     jbar=jbar)
    scene.add_particles(fl.Box((0.0, 0.0, 0.0), (a, thick, 2 * a)), liquid, name="water")
    _substeps(scene, substeps)
    sim = scene.build()
    times, fronts = [], []
    t_scale = math.sqrt(2 * G / a)
    while sim.time * t_scale <= 3.5:
        times.append(sim.time * t_scale)
        fronts.append(sim.positions("water")[:, 0].max() / a)  # the front is the farthest particle
        sim.step()
    times, fronts = np.array(times), np.array(fronts)
    z_sim = np.interp(MARTIN_MOYCE_N2[:, 0], times, fronts)
    window = (times >= 1.5) & (times <= 3.0)
    return dict(dx=dx, particles=sim.n_particles, substeps=scene.substeps, times=times, fronts=fronts,
                z_sim=z_sim, ratio=z_sim / MARTIN_MOYCE_N2[:, 1],
                speed=float(np.polyfit(times[window], fronts[window], 1)[0]))


def water_column(res: int = 16, width: float = 0.16, height: float = 0.12, steps: int = 1000, average: int = 100,
                 substeps: int | None = 10, liquid=None, flip: float = 0.0, jbar: bool = False) -> dict:
    """Water (or `liquid`) at rest (flip, jbar: the Scene's AFLIP share and J-bar), `steps` steps of 2 ms;
    pressure averaged over the last `average` steps (the liquid rings with sound waves that APIC barely damps). Particles within 1.5 cells of the floor are left out
    of the fit: their B-spline support reaches into the wall nodes. Also reported: the spread (m, std) of the
    top layer's heights at the end, a measure of how flat the free surface stays."""
    import fluidlab_core as fl
    from fluidlab_core import materials as M

    liquid = liquid or M.WATER
    dx = width / res
    scene = fl.Scene(lower=(0, 0, 0), upper=(width, 2 * dx, height + 0.04), grid_res=res, dt=2e-3, substeps=1,
                     flip=flip, jbar=jbar)
    scene.add_particles(fl.Box((0, 0, 0), (width, 2 * dx, height)), liquid, name="water")
    _substeps(scene, substeps)
    sim = scene.build()
    v0 = sim.volumes("water").sum()
    worst = 0.0
    pressures, heights = [], []
    for step in range(steps):
        sim.step()
        worst = max(worst, abs(sim.volumes("water").sum() / v0 - 1.0))
        if step >= steps - average:
            pressures.append(sim.pressures("water"))
            heights.append(sim.positions("water")[:, 2])
    p, z = np.mean(pressures, axis=0), np.mean(heights, axis=0)
    surface = z.max() + 0.25 * dx  # the top particle row sits a quarter cell (half a lattice step) below it
    depth = surface - z
    keep = z > 1.5 * dx
    edges = np.linspace(0.0, depth[keep].max(), 9)
    idx = np.digitize(depth[keep], edges[1:-1])
    d_bin = np.array([depth[keep][idx == i].mean() for i in range(8)])
    p_bin = np.array([p[keep][idx == i].mean() for i in range(8)])
    slope, intercept = np.polyfit(d_bin, p_bin, 1)
    residual = p_bin - (slope * d_bin + intercept)
    rho_g = liquid.density * G
    z_end = heights[-1]
    top = z_end > z_end.max() - 0.25 * dx  # the top layer (lattice step dx/2)
    return dict(dx=dx, substeps=scene.substeps * steps, worst_volume_error=worst, surface=surface,
                surface_spread=float(z_end[top].std()),
                slope=float(slope), slope_ratio=float(slope / rho_g), intercept=float(intercept),
                r2=float(1 - (residual ** 2).sum() / ((p_bin - p_bin.mean()) ** 2).sum()), rho_g=rho_g)


def static_tank(offset: float = 0.0, res: int = 20, size: float = 0.1, depth: float = 0.025, wall_cells: int = 2,
                times=(0.1, 1.0), liquid=None, walls: bool = False) -> dict:
    """`liquid` (the tasks' water by default) `depth` deep at rest in a square tank `size` wide, a static
    (shapes.Tank, walls `wall_cells` thick), its floor's surface `offset` cells above a node row, on a grid of `res`
    cells across `size`; or (walls=True) the same water held by the domain's walls alone (the domain the tank's
    inside). Reported at each of `times` (s): the depth 2 (mean z − floor) (m), the share of particles within
    0.05 cells of the floor, and the particles' mean J."""
    import fluidlab_core as fl
    from fluidlab_core import shapes as S
    from fluidlab_core.tasks import common

    liquid = liquid or common.WATER
    dx = size / res
    wall = wall_cells * dx
    if walls:
        inner = size - 2 * wall
        scene = fl.Scene(lower=(0, 0, 0), upper=(inner, inner, size), grid_res=res, dt=5e-3, substeps=1)
        floor, lo, hi = 0.0, 0.0, inner
    else:
        scene = fl.Scene(lower=(0, 0, 0), upper=(size, size, size), grid_res=res, dt=5e-3, substeps=1)
        scene.add_static(S.Tank((0, 0, offset * dx), (size, size, size), wall), friction=0.2, name="tank")
        floor, lo, hi = wall + offset * dx, wall, size - wall
    scene.add_particles(S.Box((lo, lo, floor), (hi, hi, floor + depth)), liquid, name="liquid")
    _substeps(scene, None)
    sim = scene.build()
    out = dict(dx=scene.dx, floor=floor, depth0=depth, substeps=scene.substeps, times=[], depth=[], on_floor=[], J=[])
    for t in times:
        while sim.time < t - 1e-9:
            sim.step()
        z = sim.positions("liquid")[:, 2]
        out["times"].append(sim.time)
        out["depth"].append(float(2.0 * (z.mean() - floor)))
        out["on_floor"].append(float((z < floor + 0.05 * scene.dx).mean()))
        out["J"].append(float(np.linalg.det(sim.deformation_gradients("liquid")).mean()))
    return out


def _layer_shape(width, thick, z0, z1, mid, amp, above):
    """Liquid above (or below) the interface z = mid + amp·cos(2πx/W) in a slab [0, W] × [0, th] × [z0, z1]."""
    from fluidlab_core.shapes import Box, Shape

    class Layer(Shape):
        def __init__(self):
            self.box = Box((0.0, 0.0, z0), (width, thick, z1))

        def bounds(self):
            return self.box.bounds()

        def sdf(self, points):
            points = np.asarray(points)
            interface = mid + amp * np.cos(2 * np.pi * points[..., 0] / width)
            side = interface - points[..., 2] if above else points[..., 2] - interface
            return np.maximum(self.box.sdf(points), side)

    return Layer()


def rayleigh_taylor(top, bottom, res: int = 64, width: float = 0.1, height: float = 0.2, amp: float = 0.005,
                    duration: float = 0.2, substeps: int | None = 12, hydrostatic: bool = False,
                    **scene_options) -> dict:
    """The seeded two-layer slab, `res` cells over its height (res/2 per wavelength W = width). Reported: times,
    spike amplitudes (m; where the interface starts lowest, x = W/2, how far below the mid-plane the top liquid
    reaches), the top layer's centroid drop (m), σ fitted over 0.04–0.2 s and σ from linear theory.
    hydrostatic: start both layers with their hydrostatic compression (Simulator.start_hydrostatic) instead of
    at J = 1 (the equation of state's liquids only). scene_options go to fl.Scene (e.g. pressure="projection")."""
    import fluidlab_core as fl

    dx = height / res
    thick = 2 * dx
    mid = height / 2
    scene = fl.Scene(lower=(0, 0, 0), upper=(width, thick, height), grid_res=res, dt=1e-3, substeps=1,
                     **scene_options)
    scene.add_particles(_layer_shape(width, thick, 0.0, height, mid, amp, above=False), bottom, name="bottom")
    scene.add_particles(_layer_shape(width, thick, 0.0, height, mid, amp, above=True), top, name="top")
    _substeps(scene, substeps)
    sim = scene.build()
    if hydrostatic:
        sim.start_hydrostatic()
    z0 = sim.positions("top")[:, 2].mean()
    times, spikes = [], []
    while sim.time <= duration:
        x = sim.positions("top")
        near_axis = np.abs(x[:, 0] - width / 2) < dx
        times.append(sim.time)
        spikes.append(mid - x[near_axis, 2].min())
        sim.step(n=10)
    times, spikes = np.array(times), np.array(spikes)
    window = (times >= 0.04) & (times <= 0.2)
    atwood = (top.density - bottom.density) / (top.density + bottom.density)
    return dict(dx=dx, substeps=scene.substeps, times=times, spikes=spikes,
                drop=float(z0 - sim.positions("top")[:, 2].mean()),
                sigma=float(np.polyfit(times[window], np.log(spikes[window]), 1)[0]) if window.sum() > 1 else math.nan,
                sigma_theory=math.sqrt(abs(atwood) * 2 * math.pi / width * G))


def submerged(x_liquid, x_body, axis, side: float, dx: float, spacing: float):
    """(fraction, share, surface m) of a floating cube of `side` whose vertical axis passes through axis = (x, y):
    its lowest face below the far-field surface over its side, and the share of its particles below that
    surface. Far field: liquid more than a side from the axis in x or y; its surface is the 99th percentile of
    those particles' heights plus a quarter cell (the top particles sit half a lattice step below it)."""
    far = (np.abs(x_liquid[:, 0] - axis[0]) > side) | (np.abs(x_liquid[:, 1] - axis[1]) > side)
    surface = float(np.percentile(x_liquid[far, 2], 99) + 0.25 * dx)
    lowest_face = x_body[:, 2].min() - 0.5 * spacing
    return float((surface - lowest_face) / side), float((x_body[:, 2] < surface).mean()), surface


def submerged_by_volume(liquid_volume: float, x_body, body_volumes, area: float):
    """(share, surface m): the share of a floating body's volume below the surface height h at which the liquid's
    volume (Σ V⁰ J, m³) and the body's part below h fill a tank of cross-section `area` (m²):
        A h = V_l + Σ_p V_p clamp((h − z_p)/s_p + ½, 0, 1),   share = Σ_p V_p clamp(…) / Σ_p V_p,
    each body particle (volume V_p, `body_volumes`) counted by the part of its layer, s_p = V_p^(1/3) thick, that
    lies below h. Exact for a flat surface, a level body and no voids; unlike `submerged`'s percentile of the top
    particles it does not read a rough surface high (the top layer of a disturbed MPM surface scatters by a
    third of a cell; at 16 cells its 99th percentile sat 1.2–2.6 mm above this surface in the catalogue's water,
    and between 0.6 mm below and 1.1 mm above it in the tasks' softer water, bench/results/buoyancy_3d.txt)."""
    v = np.asarray(body_volumes, dtype=np.float64)

    def below(h):
        return volume_below(h, x_body, v)

    lo, hi = 0.0, (liquid_volume + v.sum()) / area + 1.0  # A h − V_l − below(h) rises with h
    for _ in range(80):
        h = 0.5 * (lo + hi)
        lo, hi = (h, hi) if area * h - liquid_volume - below(h) < 0.0 else (lo, h)
    h = 0.5 * (lo + hi)
    return below(h) / float(v.sum()), h


def volume_below(h: float, x_body, body_volumes) -> float:
    """Σ_p V_p clamp((h − z_p)/s_p + ½, 0, 1) (m³): the part of a body's volume below height h, each particle
    counted by the part of its layer, s_p = V_p^(1/3) thick, under h (submerged_by_volume's count)."""
    return float(volumes_below(h, x_body, body_volumes).sum())


def volumes_below(h: float, x_body, body_volumes) -> np.ndarray:
    """Each particle's V_p clamp((h − z_p)/s_p + ½, 0, 1) (m³): volume_below's terms."""
    z = np.asarray(x_body)[:, 2]
    v = np.asarray(body_volumes, dtype=np.float64)
    return v * np.clip((h - z) / np.cbrt(v) + 0.5, 0.0, 1.0)


def pressure_zero(sim, columns) -> float:
    """The height (m) at which the pressure of a Scene(pressure="projection") simulator reaches 0: in each column of
    nodes (i, j) given, the line fitted to the solve's pressure over its liquid unknowns but the lowest and the
    highest (the floor's row and the surface's), extrapolated to p = 0; the mean over the columns."""
    from fluidlab_core.engine.projection import LIQ

    proj, model = sim.solver.proj, sim.solver.model
    kind, p = proj.kind.to_numpy(), proj.p.to_numpy()
    zeros = []
    for i, j in columns:
        rows = np.nonzero(kind[i, j, :] == LIQ)[0][1:-1]
        a, b = np.polyfit(model.origin[2] + rows * model.dx, p[i, j, rows], 1)
        zeros.append(-b / a)
    return float(np.mean(zeros))


def best_rotation(start, now) -> np.ndarray:
    """The 3×3 rotation that best maps a body's particles at `start` onto them `now`, about their centroids
    (least squares: Kabsch's SVD). For a body's tilt or roll from its particles alone."""
    a = np.asarray(start, dtype=np.float64) - np.mean(start, axis=0)
    b = np.asarray(now, dtype=np.float64) - np.mean(now, axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def gathering_submerged_shares(sim, objects, paddle: str | None = None) -> list[float]:
    """Each floating object's share of its volume below the water's surface in the Gathering tank (Transporting's
    too), the surface being the height h at which the water (every liquid body but the objects: the tank's water
    and any emitted), the objects' parts below h and the paddle's (a box PADDLE_SIZE across from its pose's z up;
    `paddle` the tool's name, or None where no tool is in the water) fill the tank's inside:
        (A − A_paddle) h = V_water + A z_floor − A_paddle z_paddle + Σ_objects volume below h
    (submerged_by_volume; Archimedes: ρ_object/ρ_water). A count of particles under the fill height
    moves in particle layers (sixths of a cube at the small size) and reads any change of the water's level."""
    from fluidlab_core.tasks.gathering import PADDLE_SIZE, TANK_LOWER, TANK_UPPER, TANK_WALL

    liquids = [h for h in sim.handles if h not in objects and sim.handles[h].material.is_liquid]
    water = sum(float(sim.volumes(h).sum()) for h in liquids)
    area = (TANK_UPPER[0] - TANK_LOWER[0] - 2 * TANK_WALL) * (TANK_UPPER[1] - TANK_LOWER[1] - 2 * TANK_WALL)
    fill = water + area * TANK_WALL
    if paddle is not None:
        a_paddle = PADDLE_SIZE[0] * PADDLE_SIZE[1]
        area, fill = area - a_paddle, fill - a_paddle * float(sim.tool_pose(paddle)[2])
    x = {b: sim.positions(b) for b in objects}
    v = {b: sim.volumes(b) for b in objects}
    _, h = submerged_by_volume(fill, np.concatenate(list(x.values())), np.concatenate(list(v.values())), area)
    return [volume_below(h, x[b], v[b]) / float(v[b].sum()) for b in objects]


def cube_volume_share(sim, width: float = 0.12):
    """(share, surface m, the liquid's positions) of floating_cube_sim's set-up: submerged_by_volume of the cube
    against every block of liquid (the particle bodies other than "cube") in the tank `width` across."""
    waters = [h for h in sim.handles if h != "cube"]
    volume = sum(float(sim.volumes(h).sum()) for h in waters)
    share, surface = submerged_by_volume(volume, sim.positions("cube"), sim.volumes("cube"), width * width)
    return share, surface, np.concatenate([sim.positions(h) for h in waters])


def floating_cube_sim(res: int, body, liquid, drop: float | None = 0.01, width: float = 0.12, level: float = 0.06,
                      side: float = 0.04, lift: float = 0.0, substep_factor: float = 1.0, **scene_options):
    """(simulator, scene) of floating_cube's set-up: `level` of `liquid` in a closed tank `width` wide and 0.12 m
    tall, `res` cells across, a cube of `side` of material `body` centred over it with its bottom `drop` above
    the surface, or (drop None) started at Archimedes' depth + `lift` with the liquid carved round it (and over it,
    when that puts it under the surface; lift = −(the depth) stands it on the floor); particles
    named "water" (the liquid, one body per block) and "cube"; the stable substep count × substep_factor.
    scene_options go to fl.Scene (e.g. contact_fill)."""
    import fluidlab_core as fl
    from fluidlab_core.shapes import Box

    scene = fl.Scene(lower=(0, 0, 0), upper=(width, width, 0.12), grid_res=res, dt=2e-3, substeps=1, **scene_options)
    c = width / 2
    if drop is not None:
        bottom = level + drop
        blocks = [((0, 0, 0), (width, width, level))]
    else:
        bottom = level - side * body.density / liquid.density + lift
        lo, hi = c - side / 2, c + side / 2
        blocks = [((0, 0, 0), (width, width, bottom)), ((0, 0, bottom), (lo, width, level)),
                  ((hi, 0, bottom), (width, width, level)), ((lo, 0, bottom), (hi, lo, level)),
                  ((lo, hi, bottom), (hi, width, level))]
        if bottom + side < level - 1e-9:  # started under the surface: the liquid over its top face too
            blocks.append(((lo, lo, bottom + side), (hi, hi, level)))
        blocks = [blk for blk in blocks if blk[1][2] - blk[0][2] > 1e-9]  # none under a cube on the floor
    for i, (a, b) in enumerate(blocks):
        scene.add_particles(Box(a, b), liquid, name="water" if i == 0 else f"water{i}")
    scene.add_particles(Box((c - side / 2, c - side / 2, bottom), (c + side / 2, c + side / 2, bottom + side)),
                        body, name="cube")
    _substeps(scene, None)
    scene.substeps = int(round(scene.substeps * substep_factor))
    return scene.build(), scene


def floating_cube(res: int = 16, density: float = 500.0, seconds: float = 2.0, drop: float | None = 0.01,
                  width: float = 0.12, level: float = 0.06, side: float = 0.04, every: float = 0.05,
                  body=None, liquid=None, progress=None, substep_factor: float = 1.0, **scene_options) -> dict:
    """A cube of `side` and `density` (a rigid body unless `body`, a material, is given) dropped from `drop`
    above the surface of `level` of water (`liquid`, default the catalogue's) in a closed tank `width` wide and
    0.12 m tall, `res` cells across, the stable substep count. Every `every` seconds: the cube's lowest face
    below the far-field surface over its side (`fraction`; far field: more than a side from the cube's axis in
    x or y) and the share of its particles below that surface (`share`), both against the 99th percentile of the
    far field's particle heights (`submerged`), and the share of its volume below the surface its liquid's
    volume fills the tank to (`volume_share`, `submerged_by_volume`: the measure to judge it by, since the
    percentile reads a disturbed surface high). progress(t, fraction) if given. drop None starts the cube at
    rest at Archimedes' depth (floating_cube_sim); substep_factor and scene_options (e.g. pressure="projection")
    as there."""
    from fluidlab_core import materials as M

    liquid = liquid or M.WATER
    body = body or M.Rigid(f"rigid_{density:g}", density=density)
    sim, scene = floating_cube_sim(res, body, liquid, drop, width, level, side, substep_factor=substep_factor,
                                   **scene_options)
    c = width / 2
    dx, s = width / res, scene.particle_spacing
    times, fractions, shares, volume_shares = [], [], [], []
    n = max(1, int(round(every / scene.dt)))
    while sim.time < seconds - 1e-9:
        sim.step(n=n)
        x_cube = sim.positions("cube")
        volume_share, _, x_water = cube_volume_share(sim, width)
        fraction, share, _ = submerged(x_water, x_cube, (c, c), side, dx, s)
        times.append(sim.time)
        fractions.append(fraction)
        shares.append(share)
        volume_shares.append(volume_share)
        if progress:
            progress(sim.time, fractions[-1])
    return dict(dx=dx, particles=sim.n_particles, substeps=scene.substeps, times=np.array(times),
                fractions=np.array(fractions), shares=np.array(shares), volume_shares=np.array(volume_shares),
                expected=body.density / liquid.density)


def _outside(outer, hole):
    """The points of shape `outer` outside shape `hole` (the liquid around a body), as a Shape."""
    from fluidlab_core.shapes.primitives import Shape

    class Outside(Shape):
        def bounds(self):
            return outer.bounds()

        def sdf(self, points):
            return np.maximum(outer.sdf(points), -hole.sdf(points))

        def volume(self):
            return outer.volume() - hole.volume()

    return Outside()


def _set_rigid_motion(state, body: slice, v, omega):
    """Give the particles `body` of `state` the rigid motion v + ω × r about their centroid (m/s, rad/s), and
    APIC's C = ∇v = [ω]×."""
    r = state.x[body] - state.x[body].mean(axis=0)
    state.v[body] = np.asarray(v) + np.cross(omega, r)
    state.C[body] = np.array([[0.0, -omega[2], omega[1]], [omega[2], 0.0, -omega[0]], [-omega[1], omega[0], 0.0]])


def magnus(res: int = 64, alpha: float = 1.0, dims: int = 2, seconds: float = 0.06, speed: float = 0.2,
           radius: float = 0.012, sound_speed: float = 4.0, contact_fill: float = 0.97, every: int = 5) -> dict:
    """A rigid body of water's density started at `speed` (m/s) along x with spin α·speed/radius (rad/s) about
    z in water of `sound_speed` (m/s; Mach speed/sound_speed), `res` cells along the 0.16 m tank.
    dims=2: a disc of `radius` through a slab two cells thick (0.16 × 0.12 m), no gravity, the liquid filling
    the slab. dims=3: a ball of `radius` at mid-depth in 0.11 m of water (0.16 × 0.10 × 0.12 m tank), gravity,
    its density that of the water at its depth (ρ/J), released 0.1 s after the water settles. Every `every`
    steps of 2 ms: displacement (m), velocity (m/s) and spin about z (rad/s) of the body."""
    import fluidlab_core as fl
    from fluidlab_core import materials as M

    width, depth = 0.16, (0.12 if dims == 2 else 0.10)
    dx = width / res
    water = M.NewtonianLiquid(f"water_c{sound_speed:g}", density=1000.0, bulk_modulus=1000.0 * sound_speed ** 2)
    if dims == 2:
        scene = fl.Scene(lower=(0, 0, 0), upper=(width, depth, 2 * dx), grid_res=res, dt=2e-3, substeps=1,
                         gravity=(0, 0, 0), contact_fill=contact_fill)
        s = scene.particle_spacing
        body_shape = fl.Cylinder((0.04 + s / 2, depth / 2 + s / 2, dx), radius, 2 * dx)
        tank, rho = fl.Box((0, 0, 0), (width, depth, 2 * dx)), 1000.0
    else:
        level, zc = 0.11, 0.055
        scene = fl.Scene(lower=(0, 0, 0), upper=(width, depth, 0.12), grid_res=res, dt=2e-3, substeps=1,
                         contact_fill=contact_fill)
        s = scene.particle_spacing
        body_shape = fl.Sphere((0.04 + s / 2, depth / 2 + s / 2, zc + s / 2), radius)
        tank = fl.Box((0, 0, 0), (width, depth, level))
        rho = 1000.0 / (1.0 - 1000.0 * G * (level - zc) / water.lam)  # the water's density at the ball's depth
    scene.add_particles(_outside(tank, body_shape), water, name="water")
    scene.add_particles(body_shape, M.Rigid(f"rigid_{rho:.0f}", density=rho), name="body")
    _substeps(scene, None)
    sim = scene.build()
    if dims == 3:
        sim.step(n=50)  # the water settles to its hydrostatic pressure
    state = sim.get_state()
    body = sim.handle("body").slice
    omega = np.array([0.0, 0.0, alpha * speed / radius])
    _set_rigid_motion(state, body, state.v[body].mean(axis=0) + np.array([speed, 0.0, 0.0]), omega)
    sim.set_state(state)
    x0, t0 = sim.positions("body").mean(axis=0), sim.time
    times, disp, vel, spin = [], [], [], []
    while sim.time - t0 < seconds - 1e-9:
        sim.step(n=every)
        x, v = sim.positions("body"), sim.velocities("body")
        c, vc = x.mean(axis=0), v.mean(axis=0)
        r = x - c
        times.append(sim.time - t0)
        disp.append(c - x0)
        vel.append(vc)
        spin.append(float(np.cross(r, v - vc)[:, 2].sum() / (r[:, :2] ** 2).sum()))
    return dict(dx=dx, substeps=scene.substeps, particles=sim.n_particles, omega=float(omega[2]),
                times=np.array(times), displacement=np.array(disp), velocity=np.array(vel), spin=np.array(spin))


def magnus_held(res: int = 32, alpha: float = 1.0, dims: int = 2, seconds: float = 0.26, speed: float = 0.2,
                radius: float | None = None, sound_speed: float = 4.0, average_from: float = 0.1,
                free_across: bool = False) -> dict:
    """A rigid body of water's density held at velocity `speed` (m/s) along x and spin ω = α·speed/radius (rad/s)
    about z, as a hand or a tool would hold it, through water at rest of `sound_speed` (m/s), `res` cells along
    the 0.16 m tank, no gravity. dims=2: a disc (radius 12 mm) through a slab two cells thick (0.16 × 0.12 m)
    full of water; dims=3: a ball (radius 15 mm) in a closed 0.16 × 0.10 × 0.12 m tank full of water. Both are
    centred 0.04 m from the x- wall, mid-width.

    Held: before every 2 ms step, the body's particles are given the rigid motion U + ω × r (and APIC's C = [ω]×),
    then run free through the step's substeps. The force of the water on the body over that step is
    F = M (v̄_end − v̄_start)/Δt (M the body's mass, v̄ its mean velocity): the impulse the hold must supply.
    Magnus: the lift F_y is along ω × U, +y for α > 0; none without spin; more with more spin. Reference for the
    disc, Kutta–Joukowski per unit span, inviscid, the fluid at the surface moving with it (Γ = 2π r² ω):
    L = ρ U Γ × (slab thickness). free_across: the y velocity is not reset, only U along x and the spin, so
    the body drifts across the stream under the lift (its displacement reported).

    The averages are over t ≥ `average_from` (s), two periods of the tank's sound (2 × 0.16 m / 4 m/s = 80 ms)
    with the defaults: the closed tank rings as the body displaces water, and the drag swings with it.
    Returns times (s), force (N, per step), lift and drag (N, means), kutta_joukowski (N, the disc's; nan for the
    ball), lift_coefficient L/(½ρU²A) with A the body's frontal area, displacement (m, per step)."""
    import fluidlab_core as fl
    from fluidlab_core import materials as M

    if dims not in (2, 3):
        raise ValueError(f"magnus_held: dims must be 2 (a disc in a slab) or 3 (a ball), got {dims!r}")
    width, height = 0.16, 0.12
    depth = 0.12 if dims == 2 else 0.10
    radius = radius or (0.012 if dims == 2 else 0.015)
    dx = width / res
    water = M.NewtonianLiquid(f"water_c{sound_speed:g}", density=1000.0, bulk_modulus=1000.0 * sound_speed ** 2)
    thick = 2 * dx if dims == 2 else height
    scene = fl.Scene(lower=(0, 0, 0), upper=(width, depth, thick), grid_res=res, dt=2e-3, substeps=1,
                     gravity=(0, 0, 0))
    s = scene.particle_spacing
    if dims == 2:
        body_shape = fl.Cylinder((0.04 + s / 2, depth / 2 + s / 2, dx), radius, thick)
        area = 2 * radius * thick
    else:
        body_shape = fl.Sphere((0.04 + s / 2, depth / 2 + s / 2, thick / 2 + s / 2), radius)
        area = math.pi * radius ** 2
    scene.add_particles(_outside(fl.Box((0, 0, 0), (width, depth, thick)), body_shape), water, name="water")
    scene.add_particles(body_shape, M.Rigid("rigid_1000", density=1000.0), name="body")
    _substeps(scene, None)
    sim = scene.build()
    body = sim.handle("body").slice
    mass = float(sim.masses("body").sum())
    omega = np.array([0.0, 0.0, alpha * speed / radius])
    state = sim.get_state()
    x0 = state.x[body].mean(axis=0)
    times, force, disp = [], [], []
    v_across = 0.0
    while sim.time < seconds - 1e-9:
        held = np.array([speed, v_across if free_across else 0.0, 0.0])
        _set_rigid_motion(state, body, held, omega)
        sim.set_state(state)
        sim.step()
        state = sim.get_state()  # the step's end, and the next step's start
        v_end = state.v[body].mean(axis=0)
        v_across = float(v_end[1])
        times.append(sim.time)
        force.append(mass * (v_end - held) / sim.dt)
        disp.append(state.x[body].mean(axis=0) - x0)
    times, force = np.array(times), np.array(force)
    late = times >= average_from - 1e-12
    lift, drag = float(force[late, 1].mean()), float(-force[late, 0].mean())
    kj = 1000.0 * speed * 2 * math.pi * radius ** 2 * omega[2] * thick if dims == 2 else math.nan
    return dict(dx=dx, substeps=scene.substeps, particles=sim.n_particles, mass=mass, omega=float(omega[2]),
                times=times, force=force, displacement=np.array(disp), lift=lift, drag=drag,
                kutta_joukowski=float(kj), lift_coefficient=lift / (0.5 * 1000.0 * speed ** 2 * area),
                drag_coefficient=drag / (0.5 * 1000.0 * speed ** 2 * area))


def sound_ring(res: int = 24, depth: float = 0.06, seconds: float = 0.4, liquid=None, hydrostatic: bool = False,
               flip: float = 0.0, jbar: bool = False) -> dict:
    """The column of `liquid` (default the catalogue's water), `depth` deep in a 12 cm slab tank, `res` cells
    across, released at rest (at J = 1, or with `hydrostatic` at its hydrostatic compression,
    Simulator.start_hydrostatic): the mean pressure of a one-cell layer of particles at mid-depth after every 1 ms
    step, and ring_figures of it. flip, jbar: the Scene's AFLIP share and J-bar."""
    import fluidlab_core as fl
    from fluidlab_core import materials as M

    liquid = liquid or M.WATER
    width = 0.12
    dx = width / res
    scene = fl.Scene(lower=(0, 0, 0), upper=(width, 2 * dx, width), grid_res=res, dt=1e-3, substeps=1, flip=flip,
                     jbar=jbar)
    scene.add_particles(fl.Box((0, 0, 0), (width, 2 * dx, depth)), liquid, name="water")
    _substeps(scene, None)
    sim = scene.build()
    if hydrostatic:
        sim.start_hydrostatic()
    x0 = sim.positions("water")
    middle = np.abs(x0[:, 2] - 0.5 * depth) < 0.5 * dx  # a layer at mid-depth
    times, pressures = [], []
    while sim.time < seconds - 1e-12:
        sim.step()
        times.append(sim.time)
        pressures.append(float(sim.pressures("water")[middle].mean()))
    times, pressures = np.array(times), np.array(pressures)
    hydro = liquid.density * G * (depth - x0[middle, 2].mean())
    period, swing, rate, mean = ring_figures(times, pressures, hydro)
    return dict(dx=dx, substeps=scene.substeps, times=times, pressures=pressures, hydro=hydro, period=period,
                first_swing=swing, decay_rate=rate, mean_over_hydro=mean,
                period_theory=4 * depth / math.sqrt(liquid.bulk_modulus / liquid.density))


def ring_figures(times, pressures, hydro):
    """(period s, amplitude of the first swing Pa, its decay rate 1/s, mean over the last half / hydrostatic)
    from the pressure's positive peaks above the hydrostatic value."""
    dev = pressures - hydro
    peaks = [i for i in range(1, len(dev) - 1) if dev[i] > dev[i - 1] and dev[i] >= dev[i + 1] and dev[i] > 0]
    period = float(np.median(np.diff(times[peaks]))) if len(peaks) > 2 else math.nan
    amp = np.abs(dev[peaks])
    rate = float(-np.polyfit(times[peaks], np.log(amp), 1)[0]) if len(peaks) > 2 else math.nan
    half = len(times) // 2
    return period, float(amp[0]) if len(amp) else math.nan, rate, float(pressures[half:].mean() / hydro)
