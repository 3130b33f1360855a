"""The `fluidlab` command.

    fluidlab demo [--out DIR] [--size small|paper] [--duration S] [--frames N] [--view NAME]
    fluidlab materials
    fluidlab bench [--particles N ...]

Every subcommand takes --arch (cpu, cuda, auto) and --precision (f32, f64); the default is the CPU in
float32.
"""
from __future__ import annotations

import argparse
import sys


def _add_backend(parser):
    parser.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"], help="Taichi backend (default cpu)")
    parser.add_argument("--precision", default="f32", choices=["f32", "f64"], help="real type (default f32)")


def _cmd_demo(args):
    import fluidlab_core
    from fluidlab_core import demo

    fluidlab_core.init(arch=args.arch, precision=args.precision, seed=args.seed)
    paths = demo.run(args.out, size=args.size, duration=args.duration, frames=args.frames, view=args.view,
                     seed=args.seed)
    print(f"wrote {len(paths)} pictures to {args.out}/ (last: {paths[-1]})")
    return 0


def _cmd_materials(args):
    from fluidlab_core import materials as M

    print(f"{'name':<18} {'model':<20} {'density kg/m3':>13} {'mu Pa':>10} {'lambda Pa':>10} {'viscosity Pa.s':>14} "
          f"{'wave speed m/s':>14}")
    for m in M.CATALOGUE.values():
        print(f"{m.name:<18} {m.model:<20} {m.density:>13.0f} {m.mu:>10.4g} {m.lam:>10.4g} {m.viscosity:>14.4g} "
              f"{m.wave_speed():>14.3g}")
    return 0


def _cmd_bench(args):
    import fluidlab_core
    from fluidlab_core import bench

    fluidlab_core.init(arch=args.arch, precision=args.precision)
    bench.main(particles=args.particles, steps=args.steps, genesis=not args.no_genesis)
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="fluidlab", description="FluidLab-ROS: differentiable fluid simulation "
                                     "for robot trajectories")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("demo", help="simulate the demo scene and write PNG pictures")
    p.add_argument("--out", default="out/demo", help="folder for the pictures (default out/demo)")
    p.add_argument("--size", default="small", choices=["small", "paper"])
    p.add_argument("--duration", type=float, default=0.6, help="simulated seconds (default 0.6)")
    p.add_argument("--frames", type=int, default=6, help="pictures after the first (default 6)")
    p.add_argument("--view", default="iso", help="front, side, top, iso (default iso)")
    p.add_argument("--seed", type=int, default=0)
    _add_backend(p)
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("materials", help="list the material catalogue in SI units")
    p.set_defaults(func=_cmd_materials)

    p = sub.add_parser("bench", help="forward throughput (particle-substeps per second) and memory")
    p.add_argument("--particles", type=int, nargs="+", default=[20_000, 50_000, 100_000])
    p.add_argument("--steps", type=int, default=5, help="timed steps per size (default 5)")
    p.add_argument("--no-genesis", action="store_true", help="skip the Genesis comparison")
    _add_backend(p)
    p.set_defaults(func=_cmd_bench)

    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, KeyError) as err:
        print(f"fluidlab: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
