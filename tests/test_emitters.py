"""Particle emitters (fluidlab_core/engine/emitters.py): conservation, exit velocity, on/off, pool exhaustion,
nozzles that would emit into a solid, bad specifications, the state round trip, and gradients through emission
(with respect to the nozzle poses, the carrying tool's pose and its actions) against central differences in
float64, checkpointing included."""
import numpy as np
import pytest

import fluidlab_core as fl
from fluidlab_core import losses
from fluidlab_core import materials as M
from fluidlab_core import shapes as S
from tests import conftest
from tests.conftest import report

DOWN = (1.0, 0.0, 0.0, 0.0)  # nozzle frame turned by π about x: the fluid leaves along −z
RATE = 2e-5  # m³/s


def jet_scene(pool=None, duration=0.3, **kw):
    sc = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=20, dt=2e-3, substeps=16)
    sc.add_particles(S.Box((0.0, 0.0, 0.0), (0.1, 0.1, 0.01)), M.WATER, name="layer")
    jet = sc.add_emitter(M.WATER, rate=RATE, nozzle="disc", size=0.006, pose=(0.05, 0.05, 0.08, *DOWN),
                         pool=pool, duration=None if pool else duration, name="jet", **kw)
    return sc, jet


@pytest.fixture(scope="module")
def jet():
    sc, handle = jet_scene()
    return sc, sc.build(), handle


def test_mass_in_the_scene_is_rate_times_density_times_time(jet):
    """After t seconds of emission the jet holds Q ρ t to within one row; switched off, it adds nothing; the
    readers see only what has left the nozzle."""
    sc, sim, h = jet
    spec = sim.emitter_specs[0]
    row_mass = spec.row_volume * M.WATER.density
    sim.set_state(sim.model.initial_state())
    assert len(sim.positions("jet")) == 0 and sim.masses("jet").sum() == 0.0
    for n in (5, 20, 40):
        info = sim.step(n=n - sim.step_count)
        mass = sim.masses("jet").sum()
        expected = RATE * M.WATER.density * sim.time
        report("emitted mass", t=sim.time, mass=mass, expected=expected, row=row_mass)
        assert abs(mass - expected) <= row_mass
        assert info["emitters"]["jet"]["emitted"] == len(sim.positions("jet")) == len(sim.velocities("jet"))
        assert info["emitters"]["jet"]["mass"] == pytest.approx(mass, rel=1e-6)
    before = sim.masses("jet").sum()
    info = sim.step(n=10, emit=False)
    assert sim.masses("jet").sum() == before and not info["emitters"]["jet"]["exhausted"]
    info = sim.step(n=10, emit={"jet": True})
    # the on-time stops while off: 50 on-steps in all
    assert abs(sim.masses("jet").sum() - RATE * M.WATER.density * 50 * sim.dt) <= row_mass
    # the whole scene's mass: the layer's and the emitted
    assert sim.masses().sum() == pytest.approx(sim.masses("layer").sum() + sim.masses("jet").sum())


def test_particles_leave_at_the_exit_speed_along_the_nozzle_axis(jet):
    """The particles of the newest rows move at u along the nozzle's axis (−z here); the stream stays a disc of
    the nozzle's radius near the exit."""
    sc, sim, h = jet
    sim.set_state(sim.model.initial_state())
    spec = sim.emitter_specs[0]
    # until the first row has just left (later rows share grid cells with the ones before them, which gravity
    # has sped up: the single-velocity grid averages them at once)
    while sim.step()["emitters"]["jet"]["emitted"] < spec.n_row:
        pass
    x, v = sim.positions("jet"), sim.velocities("jet")
    newest = slice(len(x) - spec.n_row, len(x))  # pool order is emission order
    u = spec.speed
    mean_v = v[newest].mean(axis=0)
    report("exit velocity", u=u, vz=mean_v[2], vx=mean_v[0], vy=mean_v[1])
    # born within the last step: gravity has added at most g dt
    assert abs(mean_v[2] + u) <= 9.81 * sim.dt + 0.05 * u and np.abs(mean_v[:2]).max() < 0.05 * u
    assert np.all(x[newest, 2] <= 0.08 + 1e-6) and np.all(x[newest, 2] >= 0.08 - 1.1 * u * sim.dt - 1e-6)
    r = np.linalg.norm(x[newest, :2] - 0.05, axis=1)
    assert r.max() <= 0.006 + 1e-6


