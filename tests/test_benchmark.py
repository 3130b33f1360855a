"""The optimiser benchmark (fluidlab_core/benchmark.py): a tiny sweep on a local Ray, resumed; CMA-ES budgets that
cannot hold its generations are refused; the flattening criterion."""
import json
import os
from pathlib import Path

import numpy as np
import pytest

from fluidlab_core import benchmark, optim, tasks
from fluidlab_core.optim import cmaes


def test_cma_es_population_fits_the_generations_or_the_budget_is_refused():
    task = tasks.make("LatteArtStir", "small")
    default = cmaes.default_population(cmaes.search_size(task))
    # a generous budget keeps the package's default population; a smaller one shrinks it to fit 30 generations
    assert cmaes.population_for(task, 30 * default * task.horizon, 30) == default
    assert cmaes.population_for(task, 150 * task.horizon, 30) == 5
    with pytest.raises(ValueError, match=r"CMA-ES needs at least 30 generations of at least 4 candidates: 120 "
                                         r"rollouts \(9000 simulated steps for LatteArtStir, small\); the budget "
                                         r"holds 8"):
        optim.optimise(task, "cma-es", budget=8 * task.horizon, min_generations=30)


def test_a_run_that_stops_rising_has_flattened():
    flat = [[s, 1.0 + 1.0 / s, 0.0] for s in range(10, 110, 10)]  # 1 % of change only in the early part
    assert benchmark.flattened(flat) is True
    falling = [[s, 2.0 - s / 100.0, 0.0] for s in range(10, 110, 10)]
    assert benchmark.flattened(falling) is False
    assert benchmark.flattened(flat[:2]) is None


def test_a_run_is_judged_by_its_last_checkpoint_not_its_best():
    """A checkpoint holds the reference loss of the iterate that is best by the optimiser's own loss (DP's soft
    physics), so a curve can rise (medium GatheringEasy DP: 4.68e-3 at 3,050 steps, 4.70e-3 from 4,550 on). The
    run's loss at a point of its budget is its last checkpoint by then, as its final loss is the last checkpoint's;
    taking the minimum would choose the iterate on the judging physics."""
    curve = [[100, 3.0, 1.0], [200, 2.0, 2.0], [300, 2.5, 3.0], [400, 2.5, 4.0], [500, 2.5, 5.0]]
    assert benchmark._loss_at(curve, 0, 250) == 2.0
    assert benchmark._loss_at(curve, 0, 500) == 2.5  # not 2.0, the minimum
    assert benchmark._loss_at(curve, 2, 3.5) == 2.5
    assert np.isnan(benchmark._loss_at(curve, 0, 50))
    assert benchmark.flattened(curve) is True  # it rose over its last 20 %: no improvement left
    assert benchmark.flattened([[100, 3.0, 1.0], [200, 2.0, 2.0], [300, 2.5, 3.0], [400, 2.5, 4.0],
                                [500, 2.0, 5.0]]) is False  # fell 20 % over its last 20 %


def test_runs_file_survives_a_line_cut_short(tmp_path):
    path = tmp_path / "runs.jsonl"
    path.write_text(json.dumps({"key": "a", "final_loss": 1.0}) + "\n" + '{"key": "b", "fin')
    assert [r["key"] for r in benchmark.load_runs(path)] == ["a"]


def test_sweep_on_local_ray_resumes_without_repeating_a_run(tmp_path):
    """A CMA-ES seed as a Ray job, then the same sweep with a second seed: only the second runs. Every record has
    its curve on the reference physics, its trajectory and its reward constants; the table and plot are written."""
    ray = pytest.importorskip("ray")
    # one Ray session for both sweeps: the second finds a worker that has compiled the task's kernels
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        _sweep_twice(tmp_path)
    finally:
        ray.shutdown()


