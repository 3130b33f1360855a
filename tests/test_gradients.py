"""Gradients of rollouts against central finite differences, in float64 on the CPU.

One small scene holds every material class (liquid, viscous liquid, elastic, box-yield plastic, von Mises
plastic, rigid), a static with friction and two tools (soft contact with friction, hard contact), so that
the gradient kernels compile once. Each check is a directional derivative: for a random direction d,
dL/dε of L(θ + ε d) by central differences (ε = 1e-6) against ⟨∇L, d⟩ from the backward pass.

Tolerance: relative error 5e-3. Where the loss is smooth (a liquid block away from walls) the two agree to
2e-8; here the laws' kinks (wall and contact conditions, plastic yield, friction stick/slip) lie within ε of
some of the 2,000 particles, and the measured errors are 2e-7 (rigid) to 2e-3 (ice cream), printed with -s.
The gradient bugs met while writing the backward pass (a term missing or wrong) showed as 1 % to 13 %.
"""
import numpy as np
import pytest

from tests import conftest
from fluidlab_core import losses
from fluidlab_core import materials as M
from fluidlab_core import shapes as S
from fluidlab_core.engine.checkpoint import NonFiniteGradientError, rollout_with_grad
from fluidlab_core.scene import Scene
from tests.conftest import report

REL_TOL = 5e-3
EPS = 1e-6
N_STEPS = 6


@pytest.fixture(scope="module")
def f64():
    conftest.init("f64")
    yield
    conftest.init("f32")


def build_scene():
    """Bodies at least two cells from the walls and moving: at rest against a wall, a node's velocity sits
    exactly on the kink of the wall condition (v·n < 0), where central differences average two one-sided
    slopes."""
    sc = Scene(lower=(0, 0, 0), upper=(0.12, 0.08, 0.08), grid_res=15, dt=1e-3, substeps=13)
    sc.add_particles(S.Box((0.0, 0.0, 0.0), (0.12, 0.068, 0.012)), M.WATER, name="water", velocity=(0.03, 0.02, -0.01))
    low, high = (0.016, 0.02), (0.032, 0.035)
    for i, (name, material) in enumerate([("viscous", M.FROTHED_MILK), ("elastic", M.ELASTIC),
                                          ("plastic", M.PLASTIC), ("ice_cream", M.ICE_CREAM)]):
        x0 = 0.016 + 0.022 * i
        sc.add_particles(S.Box((x0, low[0], low[1]), (x0 + 0.016, high[0], high[1])), material, name=name,
                         velocity=(0.04, 0.03, -0.02))
    sc.add_particles(S.Box((0.04, 0.045, 0.02), (0.06, 0.062, 0.035)), M.RIGID_LIGHT, name="rigid",
                     velocity=(0.05, -0.05, 0.0))
    sc.add_static(S.Box((0.0, 0.07, 0.0), (0.12, 0.08, 0.03)), friction=0.3)
    box = ((0.0, 0.0, 0.0), (0.12, 0.08, 0.08))
    sc.add_tool(S.Box((-0.004, -0.004, -0.02), (0.004, 0.004, 0.02)), pose=(0.02, 0.055, 0.03, 0, 0, 0, 1),
                name="soft", softness=400.0, friction=0.2, workspace=box)
    sc.add_tool(S.Sphere((0, 0, 0), 0.008), pose=(0.095, 0.055, 0.02, 0, 0, 0, 1), name="hard", workspace=box)
    sim = sc.build(requires_grad=True)
    # a shear flow in every body: a body in uniform motion keeps F exactly isotropic, where the SVD backward
    # drops the symmetric shear response of the plastic models (engine/svd.py)
    state = sim.get_state()
    x = state.x.astype(np.float64)
    state.v = state.v + np.stack([3.0 * (x[:, 2] - 0.02), 2.0 * (x[:, 0] - 0.06), 1.5 * (x[:, 1] - 0.03)], axis=1)
    sim.set_state(state)
    return sim


def build_problem(sim):
    """The loss (a random linear functional of every step's state plus a tool distance) and the random actions
    of the checks (also bench/gradient_regression.py's)."""
    rng = np.random.default_rng(0)
    n = sim.n_particles
    loss = (losses.Linear(a=rng.normal(size=(n, 3)), b=rng.normal(size=(n, 3)), steps="all")
            + losses.ToolDistance((0.05, 0.05, 0.05), tool=0))
    return loss, rng.normal(scale=0.1, size=(N_STEPS, 2, 6))


