"""A floating cube's stability against the metacentric criterion (issue 19: floating bodies).

A cube of side a and density ratio s = ρ/ρ_w floats face up with s a under the surface. Tilted by a small angle θ
about a horizontal axis through its centre, the buoyancy's line of action crosses the cube's vertical axis at the
metacentre M, a height BM = I / V_sub over the centre of buoyancy B, with I = a⁴/12 the waterplane's second moment
(the same about every horizontal axis of a square) and V_sub = s a³. The restoring arm is GM sin θ with

    GM = BM − BG = a / (12 s) − a (1 − s) / 2,

so the upright cube is stable (GM > 0) only when 6 s (1 − s) < 1, that is s < 0.211 or s > 0.789 (e.g. Rayner,
"Floating cubes", Math. Gazette 1970; any naval-architecture text's metacentric height). Between, it rolls over
to a tilted rest. The Gathering tasks' foam (s = 0.4) lies in that range.

Set-up (validation.floating_cube_sim's tank): a 4 cm rigid cube tilted by --tilt degrees about y, centred over
the 12 cm tank at Archimedes' depth (its centre s a − a/2 under the 6 cm surface), the tasks' water (sound speed 4
m/s) sampled round it, at rest; `res` cells across. Each row: the cube's tilt from upright (degrees; the angle
between the vertical and the nearest body axis: 45 edge down, 54.7 corner down) at times t, for each density ratio;
the criterion says whether the start tilt should grow (unstable) or stay (stable). Both liquids: "projection"
(Scene(pressure="projection"), an incompressible liquid solved with the body) and "state" (the tasks' default
weakly compressible liquid). The linearised roll grows as e^(λt), λ² = m g |GM| / (I + added inertia), with
m a²/6 for I: λ ≤ 11.6 /s at s = 0.4 (an e-fold in 0.086 s or more).

    python bench/cube_roll.py [--ratios 0.4 0.9] [--pressures projection state] [--res 16] [--tilt 5]
        [--seconds 1] [--flip A] [--water task|std] [--contact-fill F] [--out bench/results/cube_roll.txt]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from results_file import append_table  # bench/results_file.py (this script's folder is on the path)

ROOT = Path(__file__).resolve().parents[1]
SIDE, WIDTH, LEVEL = 0.04, 0.12, 0.06  # m: the cube's side, the tank's width, the water's depth


def metacentric_height(s: float, a: float = SIDE) -> float:
    """GM (m) of an upright floating cube of side a and density ratio s: positive where it is stable."""
    return a / (12.0 * s) - a * (1.0 - s) / 2.0


WATERS = {"task": "the tasks' water", "std": "the catalogue's water"}  # --water's choices, as the headers name them


def liquid_of(water: str):
    """The liquid --water names: the tasks' water (sound speed 4 m/s) or the catalogue's (2.78e5 Pa, 16.7 m/s)."""
    from fluidlab_core import materials as M
    from fluidlab_core.tasks import common

    return common.WATER if water == "task" else M.WATER


def add_liquid_options(ap):
    """--flip and --water (this script's and bench/spin_down.py's)."""
    ap.add_argument("--flip", type=float, default=None, help="Scene(flip=...): AFLIP's share (default: the Scene's, "
                    "0.99 on the projection and 0, APIC, on the default liquid)")
    ap.add_argument("--water", choices=sorted(WATERS), default="task",
                    help="the tasks' water (sound speed 4 m/s) or the catalogue's (bulk modulus 2.78e5 Pa, sound "
                    "speed 16.7 m/s)")


def build(s: float, pressure: str, res: int, tilt_deg: float, flip: float | None = None, water: str = "task",
          contact_fill: float = 0.97):
    """(simulator, body-frame z axes of the cube's particles' fit): the tilted cube at Archimedes' depth."""
    import fluidlab_core as fl
    from fluidlab_core import materials as M
    from fluidlab_core.apps import validation
    import trimesh

    from fluidlab_core.shapes import Box, Mesh
    from fluidlab_core.tasks import common
    from fluidlab_core.tasks.common import Without

    half = np.radians(tilt_deg) / 2.0
    pose = (WIDTH / 2, WIDTH / 2, LEVEL - s * SIDE + SIDE / 2, 0.0, np.sin(half), 0.0, np.cos(half))
    # a tilted rigid body needs a shape the engine's contact has an SDF for: a box mesh (trimesh) at the pose
    path = Path(tempfile.mkdtemp()) / "cube.stl"
    trimesh.creation.box(extents=(SIDE, SIDE, SIDE)).export(path)
    cube = Mesh(str(path), pose=pose)
    scene = fl.Scene(lower=(0, 0, 0), upper=(WIDTH, WIDTH, 0.12), grid_res=res, dt=2e-3, substeps=1,
                     pressure=pressure, flip=flip, contact_fill=contact_fill)
    scene.add_particles(Without(Box((0, 0, 0), (WIDTH, WIDTH, LEVEL)), [cube]), liquid_of(water), name="water")
    body = M.Rigid(f"rigid_{s:g}", density=s * common.WATER.density, bulk_modulus=M.RIGID.bulk_modulus)
    scene.add_particles(cube, body, name="cube")
    validation._substeps(scene, None)
    return scene.build(), scene