def test_a_pool_that_runs_out_stops_and_says_so():
    sc, _ = jet_scene(pool=100)
    assert sc.emitters[0].pool % sc.emitters[0].n_row == 0 and sc.emitters[0].pool >= 100  # whole rows
    sim = sc.build()
    info = sim.step(n=60)
    rep = info["emitters"]["jet"]
    assert rep["exhausted"] and rep["emitted"] == rep["pool"] and "used up its pool" in rep["message"]
    assert len(sim.positions("jet")) == rep["pool"]


def test_state_round_trip_includes_the_emission(jet):
    sc, sim, h = jet
    sim.set_state(sim.model.initial_state())
    sim.step(n=7)
    state = sim.get_state()
    assert state.emitted.shape == (1,) and state.emitted[0] > 0 and state.emit_time[0] == pytest.approx(7 * sim.dt)
    sim.step(n=5)
    after = sim.positions("jet")
    sim.set_state(state)
    assert len(sim.positions("jet")) == state.emitted[0]
    sim.step(n=5)
    np.testing.assert_allclose(sim.positions("jet"), after, atol=1e-6)


def test_bad_specifications_are_refused_with_the_numbers():
    sc = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=20)
    sc.add_static(S.Box((0.0, 0.0, 0.0), (0.1, 0.1, 0.02)), name="floor")
    ok = dict(nozzle="disc", size=0.006, pose=(0.05, 0.05, 0.08, *DOWN), duration=0.1)
    with pytest.raises(ValueError, match="flow rate must be a positive"):
        sc.add_emitter(M.WATER, rate=0.0, **ok)
    with pytest.raises(ValueError, match=r"larger than the domain's smallest side \(0.1 m\)"):
        sc.add_emitter(M.WATER, rate=RATE, **{**ok, "size": 0.06})
    with pytest.raises(ValueError, match="smaller than one row of its nozzle"):
        sc.add_emitter(M.WATER, rate=RATE, **{**ok, "duration": None, "pool": 3})
    with pytest.raises(ValueError, match="inside .*static 'floor'"):
        sc.add_emitter(M.WATER, rate=RATE, **{**ok, "pose": (0.05, 0.05, 0.015, *DOWN)})
    with pytest.raises(ValueError, match="outside the domain"):
        sc.add_emitter(M.WATER, rate=RATE, **{**ok, "pose": (0.05, 0.05, 0.099, 0, 0, 0, 1)})
    with pytest.raises(ValueError, match="dense as the liquid at rest"):
        sc.add_emitter(M.WATER, rate=RATE, speed=5.0, **ok)
    with pytest.raises(ValueError, match="give its pool"):
        sc.add_emitter(M.WATER, rate=RATE, **{**ok, "duration": None})
    with pytest.raises(ValueError, match=r"size is \(width, height\)"):
        sc.add_emitter(M.WATER, rate=RATE, **{**ok, "nozzle": "rectangle"})
    with pytest.raises(ValueError, match="rigid material"):
        sc.add_emitter(M.RIGID, rate=RATE, **ok)
    with pytest.raises(ValueError, match="no tool 'arm'"):
        sc.add_emitter(M.WATER, rate=RATE, tool="arm", **ok)


def test_a_carried_nozzle_never_emits_into_a_solid():
    """A nozzle on a tool that moves down into a static stops emitting there, and step() says why."""
    sc = fl.Scene(lower=(0, 0, 0), upper=(0.1, 0.1, 0.1), grid_res=20, dt=2e-3, substeps=16)
    sc.add_static(S.Box((0.0, 0.0, 0.0), (0.1, 0.1, 0.02)), name="floor")
    sc.add_particles(S.Box((0.01, 0.01, 0.02), (0.03, 0.03, 0.03)), M.WATER, name="puddle")
    sc.add_tool(S.Box((-0.01, -0.01, 0.0), (0.01, 0.01, 0.01)), pose=(0.06, 0.06, 0.05, 0, 0, 0, 1), name="can")
    sc.add_emitter(M.WATER, rate=RATE, size=0.004, pose=(0.0, 0.0, -0.002, *DOWN), tool="can", duration=0.5,
                   name="spout")
    sim = sc.build()
    info = sim.step(n=5)
    assert info["emitters"]["spout"]["blocked"] == ""
    n = info["emitters"]["spout"]["emitted"]
    assert n > 0
    info = sim.step([0, 0, -0.5, 0, 0, 0], n=30)  # 1 mm down per step: the exit reaches the floor
    rep = info["emitters"]["spout"]
    assert "inside (or within half a cell of) static 'floor'" in rep["blocked"], rep
    z_exit = sim.tool_pose("can")[2] - 0.002
    assert z_exit < 0.02 + 0.5 * sc.dx
    assert np.all(sim.positions("spout")[:, 2] >= 0.02 - 1e-4)  # nothing was put inside the floor