def _sweep_twice(tmp_path):
    logs = []
    kw = dict(tasks_=["LatteArtStir"], methods=["cma-es"], rollouts=8, size="small", out=tmp_path, jobs=2,
              min_generations=2, checkpoints=4, log=logs.append, use_ray=True)
    first = benchmark.sweep(seeds=[0], **kw)
    assert any("0 already in" in line and "2 to run" in line for line in logs)  # CMA-ES seed 0 and the still tool
    assert sorted(r["method"] for r in first) == ["cma-es", "still"] and all("final_loss" in r for r in first)
    still = next(r for r in first if r["method"] == "still")
    first = [r for r in first if r["method"] == "cma-es"]
    assert first[0]["final_loss"] < still["final_loss"]  # two generations already beat keeping the tool still
    for r in first:
        assert r["steps_used"] == 8 * 75 and r["settings"]["popsize"] == 4 and r["settings"]["generations"] == 2
        steps = [c[0] for c in r["curve"]]
        assert steps == [300, 600]  # checkpoints every 150 steps, reached at the end of each 300-step generation
        assert np.isclose(min(c[1] for c in r["curve"]), r["final_loss"], rtol=1e-6)
        assert (tmp_path / r["trajectory"]).is_file() and r["trajectory"].startswith("trajectories/LatteArtStir/")
        assert r["reward_c2"] > 0
        report = json.loads((tmp_path / r["trajectory"]).with_suffix("").with_suffix(".report.json").read_text())
        assert report["final_loss"] == r["final_loss"]  # beside the trajectory, for bench/ship_best.py
    logs.clear()
    again = benchmark.sweep(seeds=[0, 1], **kw)
    assert any("2 already in" in line and "1 to run" in line for line in logs)
    lines = (tmp_path / "runs.jsonl").read_text().splitlines()
    cma = [r for r in again if r["method"] == "cma-es"]
    assert len(lines) == 3 and sorted(r["seed"] for r in cma) == [0, 1]
    assert first[0] in cma  # the finished run is read back, not repeated
    table = (tmp_path / "table.txt").read_text()
    assert "LatteArtStir" in table and "cma-es" in table and " 2 " in table and "the tool kept still" in table
    assert (tmp_path / "curves_LatteArtStir.png").stat().st_size > 10_000
    assert (tmp_path / "overview.png").stat().st_size > 5_000  # the README's figure: one panel per task
    # re-evaluated on this engine: each run's trajectory replays to its recorded loss, the still tool's exactly;
    # a second call finds them all done; the table shows them as 'now'
    logs.clear()
    again_now = benchmark.reevaluate(tmp_path, log=logs.append)
    assert len(again_now) == 3 and any("re-evaluating 3 runs" in line for line in logs), logs
    for r in again:
        assert again_now[r["key"]]["final_loss_now"] == pytest.approx(r["final_loss"], rel=1e-3), r["key"]
    assert len(benchmark.reevaluate(tmp_path, log=logs.append)) == 3 and "re-evaluating 0 runs" in logs[-1]
    benchmark.report(tmp_path, log=logs.append)
    assert "  now " in (tmp_path / "table.txt").read_text()
    # an RL baseline goes through the same machinery: a Ray job, checkpoints on the reference physics, a trajectory
    pytest.importorskip("stable_baselines3")
    logs.clear()
    ppo = [r for r in benchmark.sweep(seeds=[0], **{**kw, "methods": ["ppo"]}) if r["method"] == "ppo"]
    assert any("1 to run" in line for line in logs), logs
    assert len(ppo) == 1 and "final_loss" in ppo[0], ppo
    r = ppo[0]
    assert r["steps_used"] == 8 * 75 and r["iterations"] == 8  # eight episodes, the last the deterministic policy's
    assert [c[0] for c in r["curve"]] == [150, 300, 450, 600]  # an episode ends on every checkpoint
    assert np.isclose(min(c[1] for c in r["curve"]), r["final_loss"], rtol=1e-6)
    assert (tmp_path / r["trajectory"]).is_file()
    # a sweep of one method writes the folder's table of every finished run, not of its own runs alone
    table = (tmp_path / "table.txt").read_text()
    assert "ppo" in table and "cma-es" in table and " 2 " in table, table


def test_fluidlab_benchmark_refuses_an_unknown_task_by_name(capsys):
    from fluidlab_core import cli

    assert cli.main(["benchmark", "--tasks", "Nope", "--out", "unused"]) == 2
    err = capsys.readouterr().err
    assert "fluidlab benchmark: error: unknown task 'Nope'; known tasks: LatteArtStir" in err


