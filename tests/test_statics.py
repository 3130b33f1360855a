"""Static colliders: Coulomb friction against the analytic result, sticky contact, and mesh statics and
mesh-shaped bodies built with trimesh."""
import numpy as np
import pytest
import trimesh

import fluidlab_core as fl
from fluidlab_core import materials as M
from tests.conftest import report

G = 9.81


def _sliding_block(friction, sticky=False, v0=0.5, duration=0.3):
    """An elastic block sliding along +x at v0 on a static slab; returns times and mean x velocity."""
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.3, 0.06, 0.08), grid_res=48, dt=1e-3, substeps=12)
    dx = scene.dx
    scene.add_static(fl.Box((-0.1, -0.1, -0.1), (0.4, 0.2, 0.02)), friction=friction, sticky=sticky, name="slab")
    scene.add_particles(fl.Box((0.03, 0.01, 0.02 + 0.5 * dx), (0.07, 0.05, 0.06 + 0.5 * dx)), M.ELASTIC,
                        name="block", velocity=(v0, 0.0, 0.0))
    sim = scene.build()
    x0 = sim.positions("block")
    bottom = x0[:, 2] < x0[:, 2].min() + 0.5 * dx  # the particle layer touching the slab
    times, speeds = [], []
    while sim.time < duration:
        sim.step(n=5)
        times.append(sim.time)
        speeds.append(float(sim.velocities("block")[:, 0].mean()))
    x = sim.positions("block")
    return np.array(times), np.array(speeds), (x[:, 0] - x0[:, 0]).mean(), (x[bottom, 0] - x0[bottom, 0]).mean()


def test_coulomb_friction_stops_a_sliding_block_at_mu_g():
    """A block sliding at 0.5 m/s on a slab with friction μ = 0.3 decelerates at μg = 2.94 m/s² (Coulomb) and
    stops after v0²/(2μg) = 4.2 cm; frictionless, it keeps its speed; on a sticky slab its bottom layer stops
    at once (the elastic block above it rocks)."""
    mu, v0 = 0.3, 0.5
    t, v, travel, _ = _sliding_block(mu, v0=v0)
    moving = (v > 0.1 * v0) & (v < 0.9 * v0)
    decel = -np.polyfit(t[moving], v[moving], 1)[0]
    t_free, v_free, _, _ = _sliding_block(0.0, v0=v0)
    _, _, _, travel_stick = _sliding_block(0.5, sticky=True, v0=v0, duration=0.05)
    report("friction", deceleration=decel, mu_g=mu * G, travel_m=travel, coulomb_travel_m=v0 ** 2 / (2 * mu * G),
           frictionless_final_speed=v_free[-1], sticky_bottom_travel_m=travel_stick)
    assert decel == pytest.approx(mu * G, rel=0.2)
    assert travel == pytest.approx(v0 ** 2 / (2 * mu * G), rel=0.25)
    assert abs(v[-1]) < 0.05 * v0  # stopped, bar elastic ringing
    assert v_free[-1] == pytest.approx(v0, rel=0.03)
    assert travel_stick < 0.002  # 2.5 cm when frictionless over the same 0.05 s


def test_mesh_static_and_mesh_body(tmp_path):
    """A ball of clay sampled from an icosphere mesh falls onto a block given as a mesh static (its SDF grid built
    with trimesh) and comes to rest on its top face; the ball's particle mass matches ρ × the mesh volume."""
    block = trimesh.creation.box(extents=(0.06, 0.06, 0.03))
    block.apply_translation((0.05, 0.05, 0.015))
    block_path = tmp_path / "block.stl"
    block.export(block_path)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.012)
    ball_path = tmp_path / "ball.obj"
    ball.export(ball_path)
    clay = M.VonMisesPlastic("clay", density=1000.0, shear_modulus=2e4, lame_lambda=3e4, yield_stress=300.0)
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=32, dt=1e-3, substeps=8)
    scene.add_static(fl.Mesh(str(block_path)), friction=0.5, name="block")
    body = scene.add_particles(fl.Mesh(str(ball_path), pose=(0.05, 0.05, 0.07, 0, 0, 0, 1)), clay, name="ball")
    sim = scene.build()
    mass = sim.masses(body).sum()
    sim.step(n=250)
    z = sim.positions(body)[:, 2]
    report("mesh static", ball_mass_kg=mass, expected_kg=clay.density * ball.volume, lowest_particle_m=z.min(),
           block_top_m=0.03)
    assert mass == pytest.approx(clay.density * ball.volume, rel=0.08)
    assert abs(z.min() - 0.03) < scene.dx  # resting on the top face, not sunk into it
    assert np.abs(sim.velocities(body)).max() < 0.1


@pytest.mark.parametrize("offset", [0.0, 0.5, 0.9])
def test_water_at_rest_in_a_static_tank_keeps_its_depth(offset):
    """The tasks' water (c = 4 m/s) 25 mm deep at rest in a static tank (walls two cells thick) on the tasks' small
    tank's cells (8 mm) keeps its depth, whether the floor's surface lies on a node row (offset 0, as the tasks' tank
    at the small size) or between two (0.5, 0.9 cells above one): twice its particles' mean height above the floor
    is within 0.15 cells of 25 mm after 1 s, none piled on the floor. Measured: 24.69, 24.14, 24.73 mm (its
    hydrostatic compression, ρgh/(2K) = 0.77 % on average, is 0.2 mm; held by the domain's own walls 24.71 mm at 5 mm
    cells). Before 2026-12-05 (only nodes inside a static held): 20.82, 17.69, 13.95 mm, with 3 %, 10 % and 26 % of
    the particles piled on the floor (engine/statics.py: ON_SURFACE, MEDIAL_GRADIENT, SECOND_SURFACE;
    bench/static_floor.py)."""
    from fluidlab_core.apps import validation

    r = validation.static_tank(offset=offset, res=20, size=0.16, times=(1.0,))
    report("static tank", offset=offset, depth_mm=1e3 * r["depth"][0], on_floor=r["on_floor"][0], J=r["J"][0])
    assert abs(r["depth"][0] - 0.025) < 0.15 * r["dx"]
    assert r["on_floor"][0] == 0.0
