"""`fluidlab replay`: the sub-command this package adds to the `fluidlab` command.

fluidlab_core's CLI never imports fluidlab_ros; it finds this function through the entry-point group
`fluidlab.commands` (setup.py) and calls it with its sub-parsers. fluidlab_ros holds the recording format and the
kinematics, the simulation is fluidlab_core's; neither needs a ROS graph (rclpy is used only for its message
classes and CDR).
"""
from __future__ import annotations

import sys


def register(sub, add_backend):
    """Add `replay` to the `fluidlab` command's sub-parsers (add_backend adds --arch and --precision)."""
    p = sub.add_parser("replay", help="replay a sim_node recording (rosbag2 MCAP) into the fluid and compare with "
                                      "the plan")
    p.add_argument("recording", help="a recording folder written by sim_node (~/execute)")
    p.add_argument("--out", default=None, help="report folder (default <recording>/replay)")
    p.add_argument("--disturb", default="", help="perturb the measured motion: delay=<s>,scale=<f>,noise=<rad>")
    p.add_argument("--recover", action="store_true", help="only write a closed copy of a recording that was never "
                                                          "closed (<recording>.recovered)")
    add_backend(p)
    p.set_defaults(func=run_replay)


def run_replay(args) -> int:
    from pathlib import Path

    import fluidlab_core
    from fluidlab_ros.recording import RecordingError, recover
    from fluidlab_ros.replay import replay

    try:
        if args.recover:
            print(f"wrote {recover(args.recording)}")
            return 0
        out = args.out or str(Path(args.recording) / "replay")
        fluidlab_core.init(arch=args.arch, precision=args.precision)

        def progress(name, j, n):
            if j == 1 or j == n or j % 50 == 0:
                print(f"\r{name}: step {j}/{n}", end="" if j < n else "\n", file=sys.stderr, flush=True)

        rep = replay(args.recording, out, args.disturb, progress=progress)
    except RecordingError as err:
        print(f"fluidlab: error: {err}", file=sys.stderr)
        return 2
    if not rep["closed"]:
        print("note: the recording was never closed (crash?); replayed what reached the disk", file=sys.stderr)
    print(f"{rep['task']} ({rep['trajectory']}): loss planned {rep['loss_planned']:.6g}, replayed "
          f"{rep['loss_replayed']:.6g} (gap {100 * (rep['loss_gap_relative'] or 0):+.2f} %); tool path error "
          f"max {rep['tool_path_error_task_max'] * 1e3:.3g} mm in the task segment; final particles moved "
          f"{rep['final_particle_displacement_mean'] * 1e3:.3g} mm on average")
    for note in rep.get("notes", []):
        print(f"note: {note}")
    print(f"wrote {out}/report.json and plots")
    return 0
