"""Convergence under refinement (issue: physics fidelity): the validation scenes of fluidlab_core/apps/validation.py
and apps/vortex.py, each at three resolutions, float32 on the CPU, with the observed order of convergence.

    python bench/convergence.py [--only dam hydro rt vortex float float_projection] [--quick]

Writes bench/results/convergence_cpu.json (one entry per study, replaced when that study is re-run, so the studies
can run in separate processes) and renders all of them to bench/results/convergence_cpu.txt.

Studies (error e = |measured − reference|; the observed order between two resolutions is
p = ln(e₁/e₂)/ln(Δx₁/Δx₂), and for the dam break, which has no exact reference, Richardson's
p = ln((f₁ − f₂)/(f₂ − f₃))/ln 2 from three resolutions in ratio 2):
- dam: the surge front Z = x/a of a column a = 10 cm (Martin & Moyce 1952) at T = 2.5, at 32, 64 and 128 cells
  along the 50 cm tank; and its ratio to the measurement (which inviscid, frictionless simulations lead by
  10–20 %).
- hydro: water at rest, 12 cm deep, at 8, 16 and 32 cells over the 16 cm box, 1 s, pressure averaged over its
  last 0.2 s; the slope of p(depth) over ρg (reference 1).
- rt: Rayleigh–Taylor, A = 0.5, at 16, 32 and 64 cells per wavelength; σ over √(Akg) (reference 1, linear
  inviscid theory), for a 1.5 mm seed (kA = 0.09, the linear regime) with the layers started at their
  hydrostatic compression (Simulator.start_hydrostatic), and, for comparison, the test's earlier set-up: a 5 mm
  seed (kA = 0.31) from J = 1.
- vortex: the cellular vortex (L = 10 cm, U = 0.1 m/s) at 16, 24 and 32 cells per L: the inviscid decay rate
  over 50 ms (reference 0) and the viscous excess (η = 5 Pa·s, over 100 ms) over 2νk² (reference 1).
- float: a 4 cm rigid cube of 500 kg/m³ dropped from 1 cm onto 6 cm of water in a closed 12 cm tank (3-D) at
  12, 16 and 24 cells across, 1.5 s; the share of its volume below the surface its liquid's volume fills the
  tank to, averaged over 1.0–1.5 s (reference 0.50), and over 1.0–1.5 s of a 0.8 ρ_w cube at 16 cells
  (reference 0.80); beside it the old measures against the far field's 99th-percentile surface.
- float_projection: the same cube with Scene(pressure="projection") (engine/projection.py), started at rest at
  Archimedes' depth (the dropped cube's bobbing and tipping part two runs that differ only by rounding by 0.02 in a
  second's mean, more than the discretisation's share), at 16, 24 and 32 cells, twice the flow's stable substep
  count (as the bench's runs); the volume share averaged over 0.2–1.0 s (reference 0.50).
Each run uses the stable substep count of its resolution.
"""
from __future__ import annotations

import argparse
import fcntl
import json
import math
import os
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
JSON = RESULTS / "convergence_cpu.json"
TEXT = RESULTS / "convergence_cpu.txt"


def order(e1, e2, dx1, dx2):
    if not (e1 > 0 and e2 > 0):
        return math.nan
    return math.log(e1 / e2) / math.log(dx1 / dx2)


def study_dam(quick):
    from fluidlab_core.apps import validation

    rows = []
    for res in ((32, 64) if quick else (32, 64, 128)):
        t0 = time.time()
        r = validation.dam_break(res=res, substeps=None)
        z25 = float(np.interp(2.5, r["times"], r["fronts"]))
        rows.append(dict(res=res, dx_mm=r["dx"] * 1e3, substeps=r["substeps"], Z_at_2_5=z25,
                         ratio_min=float(r["ratio"].min()), ratio_max=float(r["ratio"].max()), speed=r["speed"],
                         seconds=time.time() - t0))
        print(rows[-1], flush=True)
    richardson = math.nan
    if len(rows) == 3:
        f1, f2, f3 = (row["Z_at_2_5"] for row in rows)
        if (f1 - f2) * (f2 - f3) > 0:
            richardson = math.log((f1 - f2) / (f2 - f3)) / math.log(2)
    return dict(rows=rows, richardson_order=richardson)