def test_paper_table_has_a_row_per_method_and_a_column_per_task():
    def rec(task, method, seed, ret):
        return {"task": task, "method": method, "seed": seed, "final_loss": -ret, "return": ret, "size": "small",
                "budget": 750, "horizon": 75, "reward_c1": 1.0, "reward_c2": 2e5}

    runs = [rec("A", "still", 0, -5.0), rec("A", "dp", 0, 10.0), rec("A", "dp", 1, 14.0), rec("B", "dp", 0, 3.0),
            rec("B", "dp", 1, 5.0), rec("B", "sac", 0, 1.0), {"task": "B", "method": "ppo", "error": "x"}]
    lines = benchmark.paper_table(runs).splitlines()
    assert lines[0] == "| method | A | B |"
    assert lines[2] == "| still tool | -5.0 | – |"
    assert lines[3] == "| dp | 12.0 ± 2.0 | 4.0 ± 1.0 |"
    assert lines[4] == "| sac | – | 1.0 ± 0.0 (n=1) |"  # fewer seeds than the rest are marked; failed runs are not rows
    assert "mean ± std over 2 seeds" in lines[-1] and "A 1 − 200000 ℓ over 75 steps" in lines[-1]
    assert "replayed" not in lines[-1]
    # a run replayed on a later engine (--reevaluate) counts with its new return, marked, so that runs made before
    # and after an engine change meet on one physics
    runs[1]["key"] = "A|dp|0"
    lines = benchmark.paper_table(runs, {"A|dp|0": 20.0}).splitlines()
    assert lines[3] == "| dp | 17.0 ± 3.0* | 4.0 ± 1.0 |"
    assert "*: replayed on a later engine" in lines[-1]


def test_run_table_columns_line_up_under_a_long_method_name():
    """The run table's columns start where the header's do, whatever the longest method name (dp-window is
    nine characters; the column was eight, and every row of that method shifted by one)."""
    def rec(method, seed, loss):
        return {"task": "A", "method": method, "seed": seed, "key": f"A|{method}|{seed}", "final_loss": loss,
                "return": -loss, "size": "small", "budget": 750, "horizon": 75, "reward_c1": 1.0,
                "reward_c2": 1.0, "wall": 10.0 + seed, "steps_used": 750, "curve": [[750, loss, 5.0]]}

    runs = [rec("still", 0, 2.0), rec("dp", 0, 1.0), rec("dp-window", 20, 1.5), rec("dp-window", 22, 1.25)]
    lines = benchmark.table(runs).splitlines()
    head = next(line for line in lines if line.lstrip().startswith("method"))
    rows = {line.split()[0]: line for line in lines if line.split()[:1] in (["dp"], ["dp-window"])}
    assert set(rows) == {"dp", "dp-window"}
    # the columns are right-aligned: the wall time (10 s, 31 s) ends where the header's 'wall s' ends, and the
    # mean loss starts in the same column in every row
    wall_end = head.index("wall s") + len("wall s")
    assert rows["dp"][:wall_end].endswith(" 10") and rows["dp-window"][:wall_end].endswith(" 31"), (head, rows)
    assert rows["dp"].index("1.0000e+00") == rows["dp-window"].index("1.3750e+00"), rows


def test_a_run_reports_its_progress_at_each_checkpoint(tmp_path, capsys):
    """A benchmark run can take hours (Pouring's DP about 2.5 h on one core) and its record is written only at its
    end, so the worker prints a line at each checkpoint: the share of the budget, the reference-physics loss of
    the best iterate so far, and the time. Two CMA-ES generations of 4 on LatteArtStir, checkpoints at half and
    all of the budget."""
    spec = {"task": "LatteArtStir", "method": "cma-es", "seed": 0, "size": "small", "budget": 8 * 75, "arch": "cpu",
            "threads": 1, "min_generations": 2, "checkpoints": 2, "out": str(tmp_path)}
    record = benchmark.run_job(spec)
    assert "final_loss" in record, record.get("traceback")
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "% of the budget" in line]
    assert [line.split(":")[1].split("%")[0].strip() for line in lines] == ["50", "100"], err
    assert lines[0].startswith("  LatteArtStir cma-es seed 0: 50 % of the budget, best iterate's loss ")
    assert f"{record['curve'][-1][1]:.4e}" in lines[-1]  # the loss the record's curve holds


