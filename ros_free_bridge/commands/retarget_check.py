"""``dualflow-bridge retarget-check FOLDER``: retarget every motion in a folder and check it in physics.

    dualflow-bridge retarget-check my_clips/ --robot op3 -o out/check

Prints one row per clip (pass / fail with the stage, reason and time of the first failure /
error for unreadable files) and writes ``results.csv``, ``results.md`` and, per clip, the
trajectory, the retarget report and the physics check report under ``OUT/clips/<clip>/``.
Exit code 0 when every clip passes, 1 otherwise.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("retarget-check", help="retarget and physics-check every motion file in a folder",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folder", help="folder of motion files (BVH, npz, InterGen/HumanML3D npy); pairs use the reactor")
    p.add_argument("--robot", default="op3", help="bundled robot name (default op3)")
    p.add_argument("-o", "--out", default="out/retarget_check", help="output folder (default out/retarget_check)")
    p.add_argument("--jobs", type=int, help="worker processes (default: all cores)")
    p.add_argument("--no-balance", action="store_true", help="retarget without the centre-of-mass constraint")
    p.add_argument("--auto-retime", action="store_true", help="slow infeasible clips down (1.25x, 1.5x, 2x) instead of failing")
    p.add_argument("--no-compile", action="store_true", help="skip C code generation (for machines without a compiler)")
    p.set_defaults(func=run)


def run(args) -> int:
    from ros_free_bridge.batch import BatchConfig, find_motion_files, markdown_table, run_batch, write_results
    from ros_free_bridge.errors import BridgeError

    files = find_motion_files(args.folder)
    if not files:
        raise BridgeError(f"{args.folder}: no motion files (.bvh, .npz, .npy) in this folder")
    cfg = BatchConfig(robot=args.robot, out=Path(args.out), balance=not args.no_balance, auto_retime=args.auto_retime,
                      compile=not args.no_compile)
    results = run_batch(files, cfg, args.jobs, progress=sys.stderr.isatty() or True)
    paths = write_results(results, cfg.out)
    print(markdown_table(results))
    print(f"wrote {paths['csv']} and {paths['markdown']}")
    return 0 if all(r.status == "pass" for r in results) else 1
