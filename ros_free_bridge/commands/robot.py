"""``dualflow-bridge robot init|check|list``: bring your own robot.

- ``init MJCF -o DIR``: make a robot folder for any MJCF humanoid from the model alone: a
  retarget profile that works as written (keypoints from the kinematic tree and geometry,
  capsules fitted to the collision geoms, feet from the lowest contact geoms, limits from
  the MJCF or the actuators' ctrlrange), a hardware-config skeleton whose unknowns (servo
  IDs, directions, offsets, port) are marked ``# FILL IN``, and a README. The model is not
  copied: the folder points to it (``mjcf:``). A scene file around the robot is replaced by
  the robot model it includes. How it infers what: retarget/profile_init.py. A free-standing
  robot is then probed for stepping in physics (sim/step_probe.py: stepping leaders streamed
  with steps at slower and slower paces); the profile steps at the first pace that passes them
  all, or keeps the feet planted (``--no-step-probe`` skips it and keeps them planted).
- ``check DIR``: validate a robot folder and explain each problem with its fix (one line
  each); exit 0 when it is fine (left-over FILL IN markers are listed as to-dos), 2 when not.
  ``--hardware`` also fails on a missing hardware config or a marker left (before the
  first power-on).
- ``list``: the bundled robots and their descriptions.

Every other command takes the folder as ``--robot DIR``.
"""

from __future__ import annotations

import argparse
import sys


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "robot",
        help="make (init), validate (check) and list robot folders",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="robot_command", metavar="ACTION")

    q = sub.add_parser(
        "init",
        help="write a robot folder (profile, hardware skeleton, README) for an MJCF",
        description="Write a robot folder for an MJCF humanoid from the model alone: profile.yaml "
        "(retargets as written), hardware.yaml (a skeleton; unknowns marked FILL IN) and "
        "README.md. The MJCF is referenced, not copied.",
    )
    q.add_argument("mjcf", help="the robot's MJCF (.xml); a scene file that <include>s the robot works too")
    q.add_argument("-o", "--out", required=True, help="the robot folder to write (created if missing)")
    q.add_argument("--name", help="the robot's name in the profile and hardware config (default: the folder's name)")
    q.add_argument(
        "--force", action="store_true", help="overwrite profile.yaml, hardware.yaml and README.md if present"
    )
    q.add_argument(
        "--no-step-probe",
        action="store_true",
        help="skip the stepping probe in physics (a few seconds to a minute); the feet then stay planted",
    )
    q.set_defaults(func=run_init)

    c = sub.add_parser(
        "check",
        help="validate a robot folder; one line per problem with its fix",
        description="Validate a robot folder: the model loads in MuJoCo, the profile names only what "
        "the model has, feet for a free-standing robot, the hardware config parses and maps "
        "every actuated joint within the MJCF's limits. Exit 0 when fine, 2 when not.",
    )
    c.add_argument("folder", help="the robot folder (as written by `robot init`, or a bundled robot's name)")
    c.add_argument(
        "--hardware",
        action="store_true",
        help="also require a hardware config with no FILL IN marker left (before the first power-on)",
    )
    c.set_defaults(func=run_check)

    ls = sub.add_parser(
        "list",
        help="the bundled robots and their descriptions",
        description="List the bundled robots (firmware_cfg/robots/<name>/) with their one-line "
        "descriptions; any other robot folder works wherever --robot is taken.",
    )
    ls.set_defaults(func=run_list)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def run_init(args) -> int:
    from retarget.profile_init import init_robot_folder
    from ros_free_bridge.robots import bridge_check_config, planning_robot

    def progress(clip: str) -> None:
        print(f"  probing steps in physics: {clip}", file=sys.stderr, flush=True)

    def check_config(folder):  # the probe judges what the bridge would send, as `check` does
        return bridge_check_config(folder, mode="free")

    res = init_robot_folder(
        args.mjcf,
        args.out,
        name=args.name,
        force=args.force,
        probe_steps=not args.no_step_probe,
        progress=progress,
        check_config=check_config,
        planner=planning_robot,  # ... of the plans the bridge would make
    )
    print(f"robot folder {res.folder} for {res.mjcf}:")
    for path in (res.profile, res.hardware, res.readme):
        print(f"  {path}")
    found = ", ".join(k for k in ("legs", "arms") if getattr(res.anatomy, k)) or "no limbs"
    print(f"  found: {found}; {len(res.anatomy.points)} keypoints")
    for note in res.notes:
        print(f"  note: {note}")
    print(f"next: fill in {res.hardware.name} (lines marked FILL IN), then `dualflow-bridge robot check {res.folder}`")
    return 0


def run_check(args) -> int:
    from pathlib import Path

    from firmware_cfg.registry import BUNDLED_DIR
    from retarget.robot_check import check_robot_folder

    folder = Path(args.folder)
    if not folder.exists() and "/" not in args.folder and (BUNDLED_DIR / args.folder).is_dir():
        folder = BUNDLED_DIR / args.folder
    res = check_robot_folder(folder, hardware=args.hardware)
    for line in res.problems:
        print(f"problem: {line}", file=sys.stderr)
    if not res.ok:
        return 2
    print(f"OK {folder}: {res.summary}")
    for line in res.todos:
        print(f"  todo: {line}")
    for line in res.notes:
        print(f"  note: {line}")
    return 0


def run_list(args) -> int:
    from firmware_cfg.registry import bundled_names, resolve

    for name in bundled_names():
        robot = resolve(name)
        print(f"{name:12s} {robot.description}")
    return 0
