"""The transfer's numerical dissipation and one remedy for it, AFLIP, measured against APIC (issue: physics fidelity).

    python bench/transfer_remedies.py [--variants 0 0.9 0.97 0.99 jbar jbar+0.99 jbar-affine] [--quick [--cost]]
                                      [--out FILE]

Writes bench/results/transfer_remedies_cpu.txt (about 25 min on two cores). For each variant: a FLIP share α (0 is
APIC, the engine's default; α > 0 is AFLIP, Fei et al. 2021), `jbar` (the liquids' J averaged through the grid before
each substep, APIC), `jbar-affine` (the same with an affine fit of J at each node), or `jbar+α` (both);
engine/transfer.py has the formulas. In float32 on the CPU at the stable
substep count:
- the inviscid cellular vortex's decay rate over 50 ms at 16, 24 and 32 cells per 10 cm (Navier–Stokes: 0) and its
  observed order p = ln(r₁/r₂)/ln(Δx₁/Δx₂) (apps/vortex.py);
- the viscous excess (rate(η) − rate(inviscid)) / 2νk² over 100 ms at 24 cells for η = 2 and 5 Pa·s (Navier–Stokes:
  1; issue 19 asks for it within 10 %);
- what AFLIP must not spoil: water at rest (16 cells, 1 s: hydrostatic slope over ρg and the spread of the top layer's
  heights, a noisy surface spreads), the dam break's front Z at T = 2.5 (32 cells; APIC's 3.24 is converged,
  README), and the sound ring's decay (24 cells: AFLIP damps the weakly compressible liquid's ring less);
- the flow around a body: the rise of a submerged 4 cm, 500 kg/m³ rigid cube in its first 0.15 s at 16 and 24 cells
  (physics: 20–45 mm; bench/numerical_dissipation.py);
- cost: wall time per substep of a 3-D dam break (32 cells, ~65k particles), the variants stepped alternately in
  one process after compiling, as a ratio to APIC's.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def parse(variant: str):
    """(flip, jbar) of a variant name: "0.99", "jbar", "jbar+0.99", "jbar-affine", "jbar-affine+0.99"."""
    for name, jbar in (("jbar-affine", "affine"), ("jbar", True)):
        if variant.startswith(name):
            rest = variant[len(name):].lstrip("+")
            return (float(rest) if rest else 0.0), jbar
    return float(variant), False


def inviscid(res: int, duration: float, flip: float, jbar: bool = False):
    from fluidlab_core import materials as M
    from fluidlab_core.apps import vortex

    water = M.NewtonianLiquid("water_inviscid", density=1000.0, bulk_modulus=M.WATER.bulk_modulus)
    rate, k, sub = vortex.decay_rate(water, res=res, duration=duration, every=5, flip=flip, jbar=jbar)
    return rate, k, sub


def viscous(res: int, duration: float, eta: float, flip: float, jbar: bool = False):
    from fluidlab_core import materials as M
    from fluidlab_core.apps import vortex

    liquid = M.ViscousLiquid(f"viscous_{eta:g}", density=1000.0, bulk_modulus=M.WATER.bulk_modulus, viscosity_pas=eta)
    rate, k, sub = vortex.decay_rate(liquid, res=res, duration=duration, every=5, flip=flip, jbar=jbar)
    return rate, k, sub


def dam_scene(flip: float, jbar: bool = False, res: int = 32):
    """A 3-D dam break: a 0.5 × 1 × 0.5 m block of water in a 1 m tank (the speed probe)."""
    import fluidlab_core as fl
    from fluidlab_core import materials as M

    scene = fl.Scene(lower=(0, 0, 0), upper=(1, 1, 1), grid_res=res, dt=2e-3, substeps=1, flip=flip,
                     jbar=jbar)
    scene.add_particles(fl.Box((0, 0, 0), (0.5, 1, 0.5)), M.WATER, name="water")
    scene.substeps = scene.stable_substeps()
    return scene.build(), scene.substeps


def cost(variants, rounds: int = 3, steps: int = 3):
    """ms per substep for each variant, stepped alternately after a warm-up (compile) step."""
    sims = {}
    for a in variants:
        sim, sub = dam_scene(*parse(a))
        sim.step()  # compile
        sims[a] = (sim, sub)
    times = {a: [] for a in variants}
    for _ in range(rounds):
        for a in variants:
            sim, sub = sims[a]
            t = time.perf_counter()
            sim.step(n=steps)
            times[a].append((time.perf_counter() - t) / (steps * sub) * 1e3)
    n = next(iter(sims.values()))[0].n_particles
    return {a: float(np.median(v)) for a, v in times.items()}, n


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", nargs="+", default=["0", "0.9", "0.97", "0.99", "jbar", "jbar+0.99"],
                    help="FLIP shares (0: APIC), jbar, jbar+share")
    ap.add_argument("--quick", action="store_true", help="16 and 24 cells only, no cube at 24, no cost probe")
    ap.add_argument("--cost", action="store_true", help="the cost probe also with --quick")
    ap.add_argument("--out", default=None, help="results file (default bench/results/transfer_remedies_cpu.txt)")
    ap.add_argument("--no-save", action="store_true")
    args = ap.parse_args()
    import fluidlab_core as fl
    from fluidlab_core import materials as M
    from fluidlab_core.apps import validation
    from numerical_dissipation import cube_rise

    fl.init("cpu")
    t0 = time.time()
    lines = []

    def out(line=""):
        print(line, flush=True)
        lines.append(line)

    out("APIC, AFLIP and J-bar (bench/transfer_remedies.py), float32 CPU, stable substeps; variant: the FLIP share α "
        "(0: APIC), jbar (J averaged through the grid), jbar+α")
    vortex_res = [16, 24] if args.quick else [16, 24, 32]
    cube_res = [16] if args.quick else [16, 24]
    out()
    out("1. Inviscid cellular vortex, L = 10 cm, U = 0.1 m/s: decay rate over 50 ms (Navier–Stokes: 0), 1/s; order")
    out(f"{'variant':>9} " + " ".join(f"{f'{r} cells':>9}" for r in vortex_res) + f" {'order':>12} {'substeps':>12}")
    inv = {}
    for a in args.variants:
        rates, subs = [], []
        for r in vortex_res:
            rate, k, sub = inviscid(r, 0.05, *parse(a))
            rates.append(rate)
            subs.append(sub)
        inv[a] = rates
        orders = [math.log(rates[i] / rates[i + 1]) / math.log(vortex_res[i + 1] / vortex_res[i])
                  for i in range(len(rates) - 1) if rates[i] > 0 and rates[i + 1] > 0]
        out(f"{a:>9} " + " ".join(f"{x:>9.3f}" for x in rates) + f" {' '.join(f'{o:.2f}' for o in orders):>12} "
            f"{' '.join(str(s) for s in subs):>12}")

    out()
    out("2. Viscous excess over 100 ms at 24 cells: (rate(η) − rate(inviscid, same α)) / 2νk² (Navier–Stokes: 1)")
    out(f"{'variant':>9} {'inviscid':>9} {'eta 2':>8} {'excess':>7} {'eta 5':>8} {'excess':>7}")
    k = math.pi / 0.1
    for a in args.variants:
        base, _, _ = inviscid(24, 0.1, *parse(a))
        row = f"{a:>9} {base:>9.3f}"
        for eta in (2.0, 5.0):
            rate, _, _ = viscous(24, 0.1, eta, *parse(a))
            row += f" {rate:>8.3f} {(rate - base) / (2 * eta / 1000.0 * k * k):>7.3f}"
        out(row)

    out()
    out("3. What must not change: water at rest (16 cells, 1 s), dam break (32 cells), sound ring (24 cells); the cube")
    out(f"{'variant':>9} {'slope/rho g':>11} {'surf mm':>8} {'dam Z(2.5)':>10} {'ring 1/s':>9} {'swing Pa':>8} " +
        " ".join(f"{f'rise {r} mm':>11}" for r in cube_res))
    for a in args.variants:
        flip, jbar = parse(a)
        rest = validation.water_column(res=16, steps=500, average=100, substeps=None, flip=flip, jbar=jbar)
        dam = validation.dam_break(res=32, substeps=None, flip=flip, jbar=jbar)
        z25 = float(np.interp(2.5, dam["times"], dam["fronts"]))
        ring = validation.sound_ring(24, flip=flip, jbar=jbar)
        rises = [cube_rise(r, 0.15, flip=flip, jbar=jbar)[0] * 1e3 for r in cube_res]
        out(f"{a:>9} {rest['slope_ratio']:>11.3f} {rest['surface_spread'] * 1e3:>8.2f} {z25:>10.3f} "
            f"{ring['decay_rate']:>9.2f} {ring['first_swing']:>8.0f} " + " ".join(f"{x:>11.2f}" for x in rises))

    if not args.quick or args.cost:
        out()
        out("4. Cost: 3-D dam break, 32 cells, ms per substep (median of 3 alternating rounds) and ratio to APIC")
        probe = ["0"] + [a for a in args.variants if a not in ("0", "0.9", "0.97")]
        ms, n = cost(probe)
        for a in probe:
            out(f"{a:>9} {ms[a]:>8.2f} ms  x{ms[a] / ms['0']:.2f}   ({n} particles)")
    out()
    out(f"total {time.time() - t0:.0f} s")
    if not args.no_save:
        default = Path(__file__).resolve().parent / "results" / "transfer_remedies_cpu.txt"
        path = Path(args.out) if args.out else default
        path.write_text("\n".join(lines) + "\n")
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
