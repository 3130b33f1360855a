"""The liquid's pressure by projection, solved with a rigid body's motion (Scene(pressure="projection"),
engine/projection.py; issue 19): bodies at Archimedes' depth in 3-D, a heavy body on the floor, and what the option
refuses. CPU, float32, 16 cells across a 12 cm tank (the validation set-up of apps/validation.floating_cube_sim)."""
import json

import numpy as np
import pytest

import fluidlab_core as fl
from fluidlab_core import materials as M
from fluidlab_core.apps import validation
from fluidlab_core.shapes import Box
from tests.conftest import fresh, report

WIDTH, SIDE = 0.12, 0.04
# How far the cube's centre in a run from a restored state (Simulator.set_state) may part from the original's over
# 0.1 s (m). Measured from 2 s into the drop at 16 cells (2026-12-05, the position correction's band at 0.5 %):
# 1.6e-7 m on one thread and 9.7e-8 m on two (the solves' warm starts differ, within their tolerances); with the
# reset leaving the body's last push in place (a bug it must not have) 9.9e-7 m (band 2 %). Since the faces in the
# walls keep their velocity before the substep (2026-12-07, projection.py) the drop reads 4.77e-7 m on two threads
# and 1.06e-6 m with that bug: the bound moved from 4e-7 to 8e-7, between the two.
RESTORED_M = 8e-7


def _volume_share(sim):
    return validation.cube_volume_share(sim, WIDTH)[0]


def _dropped(density, seconds, every=0.05, on_floor=False):
    """A 4 cm rigid cube of `density` dropped from 1 cm onto 6 cm of water, or (on_floor) stood at rest on the
    floor under it (16 cells, 2 substeps of 1 ms, the projection): (times, volume shares, centre heights) every
    `every` seconds, and the simulator."""
    body = M.Rigid(f"rigid_{density:g}", density=density)
    drop, lift = (None, -(0.06 - SIDE * density / 1000.0)) if on_floor else (0.01, 0.0)
    sim, scene = validation.floating_cube_sim(16, body, M.WATER, drop=drop, lift=lift, width=WIDTH, side=SIDE,
                                              substep_factor=2, pressure="projection")
    assert scene.substeps == 2  # the flow's CFL sets the substep, not the liquid's or the body's sound speed
    n = int(round(every / scene.dt))
    times, shares, heights = [], [], []
    while sim.time < seconds - 1e-9:
        sim.step(n=n)
        times.append(sim.time)
        shares.append(_volume_share(sim))
        heights.append(float(sim.positions("cube")[:, 2].mean()))
    return np.array(times), np.array(shares), np.array(heights), sim


def test_light_cube_dropped_onto_water_floats_at_archimedes_depth():
    """Issue 19's test: a 4 cm rigid cube of 500 kg/m³ dropped from 1 cm onto 6 cm of water in a closed 12 cm tank
    (3-D, 16 cells across, float32 on the CPU) floats with the share ρ/ρ_w = 0.50 ± 0.03 of its volume under the
    surface that the liquid's volume fills the tank to, as the mean over its second second (after the landing's
    plunge and the first bobs: a real cube's landing second reads 0.49-0.54 by bench/heave_drop_model.py),
    within ± 0.05 here. Why not the issue's ± 0.03: the 10 s runs meet ± 0.03 in every second after the landing
    (0.476-0.520 at 16 cells), but two runs that differ only by the rounding of the grid sums (two threads here,
    one in the bench) part by up to 0.02 in a second's mean, since the half-density cube, unstable face-down,
    tips in its second second and sets the tank sloshing (docs/experiments/README.md, cc500.log against
    nc500.log; seconds 4-10 read 0.480-0.504 in one run and 0.515-0.520 in the other). The default coupling's
    0.40 is 0.10 off, so the bound still tells the two apart.

    The default coupling (pressure="state") fails this: 0.403 from 0.5 s to 1.5 s in the same set-up (measured
    2026-11-29), then sinking; its strict expected failure was this file's predecessor in
    tests/test_physics_solids.py. Measured here (2026-12-05, one thread): 0.528 in the first second and 0.480 in the
    second (the bench's, sampled every 0.1 s: 0.544, 0.480); 0.539 and 0.497 since the free surface's height comes
    from the B-spline's inverse (2026-12-08, projection.THETA_RULE: the linear rule put the surface 0.05 Δx high
    where the cube raises it). Over 10 s (bench/buoyancy_3d.py rigid std 10 --res 16 --drop 0.01 --substep-factor 2
    --pressure projection) the per-second means stay within ± 0.03 after the landing second (0.491-0.502 in each
    second from 1 s to 10 s, 2026-12-08; bench/results/buoyancy_3d.txt)."""
    times, shares, heights, sim = fresh(_dropped, 500.0, 2.0)
    window = times > 1.0 + 1e-9
    share = float(shares[window].mean())
    # a restored state runs on as the original did (the solve's warm starts and the body's last push are not in the
    # state: Simulator.set_state resets them, and the body's pose is primed again)
    state = sim.get_state()
    sim.step(n=50)
    first = sim.positions("cube").mean(axis=0)
    sim.set_state(state)
    sim.step(n=50)
    again = sim.positions("cube").mean(axis=0)
    report("projection, dropped cube", second_1=float(shares[times <= 1.0 + 1e-9].mean()), second_2=share,
           spread=float(np.ptp(shares[window])), expected=0.5, restored_m=float(np.abs(again - first).max()))
    assert abs(share - 0.5) < 0.05
    assert np.abs(again - first).max() < RESTORED_M


