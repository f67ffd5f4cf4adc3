"""Streaming reactive inference: compute time per emitted frame and seam continuity.

    python bench/bench_streaming.py [--checkpoint DIR] [--seconds 10] [--steps 20] [--hop 8] [--quick]

Uses a trained checkpoint (default: the bundled synthetic one, ``dualflow.checkpoint``) and
one synthetic duet (``dualflow.synthetic``, SYNTHETIC data: a procedural leader and a rule
follower) of ``--seconds`` at 30 fps. Prints, each next to a baseline measured in the same run
and the issue's target:

1. compute time per emitted reactor frame of ``ReactiveStreamer`` (hop 1: every frame as soon
   as its look-ahead arrives; hop N: N frames per window), against one offline window of the
   same length divided by its frames; target: below 33.3 ms per frame (30 fps real time).
2. seam continuity: the mean velocity jump ||p[i] - 2 p[i-1] + p[i-2]|| (mm/frame^2, joints
   averaged) at window seams vs inside windows (ratio about 1 = invisible seams), for the
   streamer (default: the emitted frames' own ODE states as context; and straight-path
   re-noised context) and for the baseline without context (windows independent);
   the follower's own ground-truth jump gives the natural scale; and for the streamer with the
   opt-in per-window canonical frames (``StreamConfig(recanonicalize=True)``, ``WindowFrame``).
3. reactor MPJPE (m) of the stream against the rule follower, and of the no-context baseline.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.table import Row, parse_args, script_main, verdict  # noqa: E402
from dualflow.checkpoint import bundled_checkpoint, load_checkpoint  # noqa: E402
from dualflow.datasets.training import positions_from_normalized  # noqa: E402
from dualflow.flow import SamplingSettings, generate  # noqa: E402
from dualflow.model import Conditions  # noqa: E402
from dualflow.motion.features import encode_pair  # noqa: E402
from dualflow.streaming import ReactiveStreamer, StreamConfig, seam_report  # noqa: E402
from dualflow.synthetic import make_duet  # noqa: E402
from dualflow.text import template_text_embedding  # noqa: E402

REALTIME_MS = 1000.0 / 30.0
# Smoke run only: a 3 s clip and 5 Euler steps instead of 20 (the rows say how many).
QUICK = ["--seconds", "3", "--steps", "5"]


def stream(model, actor, cond, stats=None, **cfg) -> ReactiveStreamer:
    s = ReactiveStreamer(model, StreamConfig(**cfg), cond, stats=stats)
    for frame in actor:
        s.push(frame)
    s.flush()
    return s


def rows(quick: bool = False, argv: list[str] = ()) -> list[Row]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", default=None, help="checkpoint directory (default: the bundled one)")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--window", type=int, default=60, help="window length (frames); the training clip length")
    ap.add_argument("--hop", type=int, default=8, help="frames per window for the seam measurement")
    ap.add_argument("--rule", default="follow")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--no-ema", action="store_true", help="use the raw weights of a training checkpoint, not its EMA")
    args = parse_args(ap, argv, quick, QUICK)
    torch.set_num_threads(args.threads)

    ckpt = load_checkpoint(bundled_checkpoint() if args.checkpoint is None else args.checkpoint)
    model = ckpt.build_model(args.device, use_ema=not args.no_ema)
    stats = ckpt.stats
    pair = make_duet(args.rule, seconds=args.seconds + 1 / 30, fps=30.0, seed=args.seed)
    feats, _ = encode_pair(pair)
    norm = stats.normalize(feats).astype(np.float32)
    actor = torch.from_numpy(norm[:, 0]).to(args.device)
    truth = positions_from_normalized(norm[:, 1], stats)
    text = torch.from_numpy(template_text_embedding([pair.text], model.config.text_dim)).to(args.device)
    music = None
    if ckpt.meta.get("music") == "beats":  # trained with the synthetic beat track as music
        music = torch.from_numpy(np.asarray(pair.meta["beats"][: len(feats)], dtype=np.float32))[None].to(args.device)
    cond = Conditions(text=text, music=music)
    n = actor.shape[0]
    L = model.config.look_ahead
    print(
        f"model: {ckpt.path} ({sum(p.numel() for p in model.parameters()) / 1e6:.2f}M params), L = {L} frames, "
        f"{n} frames ({args.seconds:.0f} s at 30 fps), rule {args.rule!r}, {args.steps} Euler steps, "
        f"window {args.window}, device {args.device}, {torch.get_num_threads()} thread(s)"
    )

    # 1. timing --------------------------------------------------------------------------
    with torch.no_grad():
        first = cond.slice_frames(0, args.window)
        generate(
            model,
            args.window,
            first,
            mode="reactive",
            x_actor=actor[None, : args.window],
            sampling=SamplingSettings(steps=2),
        )  # warm-up
        tic = time.perf_counter()
        generate(
            model,
            args.window,
            first,
            mode="reactive",
            x_actor=actor[None, : args.window],
            sampling=SamplingSettings(steps=args.steps),
        )
        offline_ms = (time.perf_counter() - tic) * 1000 / args.window
    s1 = stream(model, actor, cond, stats, window=args.window, hop=1, steps=args.steps)
    si = stream(model, actor, cond, stats, window=args.window, hop=1, steps=args.steps, incremental=True)
    sh = stream(model, actor, cond, stats, window=args.window, hop=args.hop, steps=args.steps)
    print("\ncompute time per emitted frame (ms):")
    print(f"  baseline: one offline {args.window}-frame window / {args.window} frames   {offline_ms:8.2f}")
    print(
        f"  streamer hop 1  (delay L = {L} frames + compute)      {s1.timing.per_frame_s * 1000:8.2f}"
        f"   (worst window {s1.timing.max_window_s * 1000:.1f} ms)"
    )
    print(
        f"  streamer hop 1, incremental windows             {si.timing.per_frame_s * 1000:8.2f}"
        f"   (worst window {si.timing.max_window_s * 1000:.1f} ms; catch-up of the second start included)"
    )
    print(
        f"  streamer hop {args.hop:<2d} (delay up to {L + args.hop - 1} frames + compute) "
        f"{sh.timing.per_frame_s * 1000:8.2f}"
        f"   (worst window {sh.timing.max_window_s * 1000:.1f} ms)"
    )
    print(f"  target: < {REALTIME_MS:.1f} ms per frame for 30 fps real time")

    # 2. seams ---------------------------------------------------------------------------
    sn = stream(model, actor, cond, stats, window=args.window, hop=args.hop, steps=args.steps, inpaint=False)
    sg = stream(model, actor, cond, stats, window=args.window, hop=args.hop, steps=args.steps, recanonicalize=True)
    sp = stream(model, actor, cond, stats, window=args.window, hop=args.hop, steps=args.steps, context="path")
    starts = [w[0] for w in sh.timing.windows]
    pos_h = positions_from_normalized(sh.emitted, stats)
    pos_n = positions_from_normalized(sn.emitted, stats)
    pos_g = positions_from_normalized(sg.emitted, stats)
    r_h = seam_report(pos_h, starts)
    r_n = seam_report(pos_n, [w[0] for w in sn.timing.windows])
    r_g = seam_report(pos_g, [w[0] for w in sg.timing.windows])
    r_gt = seam_report(truth, starts)
    print(f"\nvelocity jump (mm/frame^2, mean over joints), windows of {args.hop} new frames:")
    print(f"  {'':40s} {'at seams':>9s} {'inside':>9s} {'ratio':>7s}")
    r_p = seam_report(positions_from_normalized(sp.emitted, stats), [w[0] for w in sp.timing.windows])
    for label, r in (
        ("ground-truth follower (scale)", r_gt),
        ("baseline: windows without context", r_n),
        ("streamer + window frames (opt-in)", r_g),
        ("streamer, straight-path context", r_p),
        ("streamer, trajectory context (default)", r_h),
    ):
        print(f"  {label:40s} {r.seam_mean * 1000:9.2f} {r.within_mean * 1000:9.2f} {r.ratio:7.2f}")
    print("  target: seam jump about the within-window jump (ratio about 1)")

    # 3. accuracy ------------------------------------------------------------------------
    def mpjpe(p):
        return float(np.linalg.norm(p - truth, axis=-1).mean())

    pos_1 = positions_from_normalized(s1.emitted, stats)
    print("\nreactor MPJPE against the rule follower (m):")
    print(f"  baseline: windows without context  {mpjpe(pos_n):.3f}")
    print(f"  streamer hop {args.hop:<2d} + window frames    {mpjpe(pos_g):.3f}")
    print(f"  streamer hop {args.hop:<2d}, straight-path ctx {mpjpe(positions_from_normalized(sp.emitted, stats)):.3f}")
    print(f"  streamer hop {args.hop:<2d}                    {mpjpe(pos_h):.3f}")
    print(f"  streamer hop 1                     {mpjpe(pos_1):.3f}")
    print(f"  streamer hop 1, incremental        {mpjpe(positions_from_normalized(si.emitted, stats)):.3f}")

    setting = f"{args.steps} steps, {torch.get_num_threads()} thread(s)"
    base_ms = f"{offline_ms:.4g} (offline window / frames)"
    rt = f"< {REALTIME_MS:.1f} (real time)"
    no_ctx = "no-context windows"
    out = []
    for label, st in (("hop 1", s1), ("hop 1, incremental windows", si), (f"hop {args.hop}", sh)):
        ms = st.timing.per_frame_s * 1000
        out.append(
            Row(
                f"streamer compute per emitted frame, {label}, {setting} (ms)",
                ms,
                base_ms,
                rt,
                verdict(ms < REALTIME_MS),
            )
        )
    out += [
        Row(
            f"seam / inside velocity-jump ratio, streamer hop {args.hop}, trajectory context (baseline {no_ctx})",
            r_h.ratio,
            r_n.ratio,
            "about 1",
        ),
        Row(
            f"seam / inside velocity-jump ratio, streamer, straight-path context (baseline {no_ctx})",
            r_p.ratio,
            r_n.ratio,
            "about 1",
        ),
        Row(
            f"seam / inside velocity-jump ratio, streamer + window frames (baseline {no_ctx})",
            r_g.ratio,
            r_n.ratio,
            "about 1",
        ),
        Row("seam / inside velocity-jump ratio, ground-truth follower (the natural scale)", r_gt.ratio),
        Row(
            f"reactor MPJPE vs rule follower, streamer hop {args.hop} (m; baseline {no_ctx})",
            mpjpe(pos_h),
            mpjpe(pos_n),
        ),
        Row(
            f"reactor MPJPE vs rule follower, streamer hop {args.hop}, straight-path context (m)",
            mpjpe(positions_from_normalized(sp.emitted, stats)),
            mpjpe(pos_n),
        ),
        Row(f"reactor MPJPE vs rule follower, streamer hop {args.hop} + window frames (m)", mpjpe(pos_g), mpjpe(pos_n)),
        Row("reactor MPJPE vs rule follower, streamer hop 1 (m)", mpjpe(pos_1), mpjpe(pos_n)),
        Row(
            "reactor MPJPE vs rule follower, streamer hop 1, incremental windows (m)",
            mpjpe(positions_from_normalized(si.emitted, stats)),
            mpjpe(pos_n),
        ),
    ]
    return out


def main(argv: list[str] | None = None) -> int:
    return script_main(rows, argv)


if __name__ == "__main__":
    sys.exit(main())