def study_hydro(quick):
    from fluidlab_core.apps import validation

    rows = []
    for res in ((8, 16) if quick else (8, 16, 32)):
        t0 = time.time()
        r = validation.water_column(res=res, steps=500, average=100, substeps=None)
        rows.append(dict(res=res, dx_mm=r["dx"] * 1e3, substeps=r["substeps"], slope_ratio=r["slope_ratio"],
                         r2=r["r2"], intercept_Pa=r["intercept"], worst_volume_error=r["worst_volume_error"],
                         error=abs(r["slope_ratio"] - 1.0), seconds=time.time() - t0))
        print(rows[-1], flush=True)
    return dict(rows=rows)


def study_rt(quick):
    from fluidlab_core import materials as M
    from fluidlab_core.apps import validation

    rows = []
    for res in ((32, 64) if quick else (32, 64, 128)):
        t0 = time.time()
        r = validation.rayleigh_taylor(M.RT_HEAVY, M.RT_LIGHT, res=res, substeps=None, amp=0.0015, hydrostatic=True)
        old = validation.rayleigh_taylor(M.RT_HEAVY, M.RT_LIGHT, res=res, substeps=None)
        ratio = r["sigma"] / r["sigma_theory"]
        rows.append(dict(res=res, per_wavelength=res // 2, dx_mm=r["dx"] * 1e3, substeps=r["substeps"],
                         sigma=r["sigma"], ratio=ratio, error=abs(ratio - 1.0),
                         ratio_5mm_from_J1=old["sigma"] / old["sigma_theory"], seconds=time.time() - t0))
        print(rows[-1], flush=True)
    return dict(rows=rows, sigma_theory=r["sigma_theory"])


def study_vortex(quick):
    from fluidlab_core import materials as M
    from fluidlab_core.apps import vortex

    inviscid = M.WATER  # the catalogue's water has no viscosity
    viscous = M.ViscousLiquid("viscous_5", density=1000.0, bulk_modulus=M.WATER.bulk_modulus, viscosity_pas=5.0)
    rows = []
    for res in ((16, 24) if quick else (16, 24, 32)):
        t0 = time.time()
        r0, k, sub = vortex.decay_rate(inviscid, res=res, duration=0.05, every=5)
        r0_long, _, _ = vortex.decay_rate(inviscid, res=res, duration=0.1, every=5)
        rv, _, _ = vortex.decay_rate(viscous, res=res, duration=0.1, every=5)
        nu_k2 = 2 * 5.0 / 1000.0 * k * k
        excess = (rv - r0_long) / nu_k2
        rows.append(dict(res=res, dx_mm=100.0 / res, substeps=sub, inviscid_rate=r0, viscous_excess=excess,
                         excess_error=abs(excess - 1.0), seconds=time.time() - t0))
        print(rows[-1], flush=True)
    return dict(rows=rows)


def study_float(quick):
    from fluidlab_core.apps import validation

    rows = []
    cases = [(12, 500.0), (16, 500.0)] if quick else [(12, 500.0), (16, 500.0), (24, 500.0), (16, 800.0)]
    for res, rho in cases:
        t0 = time.time()
        r = validation.floating_cube(res=res, density=rho, seconds=1.5, every=0.05,
                                     progress=lambda t, f: print(f"  {res} cells, {rho:g} kg/m³: t {t:.2f} s "
                                                                 f"fraction {f:.3f}", flush=True))
        window = r["times"] > 1.0 - 1e-9
        volume_share = float(r["volume_shares"][window].mean())
        rows.append(dict(res=res, density=rho, dx_mm=r["dx"] * 1e3, substeps=r["substeps"], particles=r["particles"],
                         volume_share=volume_share, spread=float(np.ptp(r["volume_shares"][window])),
                         fraction=float(r["fractions"][window].mean()), share=float(r["shares"][window].mean()),
                         expected=r["expected"], error=abs(volume_share - r["expected"]), seconds=time.time() - t0))
        print(rows[-1], flush=True)
    return dict(rows=rows)


