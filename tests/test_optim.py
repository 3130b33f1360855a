"""Optimisers: a few DP iterations lower a task's loss; CMA-ES is reproducible from its seed; bad requests are
refused with the reason; a callback can stop a run. Float32, the default: the DP test on GatheringEasy (elastic
bodies in water) also guards against the float32 gradient overflow at nearly empty grid nodes (mpm.py,
mass_floor) that once made every elastic gradient NaN."""
from __future__ import annotations

import numpy as np
import pytest

from fluidlab_core import optim, tasks
from fluidlab_core.optim import dp


@pytest.fixture(scope="module")
def gathering():
    """One GatheringEasy task for the DP tests: its simulators (built on first use) are kept, so the second test
    does not compile them again (a simulator's kernels compile for its own fields)."""
    return tasks.make("GatheringEasy", "small")


def test_a_few_dp_iterations_lower_the_loss(gathering):
    task = gathering
    seen = []
    opts = dp.DPOptions(expanding_region=False, attraction=False)  # whole horizon each iteration: comparable
    result = dp.run(task, budget=5 * task.horizon, seed=0, callback=seen.append, options=opts)
    losses = [p.loss for p in seen]
    print(f"\nDP on GatheringEasy (small, soft contact): loss per iteration {np.round(losses, 7).tolist()}")
    assert len(losses) == 5 and all(np.isfinite(losses))
    assert losses[-1] < 0.95 * losses[0]
    assert seen[-1].steps == 5 * task.horizon and seen[-1].best_loss == min(losses)
    # the returned parameters are the best ones, and they evaluate on the reference (hard contact) physics
    par = result.parametrisation
    out = task.evaluate(par.actions(result.theta), tool_position=par.tool_position(result.theta), rewards=False)
    assert np.isfinite(out["loss"])


@pytest.mark.cpu_only  # bit-identical reruns: the CPU sums grid copies in a fixed order, CUDA's atomic adds do not
def test_cma_es_is_reproducible_and_records_its_run():
    task = tasks.make("GatheringEasy", "small")
    runs = [optim.optimise(task, "cma-es", budget=3 * task.horizon, seed=7) for _ in range(2)]
    np.testing.assert_array_equal(runs[0].twists, runs[1].twists)
    assert runs[0].loss_history == runs[1].loss_history and len(runs[0].loss_history) == 3
    other = optim.optimise(task, "cma-es", budget=task.horizon, seed=8)
    assert not np.array_equal(other.twists, runs[0].twists)
    meta = runs[0].metadata
    assert meta["final_loss"] == pytest.approx(min(runs[0].loss_history), rel=1e-9)
    assert meta["steps_used"] == 3 * task.horizon and runs[0].method == "cma-es" and runs[0].seed == 7
    # over the paper's periodic stroke the paddle returns to where it began every period (20 steps; the horizon is
    # five of them); cma-es-free spreads its knots over the whole horizon, and the paddle may end anywhere
    assert meta["settings"]["parametrisation"].startswith("periodic")
    free = optim.optimise(task, "cma-es-free", budget=task.horizon, seed=8)
    assert free.method == "cma-es-free"
    assert free.metadata["settings"]["parametrisation"] == "8 knots per axis, piecewise linear"
    span = float(np.abs(runs[0].twists).max())
    assert np.abs(runs[0].twists.sum(axis=0)).max() < 1e-6 * span * task.horizon
    assert np.abs(free.twists.sum(axis=0)).max() > 0.01 * float(np.abs(free.twists).max()) * task.horizon


def test_bad_requests_are_refused():
    task = tasks.make("Mixing", "small")
    with pytest.raises(ValueError, match="unknown method 'adam'; methods: dp, dp-h, cma-es"):
        optim.optimise(task, "adam", budget=1000)
    with pytest.raises(ValueError, match="at least one rollout"):
        optim.optimise(task, "dp", budget=10)
    with pytest.raises(ValueError, match="seed must be a non-negative integer"):
        optim.optimise(task, "cma-es", budget=1000, seed=-1)
    with pytest.raises(KeyError, match="unknown task"):
        optim.optimise("Stirring", "dp", budget=1000)
    with pytest.raises(ValueError, match="unknown DP technique.*'sharing'; techniques: soft_contact, expanding_region"):
        optim.optimise(task, "dp", budget=1000, without=["sharing"])
    with pytest.raises(ValueError, match="applies to method 'dp' only"):
        optim.optimise(task, "cma-es", budget=1000, without=["attraction"])
    with pytest.raises(ValueError, match="'dp-window' needs a loss that is a mean over the horizon's steps; Mixing"):
        optim.optimise(task, "dp-window", budget=1000)
    with pytest.raises(ValueError, match="cma-es cannot resume a saved state .resumable: dp, dp-h."):
        optim.optimise(task, "cma-es", budget=1000, resume={})


