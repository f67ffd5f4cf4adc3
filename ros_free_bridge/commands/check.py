"""``check``: play a robot trajectory through the simulated servos and judge it physically.

Writes ``<out>/<stem>.json`` and ``<out>/<stem>.md`` (with plots); exit code 0 when
the trajectory passes, 1 when it fails, 2 on a user error.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "check",
        help="judge a robot trajectory in MuJoCo (falls, collisions, torque, speed)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("trajectory", help="robot trajectory .npz (RobotTrajectory.save_npz)")
    p.add_argument(
        "--robot",
        metavar="NAME|DIR",
        help="the robot: a bundled name (op3, ub14), a robot folder (see `robot init`), or an MJCF "
        "(default: the trajectory's robot, else op3)",
    )
    add_mode_option(p)
    p.add_argument(
        "--control-hz",
        type=float,
        default=100.0,
        help="rate at which the servo targets are updated, as the bridge's loop does (default 100)",
    )
    p.add_argument(
        "--physics-hz",
        type=float,
        default=500.0,
        help="MuJoCo step rate, a whole multiple of --control-hz (default 500)",
    )
    p.add_argument(
        "--interp",
        choices=("linear", "cubic"),
        default="linear",
        help="how targets between trajectory frames are made (default linear)",
    )
    add_placement_options(p, "actor", "human actor motion file (.bvh/.npz/.npy) to place in the scene")
    p.add_argument(
        "--no-stabilizer",
        action="store_true",
        help="play the trajectory open loop: without the balance stabilizer the bridge runs for a "
        "free-standing robot (default: with it, fed by the simulated IMU)",
    )
    p.add_argument(
        "--no-safety-filter",
        action="store_true",
        help="play the trajectory's commands as they are: without the safety filter (joint, speed and "
        "acceleration limits of the robot's hardware config, else its model) that the bridge passes "
        "every command through (default: with it, as the bridge would send them)",
    )
    p.add_argument("-o", "--out", default="check_report", help="report folder (default check_report)")
    p.add_argument("--no-plots", action="store_true", help="write only the JSON report")
    p.set_defaults(func=run)


def add_mode_option(p) -> None:
    p.add_argument(
        "--mode",
        choices=("free", "fixed"),
        default="free",
        help="free: the robot stands free on the floor (it can fall); fixed: its torso is bolted in "
        "place (upper-body partners) (default free)",
    )


def add_placement_options(p, prefix: str, what: str, partner: bool = True) -> None:
    """--PREFIX FILE and where that person stands: --PREFIX-scale, -offset, -yaw and, for a
    ``partner`` (the actor), -distance. A partner stands face to face with the robot unless
    -offset or -yaw is given; anyone else is drawn where the file has them."""
    p.add_argument(f"--{prefix}", help=what)
    p.add_argument(
        f"--{prefix}-scale",
        default="robot",
        help="'robot' (shrunk to the robot's height), 'human' (life size) or a number (default robot)",
    )
    where = (
        f"(default: face to face with the robot, see --{prefix}-distance)"
        if partner
        else "(default 0 0 0: as the file has them)"
    )
    p.add_argument(
        f"--{prefix}-offset",
        type=float,
        nargs=3,
        default=None,
        metavar=("X", "Y", "Z"),
        help=f"move the person by this much after scaling, metres, instead of placing them {where}",
    )
    p.add_argument(
        f"--{prefix}-yaw",
        type=float,
        default=None,
        help=f"turn the person about +Z, degrees, with --{prefix}-offset (default 0)",
    )
    if partner:
        p.add_argument(
            f"--{prefix}-distance",
            type=float,
            default=None,
            metavar="M",
            help="face to face: from the robot's root to the person's pelvis at the first frame, metres, "
            "in front of the robot, the person turned to face it (default 0.6 x the mean height of "
            "the robot and the scaled person: a conversation or handshake distance)",
        )


def placement_from_args(args, prefix: str = "actor"):
    """A :class:`sim.human_figure.Placement` when -offset or -yaw is given (or the person is not a
    partner); else a :class:`sim.human_figure.FaceToFace`."""
    from sim.errors import SimError
    from sim.human_figure import FaceToFace, Placement

    scale = getattr(args, f"{prefix}_scale")
    if scale not in ("robot", "human"):
        try:
            scale = float(scale)
        except ValueError:
            raise SimError(f"--{prefix}-scale must be 'robot', 'human' or a number, got {scale!r}") from None
    offset, yaw = getattr(args, f"{prefix}_offset"), getattr(args, f"{prefix}_yaw")
    partner = hasattr(args, f"{prefix}_distance")
    distance = getattr(args, f"{prefix}_distance", None)
    if partner and offset is None and yaw is None:
        return FaceToFace(scale, distance)
    if distance is not None:
        raise SimError(
            f"--{prefix}-distance places the person face to face; leave out --{prefix}-offset and "
            f"--{prefix}-yaw with it"
        )
    return Placement(scale, tuple(offset) if offset is not None else (0.0, 0.0, 0.0), yaw or 0.0)


def load_human(path):
    if path is None:
        return None
    from dualflow.motion.io import load_motion

    return load_motion(path)


def run(args) -> int:
    from sim.check import CheckConfig, check_trajectory
    from sim.human_figure import People
    from sim.report import warning_lines, write_json, write_report

    fields = dict(
        control_hz=args.control_hz,
        physics_hz=args.physics_hz,
        interpolation=args.interp,
        mode=args.mode,
        stabilizer=not args.no_stabilizer,
    )
    from retarget.errors import RetargetError
    from sim.check import load_trajectory, robot_of
    from sim.errors import SimError

    try:
        traj = load_trajectory(args.trajectory)
        if args.no_safety_filter:
            config = CheckConfig(**fields)
        else:
            from ros_free_bridge.robots import bridge_check_config

            config = bridge_check_config(robot_of(traj, args.robot), **fields)
        result = check_trajectory(
            traj,
            config,
            robot=args.robot,
            people=People(load_human(args.actor), placement_from_args(args)),
        )
    except (SimError, RetargetError) as exc:  # name the file where the message does not (a joint mismatch)
        if str(args.trajectory) in str(exc) or (args.actor and str(args.actor) in str(exc)):
            raise
        raise type(exc)(f"{args.trajectory}: {exc}") from None
    out = Path(args.out)
    stem = Path(args.trajectory).stem
    if args.no_plots:
        out.mkdir(parents=True, exist_ok=True)
        paths = {"json": write_json(result, out / f"{stem}.json")}
    else:
        paths = write_report(result, out, stem)
    if result.passed:
        unjudged = f"; not checked: {', '.join(result.not_checked)}" if result.not_checked else ""
        warned = f"; {len(result.warnings)} warnings" if result.warnings else ""
        print(f"PASS {args.trajectory} ({result.robot}, {result.mode}{unjudged}{warned})")
    else:
        print(
            f"FAIL {args.trajectory}: {result.reason} at {result.first_failure_time:.2f} s: {result.failures[0].detail}"
        )
    from sim.report import stabilizer_line

    print(f"  {stabilizer_line(result)}")
    print(
        f"  entered from standing in {result.entry_transition_s:.2f} s (before the clip's 0 s)"
        if result.entry_transition_s
        else "  started in the clip's first pose"
    )
    for line in warning_lines(result):
        print(f"  {line}")
    for kind, path in paths.items():
        print(f"  {kind}: {path}")
    return 0 if result.passed else 1
