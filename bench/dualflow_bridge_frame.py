"""Per-frame cost of the bridge's generator stage on the CPU: the demo's stream, with and without
the body cleanup (issue 28), and optionally the same stage from another copy of the code.

    python bench/dualflow_bridge_frame.py [--seconds 8] [--repeats 3] [--baseline-src DIR]

For each setting, the bridge's ``ReactorStage`` (bundled checkpoint, the demo's stream settings:
window 60, hop 1, 2 Euler steps, incremental windows, predicted newest row) is fed the demo's
synthetic leader frame by frame; figures are the median over ``--repeats`` of the mean time of
a ``push`` call per emitted partner frame (wall and this process's CPU time, one torch thread),
and the cleanup's own time per frame (``BodyCleaner.step``). ``--baseline-src DIR``: the stage
of another copy of the code (e.g. ``git archive HEAD dualflow ros_free_bridge | tar -x -C DIR``),
run in a subprocess, printed as the baseline of the same run.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path


def measure(seconds: float, repeats: int, clean: bool | None) -> dict:
    import torch

    from dualflow.streaming import StreamConfig
    from dualflow.synthetic import make_leader
    from ros_free_bridge.partner.reactor import ReactorStage
    from ros_free_bridge.session import SessionOptions

    torch.set_num_threads(1)
    leader = make_leader(seconds, 30.0, 0).positions
    d = SessionOptions()
    walls, cpus, cleans = [], [], []
    for _ in range(repeats):
        cfg = StreamConfig(window=d.window, steps=d.steps, hop=d.hop, incremental=True)
        stage = ReactorStage(30.0, None, cfg) if clean is None else ReactorStage(30.0, None, cfg, clean=clean)
        cleaner = getattr(stage, "cleaner", None)
        t_clean = [0.0]
        if cleaner is not None:
            step = cleaner.step

            def timed(p, contacts=None, _step=step, _acc=t_clean):
                t0 = time.perf_counter()
                out = _step(p, contacts)
                _acc[0] += time.perf_counter() - t0
                return out

            cleaner.step = timed
        n, t0, c0 = 0, time.perf_counter(), time.process_time()
        for k, p in enumerate(leader):
            n += len(stage.push(p, 0.0, k))
        walls.append((time.perf_counter() - t0) / max(n, 1))
        cpus.append((time.process_time() - c0) / max(n, 1))
        cleans.append(t_clean[0] / max(n, 1))
    return {
        "ms_per_frame_wall": 1e3 * statistics.median(walls),
        "ms_per_frame_cpu": 1e3 * statistics.median(cpus),
        "cleanup_ms_per_frame": 1e3 * statistics.median(cleans),
        "frames": n,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--baseline-src", help="a directory holding another copy of dualflow/ and ros_free_bridge/")
    ap.add_argument("--json-only", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.json_only:  # run from inside the baseline copy (its packages first on the path)
        sys.path.insert(0, args.baseline_src)
        print(json.dumps(measure(args.seconds, args.repeats, None)))
        return 0
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    rows = {
        "this tree, cleanup on (default)": measure(args.seconds, args.repeats, True),
        "this tree, cleanup off": measure(args.seconds, args.repeats, False),
    }
    if args.baseline_src:
        proc = subprocess.run(
            [
                sys.executable,
                __file__,
                "--seconds",
                str(args.seconds),
                "--repeats",
                str(args.repeats),
                "--baseline-src",
                args.baseline_src,
                "--json-only",
            ],
            capture_output=True,
            text=True,
            check=True,
            cwd=args.baseline_src,
        )
        rows["baseline copy"] = json.loads(proc.stdout.strip().splitlines()[-1])
    print(
        f"bridge generator stage, demo stream settings, {args.seconds:g} s synthetic leader, 1 thread, "
        f"median of {args.repeats}"
    )
    print(f"{'setting':34s} {'ms/frame wall':>14s} {'ms/frame CPU':>13s} {'cleanup ms/frame':>17s}")
    for name, r in rows.items():
        print(
            f"{name:34s} {r['ms_per_frame_wall']:14.2f} {r['ms_per_frame_cpu']:13.2f} {r['cleanup_ms_per_frame']:17.3f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
