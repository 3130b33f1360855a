"""Why the cellular vortex decays too fast: its amplitude dependence and the liquid's J (issue: physics fidelity).

    python bench/vortex_jdrift.py

Writes bench/results/vortex_jdrift_cpu.txt (about 6 min on two cores). The vortex of apps/vortex.py at 24 cells per
10 cm, float32, stable substeps, in water of the catalogue's bulk modulus:
1. its decay over 100 ms against the amplitude U (0.3, 0.1, 0.03, 0.01 m/s), inviscid and with η = 5 Pa·s, by APIC
   and by AFLIP (α = 0.99, engine/transfer.py): a linear scheme decays at one rate whatever U; a transfer's
   dissipation is what AFLIP removes; and with J-bar (the liquids' J averaged through the grid, transfer.py);
2. the particles' J − 1 over time at U = 0.01 and 0.1 m/s: its rms and mean per unit U, how much of it survives an
   average over each grid cell (a smooth pattern survives, a particle-scale one does not), the correlation of the
   pattern with itself 10 ms earlier, and the pressure λ rms(J − 1) it stands for against the flow's ρU²;
3. the same small vortex (U = 0.01 m/s) over 0.8 s, and with a tenth of the bulk modulus.
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np


def water(bulk_factor=1.0, eta=0.0):
    from fluidlab_core import materials as M

    bulk = M.WATER.bulk_modulus * bulk_factor
    if eta > 0:
        return M.ViscousLiquid(f"viscous_{eta:g}_{bulk_factor:g}", density=1000.0, bulk_modulus=bulk,
                               viscosity_pas=eta)
    return M.NewtonianLiquid(f"water_inviscid_{bulk_factor:g}", density=1000.0, bulk_modulus=bulk)


def series(res, amplitude, seconds, every, flip=0.0, bulk_factor=1.0):
    """Rows (t, mode amplitude / U, rms(J−1)/U, mean(J−1)/U, rms of the cell-averaged J−1 / U, corr with the
    previous row's J pattern) every `every` steps of 1 ms."""
    from fluidlab_core.apps import vortex

    sim, k = vortex.vortex_simulator(water(bulk_factor), res, 0.1, amplitude, None, 1.0, flip)
    dx = 0.1 / res
    rows, prev = [], None
    while sim.time <= seconds + 1e-9:
        st = sim.get_state()
        x = st.x.astype(np.float64)
        J = np.linalg.det(st.F.astype(np.float64)) - 1.0
        shape, _ = vortex.mode_shape(x, k)
        amp = float((st.v * shape).sum() / (shape * shape).sum()) / amplitude
        cell = np.floor(x[:, [0, 2]] / dx).astype(int)
        key = cell[:, 0] * 10_000 + cell[:, 1]
        _, inv = np.unique(key, return_inverse=True)
        cell_mean = np.bincount(inv, J) / np.bincount(inv)
        corr = float(np.corrcoef(J, prev)[0, 1]) if prev is not None and J.std() > 0 and prev.std() > 0 else math.nan
        rows.append((sim.time, amp, math.sqrt((J ** 2).mean()) / amplitude, J.mean() / amplitude,
                     math.sqrt((cell_mean[inv] ** 2).mean()) / amplitude, corr))
        prev = J
        sim.step(n=every)
    return rows, sim.model.substeps


def main():
    import fluidlab_core as fl
    from fluidlab_core import materials as M
    from fluidlab_core.apps import vortex

    fl.init("cpu")
    t0 = time.time()
    res, k = 24, math.pi / 0.1
    lines = []

    def out(line=""):
        print(line, flush=True)
        lines.append(line)

    out(f"The cellular vortex's decay and the liquid's J (bench/vortex_jdrift.py), {res} cells per 10 cm, float32 CPU; "
        f"water λ = {M.WATER.bulk_modulus:.3g} Pa")
    out()
    out("1. Decay rate over 100 ms (1/s) against the amplitude U; excess = (rate(η = 5) − rate(inviscid)) / 2νk² "
        "(Navier–Stokes: 0 and 1)")
    out(f"{'U m/s':>6} {'APIC inv':>9} {'excess':>7} {'AFLIP inv':>9} {'excess':>7} {'J-bar inv':>9} {'excess':>7}")
    nu2k2 = 2 * 5.0 / 1000.0 * k * k
    for U in (0.3, 0.1, 0.03, 0.01):
        row = f"{U:>6g}"
        for flip, jbar in ((0.0, False), (0.99, False), (0.0, True)):
            r0 = vortex.decay_rate(water(), res=res, amplitude=U, duration=0.1, every=5, flip=flip, jbar=jbar)[0]
            r1 = vortex.decay_rate(water(eta=5.0), res=res, amplitude=U, duration=0.1, every=5, flip=flip,
                                   jbar=jbar)[0]
            row += f" {r0:>9.3f} {(r1 - r0) / nu2k2:>7.3f}"
        out(row)

    out()
    out("2. J − 1 of the particles (APIC, inviscid), per unit U; 'cells' = rms after averaging over each grid cell; "
        "p: λ rms(J − 1) against ρU²")
    for U in (0.1, 0.01):
        rows, sub = series(res, U, 0.1, 10)
        out(f"U = {U} m/s ({sub} substeps per ms)")
        out(f"{'t ms':>5} {'amp/U':>7} {'rms J-1':>9} {'mean J-1':>9} {'cells':>9} {'corr':>6} {'p Pa':>7} "
            f"{'rho U2':>7}")
        for t, amp, rms, mean, cells, corr in rows:
            out(f"{t * 1e3:>5.0f} {amp:>7.4f} {rms:>9.2e} {mean:>9.2e} {cells:>9.2e} {corr:>6.3f} "
                f"{M.WATER.bulk_modulus * rms * U:>7.2f} {1000 * U * U:>7.2f}")

    out()
    out("3. U = 0.01 m/s over 0.8 s (APIC, inviscid): the mode's amplitude / U; and with λ/10")
    long, _ = series(res, 0.01, 0.8, 80)
    soft, sub_soft = series(res, 0.01, 0.8, 80, bulk_factor=0.1)
    out(f"{'t ms':>5} {'amp/U':>7} {'rms J-1':>9} | {'amp/U, λ/10':>12} {'rms J-1':>9}")
    for a, b in zip(long, soft):
        out(f"{a[0] * 1e3:>5.0f} {a[1]:>7.4f} {a[2]:>9.2e} | {b[1]:>12.4f} {b[2]:>9.2e}")
    out()
    out(f"total {time.time() - t0:.0f} s")
    path = Path(__file__).resolve().parent / "results" / "vortex_jdrift_cpu.txt"
    if "--no-save" not in sys.argv:
        path.write_text("\n".join(lines) + "\n")
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
