"""Gradients of the gradient-test scene (tests/test_gradients.py), saved or compared with a saved run.

The engine's refactors must not change its gradients. This script runs the test scene's checkpointed
rollout (6 steps, segments of 2) in float64 on the CPU with two threads and either saves every gradient and
the loss to an .npz file, or compares them with such a file and prints the largest relative difference per
quantity (relative to that quantity's largest magnitude).

    python bench/gradient_regression.py --save bench/results/gradients_reference.npz
    python bench/gradient_regression.py --compare bench/results/gradients_reference.npz [--tol 1e-10]
                                        [--out bench/results/gradient_regression.txt]

It uses only the public API (`Scene.build`, `Simulator.rollout`) and the scene, loss and actions of
tests/test_gradients.py (`build_scene`, `build_problem`). Exit status 1 when a difference exceeds --tol.
bench/results/gradients_reference.npz holds the gradients of revision 135a8dc, before the engine redesign that
wrote each piece of physics once, made by this script there (that revision's test built the same loss and
actions inline, from the same seed).
"""
import argparse
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("FLUIDLAB_CPU_THREADS", "2")  # the scatter's summation order depends on the thread count

import numpy as np  # noqa: E402

KEYS = ("loss", "step_losses", "grad_actions", "grad_velocities", "grad_positions", "grad_tool_position",
        "grad_tool_rotation")


def run(arch: str = "cpu") -> dict:
    import fluidlab_core as fl
    from tests.test_gradients import build_problem, build_scene

    fl.init(arch=arch, precision="f64", seed=0)
    sim = build_scene()
    loss, actions = build_problem(sim)
    res = sim.rollout(actions, loss, grad=True, segment_steps=2)
    return {k: np.asarray(getattr(res, k), dtype=np.float64) for k in KEYS}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    group = ap.add_mutually_exclusive_group(required=True)
    group.add_argument("--save", help="write the gradients to this .npz file")
    group.add_argument("--compare", help="compare with this .npz file")
    ap.add_argument("--tol", type=float, default=1e-10, help="largest relative difference allowed (default 1e-10)")
    ap.add_argument("--out", default=None, help="with --compare: also write the comparison to this file")
    ap.add_argument("--arch", default="cpu", choices=["cpu", "cuda"],
                    help="Taichi backend (default cpu; on cuda the atomic scatters sum in another order, so expect "
                         "round-off differences far above 1e-10 but far below the gradient tests' 5e-3)")
    args = ap.parse_args()
    out = run(args.arch)
    if args.save:
        np.savez(args.save, **out)
        print(f"wrote {args.save}")
        return 0
    ref = np.load(args.compare)
    worst = 0.0
    where = "CPU, 2 threads" if args.arch == "cpu" else args.arch.upper()
    lines = [f"gradients of tests/test_gradients.py's scene (float64, {where}) against {args.compare}"]
    for k in KEYS:
        scale = max(np.abs(ref[k]).max(), 1e-300)
        diff = float(np.abs(out[k] - ref[k]).max() / scale)
        worst = max(worst, diff)
        lines.append(f"{k:<20} max |new - reference| / max |reference| = {diff:.3e}")
    lines.append(f"largest relative difference {worst:.3e} (tolerance {args.tol:g})")
    print("\n".join(lines))
    if args.out:
        Path(args.out).write_text("\n".join(lines) + "\n")
    return 0 if worst <= args.tol else 1


if __name__ == "__main__":
    sys.exit(main())
