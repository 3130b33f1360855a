"""The Air Circulation task (fluidlab_core/tasks/air_circulation.py), the paper's gas task: its sizes, a rollout, the
Gymnasium environment, the gradient its optimisers use, and its shipped trajectory."""
import warnings
from pathlib import Path

import numpy as np
import pytest

from fluidlab_core import tasks
from fluidlab_core.tasks import air_circulation as air
from tests.conftest import report

NAME = "AirCirculation"
_TASK: dict = {}


def small():
    """One small task for the module: a task keeps its simulators, whose kernels compile once."""
    if "small" not in _TASK:
        _TASK["small"] = tasks.make(NAME, "small")
    return _TASK["small"]


def test_sizes_follow_the_paper_and_keep_the_episode():
    """The paper size has the paper's 128 cells along the house and its 9 of height (its 128 × 9 × 128, y up), over
    the house's depth only (87 cells) rather than the paper's square domain; every size runs the same
    6 s episode, and each step's CFL number for the 1 m/s jet stays under the task's max_cfl."""
    for size, cells in (("small", 40), ("medium", 64), ("paper", 128)):
        task = tasks.make(NAME, size)
        scene = task.scene()
        g = scene.gas
        assert g.shape[0] == cells and task.horizon * task.dt == pytest.approx(6.0)
        assert scene.gas_limits()["cfl"] <= g.max_cfl
        sensors = task.sensors()
        assert sorted(sensors) == ["lower_left", "right", "upper_left"] and all(len(p) == 9 for p in sensors.values())
    assert tasks.make(NAME, "paper").scene().gas.shape == (128, 87, 9)


def test_builds_steps_observes_and_resets():
    """The house holds its rooms and walls, the air conditioner turns in place, the vent cools the air (the
    hall's mean temperature falls, nothing leaves the range T_COOL … T_WARM), the observation has its documented
    size, and reset restores the start exactly. The conditioner touches no particles, so DP's soft contact and the
    reference's hard contact are one simulator (Task.tool_touches_particles, found from the scene: it holds no
    particles); an unknown contact is refused."""
    task = small()
    assert type(task).touches_particles is None and not task.tool_touches_particles
    sim = task.simulator()
    assert task.simulator(contact="soft") is sim
    with pytest.raises(ValueError, match="contact must be one of"):
        task.simulator(contact="sticky")
    task.reset(sim)
    start = sim.get_state()
    obs0 = task.observe(sim)
    assert obs0.shape == (task.observation_size(),) == (205,) and obs0.dtype == np.float32
    np.testing.assert_allclose(obs0[-13:-6], task.initial_tool_pose(), atol=1e-6)
    for _ in range(40):
        sim.step(task.twists(np.array([[1.0]]))[0])
    pose = sim.tool_pose(task.tool_name)
    np.testing.assert_allclose(pose[:3], task.initial_tool_pose()[:3], atol=1e-12)  # it only turns
    yaw = 2 * np.arctan2(pose[5], pose[6])
    assert yaw == pytest.approx(40 * task.dt * 1.0, abs=1e-6)
    T = sim.gas_field("temperature")
    gas = ~sim.solid()
    assert T[gas].min() >= air.T_COOL - 1e-3 and T[gas].max() <= air.T_WARM + 1e-3
    assert T[gas].mean() < air.T_WARM - 0.1
    out = task.evaluate(np.zeros((task.horizon, 1)))
    assert np.isfinite(out["loss"]) and len(out["rewards"]) == task.horizon
    assert 5.0 < out["loss"] < 8.0  # K per sensor: 8 K at the start, the hall's cool air reaches a few sensors
    task.reset(sim)
    again = sim.get_state()
    for a, b in zip(again.gas.velocity, start.gas.velocity):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(again.tool_rotation, start.tool_rotation)


def test_the_gymnasium_environment_passes_the_checker():
    from gymnasium.utils.env_checker import check_env

    from fluidlab_core.envs import FluidLabEnv

    env = FluidLabEnv(NAME, render_mode="rgb_array", task=small())
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*Box observation space (minimum|maximum) value.*")
        check_env(env.unwrapped, skip_render_check=False)
    obs, _ = env.reset(seed=0)
    total = 0.0
    for _ in range(10):
        obs, reward, terminated, truncated, info = env.step(np.array([0.5], dtype=np.float32))
        total += reward
    assert obs.shape == (205,) and np.isfinite(total) and "task_loss" in info
    frame = env.render()
    assert frame.shape == (240, 320, 3) and frame.std() > 1