def test_dp_resumed_from_its_saved_state_continues_the_same_run(gathering, tmp_path):
    """A DP run (all its techniques on) resumed from the `progress.state()` of its fourth iteration, through the
    benchmark's snapshot file, makes the same iterations as the run straight through: θ, Adam's moments, the
    expanding region (25, 50, 75, 100 steps of the 100-step horizon, then 100), the attraction's decaying weight and
    the best so far all carry over. Same to float32 rounding, not bit for bit: the backward pass adds into the
    grid's gradients from several threads in no fixed order, so two runs straight through differ too (by 1e-8 to
    3e-8 of the loss after four or five iterations, and θ after the last Adam step by up to 1.8e-5 of the tool's
    top speed, seen here); the resumed run's θ after its step differs from the straight run's by 2.4e-9 of it
    (bound 3e-4), and a resume that dropped Adam's moments steps elsewhere, by 0.12 of it (bound 1e-2). A state of another run is refused by
    the field that differs."""
    from fluidlab_core import benchmark

    task = gathering
    budget = 4 * task.horizon
    straight, states = [], []
    full = dp.run(task, budget, seed=3, callback=lambda p: straight.append(p) or states.append(p.state()))
    spec = {"task": task.name, "method": "dp", "seed": 3, "size": "small", "budget": budget, "out": str(tmp_path)}
    benchmark.save_partial(benchmark.partial_path(spec), spec, states[3], {"curve": [], "eval": 0.0, "wall": 1.0})
    saved, _ = benchmark.load_partial(benchmark.partial_path(spec), spec)
    resumed = []
    again = dp.run(task, budget, seed=3, callback=resumed.append, resume=saved)
    forgetful = []  # the same state without Adam's moments: what the test must tell apart
    dp.run(task, budget, seed=3, callback=forgetful.append,
           resume={**saved, "adam_m": 0 * saved["adam_m"], "adam_v": 0 * saved["adam_v"], "adam_t": 0})
    print(f"\nDP regions straight through {[p.region for p in straight]}, resumed after 4: "
          f"{[p.region for p in resumed]}; last loss straight {straight[-1].loss:.10g}, resumed "
          f"{resumed[-1].loss:.10g}, without Adam's moments {forgetful[-1].loss:.10g}")
    assert [p.region for p in straight] == [25, 50, 75, 100, 100] and len(resumed) == 1
    assert [(p.iteration, p.steps, p.region) for p in resumed] == [(p.iteration, p.steps, p.region) for p in straight[4:]]
    assert resumed[0].loss == pytest.approx(straight[4].loss, rel=1e-6)
    assert resumed[0].best_loss == pytest.approx(straight[4].best_loss, rel=1e-6)
    # where each run would go next: θ after the last Adam step (the first that the moments steer)
    after = {name: runs[-1].state()["theta"] for name, runs in
             (("straight", straight), ("resumed", resumed), ("forgetful", forgetful))}
    off, forgot = (np.abs(after[k] - after["straight"]).max() for k in ("resumed", "forgetful"))
    print(f"largest |Δθ| after the last step against straight through: resumed {off:.3g}, without Adam's moments "
          f"{forgot:.3g} (max tool speed {task.max_tool_speed})")
    assert off < 3e-4 * task.max_tool_speed and forgot > 1e-2 * task.max_tool_speed
    np.testing.assert_allclose(again.theta, full.theta, rtol=0, atol=3e-4 * task.max_tool_speed)
    np.testing.assert_allclose(again.history, full.history, rtol=1e-6)
    assert again.iterations == full.iterations == 5
    with pytest.raises(ValueError, match="the saved DP state is for seed 3, this run has 4"):
        dp.run(task, budget, seed=4, resume=saved)
    with pytest.raises(ValueError, match="holds run 'GatheringEasy.dp.3.small.400', not 'GatheringEasy.dp-h.3"):
        benchmark.load_partial(benchmark.partial_path(spec), {**spec, "method": "dp-h"})


