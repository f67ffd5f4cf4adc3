"""``check``: play a robot trajectory through the simulated servos and judge it physically.

Writes ``<out>/<stem>.json`` and ``<out>/<stem>.md`` (with plots); exit code 0 when
the trajectory passes, 1 when it fails, 2 on a user error.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser("check", help="judge a robot trajectory in MuJoCo (falls, collisions, torque, speed)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("trajectory", help="robot trajectory .npz (RobotTrajectory.save_npz)")
    p.add_argument("--robot", metavar="NAME|DIR", help="the robot: a bundled name (op3, ub14), a robot folder (see `robot init`), or an MJCF (default: the trajectory's robot, else op3)")
    add_mode_option(p)
    p.add_argument("--control-hz", type=float, default=100.0,
                   help="rate at which the servo targets are updated, as the bridge's loop does (default 100)")
    p.add_argument("--physics-hz", type=float, default=500.0,
                   help="MuJoCo step rate, a whole multiple of --control-hz (default 500)")
    p.add_argument("--interp", choices=("linear", "cubic"), default="linear",
                   help="how targets between trajectory frames are made (default linear)")
    add_placement_options(p, "actor", "human actor motion file (.bvh/.npz/.npy) to place in the scene")
    p.add_argument("-o", "--out", default="check_report", help="report folder (default check_report)")
    p.add_argument("--no-plots", action="store_true", help="write only the JSON report")
    p.set_defaults(func=run)


def add_mode_option(p) -> None:
    p.add_argument("--mode", choices=("free", "fixed"), default="free",
                   help="free: the robot stands free on the floor (it can fall); fixed: its torso is bolted in "
                        "place (upper-body partners) (default free)")


def add_placement_options(p, prefix: str, what: str) -> None:
    """--PREFIX FILE and where that person stands: --PREFIX-scale, -offset, -yaw."""
    p.add_argument(f"--{prefix}", help=what)
    p.add_argument(f"--{prefix}-scale", default="robot",
                   help="'robot' (shrunk to the robot's height), 'human' (life size) or a number (default robot)")
    p.add_argument(f"--{prefix}-offset", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"),
                   help="move the person by this much after scaling, metres (default 0 0 0)")
    p.add_argument(f"--{prefix}-yaw", type=float, default=0.0, help="turn the person about +Z, degrees (default 0)")


def placement_from_args(args, prefix: str = "actor"):
    from sim.human_figure import Placement

    scale = getattr(args, f"{prefix}_scale")
    if scale not in ("robot", "human"):
        try:
            scale = float(scale)
        except ValueError:
            from sim.errors import SimError

            raise SimError(f"--{prefix}-scale must be 'robot', 'human' or a number, got {scale!r}") from None
    return Placement(scale, tuple(getattr(args, f"{prefix}_offset")), getattr(args, f"{prefix}_yaw"))


def load_human(path):
    if path is None:
        return None
    from dualflow.motion.io import load_motion

    return load_motion(path)


def run(args) -> int:
    from sim.check import CheckConfig, check_trajectory
    from sim.report import write_json, write_report

    config = CheckConfig(control_hz=args.control_hz, physics_hz=args.physics_hz, interpolation=args.interp,
                         mode=args.mode)
    result = check_trajectory(args.trajectory, config, robot=args.robot, actor=load_human(args.actor),
                              actor_placement=placement_from_args(args))
    out = Path(args.out)
    stem = Path(args.trajectory).stem
    if args.no_plots:
        out.mkdir(parents=True, exist_ok=True)
        paths = {"json": write_json(result, out / f"{stem}.json")}
    else:
        paths = write_report(result, out, stem)
    if result.passed:
        unjudged = f"; not checked: {', '.join(result.not_checked)}" if result.not_checked else ""
        print(f"PASS {args.trajectory} ({result.robot}, {result.mode}{unjudged})")
    else:
        print(f"FAIL {args.trajectory}: {result.reason} at {result.first_failure_time:.2f} s: {result.failures[0].detail}")
    for kind, path in paths.items():
        print(f"  {kind}: {path}")
    return 0 if result.passed else 1
