"""``dualflow-bridge retarget-check FOLDER``: retarget every motion in a folder and check it in physics.

    dualflow-bridge retarget-check my_clips/ --robot op3 -o out/check

Every motion file in FOLDER (BVH, npz, InterGen / HumanML3D npy; with --recursive, in its
whole tree) is retargeted offline onto the robot (joint and speed limits, foot contacts,
self-collision, balance; --retargeter streaming: frame by frame, as the live bridge does)
and played in MuJoCo (falls, torque, speed, collisions). For a
two-person file the robot takes the reactor's part; a folder in InterGen's layout (person1/
and person2/, or motions_processed/ holding them) gives one clip per pair, its reactor
(person2, unless InterHuman-AS's actor_reactor.json says otherwise).

Prints one row per clip: PASS; FAIL with the stage (retarget or check), the reason and the
time of the first failure (seconds into the motion file); ERROR for a file that cannot be
read, with the message. Clips run in parallel, one per core; a clip that fails, or even
crashes its worker process, never stops the batch. Writes ``results.csv`` and ``results.md``
and, per clip, the trajectory, the retarget report and the physics check report under
``OUT/clips/<clip>/`` (<clip>: the file's path relative to FOLDER).

Exit code 0 when every clip passes, 1 otherwise, 2 for a bad folder or option.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("retarget-check", help="retarget and physics-check every motion file in a folder",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folder", help="folder of motion files (BVH, npz, InterGen/HumanML3D npy); pairs use the reactor")
    p.add_argument("--robot", default="op3", metavar="NAME|DIR", help="the robot: a bundled name (op3, ub14) or a robot folder (see `robot init`) (default op3)")
    p.add_argument("-o", "--out", default="out/retarget_check", help="output folder (default out/retarget_check)")
    p.add_argument("--jobs", type=int, help="worker processes (default: every core this process may use)")
    p.add_argument("--recursive", action="store_true", help="take motion files from FOLDER's subfolders too "
                   "(OUT is left out when it lies inside FOLDER)")
    p.add_argument("--no-balance", action="store_true", help="retarget without the centre-of-mass constraint")
    p.add_argument("--auto-retime", action="store_true", help="slow infeasible clips down (1.25x, 1.5x, 2x) instead of failing")
    p.add_argument("--retargeter", choices=("offline", "streaming"), default="offline",
                   help="offline: the whole clip in windows with IPOPT (default); streaming: frame by frame as the "
                        "live bridge does it, keeping the feet planted and the CoM over them: it keeps some "
                        "single-support captures standing that offline does not, at the cost of tracking (the CMU "
                        "pair: both pass, with about 110 mm keypoint error against about 14 mm offline)")
    p.add_argument("--no-compile", action="store_true", help="skip C code generation (for machines without a compiler)")
    p.set_defaults(func=run)


def run(args) -> int:
    from ros_free_bridge.batch import BatchConfig, find_motion_files, markdown_table, run_batch, write_results
    from ros_free_bridge.errors import BridgeError

    if args.jobs is not None and args.jobs < 1:
        raise BridgeError(f"--jobs {args.jobs}: give at least 1 worker process")
    files = find_motion_files(args.folder, recursive=args.recursive, exclude=args.out)
    if not files:
        where = "this folder or its subfolders" if args.recursive else "this folder (--recursive looks in subfolders)"
        raise BridgeError(f"{args.folder}: no motion files (.bvh, .npz, .npy) in {where}")
    cfg = BatchConfig(robot=args.robot, out=Path(args.out), balance=not args.no_balance, auto_retime=args.auto_retime,
                      compile=not args.no_compile, retargeter=args.retargeter)
    results = run_batch(files, cfg, args.jobs, folder=args.folder)
    paths = write_results(results, cfg.out)
    print(markdown_table(results))
    print(f"wrote {paths['csv']} and {paths['markdown']}")
    return 0 if all(r.status == "pass" for r in results) else 1
