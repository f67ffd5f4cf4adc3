"""DualFlow generation speed: a 10 s, 30 fps reactor clip with 20 Euler steps, and streaming latency.

    python bench/dualflow_generation.py                      # small preset, bundled weights, CPU
    python bench/dualflow_generation.py --preset paper --device cuda   (where a GPU is lent)
    python bench/dualflow_generation.py --quick                        (smoke run: 2 s clip, 5 steps, 1 repeat)

Figures printed, each measured in this run (median of ``--repeats``):

* offline reactive generation of a 10 s clip (300 frames) with 20 Euler steps — the
  paper's "AITS" setting (DualFlow 1.24 s, InterGen with 50 DDIM steps 1.92 s, both on an
  RTX 5090 with the paper's 20-block model: a reference, not the same hardware or model);
* baselines from the same model in the same run: 1 Euler step (the cost of one network
  call over the clip) and interactive generation (both persons) with 20 steps;
* streaming (``dualflow.streaming.ReactiveStreamer``, window 60, 20 steps): compute time per
  emitted frame with hop 1 (a frame is generated as soon as its L-frame look-ahead arrives:
  the added latency beyond L frames) and with hop 8 (windows amortised over 8 frames),
  against the frame period (33.3 ms at 30 fps) that a live stream must keep up with.

The actor is a synthetic leader (``dualflow.synthetic.make_leader``); timings do not depend
on the weights, so ``--random-weights`` gives the same figures for any preset.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.table import NA, Row, parse_args, script_main, verdict  # noqa: E402
from dualflow.flow import SamplingSettings, generate  # noqa: E402
from dualflow.model import Conditions, DualFlow, DualFlowConfig  # noqa: E402
from dualflow.motion.features import encode_person  # noqa: E402
from dualflow.streaming import ReactiveStreamer, StreamConfig  # noqa: E402
from dualflow.synthetic import make_leader  # noqa: E402
from dualflow.text import template_text_embedding  # noqa: E402

PAPER_AITS_S = {"DualFlow, 20 RF steps, RTX 5090": 1.24, "InterGen, 50 DDIM steps, RTX 5090": 1.92}
# Smoke run only: 5 Euler steps instead of 20 (the rows say how many), a 2 s clip, 1 repeat.
QUICK = ["--seconds", "2", "--repeats", "1", "--stream-frames", "4", "--steps", "5"]


def build(args) -> tuple[DualFlow, np.ndarray | None, np.ndarray | None, str]:
    """(model in eval mode, stats mean, std, description)."""
    if not args.random_weights and args.preset == "small":
        from dualflow.checkpoint import load_model

        model, ck = load_model(args.checkpoint, device=args.device)
        return model, ck.stats.mean, ck.stats.std, f"checkpoint {ck.path}"
    torch.manual_seed(0)
    model = DualFlow(DualFlowConfig.preset(args.preset)).to(args.device).eval()
    return model, None, None, f"preset {args.preset}, random weights"


def timed(fn, repeats: int, device: str) -> float:
    """Median wall time (s) of fn() over ``repeats`` runs after one warm-up run."""
    fn()
    times = []
    for _ in range(repeats):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def rows(quick: bool = False, argv: list[str] = ()) -> list[Row]:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="small", choices=("paper", "small", "tiny"))
    p.add_argument("--checkpoint", default=None, help="checkpoint dir (default: the bundled one)")
    p.add_argument("--random-weights", action="store_true")
    p.add_argument("--device", default="cpu")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--stream-frames", type=int, default=45, help="emitted frames timed per streaming setting")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0 = default)")
    args = parse_args(p, argv, quick, QUICK)
    if args.threads:
        torch.set_num_threads(args.threads)

    model, mean, std, what = build(args)
    cfg = model.config
    n = int(round(args.seconds * args.fps))
    leader = make_leader(seconds=(n + 1) / args.fps, fps=args.fps, seed=0)
    feats = encode_person(leader)  # (n, 262) raw
    if mean is not None:
        feats = (feats - mean) / std
    actor = torch.tensor(feats, dtype=torch.float32, device=args.device)[None]
    text = torch.tensor(
        template_text_embedding(
            ["The leader steps in place on the beat; the partner mirrors the leader face to face."], cfg.text_dim
        ),
        device=args.device,
    )
    music = torch.zeros(1, n, cfg.music_dim, device=args.device)
    cond = Conditions(text=text, music=music)

    print(f"DualFlow generation benchmark: {what}")
    n_params = sum(p.numel() for p in model.parameters())
    print(
        f"model: {cfg.n_blocks} blocks x width {cfg.width} ({n_params / 1e6:.2f}M parameters, "
        f"prediction={cfg.prediction}), "
        f"device {args.device}, torch {torch.__version__}, {torch.get_num_threads()} threads"
    )
    print(f"clip: {n} frames ({args.seconds:g} s at {args.fps:g} fps), look-ahead L = {cfg.look_ahead}")

    def offline(steps: int, mode: str):
        def run():
            with torch.inference_mode():
                if mode == "reactive":
                    generate(
                        model, n, cond, mode="reactive", x_actor=actor, sampling=SamplingSettings(steps=steps, seed=0)
                    )
                else:
                    generate(
                        model, n, cond, mode="interactive", batch=1, sampling=SamplingSettings(steps=steps, seed=0)
                    )

        return run

    aits = timed(offline(args.steps, "reactive"), args.repeats, args.device)
    one = timed(offline(1, "reactive"), args.repeats, args.device)
    inter = timed(offline(args.steps, "interactive"), args.repeats, args.device)
    print()
    print(f"{'offline generation of the clip':52s} {'seconds':>9s} {'x real time':>11s}")
    timings = [
        (f"reactive, {args.steps} Euler steps (AITS setting)", aits),
        ("baseline: reactive, 1 Euler step", one),
        (f"baseline: interactive (both persons), {args.steps} steps", inter),
    ]
    for name, s in timings:
        print(f"{name:52s} {s:9.3f} {args.seconds / s:11.1f}")
    for name, s in PAPER_AITS_S.items():
        print(f"{'paper: ' + name:52s} {s:9.3f} {args.seconds / s:11.1f}")

    paper = PAPER_AITS_S["DualFlow, 20 RF steps, RTX 5090"]
    out = [
        Row(
            f"reactive generation, {args.seconds:g} s clip, {args.steps} Euler steps, {args.device} (s; baseline "
            f"interactive, both persons, {args.steps} steps)",
            aits,
            inter,
            f"ref. {paper:g} (paper, RTX 5090, 20-block model)",
            NA,
        ),
        Row(f"reactive generation, {args.seconds:g} s clip, 1 Euler step (s; one network call over the clip)", one),
    ]

    print()
    period_ms = 1000.0 / args.fps
    print(
        f"{'streaming (window 60, ' + str(args.steps) + ' steps)':40s} {'ms/frame':>9s} "
        f"{'max window ms':>14s} {'delay':>14s}"
    )
    with torch.inference_mode():
        for hop in (1, 8):
            streamer = ReactiveStreamer(model, StreamConfig(window=60, hop=hop, steps=args.steps), cond)
            limit = min(n, args.stream_frames + streamer.look_ahead + 16)
            streamer.push(actor[0, :8])  # warm-up window
            streamer.timing.windows.clear()
            for i in range(8, limit):
                streamer.push(actor[0, i])
            t = streamer.timing
            print(
                f"{'hop ' + str(hop):40s} {1000 * t.per_frame_s:9.1f} {1000 * t.max_window_s:14.1f} "
                f"{streamer.delay_frames:>5d} frames + compute   ({t.frames} frames timed)"
            )
            out.append(
                Row(
                    f"streaming compute per emitted frame, hop {hop}, window 60, {args.steps} steps, "
                    f"{torch.get_num_threads()} threads (ms)",
                    1000 * t.per_frame_s,
                    "",
                    f"< {period_ms:.1f} (real time)",
                    verdict(1000 * t.per_frame_s < period_ms),
                )
            )
    print(f"{'real time needs':40s} {period_ms:9.1f}")
    return out


def main(argv: list[str] | None = None) -> int:
    return script_main(rows, argv)


if __name__ == "__main__":
    raise SystemExit(main())