@pytest.fixture(scope="module")
def setup(f64):
    sim = build_scene()
    loss, actions = build_problem(sim)
    start = sim.get_state()
    result = sim.rollout(actions, loss, grad=True, segment_steps=2)
    return sim, loss, actions, start, result


def forward_loss(sim, state, actions, loss):
    sim.set_state(state)
    return rollout_with_grad(sim.diff, state, sim._action_sequence(actions), loss, grad=False)[0].loss


def central_difference(f):
    return (f(EPS) - f(-EPS)) / (2 * EPS)


def check(name, fd, analytic):
    rel = abs(fd - analytic) / max(abs(fd), 1e-12)
    report("gradient vs finite difference", what=name, fd=fd, analytic=analytic, rel_error=rel)
    assert rel < REL_TOL, f"{name}: finite difference {fd:.10g}, backward {analytic:.10g}"
    return rel


@pytest.mark.parametrize("body", ["water", "viscous", "elastic", "plastic", "ice_cream", "rigid"])
def test_initial_velocity_gradient_per_material(setup, body):
    sim, loss, actions, start, result = setup
    h = sim.handle(body)
    d = np.zeros((sim.n_particles, 3))
    d[h.slice] = np.random.default_rng(1).normal(size=(h.count, 3))

    def f(e):
        return forward_loss(sim, start.replace(v=start.v + e * d), actions, loss)

    check(f"initial velocities of {body}", central_difference(f), float(np.sum(result.grad_velocities * d)))


@pytest.mark.parametrize("tool", [0, 1], ids=["soft_contact", "hard_contact"])
def test_action_gradient_per_contact_model(setup, tool):
    sim, loss, actions, start, result = setup
    d = np.zeros_like(actions)
    d[:, tool] = np.random.default_rng(2).normal(size=(N_STEPS, 6))
    check(f"actions of tool {tool}", central_difference(lambda e: forward_loss(sim, start, actions + e * d, loss)),
          float(np.sum(result.grad_actions * d)))


def test_initial_tool_pose_gradient(setup):
    sim, loss, actions, start, result = setup
    rng = np.random.default_rng(3)
    dp = rng.normal(size=(2, 3))

    def moved(e):
        return forward_loss(sim, start.replace(tool_position=start.tool_position + e * dp), actions, loss)

    # A step of 1e-7 here, not EPS: the hard tool's contact is a step in position (a node inside the sphere takes
    # the tool's velocity), and its surface sweeps past nodes by ~8e-6 m a substep, so a ±1e-6 shift of the whole
    # motion moves some node across it in some substep more often than not. Measured (nodes on the walls,
    # 2026-11-26): central difference −13,165 with ±1e-6, −164.9 with ±1e-7, backward −164.2 (0.4 %); with the
    # soft tool 0.3 mm along x, −12,925, 74.01814 and 74.01816; the sphere moved by 0.1-0.3 mm gave ±1e-6
    # differences about 1.0 off the backward at every placement, ±1e-7 within 1e-6.
    check("initial tool positions", (moved(1e-7) - moved(-1e-7)) / 2e-7, float(np.sum(result.grad_tool_position * dp)))
    from scipy.spatial.transform import Rotation

    dtheta = rng.normal(size=(2, 3))

    def turned(e):
        turn = np.stack([Rotation.from_rotvec(e * dtheta[k]).as_matrix() @ start.tool_rotation[k] for k in range(2)])
        return forward_loss(sim, start.replace(tool_rotation=turn), actions, loss)

    check("initial tool rotations", central_difference(turned), float(np.sum(result.grad_tool_rotation * dtheta)))


def test_checkpointed_gradient_equals_single_segment(setup):
    """Segments of 2 steps (3 segments, gradients handed over twice) give the gradient of one segment, and
    checkpoints on disk the same as in memory."""
    sim, loss, actions, start, result = setup
    sim.set_state(start)
    whole = sim.rollout(actions, loss, grad=True, segment_steps=N_STEPS)
    assert result.stats["segments"] == 3 and whole.stats["segments"] == 1
    for key in ("grad_actions", "grad_velocities", "grad_positions", "grad_tool_position", "grad_tool_rotation"):
        a, b = getattr(result, key), getattr(whole, key)
        err = np.abs(a - b).max() / np.abs(b).max()
        report("checkpointed vs single segment", field=key, max_rel_diff=err)
        assert err < 1e-10, key
    sim.set_state(start)
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        on_disk = sim.rollout(actions, loss, grad=True, segment_steps=2, checkpoint_dir=tmp)
        # equal up to the summation order of the atomic scatter, which varies between runs
        np.testing.assert_allclose(on_disk.grad_actions, result.grad_actions, rtol=1e-9,
                                   atol=1e-9 * np.abs(result.grad_actions).max())
        assert len(__import__("os").listdir(tmp)) == 0, "checkpoint files are removed after the rollout"


