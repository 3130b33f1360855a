"""Fit the heave equation to a submerged cube's rise from the experiment's body logs (FL_LOGBODY=1 ... --dump X.npz
writes X_body.npy: per substep t, ω, v, τ, F, c; v as the rigid projection leaves it, before the substep's push F,
so the body's velocity at the end of the substep is v + F Δt / M).

    (M + m_a) dv/dt = F_net − c v      (F_net = (ρ_w − ρ) g a³, the net buoyancy of the fully submerged cube)

A least-squares line through the substeps' (v, dv/dt) after the start (t ≥ --from) gives the intercept
F_net / (M + m_a), hence the added mass coefficient C_a = m_a / (ρ_w a³), and the slope −c / (M + m_a), hence a
linear resistance c (N s/m). Steady quadratic drag ½ ρ_w C_d a² v² (C_d 1.05) is under 7 % of F_net at these speeds (v < 0.1 m/s),
so a c well above zero is a resistance the liquid should not have (the more so as the body has moved too little
for a wake to form).

It also prints each log's lag behind the potential-flow start: the time (v_ideal − v) / a₀ by which the body's
velocity trails v_ideal = a₀ t, a₀ = F_net / (M + C_a ρ_w a³) with the potential flow's C_a (--ca, 0.71 for the
mid-depth start, bench/results/added_mass.txt), at 0.01, 0.05 and 0.1 s.

    python fit_rise.py rise800start_body.npy [more logs] [--from 0.004] [--density 800] [--ca 0.71]
"""
import argparse

import numpy as np

G, RHO_W, SIDE = 9.81, 1000.0, 0.04


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="+")
    ap.add_argument("--from", dest="t0", type=float, default=0.004, help="first time fitted (s)")
    ap.add_argument("--density", type=float, default=800.0)
    ap.add_argument("--ca", type=float, default=0.71, help="the potential flow's added mass coefficient")
    args = ap.parse_args()
    M = args.density * SIDE ** 3
    f_net = (RHO_W - args.density) * G * SIDE ** 3
    print(f"# heave equation fitted to dv/dt = A - B v (t >= {args.t0} s); C_a = (F_net / A - M) / (rho_w a^3), "
          f"c = B (M + m_a)")
    a0 = f_net / (M + args.ca * RHO_W * SIDE ** 3)
    print("# log                                   substeps  v max (m/s)   A (m/s2)   B (1/s)    C_a     c (N s/m)"
          f"   lag (s) at 0.01, 0.05, 0.1 s behind a0 = {a0:.3f} m/s2")
    for path in args.logs:
        b = np.load(path)
        t = b[:, 0]
        v = b[:, 6] + b[:, 12] * (t[1] - t[0]) / M  # after the substep's push
        dvdt = np.diff(v) / np.diff(t)
        vm = 0.5 * (v[1:] + v[:-1])
        tm = 0.5 * (t[1:] + t[:-1])
        keep = tm >= args.t0
        slope, intercept = np.polyfit(vm[keep], dvdt[keep], 1)
        A, B = intercept, -slope
        mass = f_net / A
        c_a = (mass - M) / (RHO_W * SIDE ** 3)
        lags = [(a0 * t[i] - v[i]) / a0 for i in (int(np.argmin(abs(t - T))) for T in (0.01, 0.05, 0.1))]
        print(f"  {path:<38} {int(keep.sum()):8d}  {v.max():10.4f}   {A:8.3f}   {B:8.3f}   {c_a:6.3f}   {B * mass:8.4f}"
              f"   {lags[0]:.4f} {lags[1]:.4f} {lags[2]:.4f}")


if __name__ == "__main__":
    main()