def test_heavy_cube_sinks_and_rests_on_the_floor():
    """A 4 cm rigid cube of 2000 kg/m³ dropped from 1 cm above 6 cm of water sinks to the floor and rests there,
    its centre at 20 mm (half its side) within a tenth of a cell at 0.2 s and 0.3 s: the walls' contact
    (engine/rigid.py) holds a body that carries no stress. Measured (2026-12-05): 49.23 mm at 0.1 s, then 19.94,
    19.95, 19.95, 19.95 mm to 0.5 s; without the contact it sat at 17.7 mm, 0.31 Δx into the floor. With the
    liquid's pressure under it (enclose_air, the next test): 49.46, 19.97, 19.97 mm to 0.3 s; with the contact
    moving the body by its change of velocity within the substep (2026-12-06): 49.46, 20.01, 20.00 mm."""
    times, shares, heights, _ = fresh(_dropped, 2000.0, 0.3, every=0.1)
    dx = WIDTH / 16
    report("projection, heavy cube", centre_mm=(heights * 1e3).round(2).tolist(), rest_mm=SIDE / 2 * 1e3)
    assert heights[0] < 0.06  # under the surface within 0.1 s
    assert np.all(np.abs(heights[1:] - SIDE / 2) < 0.1 * dx)


def test_heavy_cube_rests_on_a_static_shelf_and_a_paddle_pushes_it_without_entering_it():
    """A rigid body beside a static and a tool on the projection: a 4 cm cube of 2000 kg/m³ dropped into water over a
    static shelf (its top at 27.5 mm, between node rows; 16 cells across a 12 cm tank) sinks and rests on it, its
    centre at 47.5 mm within 0.05 Δx from 0.3 s on; then a paddle (a tool) moving at 0.1 m/s for 0.3 s slides it
    along the shelf (against the shelf's friction, 0.5 by default) without entering it: its particles stay at least
    half their spacing (the body's surface) less 0.1 Δx from the paddle's face, and the cube stays on the shelf.
    The contact of rigid.py against the statics' and the tools' SDFs holds it. Measured (2026-12-06): the centre
    47.65 mm at 0.3 s, then 47.50 mm throughout the push, which moves the cube 15 mm, its particles 1.82 mm from
    the paddle's face at the end (half their spacing: 1.875 mm). Without the contact (the walls' alone, as
    before): the cube sank into the shelf at 3.5 mm/s (47.43, 47.25, 47.08, 46.90, 46.72, 46.55 mm over 0.35-0.6 s)
    and the paddle's face entered it (its particles 1.65, 1.17, 0.64 mm from the face over the last 0.15 s)."""
    shelf, side, dx = 0.0275, 0.04, WIDTH / 16

    def run():
        scene = fl.Scene(lower=(0, 0, 0), upper=(WIDTH, WIDTH, 0.12), grid_res=16, dt=2e-3, substeps=1,
                         pressure="projection")
        scene.add_static(Box((0, 0, 0), (WIDTH, WIDTH, shelf)), name="shelf")
        scene.add_particles(Box((0, 0, shelf), (WIDTH, WIDTH, 0.06)), M.WATER, name="water")
        scene.add_particles(Box((0.05, 0.04, 0.065), (0.05 + side, 0.04 + side, 0.065 + side)),
                            M.Rigid("heavy", density=2000.0), name="cube")
        scene.add_tool(Box((-0.005, -0.03, -0.0225), (0.005, 0.03, 0.0225)), pose=(0.03, 0.06, 0.055, 0, 0, 0, 1),
                       name="paddle")
        scene.substeps = 2 * scene.stable_substeps()
        sim = scene.build()
        heights, gaps = [], []
        for k in range(12):  # 0.05 s each: 0.3 s still, then 0.3 s of the push
            sim.step(action=(0.1 if k >= 6 else 0.0, 0, 0, 0, 0, 0), n=25)
            x = sim.positions("cube")
            heights.append(float(x[:, 2].mean()))
            gaps.append(float(x[:, 0].min() - (sim.tool_pose("paddle")[0] + 0.005)))
        return np.array(heights), np.array(gaps), sim.positions("cube")[:, 0].mean(), scene.particle_spacing
    heights, gaps, x_end, spacing = fresh(run)
    rest = shelf + side / 2
    report("projection, cube on a shelf pushed by a paddle", centre_mm=(heights * 1e3).round(2).tolist(),
           rest_mm=rest * 1e3, gap_mm=(gaps[6:] * 1e3).round(2).tolist(), x_end_mm=x_end * 1e3)
    assert np.all(np.abs(heights[5:] - rest) < 0.05 * dx)
    assert x_end > 0.07 + 0.01  # pushed: its centre started at 70 mm
    assert gaps.min() > 0.5 * spacing - 0.1 * dx


@pytest.mark.parametrize("mu", [0.8, 0.3])
def test_a_block_on_a_static_slope_sticks_or_slides_as_coulomb_says(mu):
    """A 3 cm rigid block at rest on a static floor of friction μ under gravity tilted by 30° (an incline, g sin 30°
    along it): with μ = 0.8 > tan 30° = 0.577 it stays (under 0.05 mm in 0.2 s), with μ = 0.3 it slides at
    g (sin θ − μ cos θ) = 2.356 m/s² within 3 % (fitted to its first 20 mm; a pool of water, which the projection
    needs, waits downhill). rigid.py's contact: Coulomb friction in the Gauss–Seidel sweeps, and the body moved with
    the contact's change of velocity within the substep. Measured (2026-12-06): 0.00 mm and 2.357 m/s²; frictionless
    4.95 m/s² over its first 0.1 s (g sin θ = 4.905). Before: the contact was frictionless (both slid at g sin θ),
    and with friction but the position left where the substep's pre-contact velocity put it, the held block crept
    at g sin θ Δt = 4.9 mm/s (0.97 mm in 0.2 s)."""
    theta = np.radians(30.0)
    shelf, side = 0.0275, 0.03

    def run():
        g = (9.81 * np.sin(theta), 0.0, -9.81 * np.cos(theta))
        scene = fl.Scene(lower=(0, 0, 0), upper=(WIDTH, WIDTH, WIDTH), grid_res=16, dt=2e-3, substeps=1, gravity=g,
                         pressure="projection")
        scene.add_static(Box((0, 0, 0), (WIDTH, WIDTH, shelf)), friction=mu, name="slope")
        scene.add_particles(Box((0.105, 0, shelf), (WIDTH, WIDTH, shelf + 0.01)), M.WATER, name="water")
        scene.add_particles(Box((0.02, 0.045, shelf), (0.02 + side, 0.045 + side, shelf + side)),
                            M.Rigid("block", density=1000.0), name="block")
        scene.substeps = 2 * scene.stable_substeps()
        sim = scene.build()
        x0 = sim.positions("block").mean(axis=0)
        t, x = [0.0], [0.0]
        for _ in range(10):
            sim.step(n=10)
            t.append(sim.time)
            x.append(float(sim.positions("block")[:, 0].mean() - x0[0]))
        return np.array(t), np.array(x)
    t, x = fresh(run)
    expected = max(0.0, 9.81 * (np.sin(theta) - mu * np.cos(theta)))
    early = x < 0.02
    a = 2.0 * np.polyfit(t[early], x[early], 2)[0]
    report("projection, block on a slope", mu=mu, x_mm=(x * 1e3).round(2).tolist(), a=a, expected=expected)
    if expected == 0.0:
        assert np.abs(x).max() < 5e-5
    else:
        assert a == pytest.approx(expected, rel=0.03)