def test_an_interrupted_benchmark_run_resumes_from_its_snapshot(gathering, tmp_path, monkeypatch):
    """A benchmark run of hours must survive an interrupted session: a DP run (the no-expanding-region ablation, two
    whole-horizon iterations of GatheringEasy) stopped by an error after its first iteration leaves its snapshot in
    OUT/partial/ (saved every iteration here: snapshot_minutes 0); the run started again continues there (its
    record says `resumed` at 100 steps, two iterations in all, the curve's checkpoint before the restart kept), and
    the snapshot is deleted once the record is in runs.jsonl (benchmark.finish, which the sweep calls for each run
    that returns). Both runs use this module's task, whose simulators are compiled (run_job would otherwise build
    and compile its own, and reset Taichi for its seed)."""
    import fluidlab_core
    from fluidlab_core import benchmark

    real = optim.optimise

    class Interrupted(Exception):
        pass

    def interrupted_after_one(task, method, budget, callback=None, **kw):
        def cb(p):
            callback(p)  # the run's own callback, which saves the snapshot
            raise Interrupted("the session ended")
        return real(task, method, budget, callback=cb, **kw)

    monkeypatch.setattr(tasks, "make", lambda name, size, **options: gathering)
    monkeypatch.setattr(fluidlab_core, "init", lambda **kw: None)
    spec = {"task": "GatheringEasy", "method": "dp-no-expanding", "seed": 0, "size": "small", "budget": 200,
            "arch": "cpu", "threads": None, "checkpoints": 2, "out": str(tmp_path), "snapshot_minutes": 0.0}
    monkeypatch.setattr(optim, "optimise", interrupted_after_one)
    first = benchmark.run_job(spec)
    monkeypatch.setattr(optim, "optimise", real)
    assert "Interrupted: the session ended" in first["error"]
    snap = benchmark.partial_path(spec)
    state, bench = benchmark.load_partial(snap, spec)
    assert state["steps_used"] == 100 and state["iteration"] == 1 and [c[0] for c in bench["curve"]] == [100]
    rec = benchmark.run_job(spec)
    assert "final_loss" in rec, rec.get("traceback")
    assert rec["resumed"] == [100] and rec["iterations"] == 2 and rec["steps_used"] == 200
    assert [c[0] for c in rec["curve"]] == [100, 200] and rec["curve"][0] == bench["curve"][0]
    assert rec["wall"] >= bench["wall"] and snap.exists()  # kept until the record is in runs.jsonl
    benchmark.finish(tmp_path, rec)
    assert not snap.exists()
    assert [r["key"] for r in benchmark.load_runs(tmp_path / "runs.jsonl")] == [rec["key"]]


def test_dp_windows_cover_the_horizon_once():
    """dp-window's windows (optim/dp.py): consecutive, the last one shorter where the window does not divide the
    horizon; a window outside 1 … horizon is refused by name. Which tasks offer the method follows their loss."""
    from fluidlab_core.optim import dp

    assert dp.windows(250, 60) == [(0, 60), (60, 60), (120, 60), (180, 60), (240, 10)]
    assert dp.windows(5, 5) == [(0, 5)] and dp.windows(3, 1) == [(0, 1), (1, 1), (2, 1)]
    for bad in (0, 6, 2.5):
        with pytest.raises(ValueError, match="gradient window must be a whole number of steps from 1 to the horizon"):
            dp.windows(5, bad)
    offered = {name for name in tasks.names() if tasks.make(name, "small").loss_is_step_mean}
    assert offered == {"GatheringEasy", "GatheringHard", "Transporting", "AirCirculation"}


def test_dp_records_the_techniques_it_used_and_a_task_can_decline_the_expanding_region(gathering):
    """Each DP technique is switchable and the run's settings say which were on: gradient sharing exists only
    in tasks that define it (Pouring, Transporting), and Pouring declines the expanding region (its goal is a
    final state after a detour). One iteration of GatheringEasy (whose simulators the test above compiled)."""
    task = gathering
    on = optim.optimise(task, "dp", budget=task.horizon, max_iterations=1).metadata["settings"]
    assert on["attraction"] and on["expanding_region"] and not on["gradient_sharing"]  # no sharing term here
    off = optim.optimise(task, "dp", budget=task.horizon, max_iterations=1,
                         without=["attraction", "expanding_region"]).metadata["settings"]
    assert not off["attraction"] and not off["expanding_region"]
    pouring = tasks.make("Pouring", "small")
    assert not pouring.expanding_region and pouring.gradient_sharing(1.0) is not None
    assert tasks.make("Transporting", "small").gradient_sharing(1.0) is not None


