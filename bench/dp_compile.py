"""What the differentiable solver's first gradient rollouts spend compiling, for this tree and (with --rev) an
earlier revision, in alternating fresh processes with empty Taichi caches.

    python bench/dp_compile.py [--rev HEAD~1] [--rounds 2] [--scenes GatheringEasy gradient_scene]

Scenes:
- a task's name (small size, float32): the first two iterations of DP over the whole horizon (no expanding region,
  no attraction), as tests/test_optim.py's first DP test runs it;
- `gradient_scene`: tests/test_gradients.py's float64 scene (six material classes, a box static with friction, a
  soft and a hard tool) and its first gradient rollout of 6 steps, built here as that file builds it (its
  build_scene and build_problem, imported from the tree under test).
Both with FLUIDLAB_FAST_COMPILE=1, as the test suite runs. Reported per run: the seconds to the end of the first
gradient work (nearly all compilation at these sizes), the first-launch seconds of the grid update's reverse kernel
and of all kernels (bench/compile_profile.py's wrapper on Taichi's kernel launch), and what the run computed (the
losses; the gradient's norm), which must not change. Writes bench/results/dp_compile_<backend>.txt (medians over
the rounds, and after/before ratios).
"""
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def child(scene: str) -> dict:
    import numpy as np

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import compile_profile  # times each kernel instance's first launch

    compile_profile.install()
    first = compile_profile.per_kernel
    import fluidlab_core as fl

    t0 = time.perf_counter()
    if scene == "gradient_scene":
        fl.init(arch="cpu", precision="f64", seed=0)
        sys.path.insert(0, os.getcwd())  # the tree under test's tests/
        from tests import test_gradients as tg

        sim = tg.build_scene()
        loss, actions = tg.build_problem(sim)
        r = sim.rollout(actions, loss, grad=True, segment_steps=2)
        out = {"losses": [float(r.loss)], "grad_norm": float(np.linalg.norm(r.grad_actions))}
    else:
        from fluidlab_core import tasks
        from fluidlab_core.optim import dp

        fl.init(arch="cpu", precision="f32", seed=0)
        task = tasks.make(scene, "small")
        seen = []
        dp.run(task, budget=2 * task.horizon, seed=0, callback=seen.append,
               options=dp.DPOptions(expanding_region=False, attraction=False))
        out = {"losses": [float(p.loss) for p in seen], "grad_norm": None}
    out["first_gradient_s"] = time.perf_counter() - t0
    out["grid_update_reverse_s"] = sum(v for k, v in first.items() if k.startswith("DiffSolver.grid_update[REVERSE"))
    out["compile_s_all"] = sum(first.values())
    return out


def _same(after, before) -> str:
    """Whether the runs computed what the earlier tree's did: bit for bit, or how close (a change that computes a
    gradient differently, by hand instead of by Taichi's reverse mode, moves its last bits and DP's later losses)."""
    pairs = list(zip(after, before))
    same = all(a["losses"] == b["losses"] for a, b in pairs)
    loss_diff = max(abs(x - y) / max(abs(y), 1e-300) for a, b in pairs for x, y in zip(a["losses"], b["losses"]))
    norms = [(a["grad_norm"], b["grad_norm"]) for a, b in pairs if a["grad_norm"] is not None]
    text = f"losses equal to before, bit for bit: {same}; largest relative loss difference: {loss_diff:.2g}"
    if norms:
        text += f"; gradient norm's relative difference: {max(abs(x - y) / abs(y) for x, y in norms):.2g}"
    return text


def main():
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import compile_profile

    compile_profile.before_after_cli(__doc__, Path(__file__).resolve(), child, "--scenes", ["GatheringEasy", "gradient_scene"],
                                     ["first_gradient_s", "grid_update_reverse_s", "compile_s_all"],
                                     ROOT / "bench" / "results" / "dp_compile_cpu.txt", _same)


if __name__ == "__main__":
    main()