def test_light_cube_dropped_into_a_static_tank_floats_at_archimedes_depth():
    """A rigid body in water that a static holds: a 4 cm cube of 500 kg/m³ dropped from 1 cm onto 6 cm of water in
    a static open tank (12.5 cm inside, walls and floor 17.5 mm: its inner floor between node rows; 8 mm cells)
    floats with 0.50 ± 0.03 of its volume under the surface that the water's volume fills the tank to, as the mean
    over its second second. The faces the tank and the body share are open by what both leave (projection.py), and
    the body meets the tank through rigid.py's contact. Measured (2026-12-06; the same set-up run for
    6 s): 0.541 in the landing second, then 0.507, 0.508, 0.503, 0.509, 0.509, the cube drifting 3 cm towards a
    corner without reaching the walls; 0.539, 0.503 in its first two seconds with the free surface's height from the
    B-spline's inverse (2026-12-08). Before 2026-12-06 the projection refused a rigid body beside a static."""
    from fluidlab_core.shapes import Tank

    D, wall, side = 0.16, 0.0175, 0.04
    inner = D - 2 * wall

    def run():
        scene = fl.Scene(lower=(0, 0, 0), upper=(D, D, 0.15), grid_res=20, dt=2e-3, substeps=1, pressure="projection")
        scene.add_static(Tank((0, 0, 0), (D, D, 0.14), wall), name="tank")
        level = wall + 0.06
        scene.add_particles(Box((wall, wall, wall), (D - wall, D - wall, level)), M.WATER, name="water")
        c = D / 2
        scene.add_particles(Box((c - side / 2, c - side / 2, level + 0.01), (c + side / 2, c + side / 2, level + 0.05)),
                            M.Rigid("light", density=500.0), name="cube")
        scene.substeps = 2 * scene.stable_substeps()
        sim = scene.build()
        shares = []
        while sim.time < 2.0 - 1e-9:
            sim.step(n=50)
            x = sim.positions("cube") - np.array([0.0, 0.0, wall])  # heights over the tank's inner floor
            shares.append(validation.submerged_by_volume(float(sim.volumes("water").sum()), x, sim.volumes("cube"),
                                                         inner * inner)[0])
        escaped = int((np.abs(sim.positions("water")[:, :2] - c).max(axis=1) > inner / 2 + 1e-3).sum())
        return np.array(shares), escaped
    shares, escaped = fresh(run)
    second = float(shares[10:].mean())
    report("projection, cube in a static tank", second_1=float(shares[:10].mean()), second_2=second, expected=0.5,
           escaped=escaped)
    assert abs(second - 0.5) < 0.03
    assert escaped == 0


def test_light_cube_on_the_floor_lifts_off_and_rises_to_the_surface():
    """A 4 cm rigid cube of 500 kg/m³ stood at rest on the floor under 2 cm of water lifts off and rises to where
    it floats (its centre at 60 mm): by 0.4 s its centre has passed 50 mm. The liquid cannot reach the nodes under
    a body on the floor (its particles exclude the liquid), and while those nodes read as air at p = 0 the
    liquid's pressure never reached the cube's bottom and the pressure on its top held it down: its centre stayed
    at 20.0 mm over 1 s (2026-12-05). An air pocket that no path of air joins to the free surface and that the body
    borders is now liquid (LiquidProjection.enclose_air), its nodes without liquid mass keeping their velocity
    from the last solve. Measured (2026-12-05): 21.7, 34.0, 63.6, 70.4 mm at 0.1-0.4 s (2026-12-06, the contact moving the body by its change
    of velocity: 21.7, 34.1, 63.8, 70.3) (it overshoots, as a
    buoyant body rising 4 cm does, and bobs about 60 mm; bench/buoyancy_3d.py rigid std 10 --res 16 --raise -0.04
    --substep-factor 2 --pressure projection: 0.491-0.501 over seconds 1-10). With the pocket nodes taking the
    body's velocity each substep instead: 20.9, 25.4, 46.6, 71.8 mm here, and at 24 cells the cube rose 0.15 mm
    and settled back (docs/engine.md, "Floating bodies: the projection")."""
    times, shares, heights, _ = fresh(_dropped, 500.0, 0.4, every=0.1, on_floor=True)
    report("projection, cube on the floor", centre_mm=(heights * 1e3).round(1).tolist(), floats_at_mm=60.0)
    assert heights.max() > 0.05


def _scene(**kw):
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=8, pressure="projection", **kw)
    scene.add_particles(Box((0, 0, 0), (0.1, 0.1, 0.04)), M.WATER, name="water")
    return scene


def _cube(scene, name="cube", lo=(0.03, 0.03, 0.05), side=0.03, density=500.0):
    scene.add_particles(Box(lo, tuple(v + side for v in lo)), M.Rigid(f"r_{name}", density=density), name=name)
    return scene


