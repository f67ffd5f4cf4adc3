"""``dualflow-bridge replay`` and ``dualflow-bridge plot``: use a run's telemetry afterwards.

dualflow-bridge plot runs/latest/telemetry.dftl -o runs/latest/plots
dualflow-bridge replay runs/latest/telemetry.dftl --video replay.mp4
dualflow-bridge replay runs/latest/telemetry.dftl --transport sim        # drive the virtual robot
"""

from __future__ import annotations

import sys
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser(
        "plot",
        help="figures of a run from its telemetry file",
        description="Draw a run's figures from its telemetry file: joints.png (each joint's "
        "target, command sent and measured angle), timing.png (tick lateness and "
        "compute time, stage and end-to-end latency), safety.png (bridge state, "
        "safety-filter interventions, faults). Prints their paths.",
    )
    p.add_argument("telemetry", help="a telemetry.dftl file written by run or demo")
    p.add_argument("-o", "--out", help="folder for the PNGs (default: beside the file, plots/)")
    p.set_defaults(func=plot)

    r = sub.add_parser(
        "replay",
        help="replay a run's commands on a transport or as a video",
        description="Play the joint commands a run sent (read from its telemetry file) again: as "
        "a video through the simulated servos (--video), and/or through the control "
        "loop and its safety filter to a transport (--transport), e.g. to repeat on "
        "the real robot what was first tried in simulation. Every command is played, "
        "one per control tick at the run's rate (a late tick delays the rest, none "
        "is dropped); exit code 1 if the replay ended in an e-stop or a fault.",
    )
    r.add_argument("telemetry", help="a telemetry.dftl file written by run or demo")
    r.add_argument("--robot", help="robot name or hardware config (default: the one the run used)")
    r.add_argument("--video", help="render the commands played through the simulated servos to this .mp4")
    r.add_argument(
        "--transport",
        choices=("sim", "record", "dynamixel", "serial"),
        help="drive a transport again through the control loop and its safety filter",
    )
    r.add_argument("--port", help="serial port for dynamixel/serial")
    r.add_argument("--emulate", action="store_true", help="dynamixel/serial: use the bus emulator")
    r.set_defaults(func=replay)


def plot(args) -> int:
    from ros_free_bridge.errors import BridgeError
    from ros_free_bridge.telemetry.log import read_telemetry
    from ros_free_bridge.telemetry.plots import plot_all

    tel = read_telemetry(args.telemetry)
    if len(tel.records) < 2:
        raise BridgeError(f"{args.telemetry}: holds {len(tel.records)} tick record(s); a plot needs at least 2")
    out = Path(args.out) if args.out else Path(args.telemetry).parent / "plots"
    for p in plot_all(tel, out):
        print(p)
    return 0


def replay(args) -> int:
    from ros_free_bridge.errors import BridgeError
    from ros_free_bridge.telemetry.log import read_telemetry

    tel = read_telemetry(args.telemetry)
    robot = args.robot or tel.meta.get("robot", "op3")
    if not isinstance(robot, str) or not robot:
        raise BridgeError(f"{args.telemetry}: header field 'meta.robot' is {robot!r}; give the robot with --robot")
    if not args.video and not args.transport:
        raise BridgeError("replay: give --video OUT.mp4 and/or --transport sim|record|dynamixel|serial")
    try:
        traj = tel.commands_trajectory(robot)
    except BridgeError as exc:
        raise BridgeError(f"{args.telemetry}: {exc}") from None
    ok = True
    if args.video:
        from sim.render import render_trajectory

        out, result = render_trajectory(traj, args.video, robot=robot)
        print(f"video: {out}" + ("" if result is None else f" (check: {'pass' if result.passed else 'fail'})"))
    if args.transport:
        ok = replay_on_transport(tel, traj, robot, args)
    return 0 if ok else 1


def replay_on_transport(tel, traj, robot: str, args) -> bool:
    """Play the logged commands again through the control loop (ramps, limits, e-stop);
    True when it ended in a normal stop.

    Every command is played, one per control tick (LoopConfig pace="ticks"): a tick the
    machine runs late delays the commands after it instead of dropping any, and the stream,
    complete from the start, never trips the loop's "no new frames" watchdog."""
    import time
    from contextlib import ExitStack

    from ros_free_bridge.control.loop import ControlLoop, LoopConfig
    from ros_free_bridge.control.targets import TargetBuffer, TargetFrame
    from ros_free_bridge.errors import BridgeError
    from ros_free_bridge.robots import bridge_limits, model_limits, resolve_robot
    from ros_free_bridge.session import MODEL_ONLY_TRANSPORTS, SessionOptions, open_transport

    files = resolve_robot(robot)
    if files.hardware is None and args.transport in MODEL_ONLY_TRANSPORTS:
        from retarget.robot import load_robot

        hardware = None
        limits = model_limits(load_robot(files.mjcf, files.profile))
    else:
        hardware = files.hardware_config()
        limits = bridge_limits(hardware)
    if tuple(limits.names) != tuple(tel.joint_names):
        raise BridgeError(
            f"{args.telemetry}: the telemetry's joints {tel.joint_names} are not robot {files.name}'s "
            f"{limits.names}; give the robot the run used (--robot)"
        )
    buf = TargetBuffer(tel.rate_hz, capacity=traj.n_frames + 1)
    now = time.monotonic()
    for k in range(traj.n_frames):
        buf.push(TargetFrame(k, traj.joint_pos[k], now))
    buf.close()
    opts = SessionOptions(
        robot=robot, transport=args.transport, port=args.port, emulate=args.emulate, rate_hz=tel.rate_hz
    )
    with ExitStack() as stack:
        transport, _ = open_transport(opts, files, hardware, limits.names, traj.joint_pos[0], stack)
        summary = ControlLoop(
            transport, limits, buf, LoopConfig(rate_hz=tel.rate_hz, rest_pose=traj.joint_pos[0], pace="ticks")
        ).run()
    print(
        f"replayed {summary.frames_played} of {traj.n_frames} commands: {summary.end_state} ({summary.reason})",
        file=sys.stderr,
    )
    return summary.ok
