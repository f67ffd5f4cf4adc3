"""How much the streamed partner moves, and how close it stays to the rule, as the demo runs it.

    python bench/partner_motion.py [CHECKPOINT ...] [--seeds 0,1] [--seconds 8] [--window 60]
                                   [--steps 2] [--hop 1] [--sliding] [--exact-rows]
                                   [--texts none,rule] [--json out.json]
    python bench/partner_motion.py [CHECKPOINT ...] --cmu [--cmu-seeds 8] [--cmu-stream-seeds 8] [--json out.json]

A quality check, not a speed benchmark (the figures do not depend on the machine's load).
For each leader seed: the SYNTHETIC leader of ``dualflow.synthetic.make_leader_clip`` (8 s,
30 fps; the demo's default actor), the demo's click track on its beats
(``ros_free_bridge.commands.demo.click_track``), streamed frame by frame through the bridge's
``ReactorStage`` with the demo's stream settings (``SessionOptions``' defaults: window 60,
hop 1, 2 Euler steps, incremental windows, the newest actor row encoded with a predicted
next frame; change with ``--window``, ``--steps``, ``--hop``, ``--sliding`` (re-run whole
windows) and ``--exact-rows`` (wait for the next frame); the settings before the latency
work: ``--steps 5 --hop 5 --sliding --exact-rows``). Jitter: mean over t, j of
|p[t+1] - 2 p[t] + p[t-1]| (mm/frame^2), next to the rule follower's. Text: ``none`` (the
demo's default, no cue) and/or ``rule``: each rule's
template sentence of ``make_duet(rule, 8 s, seed)``, whose leader is the same clip, so its
follower is the right answer. Default checkpoint: the bundled one.

Figures per stream (world frame, Z up, metres; partner frame k pairs with actor frame k):

* speed: mean joint speed of the partner, mean over t, j of |p[t+1, j] - p[t, j]| * fps (m/s);
  smooth: the same after a 9-frame moving average (jitter removed); excursion: mean over
  joints of the RMS distance from the joint's mean position (how far the partner travels);
  each next to the rule follower's own value, the baseline of the same run;
* err: MPJPE of the partner against the rule follower (text none: against the nearest rule),
  also over the first second and after it; root and arms (elbows, wrists) alone;
  the follower's own mean pose gives the error of the best pose that does not move.

``--cmu`` (issue 28): on the real CMU actor 18_01, the plausibility figures of
``dualflow.evaluation.plausibility`` (skate, jerk, bone-length CV, facing error, MPJPE to the
real partner 19_01, distance, diversity across seeds and texts) for the real partner, a static
first pose, the mirrored actor, and each checkpoint offline and streamed, raw and cleaned
(``dualflow.body``); also the cleanup's cost per streamed frame and each row's jerk range over
seeds (8 offline, 8 streamed: one seed's partner can run off and jerk 10x another's).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout, installed or not

ARM_JOINTS = [18, 19, 20, 21]  # SMPL-22 elbows and wrists


def joint_speed(p: np.ndarray, fps: float = 30.0) -> float:
    """Mean joint speed (m/s) of positions (T, 22, 3)."""
    return float(np.linalg.norm(np.diff(p, axis=0), axis=-1).mean() * fps)


def smooth_speed(p: np.ndarray, fps: float = 30.0, k: int = 9) -> float:
    """Mean joint speed (m/s) of the k-frame moving average of (T, 22, 3) positions."""
    c = np.cumsum(np.concatenate([np.zeros((1,) + p.shape[1:]), p]), axis=0)
    return joint_speed((c[k:] - c[:-k]) / k, fps)


def excursion(p: np.ndarray) -> float:
    """Mean over joints of the RMS distance (m) from the joint's mean position; p (T, 22, 3)."""
    return float(np.sqrt(((p - p.mean(0)) ** 2).sum(-1).mean(0)).mean())


def jitter(p: np.ndarray) -> float:
    """Mean joint jerk proxy |p[t+1] - 2 p[t] + p[t-1]| (mm/frame^2) of positions (T, 22, 3)."""
    return float(np.linalg.norm(p[2:] - 2 * p[1:-1] + p[:-2], axis=-1).mean() * 1e3)