def test_projection_refuses_what_it_does_not_handle_by_name():
    """Each unsupported part is named in the error that build() raises (before any kernel is compiled)."""
    with pytest.raises(ValueError, match="pressure must be 'state'"):
        fl.Scene(pressure="incompressible")
    scene = _scene()
    scene.add_particles(Box((0.03, 0.03, 0.05), (0.06, 0.06, 0.08)), M.Rigid("r", density=500.0), name="cube")
    with pytest.raises(ValueError, match="gradients"):
        scene.build(requires_grad=True)
    scene.add_particles(Box((0.07, 0.07, 0.05), (0.09, 0.09, 0.07)), M.Elastic("jelly", density=500.0,
                                                                                shear_modulus=1e4, lame_lambda=1e4),
                        name="jelly")
    with pytest.raises(ValueError, match=r"deformable solids \(jelly\) beside a rigid body"):
        scene.build()
    scene = _scene(jbar=True)
    scene.add_particles(Box((0.03, 0.03, 0.05), (0.06, 0.06, 0.08)), M.Rigid("r", density=500.0), name="cube")
    with pytest.raises(ValueError, match="jbar"):
        scene.build()
    with pytest.raises(ValueError, match="pressure must be 'state' or 'projection'"):
        from fluidlab_core import tasks
        tasks.make("GatheringEasy", pressure="incompressible")
    with pytest.raises(ValueError, match=r"2 rigid bodies \(a, b\)"):
        _cube(_cube(_scene(), "a"), "b", lo=(0.065, 0.065, 0.05)).build()
    with pytest.raises(ValueError, match="a scene without liquid"):
        scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=8, pressure="projection")
        _cube(scene).build()


def test_elastic_foam_dropped_onto_water_floats_at_archimedes_depth():
    """The Gathering tasks' floating foam (elastic, 400 kg/m³, E = 4.75 kPa) as a 4 cm cube dropped from 1 cm onto
    6 cm of water (16 cells, 12 cm tank) floats with 0.40 ± 0.05 of its volume under the surface over its second
    second. The foam keeps its own velocity field and stress, its nodes' velocities unknowns of the pressure solve
    (engine/projection.py, "Deformable solids"). Taken into the liquid's field as a mixture it stood on the water
    (a 500 kg/m³ cube's share 0.00-0.07 over its first second); with each face's solids' share the mean of its
    nodes' (the B-spline's smeared volume) it floated 0.07 high (a 500 kg/m³ cube: 0.426, 0.423, 0.429 over 3 s);
    with the share sharpened (clamp(½ + (s̄ − ½)·4/3)), 0.474, 0.473, 0.477 for that cube and 0.361, 0.365, 0.396
    for this foam in their first three seconds (bench/results/buoyancy_3d.txt; 2026-12-05; 0.382, 0.390 here in a
    run of this test); with each face's share of its box that the foam's particles cover (2026-12-07, the next
    test), 0.403 and 0.390 here. ± 0.05 as for the rigid cube: it runs part by 0.01-0.02 in a second's mean (another bench run of
    the foam: 0.363, 0.374). Since AFLIP stopped pushing the water beside the foam (2026-12-07, the still-water
    test below) the foam heaves freely, ± 0.21 in its second second, damping (0.409 here, spread 0.49; before:
    0.407, spread 0.19, the stirred water holding it). The default coupling (pressure="state") floats this foam, in the tasks' softer water, at
    0.51, then 0.56-0.61 (it sinks: README, floating bodies). With the free surface's height from the B-spline's
    inverse (2026-12-08, projection.THETA_RULE): 0.416 and 0.391 here, 0.392-0.402 in each second from 1 s to 10 s
    in the bench (0.380-0.395 with the linear rule)."""
    from fluidlab_core.tasks import common

    def run():
        sim, scene = validation.floating_cube_sim(16, common.FLOAT_FOAM, M.WATER, drop=0.01, width=WIDTH, side=SIDE,
                                                  pressure="projection")
        n = int(round(0.05 / scene.dt))
        times, shares = [], []
        while sim.time < 2.0 - 1e-9:
            sim.step(n=n)
            times.append(sim.time)
            shares.append(_volume_share(sim))
        return np.array(times), np.array(shares), scene.substeps
    times, shares, substeps = fresh(run)
    second = (times > 1.0 + 1e-9) & (times <= 2.0 + 1e-9)
    share = float(shares[second].mean())
    report("projection, elastic foam", substeps=substeps, second_1=float(shares[times <= 1.0 + 1e-9].mean()),
           second_2=share, spread=float(np.ptp(shares[second])), expected=0.40)
    assert share == pytest.approx(0.40, abs=0.05)


BRINE = M.NewtonianLiquid("brine", density=1200.0, bulk_modulus=2e6)


def _pressure_column(sim, xy=None):
    """(heights m, pressures Pa) of the solve's unknowns in the column of nodes nearest xy (m; default the domain's
    central column)."""
    proj, model = sim.solver.proj, sim.solver.model
    kind, p = proj.kind.to_numpy(), proj.p.to_numpy()
    i, j = model.grid_shape[0] // 2, model.grid_shape[1] // 2
    if xy is not None:
        i, j = (int(round((xy[k] - model.origin[k]) / model.dx)) for k in range(2))
    rows = np.nonzero(kind[i, j, :] == 1)[0]  # LIQ
    return model.origin[2] + rows * model.dx, p[i, j, rows]


def test_layered_liquids_without_a_body_rest_at_their_hydrostatic_pressure():
    """Brine (1200 kg/m³) under water, 4 cm each in a 12 cm tank at 16 cells, no body: the projection's density is
    each node's mass over its liquids' volume, so the pressure rises by ρ g per metre in each layer (1200 g and
    1000 g, within 3 %) and they stay layered (no brine particle more than two cells above the interface after
    0.2 s). A projection with one density for the whole liquid (what it took before 2026-12-05) reads 1000 g in
    the brine. Measured (2026-12-05): 1200 g and 998 g. Not asserted: the still liquid was not quite still under
    the projection, with or without the second liquid (rms speed 0.013-0.016 m/s after 0.2 s, 0.007-0.009 with
    APIC instead of AFLIP), until the walls' faces stopped pushing it down (2026-12-07; the still pool's test
    below)."""
    def run():
        scene = fl.Scene(lower=(0, 0, 0), upper=(0.12, 0.12, 0.12), grid_res=16, dt=2e-3, substeps=1,
                         pressure="projection")
        scene.add_particles(Box((0, 0, 0), (0.12, 0.12, 0.04)), BRINE, name="brine")
        scene.add_particles(Box((0, 0, 0.04), (0.12, 0.12, 0.08)), M.WATER, name="water")
        sim = scene.build()
        sim.step(n=100)
        return sim
    sim = fresh(run)
    z, p = _pressure_column(sim)
    dx = sim.solver.model.dx
    g = 9.81
    brine = (z > 1.5 * dx) & (z < 0.04 - 1.5 * dx)  # nodes whose stencils hold one liquid only
    water = (z > 0.04 + 1.5 * dx) & (z < 0.08 - 1.5 * dx)
    slope_brine = -np.polyfit(z[brine], p[brine], 1)[0] / g
    slope_water = -np.polyfit(z[water], p[water], 1)[0] / g
    highest_brine = float(sim.positions("brine")[:, 2].max())
    report("projection, layered liquids", slope_brine=slope_brine, slope_water=slope_water,
           highest_brine_mm=highest_brine * 1e3, nodes=(int(brine.sum()), int(water.sum())))
    assert brine.sum() >= 2 and water.sum() >= 2
    assert slope_brine == pytest.approx(1200.0, rel=0.03)
    assert slope_water == pytest.approx(1000.0, rel=0.03)
    assert highest_brine < 0.04 + 2 * dx


