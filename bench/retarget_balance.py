"""Balance-aware streaming retargeting: its speed and what it buys on the free-standing robot.

    python bench/retarget_balance.py [--robot op3] [--clip cmu|synthetic] [--seconds 20] [--quick]

On the clips of bench/retarget_speed.py (the CMU pair when present, else a synthetic duet),
in one run and on one core (sched_setaffinity, single-threaded BLAS), CPU time:

- streaming frames/s with balance (``StreamingConfig(balance=True)``, as the bridge runs it),
  next to plain streaming and the GMR-style per-frame mink/daqp baseline of
  bench/retarget_speed.py on the same targets; the issue's target is >= 1000 frames/s and
  >= 4x the baseline;
- the share of frames whose centre of mass lies inside the support polygon of the planted
  feet (kinematic, :func:`retarget.support.com_margins`), with and without balance;
- sim's free-standing physics check of each streamed clip (passed / first failure), with and
  without balance. The issue asks the free-standing robot not to fall.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.retarget_speed import Clock, gmr_style, load_clips  # noqa: E402
from bench.table import Row, parse_args, script_main, verdict  # noqa: E402
from retarget.robot import load_robot, resolve_paths, robot_ref  # noqa: E402
from retarget.streaming import StreamingConfig, StreamingRetargeter, trajectory_from_x  # noqa: E402
from retarget.support import com_margins  # noqa: E402
from retarget.targets import make_targets  # noqa: E402

QUICK = ["--clip", "synthetic", "--seconds", "8", "--no-baseline"]


def stream_all(stream: StreamingRetargeter, targets) -> tuple[list[np.ndarray], list[np.ndarray], float]:
    """Every clip frame by frame: configurations (T, nx), planted feet (T, 2), CPU seconds."""
    xs, planted, cpu = [], [], 0.0
    for tg in targets:
        stream.reset()
        X, P = [], []
        with Clock() as ck:
            for t in range(tg.keypoints.shape[0]):
                X.append(stream.step(tg.keypoints[t], tg.contacts[t]))
                P.append(stream.planted.copy() if stream.balance else tg.contacts[t])
        cpu += ck.cpu
        xs.append(np.stack(X))
        planted.append(np.array(P, dtype=bool))
    return xs, planted, cpu


def rows(quick: bool = False, argv: list[str] = ()) -> list[Row]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robot", default="op3")
    ap.add_argument("--clip", choices=("cmu", "synthetic"), default="cmu")
    ap.add_argument("--seconds", type=float, default=20.0, help="synthetic clip length")
    ap.add_argument("--no-baseline", action="store_true", help="skip the mink/daqp baseline")
    ap.add_argument("--no-physics", action="store_true", help="skip sim's check")
    args = parse_args(ap, argv, quick, QUICK)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

    rb = load_robot(args.robot)
    clips = load_clips(args.clip, args.seconds)
    targets = [make_targets(rb, c) for c in clips]
    n = sum(c.n_frames for c in clips)
    print(f"robot {rb.name}, clips {[c.name for c in clips]}, {n} frames at 30 fps; load {os.getloadavg()[0]:.2f}")
    with Clock() as c_build:
        plain = StreamingRetargeter(rb, 30.0)
        bal = StreamingRetargeter(rb, 30.0, StreamingConfig(balance=True))
    print(f"compile/load: {c_build.wall:.1f} s wall (balance {bal.compile_info})")
    stream_all(bal, targets[:1])  # warm caches once
    x_plain, p_plain, cpu_plain = stream_all(plain, targets)
    x_bal, p_bal, cpu_bal = stream_all(bal, targets)
    fps_plain, fps_bal = n / cpu_plain, n / cpu_bal
    fps_base = None
    if not args.no_baseline:
        xml, _ = resolve_paths(args.robot)
        with Clock() as c_base:
            for tg in targets:
                gmr_style(rb, xml, tg)
        fps_base = n / c_base.cpu
    out = [
        Row(
            "streaming with balance, frames/s (CPU, 1 core)",
            fps_bal,
            fps_base if fps_base else "",
            ">= 1000 and >= 4x baseline",
            verdict(fps_bal >= 1000 and (fps_base is None or fps_bal >= 4 * fps_base)),
        ),
        Row(
            "streaming without balance, frames/s (CPU, 1 core)",
            fps_plain,
            fps_base if fps_base else "",
            ">= 1000",
            verdict(fps_plain >= 1000),
        ),
        Row("balance cost: time per frame with / without", fps_plain / fps_bal),
    ]
    feet = [f.corners for f in rb.feet]
    for label, xs, ps in (("with", x_bal, p_bal), ("without", x_plain, p_plain)):
        inside, total = 0, 0
        for X, P in zip(xs, ps):
            ev = rb.evaluate(X)
            m = com_margins(ev["com"][:, :2], ev["sole"], feet, P)
            inside += int(np.sum(m >= 0))
            total += int(np.sum(np.isfinite(m)))
        out.append(
            Row(f"frames with the CoM over the planted feet, {label} balance (%)", 100.0 * inside / max(total, 1))
        )
    if not args.no_physics:
        from sim.check import CheckConfig, check_trajectory

        ref = robot_ref(args.robot)
        for label, xs in (("with", x_bal), ("without", x_plain)):
            verdicts, fell = [], False
            for clip, X in zip(clips, xs):
                res = check_trajectory(trajectory_from_x(rb, X, 30.0, {}), CheckConfig(mode="free"), robot=ref)
                verdicts.append(
                    f"{clip.name}: " + ("pass" if res.passed else f"{res.reason} at {res.first_failure_time:.2f} s")
                )
                fell |= any(f.reason == "fall" for f in res.failures)
            out.append(
                Row(
                    f"sim check, free-standing, {label} balance",
                    "; ".join(verdicts),
                    target="no fall" if label == "with" else "",
                    verdict=verdict(not fell) if label == "with" else "n/a",
                )
            )
    return out


def main(argv: list[str] | None = None) -> int:
    return script_main(rows, argv)


if __name__ == "__main__":
    raise SystemExit(main())
