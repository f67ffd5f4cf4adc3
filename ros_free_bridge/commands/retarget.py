"""``dualflow-bridge retarget``: human motion file(s) in, robot trajectory + report out.

One person: ``FILE``. Two people (``FILE FILE2``, ``--actor A --reactor B`` or a duet
``.npz``): the reactor (person B, the robot's role) is retargeted. The robot is a bundled
name (``op3``, ``ub14``: ``firmware_cfg/robots/<name>/``), a robot folder (``robot init``
makes one from an MJCF), or an MJCF with ``--profile``. Writes, under ``--out``:

- ``<stem>.npz`` and ``<stem>.csv``: the :class:`retarget.RobotTrajectory`;
- ``<stem>.report.json`` / ``.report.md``: the figures of :mod:`retarget.report`;
- ``<stem>.joints.png``: each joint against its limits.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "retarget",
        help="retarget human motion to a robot (CasADi/IPOPT), with a report",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "files", nargs="*", metavar="FILE", help="motion file, or two files (actor, reactor) in one world frame"
    )
    p.add_argument("--actor", metavar="FILE", help="actor file (with --reactor)")
    p.add_argument("--reactor", metavar="FILE", help="reactor file: the person whose motion the robot takes")
    p.add_argument(
        "--person", choices=("reactor", "actor"), default="reactor", help="which person of a pair to retarget"
    )
    p.add_argument(
        "--robot",
        default="op3",
        metavar="NAME|DIR",
        help="the robot: a bundled name (op3, ub14), a robot folder (see `robot init`), or an MJCF "
        "with --profile (default op3)",
    )
    p.add_argument("--profile", metavar="YAML", help="retarget profile (default: the robot folder's profile.yaml)")
    p.add_argument(
        "--mode",
        choices=("offline", "streaming"),
        default="offline",
        help="offline: the whole clip at once (--offline-engine: the step planner or the window "
        "optimisation); streaming: frame by frame as the live bridge does it (default offline)",
    )
    p.add_argument("--fps", type=float, default=30.0, help="resample the motion to this rate first (default 30)")
    p.add_argument("--ground", action="store_true", help="shift the motion so its lowest foot joint is at z = 0")
    p.add_argument(
        "--window",
        type=int,
        default=None,
        help="offline window length in frames (0 = whole clip; default: retarget.offline.OfflineConfig's, 80)",
    )
    p.add_argument("--overlap", type=int, default=None, help="frames shared by consecutive windows (default 10)")
    p.add_argument(
        "--balance",
        action="store_true",
        help="keep the CoM over the support polygon while feet touch (streaming: "
        "feet planted, CoM, capture point and ZMP over them; retarget.streaming)",
    )
    p.add_argument(
        "--zmp",
        action="store_true",
        help="offline --balance: keep the ZMP (CoM minus (z/g) times its "
        "acceleration) over the support polygon instead of the static CoM; what a dynamic clip needs to pass `check`",
    )
    p.add_argument("--balance-margin", type=float, default=0.01, help="support polygon shrink (m, default 0.01)")
    p.add_argument("--no-contacts", action="store_true", help="do not hold feet in contact on the ground")
    p.add_argument("--no-collision", action="store_true", help="do not keep the profile's capsule pairs apart")
    p.add_argument(
        "--foot-collision",
        choices=("sole-plane", "distance"),
        default="sole-plane",
        help="offline: keep the feet apart by a smooth separating plane along their lateral axis (default; "
        "about half the solver iterations, but feet cannot cross sideways) or by capsule distances "
        "(slower; lets a foot pass in front of the other)",
    )
    add_offline_engine(p)
    p.add_argument("--fixed-base", action="store_true", help="bolt the robot's root in place (upper-body partner)")
    p.add_argument("--retime", type=float, default=1.0, help="play the clip this many times slower (e.g. 1.5)")
    p.add_argument("--auto-retime", action="store_true", help="if infeasible, try 1.25x, 1.5x, 2x slower")
    p.add_argument(
        "--no-lead-in",
        action="store_true",
        help="offline: start the trajectory at the clip's first frame even when it is mid-motion (default: the "
        "robot is led in from its standing stance first; meta t0_s is where the clip starts)",
    )
    p.add_argument(
        "--no-compile", action="store_true", help="skip C code generation (slower; for machines without a compiler)"
    )
    p.add_argument("--out", default="out/retarget", help="output folder (default out/retarget)")
    p.add_argument("--name", help="output file stem (default: the input's stem)")
    p.add_argument("--strict", action="store_true", help="exit 1 when the report fails its checks")
    p.set_defaults(func=run)


def add_offline_engine(p) -> None:
    """The ``--offline-engine`` option (retarget.offline.OfflineConfig.engine)."""
    p.add_argument(
        "--offline-engine",
        choices=("auto", "planner", "ipopt"),
        default="auto",
        help="offline: planner: the streaming solver and its step planner over the whole clip, seeing the "
        "person's foot contacts 0.1 s early (never fails a clip; says where it changed it); ipopt: the "
        "window optimisation (closer tracking, but fast steps can make a free-standing robot fall); "
        "auto (default): the planner for a free-standing robot with balance on, ipopt for any other. "
        "The window, collision, ZMP, lead-in and re-timing options are ipopt's (the planner keeps its own "
        "margins, steps and start from standing; --retime applies to both)",
    )


def _load(args):
    from dualflow.motion import TwoPersonMotion
    from dualflow.motion.io import load_any, load_pair, put_on_ground
    from retarget.errors import RetargetError

    files = list(args.files)
    if args.actor or args.reactor:
        if not (args.actor and args.reactor) or files:
            raise RetargetError("give FILE [FILE2], or both --actor and --reactor (not both forms)")
        files = [args.actor, args.reactor]
    if not files:
        raise RetargetError("no input: give a motion FILE, two files (actor reactor), or --actor A --reactor B")
    if len(files) > 2:
        raise RetargetError(f"at most two input files (actor, reactor), got {len(files)}")
    opts = {"fps": args.fps} if args.fps else {}
    motion = load_any(files[0], **opts) if len(files) == 1 else load_pair(files[0], files[1], **opts)
    if args.ground:
        motion = put_on_ground(motion)
    if isinstance(motion, TwoPersonMotion):
        motion = motion.reactor if args.person == "reactor" else motion.actor
    stem = args.name or Path(files[-1 if args.person == "reactor" else 0]).stem
    return motion, stem


def run(args) -> int:
    from retarget.errors import RetargetError
    from ros_free_bridge.robots import planning_robot

    motion, stem = _load(args)
    robot = planning_robot(args.robot, args.profile, fixed_base=args.fixed_base)
    if args.mode == "offline" and args.offline_engine == "planner" and not (args.balance and robot.floating):
        raise RetargetError(
            "--offline-engine planner: plans a free-standing robot's steps with balance on: add --balance "
            "(and leave out --fixed-base), or use --offline-engine ipopt or auto"
        )
    try:
        traj = _retarget(args, robot, motion)
    except RetargetError as exc:
        if exc.time_s is None:
            raise  # bad input (a file, a profile): one line and exit 2 through the CLI
        # a verdict on the clip, not bad input: the robot cannot do it (an infeasible window, or
        # one the solver did not finish); exit 1 like a failed physics check
        print(f"FAIL {stem}: {exc}", file=sys.stderr)
        return 1
    return _report(args, robot, motion, stem, traj)


def _retarget(args, robot, motion):
    from retarget.lead_in import LeadInConfig
    from retarget.offline import OfflineConfig, OfflineRetargeter
    from retarget.streaming import StreamingConfig, StreamingRetargeter

    if args.mode == "streaming":
        return StreamingRetargeter(
            robot, motion.fps, StreamingConfig(compile=not args.no_compile, balance=args.balance)
        ).run(motion)
    sizes = {k: v for k, v in (("window", args.window), ("overlap", args.overlap)) if v is not None}
    cfg = OfflineConfig(
        **sizes,
        balance=args.balance,
        zmp=args.zmp,
        balance_margin=args.balance_margin,
        contacts=not args.no_contacts,
        self_collision=not args.no_collision,
        collision_model=args.foot_collision,
        retime=args.retime,
        auto_retime=args.auto_retime,
        compile=not args.no_compile,
        lead_in=None if args.no_lead_in else LeadInConfig(),
        engine=args.offline_engine,
    )
    return OfflineRetargeter(robot, cfg).retarget(motion)


def _report(args, robot, motion, stem, traj) -> int:
    from retarget.report import evaluate, plot_joints
    from retarget.targets import make_targets

    retime = float(traj.meta.get("retime", 1.0))
    src = motion if retime == 1.0 else _slowed(motion, retime)
    report = evaluate(robot, traj, make_targets(robot, src), clip=motion.name or stem)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    traj.save_npz(out / f"{stem}.npz")
    traj.save_csv(out / f"{stem}.csv")
    report.save(out, stem)
    plot_joints(robot, traj, out / f"{stem}.joints.png")
    print(report.to_markdown())
    print(f"wrote {out / (stem + '.npz')}, .csv, .report.json, .report.md, .joints.png")
    return 1 if (args.strict and not report.passed) else 0


def _slowed(motion, factor: float):
    from dualflow.motion import Motion

    return Motion(motion.positions, fps=motion.fps / factor, contacts=motion.contacts, name=motion.name).resample(
        motion.fps
    )
