"""The optimiser benchmark: tasks × methods × seeds at one budget, as independent jobs, resumable.

    python -m fluidlab_core.benchmark [--tasks ...] [--methods dp dp-h cma-es sac ppo pods] [--seeds 0 1 2]
        [--rollouts 150] [--size small] [--out bench/results/benchmark_small] [--jobs 2] [--ray-address ADDR]
        [--pressure state|projection]
    fluidlab benchmark ...            (the same)

What a run is. One optimisation of one task by one method (optim.METHODS: the paper's six by default, sac, ppo
and pods needing the `rl` extra, and dp-window, cma-es-free and dp-free, ours, when named; ABLATIONS below: DP with techniques switched
off) from one seed, with a budget of `--rollouts` × the task's horizon simulated steps. It is the same for
every method: a DP iteration over r steps counts r, an RL environment step 1, a PODS iteration 2 rollouts;
DP's backward pass costs more wall time, which is measured too. A CMA-ES run must complete at least
`--min-generations` generations (default 30). Its population is chosen to fit (optim/cmaes.py), and a budget
that cannot hold them is refused before anything runs. Every run is judged on the task's reference
physics (hard contact): its final loss and the reward return r = Σ_k (c1 − c2 ℓ_k), with c1, c2 per task
(Task.reward_c1, reward_c2; the table states them).

Curves. While a run goes on, its best iterate so far is evaluated on the reference physics at `--checkpoints`
evenly spaced points of the budget. "Best" is by the optimiser's own loss (DP's is on its soft physics), so the
value at a checkpoint is what the method would return if stopped there, judged on the reference; it can rise
from one checkpoint to the next, and the final loss is the last one's, never the curve's minimum (choosing the
minimum would select on the judging physics). These evaluations are bookkeeping: they count neither in the
budget nor in the run's wall time. So every method's curve is on the same physics and the same axis: the
reference loss of the best iterate against simulated steps, and against the run's own wall time. A curve has
flattened when its last 20 % of the budget lowered it by less than 1 % of its loss there; the table says how
many seeds did.

Jobs. With Ray installed (`pip install ray`, part of the test extras), runs are Ray tasks. On one machine a
local Ray starts with `--jobs` CPUs (default: all cores), one run per CPU, and each run's Taichi gets
`--threads` threads (default: cores / jobs). Pass `--ray-address auto` (or host:port) to use a running
cluster: start it with `ray start --head` here and `ray start --address HOST:6379` on the other machines. Each
machine needs only this package installed. Without Ray, runs go to a pool of `--jobs` processes.

The liquid. `--pressure projection` runs the tasks on the projected, incompressible liquid (engine/projection.py,
which floats bodies at Archimedes' depth) instead of the default weakly compressible one: forward only, so the
gradient methods (dp, dp-h, pods, dp-window, dp-free and DP's ablations) are refused there with the reason, and CMA-ES, SAC
and PPO run. Its runs' keys and file names end in 'projection', their records say `pressure`, the default folder is
bench/results/benchmark_SIZE_projection, and `--reevaluate` replays each run on the liquid it ran on.

Re-evaluating. `--reevaluate` replays every finished run's trajectory on the engine installed now and appends the
losses to OUT/reevaluated.jsonl (resumable; delete it to re-measure after another engine change); the table then
shows each method's loss 'now' beside the recorded one, for a sweep whose runs span engine changes.

Merging. `--merge SRC` adds the finished runs of another sweep folder (runs beside other work, or on another
machine) to OUT with their trajectories, skipping those OUT has; it refuses a folder whose still tool reads another
loss (other physics). Appends to runs.jsonl hold a lock, so a merge and a running sweep never interleave a line.

Resuming. Each finished run is appended to OUT/runs.jsonl as soon as it returns. A sweep started again with the
same OUT skips every run already there, so an interrupted sweep never repeats or loses one. A run of a method in
optim.RESUMABLE (DP, DP-H, DP's ablations) also saves its state every `--snapshot-minutes` (default 5) to
OUT/partial/<run>.npz (the optimiser's state and the run's curve and times so far, written atomically); a sweep
started again continues such a run from its last snapshot instead of from the start, and the record says so
(`resumed`: the steps at each restart; its wall time is the sum of its sessions'). The snapshot is deleted once the
run's record is in runs.jsonl. Other methods start an interrupted run again. Then come, over every run finished
in OUT (this sweep's and earlier ones'), the table (OUT/table.txt, and OUT/table2.md in the layout of the paper's
Table 2), one plot per task (OUT/curves_<task>.png), an overview of every task (OUT/overview.png) and the
trajectories (OUT/trajectories/).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

# DP ablations: benchmark methods that run DP with techniques switched off (optim.TECHNIQUES)
ABLATIONS = {"dp-no-sharing": ("gradient_sharing",), "dp-no-attraction": ("attraction",),
             "dp-neither": ("gradient_sharing", "attraction"), "dp-no-soft": ("soft_contact",),
             "dp-no-expanding": ("expanding_region",)}
STILL = "still"  # not an optimiser: the tool kept still (zero twists), the loss every method should beat
FLAT_WINDOW = 0.2  # the last share of the budget a flattened curve improves by less than FLAT_TOLERANCE
FLAT_TOLERANCE = 0.01


def run_key(spec: dict) -> str:
    """The identity of a run in runs.jsonl (a run on the projected liquid ends in '|projection'; the default
    liquid's keys are those of the sweeps before the option)."""
    key = f"{spec['task']}|{spec['method']}|{spec['seed']}|{spec['size']}|{spec['budget']}"
    pressure = spec.get("pressure", "state")
    return key if pressure == "state" else f"{key}|{pressure}"


def _record(spec: dict, task=None, **fields) -> dict:
    """A run's record: its identity, where it ran, the task's constants when built, then `fields`."""
    rec = {**{k: spec[k] for k in ("task", "method", "seed", "size", "budget")}, "key": run_key(spec),
           "host": os.uname().nodename}
    if spec.get("pressure", "state") != "state":
        rec["pressure"] = spec["pressure"]
    if task is not None:
        rec.update(horizon=task.horizon, reward_c1=task.reward_c1, reward_c2=task.reward_c2,
                   threads=spec.get("threads"))
    return {**rec, **fields}


PARTIAL_FORMAT = "fluidlab-benchmark-partial"


def run_name(spec: dict) -> str:
    """A run's file name: TASK_METHOD_seedS_SIZE, with _projection on the projected liquid."""
    name = f"{spec['task']}_{spec['method']}_seed{spec['seed']}_{spec['size']}"
    pressure = spec.get("pressure", "state")
    return name if pressure == "state" else f"{name}_{pressure}"


def partial_path(spec: dict) -> Path:
    """Where a resumable run keeps its latest snapshot."""
    return Path(spec["out"]) / "partial" / f"{run_name(spec)}.npz"


def save_partial(path: Path, spec: dict, opt_state: dict, bench: dict):
    """Write a run's snapshot atomically: the optimiser's state (its arrays as arrays, the rest as JSON) and the
    benchmark's own bookkeeping (curve, wall and evaluation seconds, restarts)."""
    import io

    from fluidlab_core.files import write_atomic

    arrays = {k: v for k, v in opt_state.items() if isinstance(v, np.ndarray)}
    meta = {"format": PARTIAL_FORMAT, "key": run_key(spec),
            "optimiser": {k: v for k, v in opt_state.items() if k not in arrays}, "bench": bench}
    buf = io.BytesIO()
    np.savez(buf, meta=np.array(json.dumps(meta)), **{f"a_{k}": v for k, v in arrays.items()})
    write_atomic(path, buf.getvalue())


def load_partial(path: Path, spec: dict) -> tuple[dict, dict]:
    """(optimiser state, bookkeeping) of a snapshot; refuses one of another run, naming both."""
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        arrays = {k[2:]: z[k] for k in z.files if k.startswith("a_")}
    if meta.get("format") != PARTIAL_FORMAT:
        raise ValueError(f"{path} is not a benchmark snapshot (format {meta.get('format')!r})")
    if meta.get("key") != run_key(spec):
        raise ValueError(f"{path} holds run {meta.get('key')!r}, not {run_key(spec)!r}: delete it or use another --out")
    return {**meta["optimiser"], **arrays}, meta["bench"]


def finish(out: Path, rec: dict):
    """Append a run's record to OUT/runs.jsonl; a finished run's snapshot is then no longer needed."""
    _append(Path(out) / "runs.jsonl", rec)
    if "final_loss" in rec:
        partial_path({**rec, "out": str(Path(out).resolve())}).unlink(missing_ok=True)


def run_job(spec: dict) -> dict:
    """One run (in a worker process): optimise, evaluate the best so far at the checkpoints, save the trajectory.
    Returns the run's record; an error becomes a record with 'error' (the sweep goes on)."""
    import traceback

    t_start = time.perf_counter()
    try:
        import fluidlab_core
        from fluidlab_core import optim, tasks
        from fluidlab_core.files import write_atomic
        from fluidlab_core.trajectory_store import TrajectoryStore, report_path

        fluidlab_core.init(arch=spec["arch"], precision="f32", cpu_threads=spec.get("threads"))
        task = tasks.make(spec["task"], size=spec["size"], pressure=spec.get("pressure", "state"))
        budget = int(spec["budget"])
        if spec["method"] == STILL:  # the reference row: the tool kept still, one rollout
            t0 = time.perf_counter()
            out = task.evaluate(np.zeros((task.horizon, task.n_actions)))
            wall = time.perf_counter() - t0
            loss = float(out["loss"])
            return _record(spec, task, final_loss=loss, steps_used=task.horizon, iterations=0, settings={},
                           curve=[[task.horizon, loss, round(wall, 3)]], wall=round(wall, 2), eval_seconds=0.0,
                           **{"return": float(out["return"])})
        marks = [int(round(budget * (i + 1) / spec["checkpoints"])) for i in range(spec["checkpoints"])]
        ref = task.simulator(grad=False, contact="hard")
        curve, spent, resumed = [], {"eval": 0.0}, []
        base_method = "dp" if spec["method"] in ABLATIONS else spec["method"]
        snap_path = partial_path(spec) if base_method in optim.RESUMABLE else None
        snap_every = 60.0 * float(spec.get("snapshot_minutes", 5.0))
        resume, before = None, 0.0
        if snap_path is not None and snap_path.exists():
            resume, bench = load_partial(snap_path, spec)
            curve, spent["eval"], before = bench["curve"], float(bench["eval"]), float(bench["wall"])
            resumed = bench.get("resumed", []) + [int(resume["steps_used"])]
            marks = [m for m in marks if m > int(resume["steps_used"])]
            print(f"  {spec['task']} {spec['method']} seed {spec['seed']}: resuming from its snapshot at "
                  f"{100 * int(resume['steps_used']) / budget:.0f} % of the budget ({snap_path})",
                  file=sys.stderr, flush=True)
        t0 = time.perf_counter() - before - spent["eval"]  # wall below = this session's and the earlier ones'
        last_snap = [time.perf_counter()]

        def evaluate(theta, par):
            e0 = time.perf_counter()
            loss = task.evaluate(par.actions(theta), tool_position=par.tool_position(theta), sim=ref,
                                 rewards=False)["loss"]
            spent["eval"] += time.perf_counter() - e0
            return float(loss)

        def callback(p):
            if marks and p.steps >= marks[0]:  # one evaluation for every checkpoint this iteration passed
                while marks and p.steps >= marks[0]:
                    marks.pop(0)
                wall = time.perf_counter() - t0 - spent["eval"]
                curve.append([int(p.steps), evaluate(p.best_theta, p.parametrisation), round(wall, 3)])
                # a run can take hours (Pouring's DP: about 2.5 h on one core): say how far it is at each checkpoint
                print(f"  {spec['task']} {spec['method']} seed {spec['seed']}: {100 * p.steps / budget:.0f} % of the "
                      f"budget, best iterate's loss {curve[-1][1]:.4e} on the reference physics, {wall / 60:.1f} min",
                      file=sys.stderr, flush=True)
            if snap_path is not None and p.state is not None and time.perf_counter() - last_snap[0] >= snap_every:
                wall = time.perf_counter() - t0 - spent["eval"]
                save_partial(snap_path, spec, p.state(), {"curve": curve, "eval": spent["eval"], "wall": wall,
                                                          "resumed": resumed})
                last_snap[0] = time.perf_counter()
            return False

        method, without = (("dp", ABLATIONS[spec["method"]]) if spec["method"] in ABLATIONS
                           else (spec["method"], ()))
        traj = optim.optimise(task, method, budget, seed=int(spec["seed"]), callback=callback, without=without,
                              min_generations=spec.get("min_generations"), resume=resume)  # (CMA-ES's only)
        wall = time.perf_counter() - t0 - spent["eval"]
        final = float(traj.metadata["final_loss"])
        if not curve or curve[-1][0] < traj.metadata["steps_used"]:
            curve.append([int(traj.metadata["steps_used"]), final, round(wall, 3)])
        store = TrajectoryStore(Path(spec["out"]) / "trajectories")
        name = run_name(spec)
        path = traj.save(store.new_path(task.name, name, overwrite=True))
        record = _record(spec, task, final_loss=final, steps_used=int(traj.metadata["steps_used"]),
                         iterations=int(traj.metadata["iterations"]), settings=traj.metadata.get("settings", {}),
                         curve=curve, wall=round(wall, 2), eval_seconds=round(spent["eval"], 2),
                         trajectory=str(path.relative_to(Path(spec["out"]))),
                         **{"return": float(traj.metadata["return"])}, **({"resumed": resumed} if resumed else {}))
        # beside the trajectory, as `fluidlab optimise` writes it (bench/ship_best.py copies both)
        write_atomic(report_path(path), json.dumps(record, indent=1).encode())
        return record
    except Exception as err:  # noqa: BLE001 - one failed run must not end the sweep; the record says why
        return _record(spec, error=f"{type(err).__name__}: {err}", traceback=traceback.format_exc()[-3000:],
                       wall=round(time.perf_counter() - t_start, 2))


def load_runs(path: Path) -> list[dict]:
    """The records of runs.jsonl (a line cut short by a crash while it was written is skipped)."""
    runs = []
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                runs.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return runs


class _Locked:
    """An exclusive lock on runs.jsonl for as long as the `with` block holds it open for appending: sweeps and merges
    into one folder write whole records and never interleave (POSIX advisory lock; elsewhere, no lock)."""

    def __init__(self, path: Path):
        self.path = Path(path)

    def __enter__(self):
        self.file = open(self.path, "a")
        try:
            import fcntl

            fcntl.flock(self.file.fileno(), fcntl.LOCK_EX)
        except ImportError:
            pass
        return self.file

    def __exit__(self, *exc):
        self.file.flush()
        os.fsync(self.file.fileno())
        self.file.close()  # closing releases the lock


def _append(path: Path, record: dict):
    with _Locked(path) as f:
        f.write(json.dumps(record) + "\n")


# Still-tool losses that agree to this relative tolerance are one physics. Another CPU's float32 rounding (a
# vector width, fused multiply-adds) moves a still rollout's loss by up to about 6e-6 (Pouring's 8 s: 1.2e-6
# between the machine of its sweep and an Intel Xeon with AVX-512, 2026-12-01; AirCirculation's 5.9e-6 on
# re-evaluation, reevaluated.jsonl); the engine changes re-evaluated there moved them by 6.2e-3 to 3.6e-2.
STILL_RTOL = 1e-4


def merge(src: Path, out: Path, log=print) -> list[dict]:
    """Add the finished runs of the sweep folder SRC to OUT: each record of SRC/runs.jsonl with a final loss whose key
    OUT/runs.jsonl lacks is appended to it, after its trajectory and report are copied to the same relative path
    under OUT. Runs done in separate folders (beside other work, on other machines) join one table this way.
    Refuses, before writing anything, a SRC whose still tool reads another loss than OUT's (beyond STILL_RTOL, which
    another CPU's rounding stays within) for the same task, size and budget (the runs were made on other physics:
    `--reevaluate` puts them on one engine, and then the re-evaluated still losses are compared),
    and a record whose trajectory file is missing. Returns the records
    added."""
    from fluidlab_core.files import write_atomic
    from fluidlab_core.trajectory_store import report_path

    src, out = Path(src), Path(out)
    src_runs = [r for r in load_runs(src / "runs.jsonl") if "final_loss" in r]
    if not src_runs:
        raise ValueError(f"nothing to merge: {src / 'runs.jsonl'} holds no finished run")
    if src.resolve() == out.resolve():
        raise ValueError(f"cannot merge {src} into itself")
    out.mkdir(parents=True, exist_ok=True)
    def still_now(folder: Path, r: dict) -> float:
        """The still tool's loss on the engine the folder's runs were last put on: the --reevaluate figure when
        there is one, else the recorded one."""
        again = {x["key"]: x for x in load_runs(folder / REEVALUATED) if "key" in x}
        return float(again[r["key"]]["final_loss_now"]) if r["key"] in again else float(r["final_loss"])

    with _Locked(out / "runs.jsonl") as f:
        have = {r["key"]: r for r in load_runs(out / "runs.jsonl") if "final_loss" in r}
        for r in src_runs:
            mine = have.get(r["key"])
            if r["method"] != STILL or mine is None:
                continue
            theirs_now, mine_now = still_now(src, r), still_now(out, mine)
            if not np.isclose(theirs_now, mine_now, rtol=STILL_RTOL, atol=0.0):
                raise ValueError(f"{r['task']} ({r['size']}, budget {r['budget']}): the still tool's loss is "
                                 f"{theirs_now:.6e} in {src} and {mine_now:.6e} in {out}; their runs "
                                 f"were made on different physics (run --reevaluate on both first)")
        todo = [r for r in src_runs if r["key"] not in have]
        for r in todo:
            if r["method"] != STILL and not (src / r.get("trajectory", "")).is_file():
                raise ValueError(f"{r['key']}: its trajectory {src / r.get('trajectory', '?')} is missing")
        for r in todo:
            if r["method"] != STILL:
                traj = Path(r["trajectory"])
                for rel in (traj, report_path(traj)):
                    if (src / rel).is_file():
                        (out / rel).parent.mkdir(parents=True, exist_ok=True)
                        write_atomic(out / rel, (src / rel).read_bytes())
            f.write(json.dumps(r) + "\n")
            log(f"  merged {r['key']}: final loss {r['final_loss']:.4e}")
    log(f"merged {len(todo)} runs from {src} into {out} ({len(src_runs) - len(todo)} already there)")
    return todo


def flattened(curve) -> bool | None:
    """Whether the last FLAT_WINDOW of the budget lowered the run's loss (`_loss_at`: the reference loss of its best
    iterate) by less than FLAT_TOLERANCE of it; None for a curve too short to say. A curve that rose over the
    window has flattened."""
    if len(curve) < 3:
        return None
    cut = curve[-1][0] * (1.0 - FLAT_WINDOW)
    if curve[0][0] > cut:  # no checkpoint before the window
        return None
    ref = _loss_at(curve, 0, cut)
    return bool(ref - curve[-1][1] <= FLAT_TOLERANCE * max(abs(ref), 1e-30))


def _loss_at(curve, axis: int, at: float) -> float:
    """A run's loss by `at` on axis 0 (steps) or 2 (wall s): the reference loss of its best iterate at its last
    checkpoint by then, what it would have returned if stopped there (not the minimum over its checkpoints,
    which would choose on the judging physics); NaN before its first checkpoint."""
    vals = [c[1] for c in curve if c[axis] <= at + 1e-9]
    return float(vals[-1]) if vals else float("nan")


def _liquid(runs: list[dict]) -> str:
    """The tables' note of the liquid the runs ran on, where it is not the default."""
    kinds = sorted({r.get("pressure", "state") for r in runs})
    return "" if kinds == ["state"] else f", liquid pressure {' and '.join(kinds)}"


def table(runs: list[dict], refused: list[dict] | None = None, now: dict | None = None) -> str:
    """now: {run key: final loss re-evaluated on today's engine} (`reevaluate`); shown after each row whose seeds
    all have one."""
    ok = [r for r in runs if "final_loss" in r]
    now = now or {}
    w = max([8] + [len(r["method"]) for r in runs])  # the method column, as wide as the longest name
    lines = []
    if ok:
        lines.append(f"Final loss and reward return on the reference physics (hard contact), mean ± std over seeds; "
                     f"size {ok[0]['size']}{_liquid(ok)}, the budget per run under each task. Lower loss, higher return "
                     f"is better.")
        lines.append("A run's loss at a point of its budget is the reference loss of its best iterate (best by the "
                     "optimiser's own loss) at its last checkpoint by then. 'flat': seeds whose loss fell < 1 % over "
                     "the last 20 % of the budget. 'loss @ equal wall': each method's loss by the wall time of the "
                     "task's fastest method ('not reached': a seed had no checkpoint by then). Wall times include "
                     "compiling or loading the kernels (the first runs of a sweep compile; later ones load Taichi's "
                     "cache). 'ms/step': wall time per simulated step of the budget, the optimiser's cost beside "
                     "the physics (DP's includes its backward pass).")
        if now:
            lines.append("'now': the mean final loss of the same trajectories replayed on today's engine "
                         "(--reevaluate, reevaluated.jsonl); the recorded one is what the run measured when it ran.")
    for task in dict.fromkeys(r["task"] for r in runs):
        tr = [r for r in ok if r["task"] == task]
        if tr:
            lines.append("")
            lines.append(f"{task}: horizon {tr[0]['horizon']} steps, budget {tr[0]['budget']} steps "
                         f"({tr[0]['budget'] // tr[0]['horizon']} rollouts), reward r = {tr[0]['reward_c1']:g} − "
                         f"{tr[0]['reward_c2']:g} ℓ per step")
            lines.append(f"  {'method':<{w}} {'final loss':>24} {'return':>20} {'n':>2} {'flat':>5} {'wall s':>8} "
                         f"{'ms/step':>8} {'loss @ equal wall':>18}")
        methods = list(dict.fromkeys(r["method"] for r in runs if r["task"] == task))
        walls = {m: np.mean([r["wall"] for r in tr if r["method"] == m]) for m in methods
                 if m != STILL and any(r["method"] == m for r in tr)}
        t_equal = min(walls.values()) if walls else float("nan")
        for m in methods:
            mr = [r for r in tr if r["method"] == m]
            failed = [r for r in runs if r["task"] == task and r["method"] == m and "error" in r]
            if not mr:
                why = failed[0]["error"][:110] if failed else "no finished run"
                lines.append(f"  {m:<{w}} ({why})")
                continue
            f = np.array([r["final_loss"] for r in mr])
            ret = np.array([r["return"] for r in mr])
            again = [now[r["key"]] for r in mr if r["key"] in now]
            now_text = f"  now {np.mean(again):.4e}" if again and len(again) == len(mr) else ""
            if m == STILL:
                lines.append(f"  {'still':<{w}} {f.mean():>12.4e} {'':<11} {ret.mean():>9.3f} {'':<10} "
                             f"(the tool kept still: the loss to beat){now_text}")
                continue
            flat = [flattened(r["curve"]) for r in mr]
            reached = [v for v in (_loss_at(r["curve"], 2, t_equal) for r in mr) if np.isfinite(v)]
            at_equal = f"{np.mean(reached):.4e}" if len(reached) == len(mr) else "not reached"
            lines.append(f"  {m:<{w}} {f.mean():>12.4e} ± {f.std():<9.2e} {ret.mean():>9.3f} ± {ret.std():<8.3f} "
                         f"{len(mr):>2} {sum(1 for x in flat if x)}/{len(mr):<3} {walls[m]:>8.0f} "
                         f"{1e3 * np.mean([r['wall'] / r['steps_used'] for r in mr]):>8.1f} {at_equal:>18}"
                         + (f"  ({len(failed)} failed)" if failed else "") + now_text)
    for r in refused or []:
        lines.append(f"refused: {r['task']} {r['method']}: {r['why']}")
    return "\n".join(lines)


def paper_table(runs: list[dict], now_returns: dict | None = None) -> str:
    """The final-reward table in the layout of the paper's Table 2, as Markdown: a row per method, a column per
    task, the reward return on the reference physics as mean ± std over seeds (the seed count where it is not the
    most common one), and the reward constants under it. now_returns {key: return}: the returns of runs replayed
    on a later engine (--reevaluate), which replace the recorded ones (a cell marked *), so that runs made before
    and after an engine change meet on one physics."""
    now_returns = now_returns or {}
    ok = [r for r in runs if "final_loss" in r]
    if not ok:
        return ""
    task_names = list(dict.fromkeys(r["task"] for r in ok))
    methods = [STILL, *[m for m in dict.fromkeys(r["method"] for r in ok) if m != STILL]]
    counts = [len([r for r in ok if r["task"] == t and r["method"] == m]) for t in task_names for m in methods
              if m != STILL]
    usual = max(set(counts), key=counts.count) if counts else 0
    lines = ["| method | " + " | ".join(task_names) + " |", "|---" * (len(task_names) + 1) + "|"]
    for m in methods:
        cells = []
        for t in task_names:
            mine = [r for r in ok if r["task"] == t and r["method"] == m]
            ret = np.array([now_returns.get(r.get("key"), r["return"]) for r in mine])
            star = "*" if any(r.get("key") in now_returns for r in mine) else ""
            if len(ret) == 0:
                cells.append("–")
            elif m == STILL:
                cells.append(f"{ret.mean():.1f}{star}")
            else:
                cells.append(f"{ret.mean():.1f} ± {ret.std():.1f}{star}"
                             + (f" (n={len(ret)})" if len(ret) != usual else ""))
        lines.append(f"| {'still tool' if m == STILL else m} | " + " | ".join(cells) + " |")
    consts = []
    for t in task_names:
        r = next(r for r in ok if r["task"] == t)
        consts.append(f"{t} {r['reward_c1']:g} − {r['reward_c2']:g} ℓ over {r['horizon']} steps")
    lines.append("")
    lines.append(f"Reward return Σ_k (c1 − c2 ℓ_k) on the reference physics, mean ± std over {usual} seeds, "
                 f"size {ok[0]['size']}{_liquid(ok)}, {ok[0]['budget'] // ok[0]['horizon']} rollouts per run. Per task: "
                 + "; ".join(consts) + "."
                 + (" *: replayed on a later engine (--reevaluate, reevaluated.jsonl), not the return recorded when "
                    "the run ran." if any(r.get("key") in now_returns for r in ok) else ""))
    return "\n".join(lines)


def plot(runs: list[dict], out: Path) -> list[Path]:
    """One PNG per task: the reference loss of the best iterate against simulated steps and against wall time,
    a line per method (the mean over seeds) with a band from the best to the worst seed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    ok = [r for r in runs if "final_loss" in r and r.get("curve")]
    for task in dict.fromkeys(r["task"] for r in ok):
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for m in dict.fromkeys(r["method"] for r in ok if r["task"] == task):
            mr = [r for r in ok if r["task"] == task and r["method"] == m]
            if m == STILL:
                for ax in axes:
                    ax.axhline(mr[0]["final_loss"], color="grey", linestyle="--", label="tool kept still")
                continue
            for ax, axis, label in ((axes[0], 0, "simulated steps"), (axes[1], 2, "wall time (s)")):
                top = max(r["curve"][-1][axis] for r in mr)
                grid = np.linspace(0, top, 60)[1:]
                ys = np.array([[_loss_at(r["curve"], axis, g) for g in grid] for r in mr])
                keep = np.isfinite(ys).all(axis=0)  # from where every seed has a point
                ys, grid = ys[:, keep], grid[keep]
                line, = ax.plot(grid, ys.mean(axis=0), label=f"{m} ({len(mr)} seeds)")
                ax.fill_between(grid, ys.min(axis=0), ys.max(axis=0), color=line.get_color(), alpha=0.2)
                ax.set_xlabel(label)
                ax.set_ylabel("loss of the best iterate (reference physics)")
        axes[0].set_title(f"{task}: loss vs simulated steps")
        axes[1].set_title(f"{task}: loss vs wall time")
        axes[0].legend()
        fig.tight_layout()
        path = out / f"curves_{task}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)
    overview = _overview(ok, out, plt)
    return paths + ([overview] if overview else [])


def _overview(ok: list[dict], out: Path, plt) -> Path | None:
    """One figure for the README: a panel per task, each method's improvement on the still tool against the share
    of the budget, (L_still − L) / |L_still| averaged over seeds, L the reference loss of the best iterate (higher
    is better; 0 is the still tool, 1 a loss of zero; it reads the same for Mixing, whose loss is negative)."""
    task_names = [t for t in dict.fromkeys(r["task"] for r in ok)
                  if any(r["task"] == t and r["method"] == STILL for r in ok)]
    methods = [m for m in dict.fromkeys(r["method"] for r in ok) if m != STILL]
    if not task_names or not methods:  # nothing beside the still tool (every method refused): nothing to draw
        return None
    cols = min(4, len(task_names))
    rows = -(-len(task_names) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.0 * rows), squeeze=False)
    colors = {m: f"C{i}" for i, m in enumerate(methods)}
    for ax, task in zip(axes.flat, task_names):
        still = next(r for r in ok if r["task"] == task and r["method"] == STILL)["final_loss"]
        for m in methods:
            mr = [r for r in ok if r["task"] == task and r["method"] == m]
            if not mr:
                continue
            grid = np.linspace(0.0, 1.0, 41)[1:]
            ys = np.array([[_loss_at(r["curve"], 0, g * r["budget"]) for g in grid] for r in mr])
            keep = np.isfinite(ys).all(axis=0)
            gain = (still - ys[:, keep].mean(axis=0)) / abs(still)
            ax.plot(grid[keep], gain, color=colors[m], label=m)
        ax.axhline(0.0, color="grey", linestyle="--", linewidth=0.8)
        ax.set_title(task, fontsize=10)
        ax.set_xlabel("share of the budget", fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(task_names):]:
        ax.axis("off")
    axes.flat[0].set_ylabel("improvement on the still tool", fontsize=8)
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(methods), fontsize=8)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    path = out / "overview.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def die_with_parent():
    """Make this process receive SIGTERM when its parent dies (Linux prctl PR_SET_PDEATHSIG; elsewhere a no-op).
    The process pool's workers call it first: without it, a sweep killed by SIGTERM or SIGKILL left its running
    job's worker computing on, unseen, for up to the length of the run (its result was never recorded)."""
    import ctypes
    import signal

    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        return
    if os.getppid() == 1:  # the parent died before the call
        os.kill(os.getpid(), signal.SIGTERM)


def _executor(jobs: int, threads: int, ray_address: str | None, use_ray: bool):
    """(submit(spec) -> handle, wait(handles) -> (done record, remaining handles), shutdown)."""
    if use_ray:
        import ray

        owned = not ray.is_initialized()  # a caller's Ray session (and its warm workers) is used and left running
        if owned and ray_address:
            ray.init(address=ray_address, log_to_driver=False, configure_logging=False)
        elif owned:
            ray.init(num_cpus=jobs, include_dashboard=False, log_to_driver=False, configure_logging=False)
        remote = ray.remote(num_cpus=1, max_retries=0)(run_job)

        def submit(spec):
            return remote.options(runtime_env={"env_vars": {"FLUIDLAB_CPU_THREADS": str(threads)}}).remote(spec)

        def wait(handles):
            done, rest = ray.wait(handles, num_returns=1)
            return ray.get(done[0]), rest

        return submit, wait, (ray.shutdown if owned else (lambda: None))
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor
    from concurrent.futures import wait as futures_wait

    pool = ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn"), initializer=die_with_parent)

    def wait_pool(handles):
        done, rest = futures_wait(handles, return_when=FIRST_COMPLETED)
        first = next(iter(done))
        return first.result(), [h for h in handles if h is not first]

    return (lambda spec: pool.submit(run_job, spec)), wait_pool, (lambda: pool.shutdown(wait=True))


def sweep(tasks_: list[str], methods: list[str], seeds: list[int], rollouts: int, size: str, out: Path,
          jobs: int | None = None, threads: int | None = None, ray_address: str | None = None,
          use_ray: bool | None = None, min_generations: int = 30, checkpoints: int = 10, arch: str = "cpu",
          log=print, baseline: bool = True, snapshot_minutes: float = 5.0, pressure: str = "state") -> list[dict]:
    """Run what is not yet in OUT/runs.jsonl, append each run as it finishes, then write the table and plots.
    pressure: the tasks' liquid, "state" (default) or "projection" (forward only: the gradient methods are refused
    there, each with the reason, and the sweep goes on with the others). Returns every record of the sweep
    (finished before or now)."""
    from fluidlab_core import optim, tasks
    from fluidlab_core.optim import cmaes

    cores = os.cpu_count() or 1
    jobs = max(1, int(jobs or cores))
    threads = max(1, int(threads or cores // jobs))
    if use_ray is None:
        try:
            import ray  # noqa: F401

            use_ray = True
        except ImportError:
            use_ray = False
    known = (*optim.METHODS, *ABLATIONS)
    unknown = [m for m in methods if m not in known]
    if unknown:
        raise ValueError(f"unknown method(s) {', '.join(unknown)}; methods: {', '.join(known)}")
    out.mkdir(parents=True, exist_ok=True)
    runs_path = out / "runs.jsonl"
    specs, refused = [], []
    for name in tasks_:
        task = tasks.make(name, size=size, pressure=pressure)  # refuses an unknown task, size or pressure by name
        budget = int(rollouts) * task.horizon
        if pressure == "projection":
            try:  # a scene the projection does not take (no liquid: the ice cream, the air): every method refused
                task.scene().check_projection()
            except ValueError as err:
                refused += [{"task": name, "method": m, "why": str(err)} for m in methods]
                continue
        if baseline:
            specs.append({"task": name, "method": STILL, "seed": 0, "size": size, "budget": budget, "arch": arch,
                          "threads": threads, "out": str(out.resolve()), "pressure": pressure})
        for m in methods:
            if m in ABLATIONS or m in optim.GRADIENT_METHODS:
                try:  # a gradient method on the projected liquid, which has no gradients yet
                    optim.check_request(task, "dp" if m in ABLATIONS else m, budget, 0)
                except ValueError as err:
                    refused.append({"task": name, "method": m, "why": str(err)})
                    continue
            if m == "dp-window":
                try:
                    optim.check_request(task, m, budget, 0)  # refuses a task whose loss is not a mean over steps
                except ValueError as err:
                    refused.append({"task": name, "method": m, "why": str(err)})
                    continue
            if m in optim.CMA_ES_METHODS:
                try:
                    cmaes.population_for(task, budget, min_generations)
                except ValueError as err:
                    refused.append({"task": name, "method": m, "why": str(err)})
                    continue
            for s in seeds:
                specs.append({"task": name, "method": m, "seed": int(s), "size": size, "budget": budget,
                              "arch": arch, "threads": threads, "min_generations": int(min_generations),
                              "checkpoints": int(checkpoints), "out": str(out.resolve()),
                              "snapshot_minutes": float(snapshot_minutes), "pressure": pressure})
    for r in refused:
        log(f"refused: {r['task']} {r['method']}: {r['why']}")
    previous = {r["key"]: r for r in load_runs(runs_path) if "final_loss" in r}
    todo = [s for s in specs if run_key(s) not in previous]
    # task by task (an interrupted sweep has whole tasks), gradient runs first within a task: they take longest
    todo.sort(key=lambda s: (tasks_.index(s["task"]), s["method"] in (*optim.CMA_ES_METHODS, STILL)))
    log(f"{len(specs)} runs in the sweep, {len(specs) - len(todo)} already in {runs_path}, {len(todo)} to run "
        f"({'Ray at ' + ray_address if ray_address else ('local Ray' if use_ray else 'process pool')}, {jobs} at a "
        f"time, {threads} Taichi thread(s) each)")
    records = [previous[run_key(s)] for s in specs if run_key(s) in previous]
    if todo:
        submit, wait, shutdown = _executor(jobs, threads, ray_address, use_ray)
        t0 = time.perf_counter()
        try:
            handles = [submit(s) for s in todo]
            for i in range(len(todo)):
                rec, handles = wait(handles)
                finish(out, rec)
                records.append(rec)
                status = (f"final loss {rec['final_loss']:.4e}, return {rec['return']:.3f}" if "final_loss" in rec
                          else f"FAILED: {rec['error']}")
                log(f"[{i + 1}/{len(todo)}] {rec['task']} {rec['method']} seed {rec['seed']}: {status} "
                    f"({rec['wall']:.0f} s; sweep {time.perf_counter() - t0:.0f} s)")
        finally:
            shutdown()
    # the table, Table 2 and the plots cover every run finished in OUT, not only this sweep's: a sweep that
    # continues one run (the README's command for a snapshot) would otherwise replace the folder's table with it
    if runs_path.exists():
        report(out, log=log, refused=refused)
    else:  # nothing ran (every request refused)
        _write_report(out, records, refused, {}, log)
    return records


def build_parser() -> argparse.ArgumentParser:
    from fluidlab_core.optim import METHODS, PAPER_METHODS
    from fluidlab_core.tasks.base import SIZES

    ap = argparse.ArgumentParser(prog="fluidlab benchmark", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", nargs="+", default=None, help="default: every registered task")
    ap.add_argument("--methods", nargs="+", default=list(PAPER_METHODS), choices=[*METHODS, *ABLATIONS],
                    help="default: the paper's six (dp-window, cma-es-free and dp-free, ours, when named); the DP ablations run DP without techniques: "
                    + ", ".join(f"{k} (without {' and '.join(v)})" for k, v in ABLATIONS.items()))
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--rollouts", type=int, default=150, help="budget per run in rollouts of the task's horizon "
                    "(default 150: 30 CMA-ES generations of 5)")
    ap.add_argument("--size", default="small", choices=list(SIZES))
    ap.add_argument("--out", default=None, help="folder (default bench/results/benchmark_SIZE)")
    ap.add_argument("--jobs", type=int, default=None, help="runs at a time on a local Ray or pool (default: cores)")
    ap.add_argument("--threads", type=int, default=None, help="Taichi CPU threads per run (default cores/jobs)")
    ap.add_argument("--ray-address", default=None, help="a running Ray cluster ('auto' or host:port)")
    ap.add_argument("--no-ray", action="store_true", help="a process pool even when Ray is installed")
    ap.add_argument("--min-generations", type=int, default=30, help="CMA-ES generations a budget must hold")
    ap.add_argument("--checkpoints", type=int, default=10, help="reference evaluations along each run's budget")
    ap.add_argument("--snapshot-minutes", type=float, default=5.0,
                    help="a resumable run (dp, dp-h, ablations) saves its state to OUT/partial/ this often, and a "
                    "sweep started again continues it from there (default 5)")
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"])
    ap.add_argument("--pressure", default="state", choices=["state", "projection"],
                    help="the tasks' liquid: state (default, weakly compressible) or projection (incompressible, "
                    "floats bodies at Archimedes' depth; no gradients, so the gradient methods are refused; default "
                    "--out bench/results/benchmark_SIZE_projection)")
    ap.add_argument("--reevaluate", action="store_true",
                    help="replay every finished run's trajectory on this engine (OUT/reevaluated.jsonl, resumable; the "
                    "table then shows each method's loss 'now' beside the recorded one), write the report, run nothing "
                    "else")
    ap.add_argument("--merge", metavar="SRC", default=None,
                    help="add the finished runs of the sweep folder SRC (and their trajectories) to OUT, skipping "
                    "those OUT has, then write the report; run nothing")
    ap.add_argument("--report-only", action="store_true",
                    help="write the table, Table 2 and the plots from OUT/runs.jsonl (the runs finished so far, e.g. "
                    "of a sweep still running or cut short) and run nothing")
    return ap


REEVALUATED = "reevaluated.jsonl"


def reevaluate(out: Path, tasks_=None, arch: str = "cpu", threads: int | None = None, log=print) -> dict:
    """Replay every finished run's trajectory (the still tool's zero actions for its row) on this engine's
    reference physics, as tests/test_tasks.py replays a shipped one, and append {key, final_loss_now,
    return_now, recorded_final_loss, date} to OUT/reevaluated.jsonl as each finishes. A sweep's runs may span
    engine changes that moved a task's physics; these figures put them on one engine. Runs already in the file
    are skipped (delete it to re-measure after another engine change). Returns {key: record} of the file."""
    import fluidlab_core
    from fluidlab_core import tasks
    from fluidlab_core.trajectory import Trajectory

    out = Path(out)
    path = out / REEVALUATED
    done = {r["key"]: r for r in load_runs(path) if "key" in r}
    todo = [r for r in load_runs(out / "runs.jsonl") if "final_loss" in r and r["key"] not in done
            and (not tasks_ or r["task"] in tasks_) and (r["method"] == STILL or "trajectory" in r)]
    log(f"re-evaluating {len(todo)} runs on this engine ({len(done)} already in {path})")
    if not todo:
        return done
    fluidlab_core.init(arch=arch, precision="f32", cpu_threads=threads)
    built = {}
    for i, r in enumerate(todo):
        t0 = time.perf_counter()
        which = (r["task"], r["size"], r.get("pressure", "state"))
        if which not in built:
            built[which] = tasks.make(r["task"], size=r["size"], pressure=which[2])
        task = built[which]
        if r["method"] == STILL:
            result = task.evaluate(np.zeros((task.horizon, task.n_actions)))
        else:
            traj_path = out / r["trajectory"]
            if not traj_path.is_file():
                log(f"  {r['key']}: no trajectory at {traj_path}; skipped")
                continue
            actions, position = task.actions_from_trajectory(Trajectory.load(traj_path))
            result = task.evaluate(actions, tool_position=position)
        rec = {"key": r["key"], "final_loss_now": float(result["loss"]), "return_now": float(result["return"]),
               "recorded_final_loss": r["final_loss"], "date": time.strftime("%Y-%m-%d")}
        _append(path, rec)
        done[r["key"]] = rec
        log(f"  [{i + 1}/{len(todo)}] {r['key']}: {rec['final_loss_now']:.4e} now, {r['final_loss']:.4e} recorded "
            f"({time.perf_counter() - t0:.0f} s)")
    return done


def report(out: Path, tasks_=None, methods=None, log=print, refused=None) -> list[dict]:
    """Table, Table 2 and plots of the finished runs in OUT/runs.jsonl (of the given tasks and methods, all by
    default), without running anything; `refused`: the sweep's refused requests, listed under the table."""
    runs_path = Path(out) / "runs.jsonl"
    if not runs_path.exists():
        raise ValueError(f"no runs to report: {runs_path} does not exist")
    records = [r for r in load_runs(runs_path) if (not tasks_ or r["task"] in tasks_)
               and (not methods or r["method"] in methods or r["method"] == STILL)]
    order = {t: i for i, t in enumerate(tasks_ or dict.fromkeys(r["task"] for r in records))}
    from fluidlab_core.optim import METHODS

    rank = {m: i for i, m in enumerate((STILL, *METHODS, *ABLATIONS))}
    records.sort(key=lambda r: (order.get(r["task"], len(order)), rank.get(r["method"], len(rank)), r["seed"]))
    again = [r for r in load_runs(Path(out) / REEVALUATED) if "key" in r]
    now = {r["key"]: r["final_loss_now"] for r in again}
    now_returns = {r["key"]: r["return_now"] for r in again if "return_now" in r}
    _write_report(Path(out), records, refused, now, log, now_returns)
    return records


def _write_report(out: Path, records: list[dict], refused, now: dict, log, now_returns: dict | None = None) -> None:
    """OUT/table.txt, OUT/table2.md (with the re-evaluated returns where there are some) and the plots of
    `records`, the table logged."""
    text = table(records, refused, now=now)
    (out / "table.txt").write_text(text + "\n")
    (out / "table2.md").write_text(paper_table(records, now_returns) + "\n")
    log(text)
    for path in plot(records, out):
        log(f"wrote {path}")


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        _dispatch(args, parser.get_default("methods"))
    except (ValueError, KeyError) as err:  # bad input: an unknown task or method, a folder that cannot merge …
        text = err.args[0] if isinstance(err, KeyError) and err.args and isinstance(err.args[0], str) else err
        print(f"fluidlab benchmark: error: {text}", file=sys.stderr)
        return 2
    return 0


def _dispatch(args, default_methods):
    """What main runs for the parsed command line: re-evaluate, merge and report, or sweep (default_methods: the
    parser's, which a report reads as "every method")."""
    from fluidlab_core import tasks

    suffix = "" if args.pressure == "state" else f"_{args.pressure}"
    out = Path(args.out or f"bench/results/benchmark_{args.size}{suffix}")
    if args.reevaluate:
        reevaluate(out, args.tasks, args.arch, args.threads)
    if args.merge:
        merge(Path(args.merge), out)
    if args.report_only or args.reevaluate or args.merge:
        report(out, args.tasks, None if args.methods == default_methods else args.methods)
        return
    sweep(args.tasks or tasks.names(), args.methods, args.seeds, args.rollouts, args.size, out, args.jobs,
          args.threads, args.ray_address, False if args.no_ray else None, args.min_generations,
          args.checkpoints, args.arch, snapshot_minutes=args.snapshot_minutes, pressure=args.pressure)


if __name__ == "__main__":
    sys.exit(main())
