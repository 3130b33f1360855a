"""A submerged cube's rise on the projection: the added mass and the linear resistance the coupling gives it
(issue 19; docs/engine.md, "The walls' contact ... A submerged body's rise"), against the potential flow's.

A 4 cm cube of 800 kg/m³ released at rest mid-depth in 100 mm of water (30 mm of liquid above and below it) in a
closed 12 cm tank (apps/validation.floating_cube_sim with level 0.10, raise −0.038) rises under its net buoyancy.
A line through the steps' (v, dv/dt) from --from on fits the heave equation

    (M + m_a) dv/dt = F_net − c v,    F_net = (ρ_w V − M) g,   C_a = m_a / (ρ_w V)

(V, M: the body's particles' volume and mass), its intercept giving C_a and its slope c (N s/m). The potential
flow around the cube in this tank gives C_a = 0.71 ± 5 % (bench/added_mass.py, bench/results/added_mass.txt); a
body that has moved under 2 mm meets next to no resistance. Also the lag: how long the body's velocity trails
a₀ t, a₀ = F_net / (M + 0.71 ρ_w V), at 0.05 and 0.1 s.

    python bench/rise_added_mass.py [--res 16 24 32] [--open-min 0.5 0.2] [--seconds 0.1] [--from 0.011]

Each (res, OPEN_MIN) runs in its own process (OPEN_MIN is read when the kernels compile). Appends its table to
bench/results/rise_added_mass.txt.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

G, RHO_W, CA_POTENTIAL = 9.81, 1000.0, 0.71


def one(res: int, open_min: float, seconds: float) -> dict:
    """Run one rise in this process: {t, v} per step, M, V, substeps."""
    import fluidlab_core as fl
    from fluidlab_core import materials as M
    from fluidlab_core.apps import validation

    fl.init("cpu")
    body = M.Rigid("rigid_800", density=800.0)
    sim, scene = validation.floating_cube_sim(res, body, M.WATER, drop=None, level=0.10, lift=-0.038,
                                              substep_factor=2, pressure="projection")
    sim.solver.proj.open_min = open_min  # the shell-node rule's threshold (read when the kernels compile)
    mass = float((sim.volumes("cube") * 800.0).sum())
    vol = float(sim.volumes("cube").sum())
    t, v, z = [0.0], [0.0], [float(sim.positions("cube")[:, 2].mean())]
    while sim.time < seconds - 1e-9:
        sim.step()
        t.append(sim.time)
        v.append(float(sim.velocities("cube")[:, 2].mean()))
        z.append(float(sim.positions("cube")[:, 2].mean()))
    return {"t": t, "v": v, "z": z, "M": mass, "V": vol, "substeps": scene.substeps}


def fit(run: dict, t0: float) -> dict:
    t, v = np.array(run["t"]), np.array(run["v"])
    f_net = (RHO_W * run["V"] - run["M"]) * G
    dvdt = np.diff(v) / np.diff(t)
    vm, tm = 0.5 * (v[1:] + v[:-1]), 0.5 * (t[1:] + t[:-1])
    keep = tm >= t0
    slope, intercept = np.polyfit(vm[keep], dvdt[keep], 1)
    mass = f_net / intercept
    c_a = (mass - run["M"]) / (RHO_W * run["V"])
    a0 = f_net / (run["M"] + CA_POTENTIAL * RHO_W * run["V"])
    lag = {T: float((a0 * T - np.interp(T, t, v)) / a0) for T in (0.05, 0.1) if T <= t[-1] + 1e-9}
    return {"C_a": float(c_a), "c": float(-slope * mass), "v_end": float(v[-1]),
            "rise_mm": float((run["z"][-1] - run["z"][0]) * 1e3), "lag": lag, "points": int(keep.sum())}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, nargs="+", default=[16, 24])
    ap.add_argument("--open-min", type=float, nargs="+", default=[0.5, 0.2])
    ap.add_argument("--seconds", type=float, default=0.1)
    ap.add_argument("--from", dest="t0", type=float, default=0.011, help="first time fitted (s)")
    ap.add_argument("--one", nargs=2, type=float, help=argparse.SUPPRESS)  # res, OPEN_MIN: one run, JSON out
    args = ap.parse_args()
    if args.one:
        print("RESULT " + json.dumps(one(int(args.one[0]), args.one[1], args.seconds)), flush=True)
        return
    rows = [f"{'cells':>5} {'OPEN_MIN':>8} {'substeps':>8} {'C_a':>6} {'c N s/m':>8} {'rise mm':>8} {'v m/s':>7}"
            f" {'lag 0.05 s':>10} {'lag 0.1 s':>9} {'wall s':>6}"]
    for res in args.res:
        for om in args.open_min:
            t0 = time.time()
            out = subprocess.run([sys.executable, __file__, "--one", str(res), str(om), "--seconds", str(args.seconds)],
                                 capture_output=True, text=True)
            line = next((x for x in out.stdout.splitlines() if x.startswith("RESULT ")), None)
            if line is None:
                raise RuntimeError(f"the run at {res} cells, OPEN_MIN {om} failed:\n{out.stderr[-3000:]}")
            run = json.loads(line[7:])
            f = fit(run, args.t0)
            rows.append(f"{res:>5} {om:>8g} {run['substeps']:>8} {f['C_a']:>6.3f} {f['c']:>8.4f} {f['rise_mm']:>8.2f}"
                        f" {f['v_end']:>7.4f} {f['lag'].get(0.05, float('nan')):>10.4f}"
                        f" {f['lag'].get(0.1, float('nan')):>9.4f} {time.time() - t0:>6.0f}")
            print(rows[-1], flush=True)
    text = "\n".join([f"Submerged 800 kg/m³ cube's rise on the projection ({time.strftime('%Y-%m-%d')}; 4 cm cube mid-depth "
                      f"in 100 mm of water, 12 cm tank; fitted from {args.t0} s to {args.seconds} s; potential flow "
                      f"C_a {CA_POTENTIAL} ± 5 %)", *rows]) + "\n"
    print(text)
    with open(Path(__file__).resolve().parent / "results" / "rise_added_mass.txt", "a") as fh:
        fh.write(text + "\n")


if __name__ == "__main__":
    main()