def tilt_degrees(start: np.ndarray, now: np.ndarray, tilt0_deg: float) -> float:
    """The cube's tilt from upright (degrees): the angle between the vertical and the nearest of its three body
    axes, so 0 face up, 45 edge down, 54.7 corner down (a cube turned by 90° is upright again). Its orientation is
    its start tilt (about y) composed with the rotation that best maps its particles at the start onto them now
    (validation.best_rotation)."""
    from fluidlab_core.apps.validation import best_rotation

    r = best_rotation(start, now)
    t = np.radians(tilt0_deg)
    axes0 = np.array([[np.cos(t), 0.0, -np.sin(t)], [0.0, 1.0, 0.0], [np.sin(t), 0.0, np.cos(t)]])  # body x, y, z
    up = np.abs((r @ axes0.T)[2]).max()
    return float(np.degrees(np.arccos(np.clip(up, -1.0, 1.0))))


def run(s: float, pressure: str, res: int, tilt: float, seconds: float, every: float, flip: float | None = None,
        water: str = "task", contact_fill: float = 0.97) -> tuple[list[float], list[float], float]:
    import fluidlab_core as fl
    from fluidlab_core.apps.validation import cube_volume_share

    sim, scene = build(s, pressure, res, tilt, flip, water, contact_fill)
    start = sim.positions("cube")
    n_every = int(round(every / scene.dt))
    angles, shares, t0 = [], [], time.perf_counter()
    for _ in range(int(round(seconds / every))):
        sim.step(n=n_every)
        angles.append(tilt_degrees(start, sim.positions("cube"), tilt))
        shares.append(cube_volume_share(sim, WIDTH)[0])
    wall = time.perf_counter() - t0
    fl.runtime.reset()
    return angles, shares, wall


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ratios", nargs="+", type=float, default=[0.4, 0.9])
    ap.add_argument("--pressures", nargs="+", default=["projection", "state"], choices=["projection", "state"])
    ap.add_argument("--res", type=int, default=16)
    ap.add_argument("--tilt", type=float, default=5.0, help="the start tilt about y (degrees)")
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--every", type=float, default=0.1, help="a column every this many seconds")
    add_liquid_options(ap)
    ap.add_argument("--contact-fill", type=float, default=0.97,
                    help="Scene(contact_fill=...) on the default liquid: the node fill at which the liquid and the "
                    "body share one velocity (engine/grid.py); above 1 fewer nodes share it, and 2 none")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "cube_roll.txt"))
    args = ap.parse_args(argv)
    import fluidlab_core as fl

    fl.init(arch="cpu")
    times = [args.every * (k + 1) for k in range(int(round(args.seconds / args.every)))]
    water = WATERS[args.water]
    fill = "" if args.contact_fill == 0.97 else f", contact_fill {args.contact_fill:g}"
    flip = "the Scene's flip (0.99 on the projection, APIC on the default)" if args.flip is None else f"flip {args.flip:g}"
    lines = [f"# bench/cube_roll.py, {time.strftime('%Y-%m-%d %H:%M')}, CPU, float32: a 4 cm rigid cube in 6 cm of "
             f"{water}, {flip}{fill}, 12 cm tank, {args.res} cells, started at rest at Archimedes' depth tilted "
             f"{args.tilt:g}° about y",
             "# criterion: upright is stable where GM = a/(12 s) − a(1 − s)/2 > 0 (s < 0.211 or s > 0.789)",
             "# pressure | s | GM mm | criterion | tilt (degrees) at " + ", ".join(f"{t:g}" for t in times)
             + " s | submerged share (s when afloat at rest; validation.cube_volume_share, a level body's count) | "
             "wall s"]
    print("\n".join(lines), flush=True)
    for pressure in args.pressures:
        for s in args.ratios:
            gm = metacentric_height(s)
            angles, shares, wall = run(s, pressure, args.res, args.tilt, args.seconds, args.every, args.flip, args.water,
                               args.contact_fill)
            line = (f"{pressure} | {s:g} | {gm * 1e3:+.2f} | {'stable' if gm > 0 else 'rolls'} | "
                    + ", ".join(f"{a:.1f}" for a in angles) + " | " + ", ".join(f"{v:.3f}" for v in shares)
                    + f" | {wall:.0f}")
            print(line, flush=True)
            lines.append(line)
    append_table(args.out, lines)


if __name__ == "__main__":
    main()