def stream_partner(
    checkpoint,
    leader: np.ndarray,
    music: str,
    text: str | None,
    window: int,
    steps: int = 2,
    hop: int = 1,
    incremental: bool = True,
    predict_next: bool = True,
    seed: int = 0,
) -> np.ndarray:
    """Partner positions (N, 22, 3) streamed by the bridge's ReactorStage (demo settings)."""
    from dualflow.streaming import StreamConfig
    from ros_free_bridge.partner.reactor import Cues, ReactorStage

    stage = ReactorStage(
        30.0,
        checkpoint,
        StreamConfig(window=window, steps=steps, hop=hop, incremental=incremental, seed=seed),
        Cues(text, music, music_frames=len(leader) + 60),
        predict_next=predict_next,
    )
    out = []
    for k, p in enumerate(leader):
        out += stage.push(p, 0.0, k)
    out += stage.flush(0.0, len(leader) - 1)
    return np.stack([f.positions for f in sorted(out, key=lambda f: f.index)])


def _mpjpe(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b, axis=-1).mean())


def evaluate(checkpoint, seed: int, seconds: float, texts: list[str], window: int, tmp: Path, **stream) -> list[dict]:
    from dualflow.synthetic import RULES, make_duet, make_leader_clip
    from ros_free_bridge.commands.demo import click_track

    clip = make_leader_clip(seconds, 30.0, seed)
    leader = clip.body.positions
    music = str(click_track(clip.beat_times, seconds, tmp / f"click_{seed}.wav"))
    followers = {r: make_duet(r, seconds, 30.0, seed).reactor.positions for r in RULES}
    prompts = {r: make_duet(r, seconds, 30.0, seed).text for r in RULES}
    cases = ([("none", None, None)] if "none" in texts else []) + (
        [("rule", r, prompts[r]) for r in RULES] if "rule" in texts else []
    )
    rows = []
    for mode, rule, text in cases:
        pos = stream_partner(checkpoint, leader, music, text, window, **stream)
        n = min(len(pos), len(leader))
        errs = {r: _mpjpe(pos[:n], f[:n]) for r, f in followers.items()}
        target = rule or min(errs, key=errs.get)
        truth = followers[target][:n]
        rows.append(
            dict(
                checkpoint=str(checkpoint or "bundled"),
                seed=seed,
                text=mode,
                rule=target,
                speed=joint_speed(pos[:n]),
                rule_speed=joint_speed(truth),
                smooth=smooth_speed(pos[:n]),
                rule_smooth=smooth_speed(truth),
                excursion=excursion(pos[:n]),
                rule_excursion=excursion(truth),
                jitter=jitter(pos[:n]),
                rule_jitter=jitter(truth),
                err=errs[target],
                err_first_s=_mpjpe(pos[:30], truth[:30]),
                err_after=_mpjpe(pos[30:n], truth[30:]),
                root_err=_mpjpe(pos[:n, 0], truth[:, 0]),
                arm_err=_mpjpe(pos[:n, ARM_JOINTS], truth[:, ARM_JOINTS]),
                still_err=_mpjpe(np.broadcast_to(truth.mean(0), truth.shape), truth),
            )
        )
    return rows


CMU_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap" / "cmu"
CUE_TEXTS = (
    "the partner mirrors the leader face to face.",
    "the partner keeps a hand-hold distance facing the leader and moves with them.",
    "the partner circles around the leader, copying the arm waves.",
    "the partner walks up to the leader and holds a hand out.",
)


def _mirror_baseline(actor: np.ndarray, real: np.ndarray) -> np.ndarray:
    """The actor reflected in the vertical plane halfway between the two pelvises at frame 0."""
    from dualflow.synthetic import _reflect

    gap = real[0, 0, :2] - actor[0, 0, :2]
    normal = gap / np.linalg.norm(gap)
    mid = actor[0, 0, :2] + 0.5 * gap
    n = len(actor)
    return _reflect(actor, np.broadcast_to(mid, (n, 2)), np.broadcast_to(normal, (n, 2)))