def test_the_task_gradient_points_downhill():
    """DP's gradient of the task loss with respect to the yaw rates (float32, the task's own physics): a step
    against it lowers the loss, and a directional derivative agrees with a central difference within 15 %
    (measured 7.5 %: 0.0117 against 0.0108). Not closer: the flow under MacCormack advection amplifies small
    changes of the yaw rate step after step, and the turning conditioner's voxelised cells switch, so the loss is
    smooth only over spans far below ±0.05 rad/s (bench/air_gradient.py: over 60 steps to about ±1e-5, over the
    whole 240-step episode to ±1e-7, whichever limiter; docs/tasks.md). The float64 check of every gradient path,
    with smooth parts only, is tests/test_gas.py (within 5e-3)."""
    task = small()
    sim = task.simulator(grad=True)
    n = 60
    rng = np.random.default_rng(1)
    actions = 0.8 + 0.2 * rng.standard_normal((n, 1))
    loss = task.loss(n)
    task.reset(sim)
    res = sim.rollout(task.twists(actions), loss, grad=True)
    g = res.grad_actions[:, 0, 5]
    d = g / np.linalg.norm(g)
    eps = 0.05

    def at(a):
        task.reset(sim)
        return sim.rollout(task.twists(a), loss).loss

    fd = (at(actions + eps * d[:, None]) - at(actions - eps * d[:, None])) / (2 * eps)
    an = float(g @ d)
    report("AirCirculation gradient", loss=res.loss, finite_difference=fd, backward=an)
    assert an > 0 and abs(fd - an) < 0.15 * abs(an)
    assert at(actions - 0.2 * d[:, None]) < res.loss


def test_dp_over_windows_differentiates_each_window_from_where_the_actions_lead():
    """"dp-window" (optim/dp.py): a window's gradient, taken from the state the current actions reach at its
    start, is the gradient of the loss of that window and its look-ahead: along the knots that move the window's
    actions and not the steps before it (so that the state at the window's start does not depend on them) it
    equals the same loss's gradient through the whole run from step 0 (a separate backward pass, measured to
    6e-7 relative), and a step against it lowers that loss. (Not against finite differences: the loss over
    120 steps is rough at DP's scales, central differences over ±0.001 … 0.2 rad/s give 0.66–1.14 of the
    gradient; docs/tasks.md.) The loop judges the whole horizon before each turn through the windows and after
    its last step, and counts every step it runs, the forward runs to a window's start included."""
    from fluidlab_core import losses, optim
    from fluidlab_core.optim import dp
    from fluidlab_core.optim import params as P

    task = small()
    assert task.gradient_window == 60 and dp.windows(task.horizon, 60) == [(0, 60), (60, 60), (120, 60), (180, 60)]
    sim = task.simulator(grad=True)
    par = P.default(task)
    rng = np.random.default_rng(1)
    theta = par.clip(np.concatenate([0.8 + 0.2 * rng.standard_normal(par.n_action_params),
                                     np.zeros(par.size - par.n_action_params)]))
    start, length, n = 60, 60, 120
    loss, g, used = dp.window_step(task, sim, par, theta, start, length)
    assert used == start + n  # the run to the window, the window and its look-ahead
    rows = par.matrix.reshape(task.horizon, task.n_actions, -1)
    inside = np.zeros(par.size, bool)  # knots that leave every action before the window as it is
    inside[: par.n_action_params] = ~np.any(rows[:start] != 0, axis=(0, 1)) & np.any(rows[start:start + length] != 0,
                                                                                      axis=(0, 1))
    assert 0 < inside.sum() < par.n_action_params
    d = np.where(inside, g, 0.0)
    d /= np.linalg.norm(d)

    class AfterStart(losses.Sum):  # the window's loss steps, counted from step 0
        def active(self, step, horizon):
            return step > start and super().active(step, horizon)

    task.reset(sim, par.tool_position(theta))
    whole = sim.rollout(task.twists(par.actions(theta))[:start + n], AfterStart([task.step_term()], 1.0 / n),
                        grad=True)
    ga = np.zeros((task.horizon, task.n_actions))  # of the window's own actions, as dp-window steps them
    ga[start:start + length] = whole.grad_actions[start:start + length, 0, list(task.action_axes)]
    g_whole = par.gradient(ga, np.zeros(3))
    report("AirCirculation window gradient (window 61-120, loss over 61-180)", loss=loss, whole_run_loss=whole.loss,
           window=float(g @ d), whole_run=float(g_whole @ d), knots=int(inside.sum()),
           relative_difference=abs(float((g_whole - g) @ d) / float(g @ d)))
    assert whole.loss == pytest.approx(loss, rel=1e-5)
    assert float(g_whole @ d) == pytest.approx(float(g @ d), rel=1e-4)
    assert dp.window_step(task, sim, par, theta - 0.2 * d, start, length, grad=False)[0] < loss
    seen = []
    out = optim.optimise(task, "dp-window", 4 * task.horizon, seed=0, callback=lambda p: seen.append(p) and False,
                         max_iterations=2)
    meta = out.metadata
    # whole horizon (240) + window 1 and its look-ahead (120) + the run to window 2, it and its look-ahead (180)
    # + the last parameters (240)
    assert meta["steps_used"] == 780 and meta["iterations"] == 2 and len(out.loss_history) == 2
    assert [p.steps for p in seen] == [360, 540] and [p.region for p in seen] == [60, 60]
    assert meta["settings"]["gradient_window"] == 60 and meta["settings"]["windows"] == 4
    assert meta["settings"]["soft_contact"] is False  # the record says what ran: no particles, no soft contact
    assert meta["final_loss"] == pytest.approx(min(out.loss_history), rel=1e-6)  # no contact: one physics


