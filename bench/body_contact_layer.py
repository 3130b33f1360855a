"""Where the liquid sits against a floating rigid body's faces over time (issue 19, the slow sinking of light
bodies; docs/engine.md, "Floating bodies in 3-D").

    python bench/body_contact_layer.py [--res 16] [--seconds 4] [--every 0.25] [--out FILE]

A 4 cm cube of 500 kg/m³ dropped from 1 cm onto 6 cm of water in a closed 12 cm tank (apps/validation.py's
floating_cube set-up, float32, CPU). Every `--every` seconds, in the cube's own frame (its pose fitted to its
particles: centre of mass and the rotation of the Kabsch fit to the rest offsets), each water particle's
signed distance φ to the cube's surface (the box's SDF; negative inside), and:
- frac: the cube's lowest face below the far-field surface over its side (validation.submerged; Archimedes 0.50);
- φ bins: how many water particles lie inside (φ < −1e-3 s), on the surface (|φ| ≤ 1e-3 s, where rigid.py's
  exclusion step puts a particle it found inside), and in the bands up to one particle spacing s outside;
- overlap: the volume the water particles within s/2 of the bottom face and of the side faces take from the
  cube, Σ (s/2 − φ) s², over the cube's volume (a water particle stands for a cube of side s about its centre,
  so at φ ≥ s/2 it takes nothing);
- vn: the mean velocity of those bottom-face particles away from the cube relative to its mean velocity, and
  the cube's vertical velocity (mm/s);
- tilt: the angle between the cube's vertical axis and the world's (degrees).
Writes the table to --out (default bench/results/body_contact_layer.txt).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
# |φ| within this many particle spacings counts as on the surface: the pose fitted to float32 positions is good to
# about 1e-7 m, 3e-5 s at 16 cells
TOL = 1e-3


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--res", type=int, default=16)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--every", type=float, default=0.25)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "body_contact_layer.txt"))
    args = ap.parse_args()

    import fluidlab_core as fl
    from fluidlab_core import materials as M
    from fluidlab_core.apps import validation as V
    from fluidlab_core.shapes import Box

    fl.init()
    width, side = 0.12, 0.04
    sim, scene = V.floating_cube_sim(args.res, M.Rigid("rigid_500", density=500.0), M.WATER, width=width, side=side)
    c = width / 2
    dx, s, h = width / args.res, scene.particle_spacing, side / 2
    cube = Box((-h, -h, -h), (h, h, h))  # in the cube's frame
    rest = sim.positions("cube").astype(np.float64)
    q = rest - rest.mean(0)
    lines = [f"# body_contact_layer: {args.res} cells (dx {dx * 1e3:.2f} mm), particle spacing s = {s * 1e3:.3f} mm, "
             f"{scene.substeps} substeps per 2 ms step; 500 kg/m³ rigid cube dropped from 10 mm (Archimedes 0.50)",
             "  t s  frac  | water by φ: inside  on-surface  (0,s/4)  [s/4,s/2)  [s/2,3s/4)  [3s/4,s) | overlap/V: "
             "bottom  sides | vn bottom mm/s  cube vz mm/s | tilt °"]

    def log(line):
        print(line, flush=True)
        lines.append(line)

    for line in lines:
        print(line)
    t0 = time.time()
    while sim.time < args.seconds - 1e-9:
        sim.step(n=max(1, int(round(args.every / scene.dt))))
        xw = sim.positions("water").astype(np.float64)
        xc = sim.positions("cube").astype(np.float64)
        frac, _, _ = V.submerged(xw, xc, (c, c), side, dx, s)
        centre = xc.mean(0)
        u, _, vt = np.linalg.svd((xc - centre).T @ q)
        rot = u @ vt
        local = (xw - centre) @ rot  # Rᵀ (x − c) for each particle
        phi = cube.sdf(local)
        dist = np.abs(local) - h  # per axis: the largest says which face is nearest
        near = phi < s
        face = np.argmax(dist, axis=1)
        bottom_face = near & (face == 2) & (local[:, 2] < 0)
        side_face = near & (face < 2)
        counts = [int((phi < -TOL * s).sum()), int((np.abs(phi) <= TOL * s).sum())]
        counts += np.histogram(phi[near & (phi > TOL * s)], bins=[TOL * s, 0.25 * s, 0.5 * s, 0.75 * s, s])[0].tolist()
        overlap = np.clip(0.5 * s - phi, 0.0, s) * s * s / side ** 3
        vw = sim.velocities("water").astype(np.float64)
        vc = sim.velocities("cube").astype(np.float64).mean(0)
        vn = -((vw[bottom_face] - vc) @ rot)[:, 2]  # away from the bottom face (its outward normal is −z)
        log(f"{sim.time:5.2f}  {frac:.3f} | {counts[0]:16d}  {counts[1]:10d}  {counts[2]:7d}  {counts[3]:9d}  "
            f"{counts[4]:10d}  {counts[5]:8d} | {overlap[bottom_face].sum():17.3f}  {overlap[side_face].sum():5.3f} | "
            f"{vn.mean() * 1e3:+14.3f}  {vc[2] * 1e3:+12.2f} | {np.degrees(np.arccos(np.clip(rot[2, 2], -1, 1))):.2f}")
    log(f"# {time.time() - t0:.0f} s")
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