def test_a_killed_sweep_takes_its_pool_workers_with_it(tmp_path):
    """The process pool's workers die with the sweep (benchmark.die_with_parent): a sweep killed by SIGKILL used to
    leave its running job's worker computing on for up to the rest of the run, its result never recorded (seen
    here: two orphaned AirCirculation runs, an hour of two cores). A parent process starts a pool worker on a
    60 s job, the test kills the parent, and the worker must be gone within 10 s."""
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "parent.py"
    script.write_text(
        "import multiprocessing as mp, os, sys, time\n"
        "from concurrent.futures import ProcessPoolExecutor\n"
        "from fluidlab_core.benchmark import die_with_parent\n"
        "if __name__ == '__main__':\n"
        "    pool = ProcessPoolExecutor(1, mp_context=mp.get_context('spawn'), initializer=die_with_parent)\n"
        "    print(pool.submit(os.getpid).result(), flush=True)\n"
        "    pool.submit(time.sleep, 60)\n"
        "    time.sleep(60)\n")
    root = str(Path(__file__).resolve().parents[1])
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, cwd=root,
                              env={**os.environ, "PYTHONPATH": root})
    try:
        worker = int(parent.stdout.readline())
        os.kill(worker, 0)  # alive
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and _alive(worker):
            time.sleep(0.1)
        if _alive(worker):
            os.kill(worker, signal.SIGKILL)
            raise AssertionError(f"the pool worker {worker} outlived its killed parent by 10 s")
    finally:
        if parent.poll() is None:
            parent.kill()


def _alive(pid: int) -> bool:
    """Whether process pid runs (a zombie, dead but not yet reaped by whoever adopted it, does not)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


def _fake_run(out: Path, task: str, method: str, seed: int, loss: float, size="medium", budget=100) -> dict:
    """A finished run's record as a sweep writes it, with its trajectory and report files under OUT."""
    spec = {"task": task, "method": method, "seed": seed, "size": size, "budget": budget}
    rec = {**spec, "key": benchmark.run_key(spec), "final_loss": loss, "curve": [[budget, loss, 1.0]], "wall": 1.0,
           "return": 0.0, "horizon": min(budget, 100), "reward_c1": 1.0, "reward_c2": 200.0}
    if method != benchmark.STILL:
        rel = Path("trajectories") / task / f"{task}_{method}_seed{seed}_{size}.json"
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_text(json.dumps({"loss": loss}))
        (out / rel.with_name(rel.stem + ".report.json")).write_text(json.dumps(rec))
        rec["trajectory"] = str(rel)
    out.mkdir(parents=True, exist_ok=True)
    benchmark._append(out / "runs.jsonl", rec)
    return rec


def test_merge_adds_another_folders_runs_once_and_refuses_other_physics(tmp_path, capsys):
    """Runs done in a separate folder join the main one with their trajectories; a run the main folder has is not
    added twice; a folder whose still tool reads another loss (its runs were made on other physics) is refused before
    anything is written, until `--reevaluate` has put the main folder's runs on the other's engine; `--merge` then
    writes the report."""
    main, side, other = tmp_path / "main", tmp_path / "side", tmp_path / "other"
    _fake_run(main, "GatheringEasy", "still", 0, 5e-3)
    _fake_run(main, "GatheringEasy", "dp", 0, 4.6e-3)
    _fake_run(side, "GatheringEasy", "still", 0, 5e-3)
    _fake_run(side, "GatheringEasy", "dp", 0, 9.9e-3)  # the main folder's record of this key stays
    sac = _fake_run(side, "GatheringEasy", "sac", 0, 4.4e-3)
    with (side / "runs.jsonl").open("a") as f:
        f.write('{"key": "cut sho')  # a sweep killed while writing that line: skipped

    added = benchmark.merge(side, main, log=lambda *_: None)
    assert [r["key"] for r in added] == [sac["key"]]
    runs = {r["key"]: r for r in benchmark.load_runs(main / "runs.jsonl")}
    assert len(runs) == 3 and runs["GatheringEasy|dp|0|medium|100"]["final_loss"] == 4.6e-3
    assert json.loads((main / sac["trajectory"]).read_text()) == {"loss": 4.4e-3}
    assert (main / sac["trajectory"]).with_name(Path(sac["trajectory"]).stem + ".report.json").is_file()
    assert benchmark.merge(side, main, log=lambda *_: None) == []  # again: nothing new

    # another machine's float32 rounding moves the still tool's loss by about 1e-6 (Pouring's: 1.2e-6): one physics
    cpu2 = tmp_path / "cpu2"
    _fake_run(cpu2, "GatheringEasy", "still", 0, 5e-3 * (1 + 2e-6))
    ppo = _fake_run(cpu2, "GatheringEasy", "ppo", 0, 4.9e-3)
    assert [r["key"] for r in benchmark.merge(cpu2, main, log=lambda *_: None)] == [ppo["key"]]

    _fake_run(other, "GatheringEasy", "still", 0, 5.1e-3)
    _fake_run(other, "GatheringEasy", "pods", 0, 4.8e-3)
    before = (main / "runs.jsonl").read_text()
    with pytest.raises(ValueError, match=r"still tool's loss is 5.100000e-03 in .*other and 5.000000e-03 in .*main; "
                                         r"their runs were made on different physics"):
        benchmark.merge(other, main, log=lambda *_: None)
    assert (main / "runs.jsonl").read_text() == before
    assert not (main / "trajectories" / "GatheringEasy" / "GatheringEasy_pods_seed0_medium.json").exists()

    (side / sac["trajectory"]).unlink()
    fresh = tmp_path / "fresh"
    with pytest.raises(ValueError, match=r"GatheringEasy\|sac\|0\|medium\|100: its trajectory .* is missing"):
        benchmark.merge(side, fresh, log=lambda *_: None)
    assert benchmark.load_runs(fresh / "runs.jsonl") == []

    assert benchmark.main(["--merge", str(other), "--out", str(main)]) == 2
    assert "different physics" in capsys.readouterr().err

    # once the main folder's runs are re-evaluated on the other folder's engine (--reevaluate), the still tools
    # agree and the merge goes ahead
    with (main / benchmark.REEVALUATED).open("w") as f:
        f.write(json.dumps({"key": "GatheringEasy|still|0|medium|100", "final_loss_now": 5.1e-3,
                            "recorded_final_loss": 5e-3}) + "\n")
    added = benchmark.merge(other, main, log=lambda *_: None)
    assert [r["key"] for r in added] == ["GatheringEasy|pods|0|medium|100"]


