"""``dualflow-bridge motion info|convert|preview``: look at, convert and draw motion files.

One person: ``FILE``; two people in one world frame: ``FILE FILE2`` or
``--actor A --reactor B`` (e.g. the two BVH files of one CMU capture), or a duet
``.npz``. Formats are those of :mod:`dualflow.motion.io.formats`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from dualflow.errors import DualFlowError

DEFAULT_SAMPLE_RULE = "hand_hold"


def _add_load_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("reading")
    g.add_argument("--actor", metavar="FILE", help="actor (person A) file; use with --reactor")
    g.add_argument("--reactor", metavar="FILE", help="reactor (person B) file, same world frame as --actor")
    g.add_argument("--fps", type=float, help="resample to this frame rate")
    g.add_argument("--source-fps", type=float, help="the file's frame rate where the file does not store it")
    g.add_argument("--scale", type=float, help="metres per file unit (default: detected from the person's height)")
    g.add_argument(
        "--up",
        choices=("auto", "y", "z"),
        help="up axis of the file (default: auto for BVH, the format's own otherwise)",
    )
    g.add_argument(
        "--joint-map",
        metavar="NAME|FILE",
        help="BVH joint map: cmu, mixamo, mixamo_spine3, smpl, or a .yaml/.json file",
    )
    first = g.add_mutually_exclusive_group()
    first.add_argument(
        "--keep-first-frame",
        dest="drop_first",
        action="store_const",
        const=False,
        default="auto",
        help="BVH: keep frame 0 even if it looks like a reference pose",
    )
    first.add_argument(
        "--drop-first-frame",
        dest="drop_first",
        action="store_const",
        const=True,
        help="BVH: always drop frame 0 (a T-pose / reference pose)",
    )
    g.add_argument("--no-height-check", action="store_true", help="accept people outside 1.4-2.1 m tall")
    g.add_argument("--ground", action="store_true", help="shift vertically so the lowest foot joint is at z = 0")


def _options(args) -> dict:
    opts = {
        "fps": args.fps,
        "source_fps": args.source_fps,
        "scale": args.scale,
        "joint_map": args.joint_map,
        "drop_first": args.drop_first,
    }
    if args.up and args.up != "auto":
        opts["up"] = args.up
    if args.no_height_check:
        opts["height_range"] = None
    return opts


def _inputs(args, files: list[str]) -> list[str]:
    if args.actor or args.reactor:
        if not (args.actor and args.reactor):
            raise DualFlowError("give both --actor and --reactor (two files in one world frame)")
        if files:
            raise DualFlowError("give either FILE [FILE2] or --actor/--reactor, not both")
        return [args.actor, args.reactor]
    if not files:
        raise DualFlowError("no input: give FILE [FILE2] or --actor A --reactor B")
    if len(files) > 2:
        raise DualFlowError(f"at most two input files (actor, reactor), got {len(files)}")
    return files


def _load(args, files: list[str]):
    from dualflow.motion.io import load_any, load_pair, put_on_ground

    opts = _options(args)
    motion = load_any(files[0], **opts) if len(files) == 1 else load_pair(files[0], files[1], **opts)
    return put_on_ground(motion) if args.ground else motion


# ---------------------------------------------------------------------------
# info
# ---------------------------------------------------------------------------
def describe(motion) -> str:
    """Human-readable summary of a Motion or TwoPersonMotion (metres, seconds)."""
    import numpy as np

    from dualflow.motion import FOOT_JOINTS, TwoPersonMotion
    from dualflow.motion.io.units import estimate_height

    people = (
        [("actor", motion.actor), ("reactor", motion.reactor)]
        if isinstance(motion, TwoPersonMotion)
        else [("person", motion)]
    )
    first = people[0][1]
    lines = [f"frames    {first.n_frames}", f"fps       {first.fps:g}", f"duration  {first.duration:.3f} s"]
    if isinstance(motion, TwoPersonMotion) and motion.text:
        lines.append(f"text      {motion.text}")
    for role, m in people:
        pos = m.positions
        lo, hi = pos.reshape(-1, 3).min(axis=0), pos.reshape(-1, 3).max(axis=0)
        lines.append(f"{role}: {m.name}" if m.name else f"{role}:")
        lines.append(f"  height (standing estimate)  {estimate_height(pos):.2f} m")
        lines.append(f"  pelvis height               {pos[:, 0, 2].min():.2f} .. {pos[:, 0, 2].max():.2f} m")
        lines.append(f"  lowest foot joint           {pos[:, list(FOOT_JOINTS), 2].min():+.3f} m")
        lines.append(
            f"  extents  x {lo[0]:+.2f} .. {hi[0]:+.2f}   y {lo[1]:+.2f} .. {hi[1]:+.2f}   "
            f"z {lo[2]:+.2f} .. {hi[2]:+.2f} m"
        )
        path = np.linalg.norm(np.diff(pos[:, 0, :2], axis=0), axis=-1).sum()
        lines.append(f"  pelvis ground path          {path:.2f} m")
    if isinstance(motion, TwoPersonMotion):
        d = np.linalg.norm(motion.actor.positions[:, 0, :2] - motion.reactor.positions[:, 0, :2], axis=-1)
        lines.append(f"pelvis distance  {d.min():.2f} .. {d.max():.2f} m (closest at {d.argmin() / first.fps:.2f} s)")
    return "\n".join(lines)


def _bvh_notes(args, files: list[str]) -> list[str]:
    from dualflow.motion.io.bvh_motion import read_bvh_motion
    from dualflow.motion.io.formats import _bvh_options
    from dualflow.motion.io.units import unit_name

    notes = []
    opts = _options(args)
    shared = dict(opts)
    for f in files:
        if Path(f).suffix.lower() != ".bvh":
            continue
        r = read_bvh_motion(f, _bvh_options(shared))
        shared.update(scale=r.scale, axes=r.axes)
        notes.append(
            f"{f}: joint map {r.joint_map}, unit {unit_name(r.scale)} ({r.scale:.5g} m), "
            f"{'dropped' if r.dropped_first_frame else 'kept'} frame 0, {r.motion.fps:g} fps in the file"
        )
    return notes


def _info(args) -> int:
    files = _inputs(args, args.files)
    motion = _load(args, files)
    print(describe(motion))
    for note in _bvh_notes(args, files):
        print(note)
    return 0


# ---------------------------------------------------------------------------
# convert
# ---------------------------------------------------------------------------
def _convert(args) -> int:
    from dualflow.motion import TwoPersonMotion
    from dualflow.motion.io import save_motion

    paths = list(args.paths)
    out = Path(paths.pop())
    files = _inputs(args, paths)
    motion = _load(args, files)
    if isinstance(motion, TwoPersonMotion) and out.suffix.lower() == ".bvh":
        written = []
        for role, m in (("actor", motion.actor), ("reactor", motion.reactor)):
            target = out.with_name(f"{out.stem}_{role}.bvh")
            save_motion(m, target, translations=args.bvh_translations)
            written.append(str(target))
        print(f"wrote {' and '.join(written)} (a BVH file holds one person)")
        return 0
    save_motion(motion, out, translations=args.bvh_translations)
    print(f"wrote {out} ({motion.n_frames} frames at {motion.fps:g} fps)")
    return 0


# ---------------------------------------------------------------------------
# preview
# ---------------------------------------------------------------------------
def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 640x480, got {text!r}") from None
    return w, h


def _preview(args) -> int:
    import time

    from dualflow.motion.preview import PreviewConfig, render_preview

    if args.sample is not None:
        if args.files or args.actor or args.reactor:
            raise DualFlowError("--sample draws the bundled synthetic duet; give no input files with it")
        from dualflow.synthetic import make_duet

        motion = make_duet(args.sample, seconds=args.seconds, fps=args.fps or 30.0, seed=args.seed)
        title = args.title or f"synthetic sample: {args.sample} (seed {args.seed})"
    else:
        files = _inputs(args, args.files)
        motion = _load(args, files)
        title = args.title if args.title is not None else " + ".join(Path(f).name for f in files)
    width, height = args.size
    start = time.perf_counter()
    out = render_preview(motion, args.output, PreviewConfig(width=width, height=height, fps=args.fps, title=title))
    print(f"wrote {out} ({motion.n_frames} frames, {time.perf_counter() - start:.1f} s)")
    return 0


def register(subparsers) -> None:
    motion = subparsers.add_parser(
        "motion", help="inspect, convert and preview human motion files", description=__doc__.split("\n\n")[0]
    )
    sub = motion.add_subparsers(dest="motion_command", metavar="ACTION", required=True)

    info = sub.add_parser(
        "info",
        help="frames, fps, duration, height and extents of a motion file",
        description="Read a motion file (or a pair) and print what the bridge sees: frames, "
        "frame rate, duration, each person's height, pelvis height, lowest foot, extents and "
        "path, the distance between two people, and for BVH the joint map and "
        "length unit it detected. Use it to check a file before retargeting it.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    info.add_argument("files", nargs="*", metavar="FILE", help="motion file, and optionally the partner's (FILE2)")
    _add_load_options(info)
    info.set_defaults(func=_info)

    conv = sub.add_parser(
        "convert",
        help="convert between BVH / npz / npy motion files (writes .npz or .bvh)",
        description="Convert a motion file (BVH, npz, AMASS npz, HumanML3D / InterGen npy) to our "
        ".npz or to BVH, with the reading options below (unit, up axis, joint map, "
        "resampling).\n\n"
        "  motion convert IN OUT                        one person\n"
        "  motion convert IN IN2 OUT                    two people, one world frame\n"
        "  motion convert --actor A --reactor B OUT     the same\n\n"
        "A pair becomes a duet .npz, or two BVH files OUT_actor.bvh and OUT_reactor.bvh.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    conv.add_argument("paths", nargs="+", metavar="PATH", help="input file(s) then the output (.npz or .bvh)")
    conv.add_argument(
        "--bvh-translations",
        choices=("root", "all"),
        default="root",
        help="BVH output: position channels on the root only (usual) or on every joint (exact)",
    )
    _add_load_options(conv)
    conv.set_defaults(func=_convert)

    prev = sub.add_parser(
        "preview",
        help="draw stick figures of one or two people to .mp4 or .gif",
        description="Draw one or two people as stick figures, in 3-D with the ground, to an "
        ".mp4 or .gif: a quick look at a file (or at the bundled synthetic duet, "
        "--sample) without MuJoCo.",
    )
    prev.add_argument("files", nargs="*", metavar="FILE", help="motion file, and optionally the partner's (FILE2)")
    prev.add_argument("-o", "--output", required=True, help="output video, .mp4 or .gif")
    prev.add_argument(
        "--sample",
        nargs="?",
        const=DEFAULT_SAMPLE_RULE,
        metavar="RULE",
        help="preview the bundled synthetic duet (rule: mirror, follow, hand_hold, orbit; "
        f"default {DEFAULT_SAMPLE_RULE})",
    )
    prev.add_argument("--seconds", type=float, default=8.0, help="length of the --sample clip (s)")
    prev.add_argument("--seed", type=int, default=0, help="seed of the --sample clip")
    prev.add_argument("--size", type=_size, default=(640, 480), help="video size WxH in pixels (even numbers)")
    prev.add_argument("--title", help="caption (default: the file names)")
    _add_load_options(prev)
    prev.set_defaults(func=_preview)
