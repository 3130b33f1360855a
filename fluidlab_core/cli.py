"""The `fluidlab` command.

    fluidlab demo [--out DIR] [--size small|paper] [--duration S] [--frames N] [--view NAME]
    fluidlab materials
    fluidlab bench [--particles N ...]
    fluidlab list
    fluidlab optimise TASK [--method dp|dp-h|cma-es|sac|ppo|pods] [--budget STEPS] [--seed S]
                           [--size small|medium|paper] [--name NAME] [--root out/trajectories] [--force]
    fluidlab evaluate TRAJECTORY.json
    fluidlab render TRAJECTORY.json [--out DIR] [--every N] [--no-mp4]
    fluidlab replay RECORDING [--out DIR] [--disturb delay=S,scale=F,noise=RAD] [--recover]   (from fluidlab_ros)

Every simulating subcommand takes --arch (cpu, cuda, auto) and --precision (f32, f64); the default is the
CPU in float32. A trajectory's report records the precision it was optimised in; evaluate it in the same one
to reproduce the reported loss exactly.
"""
from __future__ import annotations

import argparse
import sys

from fluidlab_core.files import write_atomic

DEFAULT_ROOT = "out/trajectories"


def _add_backend(parser, precision="f32"):
    parser.add_argument("--arch", default="cpu", choices=["cpu", "cuda", "auto"], help="Taichi backend (default cpu)")
    parser.add_argument("--precision", default=precision, choices=["f32", "f64"],
                        help=f"real type (default {precision})")


class _Bar:
    """A one-line progress bar on stderr."""

    def __init__(self, total: int, width: int = 30):
        self.total, self.width = max(1, total), width
        self.tty = sys.stderr.isatty()

    def update(self, done: int, text: str):
        filled = int(self.width * min(done, self.total) / self.total)
        line = f"[{'#' * filled}{'.' * (self.width - filled)}] {text}"
        if self.tty:
            print("\r" + line, end="", file=sys.stderr, flush=True)
        else:
            print(line, file=sys.stderr, flush=True)

    def close(self):
        if self.tty:
            print(file=sys.stderr)


def _compile_notice(phase: str, what: str, seconds: float):
    """runtime.on_compile listener: a line before and after a first run that compiles kernels."""
    clear = "\r\033[K" if sys.stderr.isatty() else ""
    if phase == "start":
        print(f"{clear}compiling {what} on the first run (a minute or more on two cores; Taichi caches the "
              f"result in ~/.cache/taichi, so later runs start in seconds) ...", file=sys.stderr, flush=True)
    else:
        print(f"{clear}{what}: compiled, first run took {seconds:.1f} s", file=sys.stderr, flush=True)


def _cmd_list(args):
    from fluidlab_core import tasks

    print(f"{'task':<15} {'size':<6} {'grid':>4} {'dt s':>7} {'horizon':>7} {'tool':<7} actions")
    for name in tasks.names():
        for size in [s for s in tasks.SIZES if s in tasks.task_class(name).sizes]:  # a task of yours may lack one
            t = tasks.make(name, size)
            c = t.config
            print(f"{name:<15} {size:<6} {c.grid_res:>4} {c.dt:>7.4f} {c.horizon:>7} {t.tool_name:<7} "
                  f"{', '.join(t.action_axis_names())} (m/s, |v| <= {t.max_tool_speed})")
    return 0


def _trajectory_root(root: str):
    """The folder `fluidlab optimise` writes into, refused when it lies inside the installed packages (their
    folders are replaced on the next install, and a package is no place for a user's results)."""
    from pathlib import Path

    import fluidlab_core

    folder = Path(root).expanduser().resolve()
    package_dirs = [Path(fluidlab_core.__file__).resolve().parent]
    try:
        import robot_models

        package_dirs.append(Path(robot_models.__file__).resolve().parent)
    except ImportError:
        pass
    for pkg in package_dirs:
        if folder == pkg or pkg in folder.parents:
            raise ValueError(f"--root {root} is inside the installed package {pkg}; write trajectories to a folder "
                             f"of your own (default {DEFAULT_ROOT})")
    return folder