def test_a_sweep_on_the_projected_liquid_refuses_the_gradient_methods_and_keeps_its_runs_apart(tmp_path):
    """--pressure projection: the gradient methods and DP's ablations are refused with the reason (the projection has
    no gradients), before anything runs; the runs' keys and file names say the liquid, so that they never collide with
    the default liquid's runs of the same task, method, seed and budget."""
    logs = []
    records = benchmark.sweep(["GatheringEasy"], ["dp", "dp-h", "pods", "dp-no-sharing"], [0], 8, "small", tmp_path,
                              jobs=1, use_ray=False, log=logs.append, baseline=False, pressure="projection")
    assert records == [] and not (tmp_path / "runs.jsonl").exists()
    refused = [line for line in logs if line.startswith("refused: GatheringEasy") and "\n" not in line]
    assert len(refused) == 4 and all("needs the simulator's gradients" in line for line in refused), logs
    assert "0 runs in the sweep" in " ".join(logs) and "refused: GatheringEasy pods" in logs[-1]  # under the table
    spec = {"task": "GatheringEasy", "method": "cma-es", "seed": 0, "size": "small", "budget": 800}
    assert benchmark.run_key(spec) == "GatheringEasy|cma-es|0|small|800"  # the default liquid's keys as before
    assert benchmark.run_key({**spec, "pressure": "projection"}) == "GatheringEasy|cma-es|0|small|800|projection"
    assert benchmark.run_name({**spec, "pressure": "projection"}) == "GatheringEasy_cma-es_seed0_small_projection"
    assert benchmark._record({**spec, "pressure": "projection"})["pressure"] == "projection"
    assert "pressure" not in benchmark._record(spec)

    # a task whose scene the projection does not take (no liquid: the ice cream is none to it) is refused whole before
    # anything runs, with the build's reason, instead of failing in its workers one run at a time
    logs.clear()
    records = benchmark.sweep(["IceCreamStatic"], ["cma-es", "ppo"], [0], 150, "small", tmp_path, jobs=1,
                              use_ray=False, log=logs.append, pressure="projection")
    assert records == [] and not (tmp_path / "runs.jsonl").exists()
    refused = [line for line in logs if line.startswith("refused: IceCreamStatic") and "\n" not in line]
    assert len(refused) == 2 and all("a scene without liquid" in line for line in refused), logs


def test_a_folder_with_only_the_still_tools_runs_reports_without_a_figure_of_methods(tmp_path):
    """A sweep whose every method was refused (a budget too small for CMA-ES's 30 generations) still runs the still
    tool; its report used to end in matplotlib's 'number sections must be larger than 0' (a legend of no methods)."""
    _fake_run(tmp_path, "GatheringEasy", "still", 0, 5e-3)
    _fake_run(tmp_path, "GatheringHard", "still", 0, 4e-3)
    records = benchmark.report(tmp_path, log=lambda *_: None)
    assert [r["method"] for r in records] == ["still", "still"]
    assert "GatheringHard" in (tmp_path / "table.txt").read_text()
    assert (tmp_path / "curves_GatheringEasy.png").is_file() and not (tmp_path / "overview.png").exists()