def cmu_table(checkpoints: list, seeds: int = 8, stream_seeds: int = 8, steps: int = 20) -> list[dict]:
    """The issue-28 table on the real CMU actor 18_01 against its real partner 19_01 (30 fps):
    baselines (real, static first pose, mirrored actor) and, per checkpoint, offline generation
    (``seeds`` seeds, no text; then the four CUE_TEXTS at seed 0) and the bridge's streamer
    (demo settings, ``stream_seeds`` seeds), each raw (``clean=False``) and cleaned
    (``dualflow.body``). Diversity: mean pairwise MPJPE across seeds / across texts. Offline
    and streamed use as many seeds by default: the jerk differs up to 10x between seeds (a
    partner that runs off in the clip's last second), so two seeds are not a sample."""
    import time

    from dualflow.duet_generator import DuetGenerator
    from dualflow.evaluation.plausibility import diversity, plausibility
    from dualflow.motion.io.formats import load_pair
    from dualflow.streaming import StreamConfig
    from ros_free_bridge.partner.reactor import ReactorStage
    from ros_free_bridge.session import SessionOptions

    pair = load_pair(CMU_DIR / "18_01.bvh", CMU_DIR / "19_01.bvh", fps=30.0)
    actor, real = pair.actor.positions, pair.reactor.positions
    rows = []

    def add(name, clips, **extra):
        figs = [plausibility(c, actor, real) for c in clips]
        row = {"partner": name, **{k: float(np.mean([f[k] for f in figs])) for k in figs[0]}, **extra}
        if len(clips) > 1:
            row["jerk_seeds"] = [float(f["jerk"]) for f in figs]
        if len(clips) > 1:
            row.setdefault("diversity_seeds", diversity(clips))
        rows.append(row)
        return row

    add("real 19_01", [real])
    add("static first pose", [np.broadcast_to(real[0], real.shape).copy()])
    add("mirrored actor", [_mirror_baseline(actor, real)])
    d = SessionOptions()
    for ck in checkpoints:
        label = Path(ck).name if ck else "bundled"
        gen = DuetGenerator.from_checkpoint(ck)
        raw_runs = {}
        for clean in (False, True):
            tag = "clean" if clean else "raw"
            gen.clean = clean
            seeded = [gen.generate(actor=pair.actor, seed=s, steps=steps)[0].reactor.positions for s in range(seeds)]
            texted = [
                gen.generate(actor=pair.actor, text=t, seed=0, steps=steps)[0].reactor.positions for t in CUE_TEXTS
            ]
            add(f"{label} offline {seeds} seeds, no text, {tag}", seeded, diversity_texts=diversity(texted))
            if not clean:
                raw_runs["offline"] = seeded
            streamed, per_frame = [], []
            for s in range(stream_seeds):
                cfg = StreamConfig(window=d.window, steps=d.steps, hop=d.hop, incremental=True, seed=s)
                stage = ReactorStage(30.0, ck, cfg, clean=clean)
                out, _t_clean = [], 0.0
                for k, p in enumerate(actor):
                    out += stage.push(p, 0.0, k)
                out += stage.flush(0.0, len(actor) - 1)
                streamed.append(np.stack([f.positions for f in sorted(out, key=lambda f: f.index)]))
                if clean:  # the cleaner's own cost per frame, replayed on this stream's raw frames
                    from dualflow.body import BodyCleaner

                    raw = ReactorStage(30.0, ck, cfg, clean=False)
                    frames = []
                    for k, p in enumerate(actor):
                        frames += raw.push(p, 0.0, k)
                    frames += raw.flush(0.0, len(actor) - 1)
                    cleaner = BodyCleaner(30.0)
                    t0 = time.perf_counter()
                    for f in frames:
                        cleaner.step(f.positions)
                    per_frame.append((time.perf_counter() - t0) / len(frames))
            extra = {"clean_ms_per_frame": 1e3 * float(np.mean(per_frame))} if per_frame else {}
            add(f"{label} streaming (demo settings), {tag}", streamed, **extra)
            if not clean:
                raw_runs["streaming (demo settings)"] = streamed
        # the same raw clips cleaned as before the travel limit (CleanConfig.max_speed / max_accel
        # off): the cleaner only reads the frames it is given, so this is the old row, same run
        from dualflow.body import CleanConfig, clean_positions

        before = CleanConfig(max_speed=0.0, max_accel=0.0)
        for mode, clips in raw_runs.items():
            add(
                f"{label} {mode}, clean without the travel limit",
                [clean_positions(c, 30.0, config=before)[0] for c in clips],
            )
    return rows