def _cmd_optimise(args):
    import json

    import fluidlab_core
    from fluidlab_core import optim, tasks
    from fluidlab_core.trajectory_store import TrajectoryStore, report_path

    # everything that can be refused is refused before anything is announced or computed
    task = tasks.make(args.task, size=args.size, pressure=args.pressure)
    budget = args.budget if args.budget is not None else 12 * task.horizon
    optim.check_request(task, args.method, budget, args.seed)
    if args.without and args.method != "dp":
        raise ValueError(f"--without switches off techniques of --method dp; {args.method} has none")
    store = TrajectoryStore(_trajectory_root(args.root))
    name = args.name or f"{task.name}_{args.method}_seed{args.seed}_{args.size}"
    path = store.new_path(task.name, name, overwrite=args.force)
    fluidlab_core.init(arch=args.arch, precision=args.precision)
    print(f"optimising {task.name} ({args.size}) with {args.method}, budget {budget} simulated steps "
          f"({budget / task.horizon:.3g} rollouts of {task.horizon} steps), seed {args.seed}; the trajectory will "
          f"be written to {path}" + (" (replacing the file there)" if path.exists() else ""), file=sys.stderr)
    bar = _Bar(budget)
    traj = optim.optimise(task, args.method, budget, seed=args.seed,
                          callback=lambda p: bar.update(p.steps, p.line()), without=args.without)
    bar.close()
    path = traj.save(path)
    report = {"task": task.name, "size": args.size, "pressure": args.pressure, "method": args.method, "seed": args.seed,
              "trajectory": str(path),
              **{k: traj.metadata[k] for k in ("final_loss", "return", "budget_steps", "steps_used", "iterations",
                                               "seconds")},
              "loss_first": traj.loss_history[0] if traj.loss_history else None,
              "loss_best": min(traj.loss_history) if traj.loss_history else None,
              "precision": args.precision, "arch": args.arch, "without": list(args.without)}
    report_file = report_path(path)
    write_atomic(report_file, json.dumps(report, indent=1).encode())
    print(f"final loss {report['final_loss']:.6g} (reference physics), return {report['return']:.4g}")
    print(f"wrote {path} and {report_file}")
    return 0


def _load_trajectory(path):
    from fluidlab_core.trajectory import Trajectory

    return Trajectory.load(path)


def _cmd_evaluate(args):
    import fluidlab_core
    from fluidlab_core.episode import task_for

    traj = _load_trajectory(args.trajectory)
    task = task_for(traj, args.size, args.pressure)
    fluidlab_core.init(arch=args.arch, precision=args.precision)
    actions, position = task.actions_from_trajectory(traj)
    out = task.evaluate(actions, tool_position=position)
    print(f"{task.name} ({task.size}, pressure {task.pressure}): loss {out['loss']:.6g}, return {out['return']:.4g} over {len(actions)} steps "
          f"({len(actions) * task.dt:.3g} s); workspace clipped {out['clipped_steps']} steps")
    return 0


def _cmd_render(args):
    import fluidlab_core
    from fluidlab_core.episode import render_episode, task_for

    if args.every < 1:
        raise ValueError(f"--every must be at least 1 step, got {args.every}")
    traj = _load_trajectory(args.trajectory)
    task = task_for(traj, args.size)
    fluidlab_core.init(arch=args.arch, precision=args.precision)
    bar = _Bar(traj.n_steps)
    out = render_episode(traj, args.out, every=args.every, mp4=not args.no_mp4, task=task,
                         progress=lambda k, n: bar.update(k, f"step {k}/{n}"))
    bar.close()
    print(f"wrote {len(out['frames'])} frames to {args.out}/" + (f" and {out['mp4']}" if out["mp4"] else "")
          + f"; loss {out['loss']:.6g}")
    return 0


def _cmd_demo(args):
    import fluidlab_core
    from fluidlab_core.apps import demo

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
    from fluidlab_core.apps import throughput as bench

    fluidlab_core.init(arch=args.arch, precision=args.precision)
    bench.main(particles=args.particles, steps=args.steps, genesis=not args.no_genesis)
    return 0


PLUGIN_GROUP = "fluidlab.commands"


def _register_plugins(sub):
    """Sub-commands that other installed packages add through the entry-point group `fluidlab.commands`: each
    entry point is a function register(subparsers, add_backend) (fluidlab_ros adds `replay` this way, so that
    this package never imports it). A plug-in that fails to load is reported, not fatal."""
    from importlib.metadata import entry_points

    for ep in sorted(entry_points(group=PLUGIN_GROUP), key=lambda e: e.name):
        try:
            register = ep.load()
        except Exception as err:  # noqa: BLE001 - a broken plug-in must not break the other commands
            print(f"fluidlab: note: sub-command {ep.name!r} ({ep.value}) is unavailable: {err}", file=sys.stderr)
            continue
        register(sub, _add_backend)