def test_a_still_pool_stays_still_beside_the_walls_and_its_pressure_is_zero_at_its_surface():
    """6 cm and a quarter cell of water in a closed 12 cm box at 16 cells, the Scene's AFLIP 0.99 on the projection,
    left alone for 1 s: its particles' rms speed is under 0.005 m/s, and under 0.005 within the last 1.5 cells of
    the side walls. It read 0.033 m/s (0.052 beside the walls) until 2026-12-07 (this test then, at 6 cm: 0.0333 and
    0.0507): the faces inside the walls, outside the solve, took the nodes' mean velocity, which carried gravity that
    no pressure balances, and AFLIP gave the liquid beside the walls that push every substep (projection.py, the face
    velocities; docs/engine.md). Measured with the fix: 0.00047 and 0.00060 m/s at 6 cm
    (bench/still_pool_projection.py: 0.0005 m/s at 1 s, 0.0001 at 2 s).

    And the pressure's zero, extrapolated from its linear fit in the interior columns, lies where the water's volume
    fills the box, within 0.02 Δx: the surface a quarter cell above a node row is where the linear θ = (φ_I − ½)/(φ_I
    − φ_J) put it 0.059 Δx high, and θ from the B-spline's inverse (projection.THETA_RULE) 0.0075 Δx
    (bench/free_surface_level.py, 2026-12-08; over a quarter cell's phases 0.005-0.011 against -0.047 to +0.059)."""
    dx = 0.12 / 16
    level = 0.06 + 0.25 * dx

    def run():
        scene = fl.Scene(lower=(0, 0, 0), upper=(0.12, 0.12, 0.12), grid_res=16, dt=2e-3, substeps=1,
                         pressure="projection")
        scene.add_particles(Box((0, 0, 0), (0.12, 0.12, level)), M.WATER, name="water")
        sim = scene.build()
        sim.step(n=500)
        return sim
    sim = fresh(run)
    assert sim.solver.model.flip == 0.99  # the Scene's default on the projection (AFLIP)
    x, v = sim.positions("water"), sim.velocities("water")
    beside = np.abs(x[:, :2] - 0.06).max(axis=1) > 0.06 - 1.5 * sim.solver.model.dx
    rms = float(np.sqrt((v ** 2).sum(axis=1).mean()))
    rms_beside = float(np.sqrt((v[beside] ** 2).sum(axis=1).mean()))
    pad = int(round(-sim.solver.model.origin[0] / dx))  # the interior columns: not the walls' nor those next to them
    interior = [(pad + i, pad + j) for i in range(2, 15) for j in range(2, 15)]
    level_now = float(sim.volumes("water").sum()) / 0.12 ** 2
    gap = (validation.pressure_zero(sim, interior) - level_now) / dx
    report("projection, still pool", rms=rms, rms_beside_walls=rms_beside, particles_beside=int(beside.sum()),
           pressure_zero_over_volume_level_cells=gap)
    assert beside.sum() > 1000
    assert rms < 0.005 and rms_beside < 0.005
    assert abs(gap) < 0.02


def test_a_floating_elastic_body_stays_at_archimedes_depth_and_leaves_the_still_water_around_it_still():
    """The Gathering tasks' foam (elastic, 400 kg/m³) as a 4 cm cube started at Archimedes' depth in 6 cm of still
    water (16 cells, 12 cm box), the Scene's AFLIP 0.99 on the projection: over its first 0.25 s the share of its
    volume under the surface stays within 0.01 of 0.40, and over its first 0.375 s the water's rms speed stays
    under 0.02 m/s and no particle reaches 0.2 m/s.

    The share: each face's solids' share σ is the share of its box that the foam's particles cover
    (projection.py, soft_faces). Measured (2026-12-07, every 0.025 s): 0.398-0.401 throughout on two threads; on
    one, 0.399-0.402 to 0.275 s, then 0.405, 0.408, 0.411, 0.415 as the cube starts to roll (a cube of density
    ratio 0.4 is unstable upright, docs/engine.md; when it starts depends on the sums' rounding). With
    σ from the mean of its two nodes' B-spline volume shares (until 2026-12-07), which read the faces under the
    body's edges as open, the pressure's force fell short and the foam sank from Archimedes' depth: 0.402, 0.406,
    0.415, 0.428, 0.434, 0.436 over its first 0.15 s (and an 800 kg/m³ elastic cube to 0.845 for 0.80). The
    water's rms speed now reads 0.012, 0.009, 0.008 m/s (before: 0.006, 0.008, 0.010, the foam bobbing instead).

    The water: until 2026-12-07 a face the foam shares took, for
    AFLIP's "before the substep", the foam's velocity v* − Δt g after its stress: a body at rest holds Δt f/m there
    against the pressure, and AFLIP gave the water beside it that push every substep (projection.py, the face
    velocities; docs/engine.md). Measured then: rms 0.031, 0.050, 0.072 m/s at 0.125, 0.25, 0.375 s, fastest 0.41,
    0.60, 0.98 m/s; with the foam's transfer velocity without its stress: 0.0059, 0.0081, 0.0095, fastest 0.027,
    0.042, 0.069 (the foam's own bob, ± 0.015 m/s, is the same in both)."""
    from fluidlab_core.tasks import common

    def run():
        sim, scene = validation.floating_cube_sim(16, common.FLOAT_FOAM, M.WATER, drop=None, width=WIDTH, side=SIDE,
                                                  pressure="projection")
        names = [n for n in sim.handles if n != "cube"]
        shares, rms, fastest = [], [], []
        for k in range(15):  # 0.025 s each
            sim.step(n=int(round(0.025 / scene.dt)))
            shares.append(_volume_share(sim))
            if k % 5 == 4:
                speed = np.linalg.norm(np.concatenate([sim.velocities(n) for n in names]), axis=1)
                rms.append(float(np.sqrt((speed ** 2).mean())))
                fastest.append(float(speed.max()))
        return sim.solver.model.flip, np.array(shares), rms, fastest
    flip, shares, rms, fastest = fresh(run)
    report("projection, still water round a floating foam", shares=shares.round(3).tolist(), rms=rms,
           fastest=fastest)
    assert flip == 0.99
    assert np.abs(shares[:10] - 0.40).max() < 0.01
    assert max(rms) < 0.02 and max(fastest) < 0.2