# --- gradients (float64) ---------------------------------------------------------------------------------
EPS = 1e-6
REL_TOL = 5e-3
N_STEPS = 10


@pytest.fixture(scope="module")
def f64():
    conftest.init("f64")
    yield
    conftest.init("f32")


def gradient_scene():
    """A fixed nozzle submerged in a water layer, pointing along +x, and a nozzle carried by a tool above the
    water, pointing down. The tool has hard contact and nothing touches it: the soft contact law's cut-off
    at 5/softness is a kink that central differences straddle (docs/engine.md)."""
    sc = fl.Scene(lower=(0, 0, 0), upper=(0.08, 0.08, 0.08), grid_res=12, dt=2e-3, substeps=12)
    sc.add_particles(S.Box((0.0, 0.0, 0.0), (0.08, 0.08, 0.02)), M.WATER, name="water", velocity=(0.02, 0.0, 0))
    sc.add_tool(S.Sphere((0, 0, 0), 0.008), pose=(0.04, 0.03, 0.05, 0, 0, 0, 1), name="tool")
    s45 = np.sqrt(0.5)
    sc.add_emitter(M.WATER, rate=3e-5, nozzle="disc", size=0.006, pose=(0.023, 0.052, 0.009, 0, s45, 0, s45),
                   duration=0.05, name="jet")
    sc.add_emitter(M.WATER, rate=2e-5, nozzle="rectangle", size=(0.008, 0.006), pose=(0.0, 0.0, -0.012, *DOWN),
                   tool="tool", duration=0.05, name="carried")
    return sc.build(requires_grad=True, grad_max_steps=4)


def test_gradients_through_emission_match_finite_differences(f64):
    from scipy.spatial.transform import Rotation

    sim = gradient_scene()
    rng = np.random.default_rng(0)
    n = sim.n_particles
    loss = losses.Linear(a=rng.normal(size=(n, 3)), b=rng.normal(size=(n, 3)), steps="all")
    actions = rng.normal(scale=0.05, size=(N_STEPS, 6))
    start = sim.get_state()
    res = sim.rollout(actions, loss, grad=True)  # 3 segments of at most 4 steps
    assert res.stats["segments"] == 3
    sim.set_state(start)
    one = sim.rollout(actions, loss, grad=True, segment_steps=4)
    np.testing.assert_allclose(one.grad_actions, res.grad_actions, rtol=1e-10, atol=1e-12)
    sim.set_state(start)
    fast = sim.rollout(actions, loss)
    assert fast.loss == pytest.approx(res.loss, rel=1e-12)  # the fast and the differentiable forward agree
    pool = np.concatenate([np.arange(sim.n_particles)[sim.handle(h).slice] for h in ("jet", "carried")])
    assert not np.any(res.grad_positions[pool]) and not np.any(res.grad_velocities[pool])

    def L(state=start):
        sim.set_state(state)
        return sim.rollout(actions, loss).loss

    def central(f):
        return (f(EPS) - f(-EPS)) / (2 * EPS)

    checks = []
    d = rng.normal(size=actions.shape)
    checks.append(("actions", central(lambda e: (sim.set_state(start), sim.rollout(actions + e * d, loss).loss)[1]),
                   float(np.sum(res.grad_actions[:, 0] * d))))
    dp = rng.normal(size=3)
    checks.append(("tool position", central(lambda e: L(start.replace(tool_position=start.tool_position + e * dp))),
                   float(res.grad_tool_position[0] @ dp)))
    for e_i, name in enumerate(("jet", "carried")):
        base = sim.emitter_pose(name)

        def at_pose(pose):
            sim.set_emitter_pose(name, pose)
            try:
                return L()
            finally:
                sim.set_emitter_pose(name, base)

        dp = rng.normal(size=3)
        checks.append((f"{name} position", central(lambda e: at_pose(np.r_[base[:3] + e * dp, base[3:]])),
                       float(res.grad_emitter_position[e_i] @ dp)))
        th = rng.normal(size=3)
        checks.append((f"{name} rotation", central(lambda e: at_pose(np.r_[base[:3], (
            Rotation.from_rotvec(e * th) * Rotation.from_quat(base[3:])).as_quat()])),
                       float(res.grad_emitter_rotation[e_i] @ th)))
    for what, fd, analytic in checks:
        err = abs(fd - analytic) / abs(fd)
        report("emission gradient vs finite difference", what=what, fd=fd, analytic=analytic, rel_error=err)
        assert err < REL_TOL, what
