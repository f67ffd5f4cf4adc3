"""Motion import and preview speed, each next to a baseline measured in the same run.

1. BVH forward kinematics (the CMU file 18_01, 304 frames x 38 joints, or a synthetic
   SMPL-22 clip where ../shared/data is absent): our vectorised FK (one pass over
   joints, all frames at once) against a per-frame, per-joint loop with scipy
   Rotation objects (the baseline). Both give the same positions (checked).
2. Stick-figure preview of a 10 s two-person clip at 30 fps (300 frames, 640x480
   mp4): our renderer (reused Agg figure, background blitted, streamed to ffmpeg)
   against a baseline that redraws the whole figure every frame with matplotlib's
   3D axes (the usual ``Axes3D`` approach), writing to the same encoder. The issue's
   target: "a person can look at any motion in seconds".

    python bench/motion_io.py [--seconds 10] [--quick]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.table import NA, Row, parse_args, script_main  # noqa: E402
from dualflow.motion import PARENTS  # noqa: E402
from dualflow.motion.io import motion_to_bvh, read_bvh  # noqa: E402
from dualflow.motion.preview import PreviewConfig, render_preview  # noqa: E402
from dualflow.synthetic import make_duet  # noqa: E402

CMU = Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap" / "cmu" / "18_01.bvh"
QUICK = ["--seconds", "2"]


def loop_fk(clip) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    out = np.zeros((clip.n_frames, len(clip.joints), 3))
    starts = clip.channel_offsets()
    for t in range(clip.n_frames):
        glob = [None] * len(clip.joints)
        for j, joint in enumerate(clip.joints):
            vals = clip.motion[t, starts[j] : starts[j] + len(joint.channels)]
            trans = np.array(joint.offset, float)
            axes, angles = "", []
            for ch, v in zip(joint.channels, vals):
                if ch.endswith("position"):
                    trans["XYZ".index(ch[0])] = v
                else:
                    axes += ch[0]
                    angles.append(v)
            local = Rotation.from_euler(axes, angles, degrees=True) if axes else Rotation.identity()
            if joint.parent < 0:
                out[t, j], glob[j] = trans, local
            else:
                out[t, j] = out[t, joint.parent] + glob[joint.parent].apply(trans)
                glob[j] = glob[joint.parent] * local
    return out


def best_of(fn, repeats=3) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def baseline_preview(pair, path: Path, cfg: PreviewConfig) -> None:
    """Full redraw of a matplotlib 3D axes per frame (the common approach)."""
    import imageio_ffmpeg
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(cfg.width / 100, cfg.height / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    people = [pair.actor.positions, pair.reactor.positions]
    allpos = np.concatenate([p.reshape(-1, 3) for p in people])
    lo, hi = allpos.min(axis=0), allpos.max(axis=0)
    writer = imageio_ffmpeg.write_frames(
        str(path),
        (cfg.width, cfg.height),
        fps=pair.fps,
        codec="libx264",
        pix_fmt_out="yuv420p",
        macro_block_size=2,
        ffmpeg_log_level="error",
    )
    writer.send(None)
    for i in range(pair.n_frames):
        ax.cla()
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_zlim(0, hi[2])
        for k, pos in enumerate(people):
            for j in range(1, 22):
                a, b = pos[i, PARENTS[j]], pos[i, j]
                ax.plot([a[0], b[0]], [a[1], b[1]], [a[2], b[2]], color=f"C{k}", lw=3)
        canvas.draw()
        writer.send(np.asarray(canvas.buffer_rgba())[:, :, :3].copy())
    writer.close()


def rows(quick: bool = False, argv: list[str] = ()) -> list[Row]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="preview clip length (s)")
    args = parse_args(parser, argv, quick, QUICK)

    if CMU.exists():
        clip, what = read_bvh(CMU), f"CMU 18_01 ({CMU.name})"
    else:
        clip, what = motion_to_bvh(make_duet("mirror", 10.0, 30.0, 0).actor), "synthetic SMPL-22 clip"
    ours = best_of(clip.global_positions)
    base = best_of(lambda: loop_fk(clip), repeats=1)
    assert np.allclose(clip.global_positions(), loop_fk(clip), atol=1e-9)
    print(f"BVH FK, {what}: {clip.n_frames} frames x {len(clip.joints)} joints")
    print(f"  vectorised  {ours * 1e3:8.1f} ms   ({clip.n_frames / ours:,.0f} frames/s)")
    print(f"  baseline    {base * 1e3:8.1f} ms   per-frame scipy loop   -> {base / ours:.0f}x faster")
    out = [
        Row(
            f"BVH forward kinematics, {clip.n_frames} frames x {len(clip.joints)} joints (ms; baseline per-frame "
            "scipy loop)",
            ours * 1e3,
            base * 1e3,
            "",
            NA,
        )
    ]

    pair = make_duet("hand_hold", args.seconds, 30.0, 0)
    cfg = PreviewConfig()
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        render_preview(pair, Path(tmp) / "ours.mp4", cfg)
        ours = time.perf_counter() - start
        start = time.perf_counter()
        baseline_preview(pair, Path(tmp) / "base.mp4", cfg)
        base = time.perf_counter() - start
    print(f"preview, {args.seconds:g} s two-person clip, {pair.n_frames} frames, {cfg.width}x{cfg.height} mp4")
    print(f"  ours        {ours:8.2f} s    ({pair.n_frames / ours:.0f} frames/s)   target: seconds")
    print(f"  baseline    {base:8.2f} s    Axes3D full redraw     -> {base / ours:.1f}x faster")
    out.append(
        Row(
            f"stick-figure preview, {args.seconds:g} s two-person clip, 640x480 mp4 (s; baseline Axes3D full redraw)",
            ours,
            base,
            "seconds (no number given)",
            NA,
        )
    )
    return out


def main(argv: list[str] | None = None) -> int:
    return script_main(rows, argv)


if __name__ == "__main__":
    raise SystemExit(main())