def build_parser() -> argparse.ArgumentParser:
    """The `fluidlab` argument parser, plug-in sub-commands included (tests parse documented commands with it)."""
    from fluidlab_core.tasks.base import SIZES
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

    # listed for `fluidlab --help`; main() hands `fluidlab benchmark ...` to fluidlab_core.benchmark's own parser
    sub.add_parser("benchmark", help="the optimiser benchmark: tasks x methods x seeds as jobs, resumable "
                   "(fluidlab benchmark --help)")

    p = sub.add_parser("list", help="list the tasks and their sizes")
    p.set_defaults(func=_cmd_list)

    from fluidlab_core.optim import DESCRIPTIONS, METHODS, TECHNIQUES

    p = sub.add_parser("optimise", aliases=["optimize"], help="optimise a task's trajectory and save it",
                       description="Optimise a task's tool trajectory and save it as TASK/NAME.json under --root, "
                                   "with NAME.report.json beside it. Methods: " + "; ".join(
                                       f"{m}: {DESCRIPTIONS[m]}" for m in METHODS) + ".")
    p.add_argument("task", help="task name (fluidlab list)")
    p.add_argument("--method", default="dp", choices=METHODS, help="dp (default), dp-h, cma-es, sac, ppo, pods, dp-window, cma-es-free or dp-free (see above)")
    p.add_argument("--budget", type=int, default=None,
                   help="simulated steps; a rollout of the horizon costs the horizon (default 12 rollouts)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--size", default="small", choices=list(SIZES))
    p.add_argument("--name", default=None, help="trajectory name (default TASK_METHOD_seedS_SIZE); a name in use "
                   "anywhere under --root is refused (sim_node finds trajectories by name)")
    p.add_argument("--root", default=DEFAULT_ROOT,
                   help=f"folder of trajectories (default ./{DEFAULT_ROOT}; the repository's shipped trajectories/ "
                        f"only when you name it)")
    p.add_argument("--force", action="store_true", help="replace a trajectory of the same task and name")
    p.add_argument("--without", nargs="+", default=[], choices=TECHNIQUES, metavar="TECHNIQUE",
                   help="switch DP techniques off, for ablations: " + ", ".join(TECHNIQUES))
    p.add_argument("--pressure", default="state", choices=("state", "projection"),
                   help="the liquids' pressure: state (default, weakly compressible) or projection (incompressible, "
                        "floats bodies at Archimedes' depth; no gradients, so cma-es, sac or ppo only)")
    _add_backend(p)
    p.set_defaults(func=_cmd_optimise)

    p = sub.add_parser("evaluate", help="loss and return of a trajectory on its task's reference physics")
    p.add_argument("trajectory", help="a trajectory JSON file")
    p.add_argument("--size", default=None, choices=list(SIZES), help="default: the size it records")
    p.add_argument("--pressure", default=None, choices=("state", "projection"),
                   help="the liquids' pressure (default: the one it records, else state)")
    _add_backend(p)
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser("render", help="play a trajectory and write PNG frames and an MP4")
    p.add_argument("trajectory", help="a trajectory JSON file")
    p.add_argument("--out", default="out/render", help="folder (default out/render)")
    p.add_argument("--every", type=int, default=2, help="steps between frames (default 2)")
    p.add_argument("--no-mp4", action="store_true", help="frames only")
    p.add_argument("--size", default=None, choices=list(SIZES), help="default: the size it records")
    _add_backend(p)
    p.set_defaults(func=_cmd_render)

    _register_plugins(sub)
    return parser


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["benchmark"]:  # its own parser (fluidlab_core/benchmark.py), options and all
        from fluidlab_core import benchmark

        return benchmark.main(argv[1:])
    args = build_parser().parse_args(argv)
    from fluidlab_core import runtime

    runtime.on_compile(_compile_notice)
    try:
        return args.func(args)
    except (ValueError, KeyError, OSError, ImportError) as err:
        # a KeyError's str() is the repr of its message (quoted); print the message itself
        text = err.args[0] if isinstance(err, KeyError) and err.args and isinstance(err.args[0], str) else err
        print(f"fluidlab: error: {text}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