def study_float_projection(quick):
    from fluidlab_core.apps import validation

    rows = []
    for res in ((16, 24) if quick else (16, 24, 32)):
        t0 = time.time()
        r = validation.floating_cube(res=res, density=500.0, seconds=1.0, drop=None, every=0.05, substep_factor=2,
                                     pressure="projection",
                                     progress=lambda t, f: print(f"  {res} cells: t {t:.2f} s", flush=True))
        window = r["times"] > 0.2 - 1e-9
        volume_share = float(r["volume_shares"][window].mean())
        rows.append(dict(res=res, density=500.0, dx_mm=r["dx"] * 1e3, substeps=r["substeps"],
                         particles=r["particles"], volume_share=volume_share,
                         spread=float(np.ptp(r["volume_shares"][window])), expected=r["expected"],
                         error=abs(volume_share - r["expected"]), seconds=time.time() - t0))
        print(rows[-1], flush=True)
    return dict(rows=rows)


STUDIES = {"dam": study_dam, "hydro": study_hydro, "rt": study_rt, "vortex": study_vortex, "float": study_float,
           "float_projection": study_float_projection}


def orders(rows, key="error"):
    """The observed order between each row and the one above (nan for the first)."""
    return [math.nan] + [order(a[key], b[key], a["dx_mm"], b["dx_mm"]) for a, b in zip(rows, rows[1:])]


def fmt(x, spec):
    return "" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def table(columns, rows):
    """Lines of a right-aligned table: columns are (header, width, key of the row, format spec)."""
    lines = [" ".join(f"{head:>{width}}" for head, width, _, _ in columns)]
    for row in rows:
        lines.append(" ".join(f"{fmt(row[key], spec):>{width}}" for _, width, key, spec in columns))
    return lines