def test_shipped_trajectory_reproduces_its_loss_and_beats_the_still_tool():
    from fluidlab_core.trajectory import Trajectory

    root = Path(__file__).resolve().parents[1] / "trajectories" / NAME
    files = sorted(root.glob("*_small.json"))
    assert len(files) == 1, files
    assert files[0].with_suffix(".mp4").stat().st_size > 10_000
    traj = Trajectory.load(files[0])
    task = small()
    actions, position = task.actions_from_trajectory(traj)
    loss = task.evaluate(actions, tool_position=position, rewards=False)["loss"]
    still = task.evaluate(np.zeros_like(actions), rewards=False)["loss"]
    report("AirCirculation shipped", loss=loss, still=still, recorded=traj.metadata["final_loss"])
    assert loss == pytest.approx(traj.metadata["final_loss"], rel=1e-3)
    assert loss < still


def test_the_twin_worker_publishes_the_gas_coloured_by_temperature():
    """sim_node's fluid worker (fluidlab_ros/workers.py, in its own process as the node runs it) on the gas task:
    it reports the scene (walls, the air conditioner) and publishes the gas's mid-plane as points coloured by
    temperature, whose colours change as the conditioner blows (the twin of a gas task in RViz/Foxglove)."""
    import multiprocessing as mp
    import queue

    from fluidlab_ros.workers import fluid_worker

    ctx = mp.get_context("spawn")
    inbox, out, stop = ctx.Queue(), ctx.Queue(), ctx.Event()
    proc = ctx.Process(target=fluid_worker, args=(NAME, "small", inbox, out), kwargs={"nice": 0, "stop": stop},
                       daemon=True)
    proc.start()
    try:
        msgs = []

        def until(kind, timeout=600):
            while True:
                m = out.get(timeout=timeout)
                msgs.append(m)
                assert m["kind"] != "error", m.get("traceback")
                if m["kind"] == kind:
                    return m

        ready = until("ready")
        assert ready["n"] > 100 and len(ready["statics"]) == 6 and ready["tools"][0][0] == "air_conditioner"
        inbox.put({"kind": "reset"})
        first = until("particles")
        pose = small().initial_tool_pose()
        for k in range(10):
            inbox.put({"kind": "pose", "pose": pose, "last": k == 9})
        last = until("particles")
        while True:  # the last publication after the tenth pose
            try:
                last = out.get(timeout=5)
            except queue.Empty:
                break
        assert first["positions"].shape == last["positions"].shape and first["positions"].shape[1] == 3
        assert first["colors"].dtype == np.uint8 and first["colors"].shape == first["positions"].shape
        assert np.abs(first["colors"].astype(int) - last["colors"].astype(int)).max() > 20
    finally:
        stop.set()
        proc.join(timeout=30)