def test_differentiable_forward_matches_fast_solver(setup):
    """The gradient solver's forward pass (atomic scatter, SVD polar) agrees with the fast solver's loss."""
    sim, loss, actions, start, result = setup
    sim.set_state(start)
    fast = sim.rollout(actions, loss, grad=False)
    report("loss, fast vs differentiable forward", fast=fast.loss, differentiable=result.loss)
    assert abs(fast.loss - result.loss) < 1e-9 * abs(fast.loss)
    end_fast = sim.get_state()
    sim.set_state(start)
    sim.rollout(actions, loss, grad=True)
    end_diff = sim.get_state()
    assert end_diff.step == end_fast.step == start.step + N_STEPS
    np.testing.assert_allclose(end_diff.x, end_fast.x, atol=1e-10)


def test_nonfinite_loss_gradient_names_the_step(setup):
    sim, loss, actions, start, result = setup
    sim.set_state(start)

    def bad(state, grad):
        return 0.0, ({"x": np.full_like(state.x, np.nan)} if grad else None)

    with pytest.raises(NonFiniteGradientError, match="step 4"):
        sim.rollout(actions, losses.Callable(bad, steps=[4]), grad=True)


def test_nonfinite_dynamics_gradient_names_the_step(setup):
    """A finite loss gradient that overflows in the backward of the dynamics is reported at the step where it
    did, with the fields, although the watch runs once per segment."""
    sim, loss, actions, start, result = setup
    sim.set_state(start)

    def huge(state, grad):
        return 0.0, ({"v": np.full_like(state.v, 1e308)} if grad else None)

    with pytest.raises(NonFiniteGradientError, match=r"NaN or infinite in \w.* at step 3 \(t = 0.003 s\)"):
        sim.rollout(actions, losses.Callable(huge, steps=[4]), grad=True, segment_steps=N_STEPS)


def test_rollout_refusals(setup):
    sim, loss, actions, start, result = setup
    sim.set_state(start)
    with pytest.raises(ValueError, match=r"shape \(N, 6\) for one tool or \(N, 2, 6\)"):
        sim.rollout(np.zeros((3, 6)), loss)
    with pytest.raises(ValueError, match="NaN"):
        sim.rollout(np.full((3, 2, 6), np.nan), loss)
    with pytest.raises(ValueError, match="exceeds the gradient buffer"):
        sim.rollout(np.zeros((3, 2, 6)), loss, grad=True, segment_steps=10_000)
    with pytest.raises(TypeError, match="Loss"):
        sim.rollout(np.zeros((3, 2, 6)), lambda s: 0.0)
    assert sim.get_state().step == start.step, "a refused rollout does not step"