def render(doc: dict) -> str:
    lines = ["Convergence under refinement (bench/convergence.py), float32 CPU, stable substeps at each resolution.",
             "Observed order p = ln(e1/e2)/ln(dx1/dx2) of the error e against the reference, between a row and the one above.",
             ""]
    if "dam" in doc:
        d = doc["dam"]
        lines += ["Dam break (Martin & Moyce 1952, a = 10 cm): surge front Z at T = 2.5; ratio to the measurement over "
                  "0.8 <= T <= 3.4"]
        lines += table([("cells", 6, "res", ""), ("dx mm", 6, "dx_mm", ".2f"), ("subst", 5, "substeps", ""),
                        ("Z(2.5)", 7, "Z_at_2_5", ".3f"), ("ratio min", 9, "ratio_min", ".3f"),
                        ("ratio max", 9, "ratio_max", ".3f"), ("dZ/dT", 6, "speed", ".3f"), ("s", 6, "seconds", ".0f")],
                       d["rows"])
        lines += [f"Richardson order of Z(2.5) from the three: {fmt(d['richardson_order'], '.2f') or 'n/a'}", ""]
    if "hydro" in doc:
        rows = doc["hydro"]["rows"]
        rows = [dict(r, order=p) for r, p in zip(rows, orders(rows))]
        lines += ["Hydrostatics (12 cm of water at rest, 1 s): slope of p(depth) over rho g (reference 1)"]
        lines += table([("cells", 6, "res", ""), ("dx mm", 6, "dx_mm", ".2f"), ("slope/rhog", 10, "slope_ratio", ".4f"),
                        ("r2", 7, "r2", ".4f"), ("intercept Pa", 12, "intercept_Pa", ".1f"),
                        ("volume err", 10, "worst_volume_error", ".2e"), ("order", 6, "order", ".2f")], rows)
        lines.append("")
    if "rt" in doc:
        rows = doc["rt"]["rows"]
        rows = [dict(r, order=p) for r, p in zip(rows, orders(rows))]
        lines += [f"Rayleigh-Taylor (A = 0.5, W = 10 cm): sigma over sqrt(Akg) = {doc['rt']['sigma_theory']:.1f} /s "
                  "(reference 1), fitted over 0.04-0.2 s; 1.5 mm seed, layers started at their hydrostatic compression; "
                  "last column: 5 mm seed from J = 1"]
        lines += table([("cells/W", 7, "per_wavelength", ""), ("dx mm", 6, "dx_mm", ".2f"), ("subst", 5, "substeps", ""),
                        ("sigma 1/s", 9, "sigma", ".2f"), ("ratio", 6, "ratio", ".3f"), ("order", 6, "order", ".2f"),
                        ("5mm/J=1", 7, "ratio_5mm_from_J1", ".3f")], rows)
        lines.append("")
    if "vortex" in doc:
        rows = doc["vortex"]["rows"]
        rows = [dict(r, order_inviscid=a, order_excess=b)
                for r, a, b in zip(rows, orders(rows, "inviscid_rate"), orders(rows, "excess_error"))]
        lines += ["Cellular (Taylor-Green) vortex, L = 10 cm: inviscid decay rate over 50 ms (reference 0) and the viscous "
                  "excess over 100 ms, eta = 5 Pa s, over 2 nu k^2 (reference 1)"]
        lines += table([("cells/L", 7, "res", ""), ("dx mm", 6, "dx_mm", ".2f"), ("subst", 5, "substeps", ""),
                        ("inviscid 1/s", 12, "inviscid_rate", ".2f"), ("order", 6, "order_inviscid", ".2f"),
                        ("excess", 7, "viscous_excess", ".3f"), ("order", 6, "order_excess", ".2f")], rows)
        lines.append("")
    if "float" in doc:
        rows = doc["float"]["rows"]
        half = [r for r in rows if r["density"] == 500.0]  # the resolution series; other densities stand alone
        order_of = {id(r): p for r, p in zip(half, orders(half))}
        rows = [dict(r, order=order_of.get(id(r), math.nan)) for r in rows]
        lines += ["Floating cube (3-D, 4 cm rigid cube dropped onto 6 cm of water, 12 cm tank): the share of its volume "
                  "below the surface its liquid's volume fills the tank to, over 1.0-1.5 s (reference rho/rho_w; "
                  "validation.submerged_by_volume), its spread, and the old measures against the far field's "
                  "99th-percentile surface (lowest face: fraction; particles: share), which read a disturbed surface high"]
        lines += table([("cells", 6, "res", ""), ("dx mm", 6, "dx_mm", ".2f"), ("kg/m3", 6, "density", ".0f"),
                        ("subst", 5, "substeps", ""), ("vol share", 9, "volume_share", ".3f"),
                        ("spread", 6, "spread", ".3f"), ("fraction", 8, "fraction", ".3f"), ("share", 6, "share", ".3f"),
                        ("expect", 6, "expected", ".2f"), ("order", 6, "order", ".2f"), ("s", 6, "seconds", ".0f")], rows)
        lines.append("")
    if "float_projection" in doc:
        rows = doc["float_projection"]["rows"]
        rows = [dict(r, order=p) for r, p in zip(rows, orders(rows))]
        lines += ["Floating cube with Scene(pressure=\"projection\"): a 4 cm rigid cube of 500 kg/m3 started at rest at "
                  "Archimedes' depth in 6 cm of water, 12 cm tank, twice the flow's stable substeps; the share of its "
                  "volume below the surface its liquid's volume fills the tank to, over 0.2-1.0 s (reference 0.50)"]
        lines += table([("cells", 6, "res", ""), ("dx mm", 6, "dx_mm", ".2f"), ("subst", 5, "substeps", ""),
                        ("particles", 9, "particles", ""), ("vol share", 9, "volume_share", ".3f"),
                        ("spread", 6, "spread", ".3f"), ("error", 6, "error", ".3f"), ("order", 6, "order", ".2f"),
                        ("s", 6, "seconds", ".0f")], rows)
        lines.append("")
    return "\n".join(lines)


def save(name: str, result: dict):
    """Merge one study into the JSON under a lock (studies may run in parallel processes), re-render the text."""
    RESULTS.mkdir(exist_ok=True)
    with open(RESULTS / ".convergence.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        doc = json.loads(JSON.read_text()) if JSON.exists() else {}
        doc[name] = result
        for path, text in ((JSON, json.dumps(doc, indent=1)), (TEXT, render(doc))):
            tmp = path.with_suffix(path.suffix + ".tmp")
            tmp.write_text(text + "\n")
            os.replace(tmp, path)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", choices=list(STUDIES), default=list(STUDIES))
    ap.add_argument("--quick", action="store_true", help="two resolutions each (a smoke run; not saved)")
    args = ap.parse_args()
    import fluidlab_core as fl

    fl.init("cpu")
    for name in args.only:
        t0 = time.time()
        print(f"== {name}", flush=True)
        result = STUDIES[name](args.quick)
        result["seconds"] = time.time() - t0
        result["date"] = time.strftime("%Y-%m-%d")
        if args.quick:
            print(render({name: result}), flush=True)
        else:
            save(name, result)
            print(render({name: result}), flush=True)


if __name__ == "__main__":
    main()
