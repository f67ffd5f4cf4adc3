"""``view``: the interactive MuJoCo viewer playing a robot trajectory (needs a display;
without one it says so and suggests ``render``)."""

from __future__ import annotations

import argparse


def register(subparsers) -> None:
    from ros_free_bridge.commands.check import add_mode_option, add_placement_options

    p = subparsers.add_parser(
        "view",
        help="open the interactive MuJoCo viewer",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("trajectory", nargs="?", help="robot trajectory .npz (default: the robot standing)")
    p.add_argument(
        "--robot",
        metavar="NAME|DIR",
        help="the robot: a bundled name (op3, ub14), a robot folder (see `robot init`), or an MJCF "
        "(default: the trajectory's robot, else op3)",
    )
    add_mode_option(p)
    p.add_argument("--loop", action="store_true", help="replay until the window is closed")
    add_placement_options(p, "actor", "human actor motion file, shown beside the robot")
    p.set_defaults(func=run)


def run(args) -> int:
    from ros_free_bridge.commands.check import load_human, placement_from_args
    from sim.check import CheckConfig
    from sim.human_figure import People
    from sim.viewer import require_display, view

    require_display()
    view(
        args.trajectory,
        robot=args.robot,
        check_config=CheckConfig(mode=args.mode),
        people=People(load_human(args.actor), placement_from_args(args)),
        loop=args.loop,
    )
    return 0