def test_a_closed_box_full_of_liquid_stays_at_rest():
    """Water filling a closed 10 cm box (no air anywhere) at 8 cells stays where it is: with no air node both
    solves are pure Neumann problems, singular and by rounding inconsistent, and the liquid was thrown across the
    box within two steps (a Rayleigh-Taylor slab); the highest liquid node is now pinned to p = 0 (projection.py,
    _pin_node). After 0.1 s no particle has moved by a tenth of a cell (measured 2026-12-05: 0.66 mm of 12.5) and
    none moves at 5 cm/s (the fastest: 1.35 cm/s, rms 0.24 cm/s, measured before the walls' faces stopped pushing
    the liquid beside them down, 2026-12-07: the still pool's test above)."""
    def run():
        scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=8, pressure="projection")
        scene.add_particles(Box((0, 0, 0), (0.1, 0.1, 0.1)), M.WATER, name="water")
        sim = scene.build()
        x0 = sim.positions("water")
        sim.step(n=50)
        return sim, x0
    sim, x0 = fresh(run)
    moved = float(np.abs(sim.positions("water") - x0).max())
    speed = float(np.abs(sim.velocities("water")).max())
    report("projection, full box", moved_mm=moved * 1e3, max_speed=speed)
    assert speed < 0.05
    assert moved < 0.1 * sim.solver.model.dx


def test_a_jet_into_water_on_the_projection_adds_its_volume_to_the_layer():
    """A nozzle (radius 8 mm, 5e-5 m³/s for 0.3 s) pours water from 6 cm onto a 2 cm layer in a closed 10 cm box at
    16 cells with pressure="projection": the emitted mass is Q ρ t to within a row, and 0.3 s after the jet stops
    the layer is as deep as the water's volume over the box's floor, 20 mm + Q t / A = 21.47 mm, measured as twice
    its particles' mean height: within 1 % (measured 2026-12-05: 21.60 mm; the layer alone, without the jet, 20.13
    mm over the same time: the position correction's loosening). The default liquid reads 22.34 mm (20.0 alone): the
    jet's particles, scrambled where they land, fill more room than their J says. No particle leaves the box."""
    rate, seconds, area = 5e-5, 0.3, 0.1 * 0.1

    def run():
        scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=16, dt=2e-3, substeps=1,
                         pressure="projection")
        scene.add_particles(Box((0, 0, 0), (0.1, 0.1, 0.02)), M.WATER, name="layer")
        scene.add_emitter(M.WATER, rate=rate, nozzle="disc", size=0.008, pose=(0.05, 0.05, 0.06, 1.0, 0.0, 0.0, 0.0),
                          duration=seconds, name="jet")
        scene.substeps = scene.stable_substeps()
        sim = scene.build()
        sim.step(n=300)
        return sim
    sim = fresh(run)
    spec = sim.emitter_specs[0]
    mass = sim.masses("jet").sum()
    assert abs(mass - rate * M.WATER.density * seconds) <= spec.row_volume * M.WATER.density
    x = sim.positions()
    depth = 2.0 * x[:, 2].mean()
    expected = 0.02 + mass / M.WATER.density / area
    report("jet into water, projection", depth_mm=depth * 1e3, expected_mm=expected * 1e3,
           fastest=float(np.abs(sim.velocities()).max()))
    assert depth == pytest.approx(expected, rel=0.01)
    assert np.all((x >= 0.0) & (x <= 0.1))


