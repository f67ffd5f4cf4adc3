"""``render``: film a robot trajectory (with the human actor, optionally the generated
reactor) to an mp4 using MuJoCo's offscreen renderer (headless: MUJOCO_GL=egl)."""

from __future__ import annotations

import argparse


def register(subparsers) -> None:
    from ros_free_bridge.commands.check import add_mode_option, add_placement_options

    p = subparsers.add_parser(
        "render",
        help="render a robot trajectory to an mp4",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("trajectory", help="robot trajectory .npz")
    p.add_argument("-o", "--out", required=True, help="output .mp4")
    p.add_argument(
        "--robot",
        metavar="NAME|DIR",
        help="the robot: a bundled name (op3, ub14), a robot folder (see `robot init`), or an MJCF "
        "(default: the trajectory's robot, else op3)",
    )
    add_mode_option(p)
    p.add_argument(
        "--playback",
        choices=("physics", "kinematic"),
        default="physics",
        help="physics: the simulated servos play the trajectory and the video shows what they do (and the "
        "check's verdict is printed); kinematic: the poses exactly as written (default physics)",
    )
    p.add_argument("--width", type=int, default=640, help="width of each panel, pixels (default 640)")
    p.add_argument("--height", type=int, default=480, help="height, pixels (default 480)")
    p.add_argument("--fps", type=float, default=30.0, help="video frame rate (default 30)")
    p.add_argument(
        "--azimuth", type=float, default=160.0, help="camera azimuth, degrees (180 = facing the robot; default 160)"
    )
    p.add_argument(
        "--elevation", type=float, default=-15.0, help="camera elevation, degrees (negative: looking down; default -15)"
    )
    p.add_argument("--distance", type=float, help="camera distance in m (default 2.4 x robot height)")
    p.add_argument(
        "--quality", choices=("fast", "full"), default="fast", help="full: shadows, reflections, MSAA (default fast)"
    )
    add_placement_options(p, "actor", "human actor motion file, drawn beside the robot")
    add_placement_options(p, "reactor", "generated reactor motion file, drawn as a stick figure", partner=False)
    p.add_argument("--side-by-side", action="store_true", help="three panels: actor | reactor | robot")
    p.set_defaults(func=run)


def run(args) -> int:
    from ros_free_bridge.commands.check import load_human, placement_from_args
    from sim.human_figure import People
    from sim.render import CameraConfig, RenderConfig, render_trajectory
    from sim.report import verdict, warning_lines

    config = RenderConfig(
        width=args.width,
        height=args.height,
        fps=args.fps,
        camera=CameraConfig(distance=args.distance, azimuth=args.azimuth, elevation=args.elevation),
        side_by_side=args.side_by_side,
        playback=args.playback,
        quality=args.quality,
    )
    from ros_free_bridge.robots import bridge_check_config
    from sim.check import load_trajectory, robot_of

    traj = load_trajectory(args.trajectory)
    path, result = render_trajectory(
        traj,
        args.out,
        config,
        bridge_check_config(robot_of(traj, args.robot), mode=args.mode),  # as `check` judges
        robot=args.robot,
        people=People(
            load_human(args.actor),
            placement_from_args(args, "actor"),
            load_human(args.reactor),
            placement_from_args(args, "reactor"),
        ),
    )
    print(f"wrote {path}")
    print(f"check: {verdict(result)}")  # the same check `check` runs, on the same scene
    for line in warning_lines(result):
        print(f"  {line}")
    return 0