def test_segments_fill_the_buffer():
    """Segments as long as the buffer allows (it is allocated at build): one segment when the horizon fits,
    otherwise equal segments, so checkpoints stay under sqrt(N) while the buffer holds sqrt(N) steps."""
    from fluidlab_core.engine.checkpoint import plan_segments

    assert plan_segments(100, 200) == 100  # fits: one segment, nothing recomputed
    assert plan_segments(1000, 200) == 200  # 5 checkpoints
    assert plan_segments(1001, 200) == 167  # 6 equal segments, not 5 of 200 and one of 1
    assert plan_segments(10_000, 200) == 200  # 50 checkpoints < sqrt(10,000)
    assert -(-10_000 // plan_segments(10_000, 200)) <= 100
    assert plan_segments(5, 200, segment_steps=2) == 2
    assert plan_segments(5, 200, segment_steps=50) == 5
    with pytest.raises(ValueError, match="exceeds the gradient buffer"):
        plan_segments(100, 10, segment_steps=20)
    with pytest.raises(ValueError, match="at least 1"):
        plan_segments(100, 10, segment_steps=0)
    with pytest.raises(ValueError, match="grad_memory"):
        plan_segments(100, 0)


def test_atomic_scatter_path_matches_finite_differences(f64, monkeypatch):
    """The GPU code path (atomic scatters in P2G and in the gather's backward), run on the CPU with
    FLUIDLAB_SCATTER_COPIES=0: its action and initial-velocity gradients against central differences. An
    elastic block lies on the water, so that both velocity fields of the grid (fluids, solids) and their
    contact nodes are on that path too."""
    monkeypatch.setenv("FLUIDLAB_SCATTER_COPIES", "0")
    sc = Scene(lower=(0, 0, 0), upper=(0.06, 0.06, 0.06), grid_res=10, dt=1e-3, substeps=7)
    sc.add_particles(S.Box((0.0, 0.0, 0.0), (0.06, 0.06, 0.02)), M.WATER, name="water", velocity=(0.02, 0.01, 0))
    sc.add_particles(S.Box((0.012, 0.012, 0.02), (0.03, 0.03, 0.032)),
                     M.Elastic("soft_block", density=800.0, shear_modulus=2e4, lame_lambda=5e4), name="block")
    # a frictional ledge along a wall, above the water and beside the block: no particle starts inside it. With
    # the water filling the ledge's lower part, as before, the particles pushed out of it through the first
    # substeps made the check 0.5-0.7 % (nodes on the walls) and 0.18 % (before); clear of it, 4e-8 (2026-11-26)
    sc.add_static(S.Box((0.0, 0.0, 0.02), (0.06, 0.01, 0.03)), friction=0.3)
    sc.add_tool(S.Sphere((0, 0, 0), 0.008), pose=(0.03, 0.035, 0.02, 0, 0, 0, 1), softness=400.0, friction=0.2)
    sim = sc.build(requires_grad=True, grad_max_steps=8)
    assert not sim.diff.private, "FLUIDLAB_SCATTER_COPIES=0 selects the atomic path"
    assert sim.model.two_fields
    rng = np.random.default_rng(1)
    n = sim.n_particles
    loss = losses.Linear(a=rng.normal(size=(n, 3)), b=rng.normal(size=(n, 3)), steps="all")
    actions = rng.normal(scale=0.05, size=(5, 6))
    start = sim.get_state()
    result = sim.rollout(actions, loss, grad=True)
    for what, direction in (("actions", rng.normal(size=actions.shape)), ("velocities", rng.normal(size=(n, 3)))):
        def at(eps):
            state, acts = start, actions
            if what == "actions":
                acts = actions + eps * direction
            else:
                state = start.replace(v=start.v + eps * direction)
            return forward_loss(sim, state, acts, loss)

        fd = (at(EPS) - at(-EPS)) / (2 * EPS)
        grad = result.grad_actions[:, 0] if what == "actions" else result.grad_velocities
        analytic = float(np.sum(grad * direction))
        err = abs(fd - analytic) / abs(fd)
        report("atomic scatter path vs finite difference", what=what, fd=fd, analytic=analytic, rel_error=err)
        assert err < REL_TOL, what


def test_bulk_viscous_liquid_gradient_matches_finite_differences(f64):
    """materials.DampedLiquid (bulk viscosity ζ, engine/constitutive.py `damped_liquid`): the gradient of a
    liquid-only rollout with respect to the initial velocities against central differences. The block starts
    away from the walls with an expanding velocity field (div v = 6 /s), so that the bulk stress ζ J tr(C) is
    large (ζ = 20 Pa·s: 120 Pa against the pressure's tens of Pa) and its backward is what is checked."""
    sc = Scene(lower=(0, 0, 0), upper=(0.06, 0.06, 0.06), grid_res=10, dt=1e-3, substeps=1)
    liquid = M.DampedLiquid("damped_water", density=1000.0, bulk_modulus=M.WATER.bulk_modulus, bulk_viscosity_pas=20.0)
    sc.add_particles(S.Box((0.015, 0.015, 0.02), (0.045, 0.045, 0.04)), liquid, name="liquid")
    sc.substeps = sc.stable_substeps()
    sim = sc.build(requires_grad=True, grad_max_steps=8)
    state = sim.get_state()
    centre = np.array([0.03, 0.03, 0.03])
    sim.set_state(state.replace(v=2.0 * (state.x.astype(np.float64) - centre)))
    rng = np.random.default_rng(2)
    n = sim.n_particles
    loss = losses.Linear(a=rng.normal(size=(n, 3)), b=rng.normal(size=(n, 3)), steps="all")
    start = sim.get_state()
    result = sim.rollout(6, loss, grad=True)
    direction = rng.normal(size=(n, 3))

    def f(eps):
        sim.set_state(start.replace(v=start.v + eps * direction))
        return sim.rollout(6, loss, grad=False).loss

    check("initial velocities of a bulk-viscous liquid", central_difference(f),
          float(np.sum(result.grad_velocities * direction)))
