"""What a gas scene's first gradient rollout spends compiling, and what the gas step runs at, for this tree and
(with --rev) an earlier revision, in alternating fresh processes with empty Taichi caches.

    python bench/gas_compile.py [--rev HEAD~1] [--rounds 2] [--limiter cell continuous]

Scene: tests/test_gas.py's float64 gradient room (10 × 8 × 6 cells, an inflow wall, open walls, a static block, a
fan tool carrying a cooling smoky vent, vorticity confinement, viscosity; 4 steps, a sensor loss), built with
requires_grad as the test suite builds it (FLUIDLAB_FAST_COMPILE=1). Reported per run: the seconds to the end of
the first gradient rollout (nearly all compilation at this size), the seconds of a second one (the run itself),
the first-call seconds of the advection's kernels (forward and reverse; a wrapper on Taichi's kernel launch), and
the forward step time of a float32 32³ smoke plume without gradients (the held speed). The earlier revision is
checked out into a temporary git worktree and runs this script's child code against its own package. Writes
bench/results/gas_compile_<backend>.txt (medians over the rounds, and after/before ratios).
"""
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def child(limiter: str) -> dict:
    import numpy as np

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import compile_profile  # times each kernel instance's first launch

    compile_profile.install()
    first = compile_profile.per_kernel
    import fluidlab_core as fl
    from fluidlab_core import losses

    fl.init(arch="cpu", precision="f64", seed=0)
    t0 = time.perf_counter()
    scene = fl.Scene(lower=(0, 0, 0), upper=(0.5, 0.4, 0.3), grid_res=10, dt=0.03)
    scene.add_gas(resolution=10, walls={"x-": (0.2, 0, 0), "x+": "open", "z+": "open"}, vorticity=0.3,
                  viscosity=1e-3, tolerance=1e-12, max_iterations=500, tools_block=False, limiter=limiter)
    scene.add_static(fl.Box((0.2, 0.15, 0.0), (0.3, 0.25, 0.15)))
    scene.add_tool(fl.Box((-0.03, -0.03, -0.03), (0.03, 0.03, 0.03)), pose=(0.35, 0.2, 0.15, 0, 0, 0, 1),
                   name="fan", action_mask=(1, 1, 0, 0, 0, 1), max_speed=0.3)
    scene.add_gas_source("vent", "box", (0.02, 0.04, 0.04), pose=(0.05, 0, 0, 0, 0.7071068, 0, 0.7071068),
                         tool="fan", speed=0.5, temperature=285.0, smoke=0.005, relaxation_time=0.05)
    sim = scene.build(requires_grad=True)
    c = sim.cell_centers()
    s0 = sim.get_state()
    s0.gas.scalars[0] = 293.15 + 2.0 * np.sin(7 * c[..., 0] + 3 * c[..., 1]) * np.cos(5 * c[..., 2])
    s0.gas.scalars[1] = 0.002 * (1 + np.sin(6 * c[..., 1] + 4 * c[..., 0]))
    acts = np.zeros((4, 6))
    acts[:, 5] = 0.8
    sensors = np.array([[0.1, 0.1, 0.1], [0.4, 0.3, 0.1], [0.42, 0.12, 0.2]])
    loss = losses.GasSensors(sensors, "temperature", target=280.0, power=2)
    sim.set_state(s0)
    r1 = sim.rollout(acts, loss, grad=True)
    t_first = time.perf_counter() - t0
    sim.set_state(s0)
    t = time.perf_counter()
    r2 = sim.rollout(acts, loss, grad=True)
    t_second = time.perf_counter() - t
    advect = {k: v for k, v in first.items() if any(s in k for s in ("advect", "trace"))}
    out = {"first_rollout_s": t_first, "second_rollout_s": t_second, "compile_s_all": sum(first.values()),
           "advection_first_calls_s": sum(advect.values()), "loss": float(r1.loss),
           "grad_norm": float(np.linalg.norm(r1.grad_actions)), "grads_equal": bool(np.allclose(
               r1.grad_actions, r2.grad_actions, rtol=1e-9, atol=1e-12))}
    # the held speed: a float32 plume forward, no gradients, in a fresh Taichi program
    fl.init(arch="cpu", precision="f32", seed=0)
    plume = fl.Scene(lower=(0, 0, 0), upper=(1.0, 1.0, 1.0), grid_res=32, dt=0.02)
    plume.add_gas(resolution=32, vorticity=0.2)
    plume.add_gas_source("heater", "disc", (0.1, 0.03), pose=(0.5, 0.5, 0.1, 0, 0, 0, 1), temperature=320.0,
                         smoke=0.01)
    p = plume.build()
    p.step(n=5)
    t = time.perf_counter()
    p.step(n=100)
    out["plume32_ms_per_step"] = (time.perf_counter() - t) / 100 * 1e3
    return out


def _same(after, before) -> str:
    same = all(abs(a["loss"] - b["loss"]) <= 1e-9 * abs(b["loss"]) and
               abs(a["grad_norm"] - b["grad_norm"]) <= 1e-6 * abs(b["grad_norm"]) for a, b in zip(after, before))
    return f"loss and gradient norm equal to before (1e-9, 1e-6 relative): {same}"


def main():
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import compile_profile

    compile_profile.before_after_cli(__doc__, Path(__file__).resolve(), child, "--limiter", ["cell", "continuous"],
                                     ["first_rollout_s", "advection_first_calls_s", "compile_s_all", "second_rollout_s",
                                      "plume32_ms_per_step"],
                                     ROOT / "bench" / "results" / "gas_compile_cpu.txt", _same)


if __name__ == "__main__":
    main()