def test_gas_blows_over_a_projected_pool_and_drags_a_foam_blob_above_it():
    """Gas beside the projected liquid (engine/gas_coupling.py; the coupling acts on the particles' state between
    the particle step and the gas step, whichever pressure the liquid has). A 3 cm pool of water over the whole
    floor of a 20 × 10 × 15 cm box (1 cm cells, gravity on), a wind of 0.5 m/s blowing in through the x− wall and
    out through x+, and a 2 cm blob of foam (500 kg/m³) 6 cm above the water that the gas drags (k = 20 /s).
    After 0.06 s: the pool's cells are solid for the gas, three rows everywhere; the gas is divergence-free beside
    them; the foam's mean x velocity is the wind's U (1 − exp(−k t)) = 0.349 m/s within 5 % (measured 0.342, 2 %
    under; test_gas.py's coupling scene, without gravity, reads 0.3 % under at 0.2 s on either liquid); and the pool stays at
    rest, its mean speed under 3 cm/s (measured 1.5 cm/s: the initial packing settling, its top 1 mm lower; with
    the liquid standing along the wrong axis, a dam break, the same reads 0.42 m/s)."""
    U, k, t = 0.5, 20.0, 0.06
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.2, 0.1, 0.15), grid_res=20, dt=4e-3, pressure="projection")
    scene.add_gas(resolution=20, walls={"x-": (U, 0.0, 0.0), "x+": "open"}, particles_block=True,
                  particle_drag=k, drag_bodies=["foam"])
    pool = scene.add_particles(Box((0.0, 0.0, 0.0), (0.2, 0.1, 0.03)), M.WATER, name="pool")
    foam = scene.add_particles(Box((0.03, 0.04, 0.09), (0.05, 0.06, 0.11)), M.MILK_FOAM, name="foam")
    scene.substeps = scene.stable_substeps()
    sim = scene.build()
    sim.step(n=int(round(t / scene.dt)))
    solid = sim.gas.solid.to_numpy() != 0
    ux, uy, uz = sim.gas_state().velocity
    div = (ux[1:] - ux[:-1]) + (uy[:, 1:] - uy[:, :-1]) + (uz[:, :, 1:] - uz[:, :, :-1])
    div = np.where(solid, 0.0, div)
    rows = solid.sum(axis=2)  # solid cells per (x, y) column: the pool's
    foam_vx = float(sim.velocities(foam)[:, 0].mean())
    expected = U * (1.0 - np.exp(-k * t))
    speed = float(np.linalg.norm(sim.velocities(pool), axis=1).mean())
    report("gas over a projected pool", pool_rows=sorted(set(rows.ravel().tolist())), max_divergence=float(
        np.abs(div).max()), foam_vx=foam_vx, expected=expected, pool_mean_speed=speed)
    assert rows.min() == 3 and rows.max() == 3
    assert np.abs(div).max() < 1e-3 * U
    assert abs(foam_vx / expected - 1.0) < 0.05
    assert speed < 0.03


def test_gathering_tank_on_the_projection_floats_its_foam_and_the_paddle_pushes_the_water():
    """GatheringEasy (small: 8 mm cells, a static tank with 16 mm walls, two 24 mm foam cubes, the paddle) with
    pressure="projection": the statics and the tool close the solve's faces by their share of each face (the tool's
    flux on the right-hand side), and their nodes' stencil shares come from a quadrature of their SDF. Checked:
    - the paddle held still for 1 s: the foam (400 kg/m³) floats with 0.40 ± 0.03 of its volume under the water's
      surface over 0.2-1 s (Archimedes 0.40; the default liquid sinks it to 0.94, bench/gathering_projection.py).
      The surface is the height at which the water's volume, the foam's part below it and the paddle's fill the
      tank (validation.gathering_submerged_shares). Measured 2026-12-08: 0.392, since the free surface's height
      between nodes comes from the B-spline's inverse (projection.THETA_RULE; 0.381 with the linear rule, 2026-12-07,
      the surface raised 0.05 Δx there). Since 2026-12-07 each face's share inside the
      foam is the share of its box that the foam's particles cover (projection.py, soft_faces); before, from its
      nodes' B-spline volume shares, 0.464 (1.5 mm, 0.18 of an 8 mm cell, deeper than Archimedes; 0.43 at the
      medium size), which this bound fails. Until 2026-12-07 this also counted the particles below the fill height
      WATER_DEPTH over the floor, in six 4 mm layers: 0.38-0.39, because the water that started inside the paddle
      raised the level by 1.1 mm and hid the offset.
      With the projection the cubes also roll about y (26° in 1.25 s): a floating cube whose density ratio s
      has s(1 − s) > 1/6 is unstable upright (its metacentre lies under its centre of mass), which the volume
      share does not depend on. The water stays still but for the roll (rms particle speed under 0.02 m/s at 1 s:
      with the Scene's AFLIP 0.99 on the projection it was 0.077 and the fastest particles 0.54 m/s, Task.scene; the
      tasks' APIC read 0.001-0.003 while the cubes rolled slowly, and the bound was 0.01). Why 0.02: the cubes roll
      to about 50° within the first second and rock back to 41°, and the water round them moves with them: 0.0055
      m/s at 1 s (2026-12-07, 54°) and 0.0116 (2026-12-08, 52°; this test and bench/gathering_projection.py
      --float-seconds 3), then 0.0003-0.0004 at 2 and 3 s, when the cubes have settled. And it stays in the tank (no particle a millimetre inside its walls), and its pressure rises by
      ρ g (± 3 %) down a column of open water;
    - the paddle pushed 12.5 mm towards the objects at 0.15 m/s: no water inside it (a millimetre deep) and the
      water moves with it (its mean x velocity positive).
    Before the quadrature, statics.bspline_cdf's share from φ alone counted ½ at the tank's inner corners, where ⅞ is
    wall: the corners' liquid read as air, and the water drained through the walls within 0.3 s; a stray particle's
    mass in a wall then made a node an unknown with faces open by hundredths, whose position correction threw the
    liquid 14 m in a substep (engine/projection.py, classify)."""
    from fluidlab_core import tasks
    from fluidlab_core.tasks import gathering as G

    def run():
        task = tasks.make("GatheringEasy", "small", pressure="projection")
        with pytest.raises(ValueError, match="gradients"):
            task.simulator(grad=True)
        sim = task.simulator()
        task.reset(sim)
        level = G.TANK_WALL + G.WATER_DEPTH
        objects = ("object_a", "object_b")
        shares, layers = [], []
        for k in range(200):
            sim.step(action=np.zeros(6))
            if sim.time > 0.2 - 1e-9:
                shares.append(validation.gathering_submerged_shares(sim, objects, paddle=task.tool_name))
                layers.append([(sim.positions(b)[:, 2] < level).mean() for b in objects])
        speed = np.linalg.norm(sim.velocities("water"), axis=1)
        rms = float(np.sqrt((speed ** 2).mean()))
        tank = G.S.Tank(G.TANK_LOWER, G.TANK_UPPER, G.TANK_WALL)
        in_walls = int((tank._hollow().sdf(sim.positions("water")) > 1e-3).sum())
        z, p = _pressure_column(sim, (0.54, 0.0))
        slope = -np.polyfit(z, p, 1)[0] / 9.81 if len(z) >= 2 else float("nan")
        n = int(round(0.0125 / 0.15 / task.dt))
        sim.step(action=(0.15, 0, 0, 0, 0, 0), n=n)
        pose = sim.tool_pose("paddle")
        w = sim.positions("water")
        local = w - pose[:3]  # the paddle is not rotated
        tx, ty, tz = G.PADDLE_SIZE
        inside = int(np.sum((np.abs(local[:, 0]) < 0.5 * tx - 1e-3) & (np.abs(local[:, 1]) < 0.5 * ty - 1e-3)
                            & (local[:, 2] > 1e-3) & (local[:, 2] < tz - 1e-3)))
        vx = float(sim.velocities("water")[:, 0].mean())
        return np.array(shares), np.array(layers), rms, in_walls, slope, len(z), inside, vx, pose
    shares, layers, rms, in_walls, slope, rows, inside, vx, pose = fresh(run)
    share = float(shares.mean())
    report("projection, Gathering tank", share=share, shares=shares.mean(axis=0).round(3).tolist(), expected=0.40,
           layer_count=layers.mean(axis=0).round(3).tolist(),
           still_rms=rms, in_walls=in_walls, slope_rho=slope, rows=rows, paddle_x=float(pose[0]), water_in_paddle=inside,
           water_vx=vx)
    assert abs(share - 0.40) < 0.03
    assert rms < 0.02
    assert in_walls == 0
    assert rows >= 2 and slope == pytest.approx(1000.0, rel=0.03)
    assert pose[0] > 0.47
    assert inside == 0
    assert vx > 0.0