def test_a_callback_stops_the_run():
    task = tasks.make("Mixing", "small")
    calls = []
    traj = optim.optimise(task, "cma-es", budget=50 * task.horizon, seed=0,
                          callback=lambda p: calls.append(p) or True)
    assert len(calls) == 1 and traj.metadata["steps_used"] < 50 * task.horizon


def test_the_temporally_expanding_region_grows_to_the_whole_horizon(gathering):
    """DP's expanding region (the paper's technique): the first iterations optimise a quarter of the horizon,
    the region grows by a quarter at a time and never shrinks, it covers the whole horizon by half the budget,
    each iteration costs its region in simulated steps, and only whole-horizon losses count as the best.
    (GatheringEasy: its periodic policy's period, 20 steps, is under a quarter of its 100-step horizon; the
    simulator is the one the test above compiled.)"""
    task = gathering
    seen = []
    budget = 6 * task.horizon
    dp.run(task, budget=budget, seed=0, callback=seen.append, options=dp.DPOptions(attraction=False))
    regions = [p.region for p in seen]
    quarter = int(np.ceil(0.25 * task.horizon))
    print(f"\nDP regions on GatheringEasy (horizon {task.horizon}): {regions}")
    assert regions[0] == quarter
    assert all(b >= a for a, b in zip(regions, regions[1:]))
    assert set(np.diff(regions)) <= {0, quarter} | {task.horizon - r for r in regions}
    assert regions[-1] == task.horizon
    half = next(p for p in seen if p.steps >= budget // 2)
    assert half.region == task.horizon
    steps = [p.steps for p in seen]
    assert np.diff([0] + steps).tolist() == regions
    assert all(not np.isfinite(p.best_loss) for p, r in zip(seen, regions) if r < task.horizon and
               all(q < task.horizon for q in regions[: seen.index(p) + 1]))


def test_dp_free_descends_over_knots_that_span_the_whole_horizon(gathering):
    """"dp-free": DP (its techniques on) over cma-es-free's knots, 8 per axis over the whole horizon, where the task
    has the paper's periodic stroke. On GatheringEasy its parametrisation is cma-es-free's (18 parameters: 8 knots
    on each of the 2 action axes and the paddle's start), its region starts at a quarter of the horizon (25, 50,
    75, 100 steps in a budget of 2.5 rollouts: 250 steps), the paddle need not come back to where it began (under
    the stroke it does every 20 steps), and its gradient steps move the knots: each knot's change over the run is
    what Adam's steps allow (each under lr (1 − β1)/√(1 − β2) = 3.16 lr, Kingma & Ba 2015, §2.1, with lr 0.1 of the
    tool's top speed), and at least one moved by over half of lr. It records its method in the trajectory and in the
    DP state it hands out (so that a snapshot of a dp run is not taken for it)."""
    task = gathering
    seen, states = [], []
    traj = optim.optimise(task, "dp-free", budget=250, seed=2,
                          callback=lambda p: seen.append(p) or states.append(p.state()))
    settings = traj.metadata["settings"]
    assert traj.method == "dp-free" and settings["parametrisation"] == "8 knots per axis, piecewise linear"
    assert [p.region for p in seen] == [25, 50, 75, 100] and traj.metadata["steps_used"] == 250
    assert settings["soft_contact"] and settings["expanding_region"] and settings["attraction"]
    state = states[-1]
    assert state["method"] == "dp-free" and state["n_params"] == 8 * 2 + 2
    moved = np.abs(state["theta"] - states[0]["theta"])[:16]  # over the last 3 of the 4 Adam steps
    lr = 0.1 * task.max_tool_speed  # Adam's step on the knots (DPOptions.learning_rate)
    print(f"\ndp-free on GatheringEasy: regions {[p.region for p in seen]}, largest knot change over the last 3 "
          f"steps {moved.max() / lr:.3g} lr")
    assert 0.5 * lr < moved.max() <= 3 * lr * 0.1 / np.sqrt(1e-3) * (1 + 1e-6)
    assert np.isfinite(traj.metadata["final_loss"]) and len(traj.loss_history) == 1
    twists = traj.twists
    assert np.abs(twists.sum(axis=0)).max() > 0.01 * float(np.abs(twists).max()) * task.horizon
    with pytest.raises(ValueError, match="needs the simulator's gradients"):
        optim.optimise(tasks.make("GatheringEasy", "small", pressure="projection"), "dp-free", budget=100)