def print_cmu_table(rows: list[dict]) -> None:
    print(
        "| partner | skate | jerk m/s^3 | bone-length CV | facing error | MPJPE to real (m) | distance (m) | "
        "in 0.5-1.5 m | diversity seeds (m) | diversity texts (m) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:

        def div(k, r=r):
            return f"{r[k]:.3f}" if k in r else "-"

        print(
            f"| {r['partner']} | {r['skate']:.2f} | {r['jerk']:.0f} | {r['bone_cv']:.4f} | {r['facing_deg']:.0f}° | "
            f"{r['mpjpe_real']:.2f} | {r['dist_mean']:.2f} | {100 * r['dist_in_range']:.0f} % | "
            f"{div('diversity_seeds')} | {div('diversity_texts')} |"
            + (f" cleanup {r['clean_ms_per_frame']:.2f} ms/frame" if "clean_ms_per_frame" in r else "")
            + (
                f" jerk per seed {min(r['jerk_seeds']):.0f}-{max(r['jerk_seeds']):.0f}"
                f" (median {np.median(r['jerk_seeds']):.0f})"
                if "jerk_seeds" in r
                else ""
            )
        )


def main(argv: list[str] | None = None) -> int:
    import tempfile

    import torch

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoints", nargs="*", help="checkpoint directories (default: the bundled one)")
    ap.add_argument("--seeds", default="0", help="leader seeds, comma separated (default 0, the demo's)")
    ap.add_argument("--seconds", type=float, default=8.0, help="leader length (default 8 s, the demo's)")
    from ros_free_bridge.session import SessionOptions

    d = SessionOptions()
    ap.add_argument(
        "--window", type=int, default=d.window, help=f"frames per streamed window (default {d.window}, the demo's)"
    )
    ap.add_argument("--steps", type=int, default=d.steps, help=f"Euler steps per window (default {d.steps})")
    ap.add_argument("--hop", type=int, default=d.hop, help=f"frames per window (default {d.hop})")
    ap.add_argument("--sliding", action="store_true", help="re-run whole windows (not incremental)")
    ap.add_argument("--exact-rows", action="store_true", help="the newest actor row waits for the next frame")
    ap.add_argument("--texts", default="none,rule", help="none (no cue), rule (each rule's sentence), or both")
    ap.add_argument("--json", help="also write every row to this json file")
    ap.add_argument(
        "--cmu",
        action="store_true",
        help="instead: the plausibility table on the real CMU actor 18_01 vs its partner 19_01 "
        "(../shared/data/mocap/cmu), baselines and each checkpoint raw / cleaned",
    )
    ap.add_argument("--cmu-seeds", type=int, default=8, help="offline seeds for --cmu (default 8)")
    ap.add_argument("--cmu-stream-seeds", type=int, default=8, help="streamed seeds for --cmu (default 8)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if args.cmu:
        if not (CMU_DIR / "18_01.bvh").is_file():
            print(f"error: {CMU_DIR}/18_01.bvh not found; --cmu needs the CMU pair in ../shared/data", file=sys.stderr)
            return 2
        rows = cmu_table(args.checkpoints or [None], seeds=args.cmu_seeds, stream_seeds=args.cmu_stream_seeds)
        print_cmu_table(rows)
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
        return 0
    texts = [t for t in args.texts.split(",") if t]
    if not texts or set(texts) - {"none", "rule"}:
        print(f"error: --texts must list none and/or rule, got {args.texts!r}", file=sys.stderr)
        return 2
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in (int(s) for s in args.seeds.split(",")):
            for ck in args.checkpoints or [None]:
                for r in evaluate(
                    ck,
                    seed,
                    args.seconds,
                    texts,
                    args.window,
                    Path(tmp),
                    steps=args.steps,
                    hop=args.hop,
                    incremental=not args.sliding,
                    predict_next=not args.exact_rows,
                ):
                    rows.append(r)
                    print(
                        f"{Path(r['checkpoint']).name} seed {seed} text {r['text']:4s} rule {r['rule']:9s} "
                        f"speed {r['speed']:.3f} (rule {r['rule_speed']:.3f}) smooth {r['smooth']:.3f} "
                        f"({r['rule_smooth']:.3f}) excursion {r['excursion']:.3f} ({r['rule_excursion']:.3f}) | "
                        f"err {r['err']:.3f} [first s {r['err_first_s']:.3f}, after {r['err_after']:.3f}] "
                        f"root {r['root_err']:.3f} arms {r['arm_err']:.3f} (still at the rule's mean pose "
                        f"{r['still_err']:.3f})",
                        flush=True,
                    )
    print("\nmean over seeds and rules (partner | rule follower):")
    keys = ("speed", "smooth", "excursion", "err", "err_first_s", "err_after", "still_err", "jitter")
    for ck in args.checkpoints or [None]:
        for mode in texts:
            sel = [r for r in rows if r["checkpoint"] == str(ck or "bundled") and r["text"] == mode]
            m = {
                k: float(np.mean([r[k] for r in sel]))
                for k in keys + ("rule_speed", "rule_smooth", "rule_excursion", "rule_jitter")
            }
            print(
                f"  {ck or 'bundled'} text {mode}: speed {m['speed']:.3f} | {m['rule_speed']:.3f} m/s, smooth "
                f"{m['smooth']:.3f} | {m['rule_smooth']:.3f} m/s, excursion {m['excursion']:.3f} | "
                f"{m['rule_excursion']:.3f} m; err {m['err']:.3f} m (first s {m['err_first_s']:.3f}, after "
                f"{m['err_after']:.3f}; still {m['still_err']:.3f}); jitter {m['jitter']:.1f} | "
                f"{m['rule_jitter']:.1f} mm/frame^2"
            )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