def test_a_trajectory_found_on_the_projection_records_it_and_replays_on_it():
    """A task made with pressure="projection" writes it into the trajectories it makes (metadata.pressure), and the
    task a trajectory is replayed on (episode.task_for, `fluidlab evaluate`) takes it from there; trajectories of
    the default liquid carry no such key (the shipped ones were written before it existed). No simulation."""
    from fluidlab_core import tasks
    from fluidlab_core.episode import task_for
    from fluidlab_core.trajectory import Trajectory

    task = tasks.make("GatheringEasy", "small", pressure="projection")
    written = task.trajectory(np.zeros((task.horizon, task.n_actions)))
    traj = Trajectory.loads(json.dumps(written.to_dict()))  # through its document, as a file would
    assert traj.metadata["pressure"] == "projection"
    assert task_for(traj).pressure == "projection"
    assert task_for(traj, pressure="state").pressure == "state"
    plain = tasks.make("GatheringEasy", "small").trajectory(np.zeros((task.horizon, task.n_actions)))
    assert "pressure" not in plain.metadata and task_for(plain).pressure == "state"


@pytest.mark.parametrize("body", ["rigid", "elastic"])
def test_the_serial_and_the_parallel_cg_give_the_same_flow(body):
    """The pressure solve's two paths (projection.py, serial_cg): one serial launch for the whole CG (the CPU's) and
    one parallel launch an iteration (a GPU's) do the same arithmetic, the parallel path's sums in a fixed order of
    chunks. A 500 kg/m³ cube, rigid (the body's rank-6 term) or elastic (the solids' nodes as unknowns), dropped onto
    water at 12 cells for 40 steps (0.08 s): the same CG iterations in every substep to within one, and every
    particle within 1e-5 m of the other path's (measured 2026-12-06: the same bits on both paths, 681 and 2612
    iterations). It caught the serial path's first form, which read the body's sums back from a field inside its
    loop: right at Taichi's opt_level 1, 400 iterations a substep at the suite's opt_level 0 (projection.py,
    _bx_of_serial).

    The GPU's preconditioner, the diagonal (Jacobi: MIC(0)'s sweeps are serial, and its unknowns listed by columns in
    parallel), on the parallel path: the same flow to the solves' tolerances (the pressure's 1e-7, the position
    correction's 1e-3), in 2-5x MIC(0)'s iterations. Measured 2026-12-06 (the suite's opt_level 0): 2231 and 8013
    iterations against 681 and 2614 (3.3x, 3.1x); the particles' median distance from the MIC(0) run's 1.9e-6 m
    (rigid) and 3.3e-6 m (elastic; 6.4e-5 m at opt_level 1), a few surface particles' up to 0.7 and 1.3 mm (a
    tenth of a cell: the position correction's tolerance, 1e-3), the cube's centre 1.2e-5 and 1.9e-6 m apart."""
    material = (M.Rigid("rigid_500", density=500.0) if body == "rigid"
                else M.Elastic("elastic_500", density=500.0, shear_modulus=5e3, lame_lambda=1e4))

    def run(serial, preconditioner="mic"):
        sim, scene = validation.floating_cube_sim(12, material, M.WATER, drop=0.01, width=WIDTH, side=SIDE,
                                                  pressure="projection")
        proj = sim.solver.proj
        proj.serial_cg = serial
        proj.preconditioner = preconditioner
        sim.step(n=40)
        return (np.r_[sim.positions("water"), sim.positions("cube")], sim.positions("cube").mean(axis=0),
                list(proj.iterations), list(proj.correction_iterations))
    x_s, c_s, it_s, pc_s = fresh(lambda: run(True))
    x_p, c_p, it_p, pc_p = fresh(lambda: run(False))
    x_j, c_j, it_j, pc_j = fresh(lambda: run(False, "jacobi"))
    moved = float(np.abs(x_s - x_p).max())
    apart = np.linalg.norm(x_s - x_j, axis=1)
    report(f"projection, serial and parallel CG ({body})", max_position_difference=moved,
           iterations=(sum(it_s), sum(it_p)), correction_iterations=(sum(pc_s), sum(pc_p)),
           jacobi_iterations=sum(it_j), jacobi_median_distance=float(np.median(apart)),
           jacobi_centre_distance=float(np.linalg.norm(c_s - c_j)))
    assert len(it_s) == len(it_p) and max(abs(a - b) for a, b in zip(it_s, it_p)) <= 1
    assert max(abs(a - b) for a, b in zip(pc_s, pc_p)) <= 1
    assert sum(it_s) > 0 and moved < 1e-5
    assert 2 * sum(it_s) < sum(it_j) < 5 * sum(it_s) and max(it_j) < 400  # (MIC(0)'s cap; Jacobi's is higher)
    assert np.median(apart) < 2e-4 and np.linalg.norm(c_s - c_j) < 1e-4
