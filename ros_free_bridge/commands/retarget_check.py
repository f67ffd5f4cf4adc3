"""``dualflow-bridge retarget-check FOLDER``: retarget every motion in a folder and check it in physics.

    dualflow-bridge retarget-check my_clips/ --robot op3 -o out/check
    dualflow-bridge retarget-check captures/ --pairs '{name}_S1.bvh,{name}_S2.bvh' -o out/check
    dualflow-bridge retarget-check dataset/ --recursive --engine ray --address auto -o out/check --resume

Every motion file in FOLDER (BVH, npz, InterGen / HumanML3D npy; with --recursive, in its
whole tree) is retargeted offline onto the robot (joint and speed limits, foot contacts,
self-collision, balance; --retargeter streaming: frame by frame, as the live bridge does)
and played in MuJoCo (falls, torque, speed, collisions). For a two-person file the robot
takes the reactor's part; --pairs joins the two files of one capture (actor first) into one
clip, the robot playing the second file's person next to the first in the capture's world
frame; a folder in InterGen's layout (person1/ and person2/, or motions_processed/ holding
them) gives one clip per pair, its reactor (person2, unless InterHuman-AS's
actor_reactor.json says otherwise).

Prints one row per clip: PASS; FAIL with the stage (retarget or check), the reason and the
time of the first failure (seconds into the motion file); ERROR for a file that cannot be
read, with the message. Clips run in parallel, one per core (--engine ray: as Ray tasks on a
cluster or a local Ray instance); a clip that fails, or even crashes its worker process,
never stops the batch. Each clip's row is added to ``results.jsonl`` and ``results.csv`` as
soon as it ends, so an interrupted batch loses nothing: --resume skips the clips already
complete. At the end ``results.csv`` (in clip order), ``results.md`` and ``index.html`` (a
sortable, filterable report that opens from disk) are written; per clip, under
``OUT/clips/<clip>/`` (<clip>: the file's path relative to FOLDER), the trajectory, the
retarget report, the physics check report with plots, a video of the person and the robot
(unless --no-video) and a page linking them.

Exit code 0 when every clip passes, 1 otherwise, 2 for a bad folder or option, 130 when
interrupted (the finished clips are kept; --resume continues).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ros_free_bridge.commands.retarget import add_offline_engine


def register(sub) -> None:
    p = sub.add_parser(
        "retarget-check",
        help="retarget and physics-check every motion file in a folder",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("folder", help="folder of motion files (BVH, npz, InterGen/HumanML3D npy); pairs use the reactor")
    p.add_argument(
        "--robot",
        default="op3",
        metavar="NAME|DIR",
        help="the robot: a bundled name (op3, ub14) or a robot folder (see `robot init`) (default op3)",
    )
    p.add_argument("-o", "--out", default="out/retarget_check", help="output folder (default out/retarget_check)")
    p.add_argument("--jobs", type=int, help="worker processes (default: every core this process may use)")
    p.add_argument(
        "--recursive",
        action="store_true",
        help="take motion files from FOLDER's subfolders too (OUT is left out when it lies inside FOLDER)",
    )
    p.add_argument("--no-balance", action="store_true", help="retarget without the centre-of-mass constraint")
    p.add_argument(
        "--auto-retime", action="store_true", help="slow infeasible clips down (1.25x, 1.5x, 2x) instead of failing"
    )
    p.add_argument(
        "--no-lead-in",
        action="store_true",
        help="offline: judge a clip that starts mid-motion from its first frame, without the lead-in from "
        "standing (the check's joint-space entry only)",
    )
    p.add_argument(
        "--retargeter",
        choices=("offline", "streaming"),
        default="offline",
        help="offline: the whole clip at once (default; see --offline-engine); streaming: frame by frame as "
        "the live bridge does it (steps at the robot's pace, its weight over its feet)",
    )
    add_offline_engine(p)
    p.add_argument("--no-compile", action="store_true", help="skip C code generation (for machines without a compiler)")
    p.add_argument(
        "--pairs",
        metavar="PATTERN",
        help="join the two files of one capture into one two-person clip: two file-name patterns with "
        "{name}, actor first, e.g. '{name}_S1.bvh,{name}_S2.bvh'; the robot takes the second file's "
        "part and the first person stands beside it in the shared world frame",
    )
    p.add_argument(
        "--no-video", action="store_true", help="skip each clip's video (person and robot side by side); faster"
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="keep the clips a previous run in OUT completed with the same "
        "options and robot files, and check only the rest",
    )
    p.add_argument(
        "--engine",
        choices=("local", "ray"),
        default="local",
        help="local: worker processes on this machine (default); ray: one Ray task per clip, on the "
        'cluster at --address or a local Ray instance (needs `pip install -e ".[cluster]"`)',
    )
    p.add_argument(
        "--address",
        metavar="ADDR",
        help="--engine ray: the Ray cluster to use ('auto', 'HOST:6379', "
        "'ray://HOST:10001'; default: start a local Ray instance with --jobs CPUs)",
    )
    p.set_defaults(func=run)


def run(args) -> int:
    from ros_free_bridge.batch.clips import PairPattern, find_clips
    from ros_free_bridge.batch.config import BatchConfig
    from ros_free_bridge.batch.results import markdown_table
    from ros_free_bridge.batch.run import run_batch
    from ros_free_bridge.errors import BridgeError

    if args.jobs is not None and args.jobs < 1:
        raise BridgeError(f"--jobs {args.jobs}: give at least 1 worker process")
    if args.address and args.engine != "ray":
        raise BridgeError("--address names a Ray cluster: add --engine ray")
    if args.retargeter == "offline" and args.offline_engine == "planner":
        from ros_free_bridge.robots import resolve_robot

        fixed = resolve_robot(args.robot).fixed_base
        if args.no_balance or fixed:
            raise BridgeError(
                f"--offline-engine planner: plans a free-standing robot's steps with balance on ({args.robot} is "
                f"{'fixed-base' if fixed else 'checked with --no-balance'}); "
                "use --offline-engine ipopt or auto"
            )
    _require_robot(args.robot)
    pairs = PairPattern.parse(args.pairs) if args.pairs else None
    clips = find_clips(args.folder, recursive=args.recursive, exclude=args.out, pairs=pairs)
    if not clips:
        where = "this folder or its subfolders" if args.recursive else "this folder (--recursive looks in subfolders)"
        raise BridgeError(f"{args.folder}: no motion files (.bvh, .npz, .npy) in {where}")
    cfg = BatchConfig(
        robot=args.robot,
        out=Path(args.out),
        balance=not args.no_balance,
        auto_retime=args.auto_retime,
        lead_in=not args.no_lead_in,
        compile=not args.no_compile,
        retargeter=args.retargeter,
        offline_engine=args.offline_engine,
        video=not args.no_video,
    )
    try:
        results = run_batch(clips, cfg, args.jobs, engine=args.engine, address=args.address, resume=args.resume)
    except KeyboardInterrupt:
        print(
            f"interrupted: the finished clips are in {cfg.out}; add --resume to the same command to check the rest",
            file=sys.stderr,
        )
        raise
    print(markdown_table(results))
    print(f"wrote {cfg.out / 'results.csv'}, {cfg.out / 'results.md'} and {cfg.out / 'index.html'}")
    return 0 if all(r.status == "pass" for r in results) else 1


def _require_robot(robot: str) -> None:
    """The robot and its profile load and bind, and its hardware config gives the loop its
    limits (which the physics check's safety filter plays each clip with; well under a second),
    or one BridgeError naming the file and field: an unknown robot, a broken profile or a
    hardware config the loop refuses failed every clip, one row each."""
    from firmware_cfg.errors import ConfigError
    from retarget.errors import RetargetError
    from retarget.robot import load_robot
    from ros_free_bridge.errors import BridgeError
    from ros_free_bridge.robots import loop_limits, resolve_robot

    try:
        load_robot(robot)
        loop_limits(resolve_robot(robot))
    except (RetargetError, ConfigError) as exc:
        raise BridgeError(str(exc)) from None
