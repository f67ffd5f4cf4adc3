"""retarget-check throughput: the local engine against Ray, on the same clips, on this machine.

Prints clips per minute for
  - the local engine (forked worker processes) with 1 and 2 workers;
  - the Ray engine (one Ray task per clip, a local Ray instance) with 1 and 2 workers, each
    next to the local engine with as many workers as its baseline;
Ray's overhead per clip (its wall time minus the local engine's, over the clips, same workers),
the start and shutdown of a local Ray instance (paid once per batch), the retargeting-and-check
work per frame, and from these an estimate for a 10,000-clip dataset.

The clips: the CMU two-person capture in ../shared/data (18_01 and 19_01, 2.5 s each) made into
8 clips: each person whole, mirrored left-right, and the first and last 1.5 s of the mirrored
take (484 frames at 30 fps in all); where that data is absent, 8 synthetic leader clips of the
same lengths. Each clip is retargeted offline, checked in MuJoCo, no video (``--no-video``:
the figure people scale a dataset with; ``--video`` adds one row with the videos). The C code
of the robot's derivatives is compiled (and cached) before timing. Every engine's rows are
compared: the table is the same whichever engine made it.

Times are wall clock (the engines differ in processes, not in the work of a clip), the best of
``--repeats`` runs. A local Ray instance runs its own processes (GCS, raylet) beside the workers:
on a 2-core machine they compete with the 2 workers, which a cluster node with more cores hides.

Usage: python bench/retarget_check_engines.py [--robot op3] [--video] [--repeats 1] [--quick]
Needs Ray for its Ray rows (``pip install -e ".[cluster]"``); without it those rows say so.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.table import NA, Row, cpu_counters, parse_args, script_main, steal_percent  # noqa: E402

CMU = Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap" / "cmu"
QUICK = ["--clips", "2"]
DATASET_CLIPS = 10_000


def make_clips(folder: Path, n: int) -> tuple[list[Path], str]:
    """``n`` (up to 8) motion files in ``folder`` and what they are."""
    import numpy as np

    from dualflow.motion import Motion
    from dualflow.motion.io import load_motion, save_motion
    from dualflow.motion.skeleton import MIRROR_INDEX

    def mirrored(m: Motion) -> Motion:  # reflect across the x-z plane: left and right swap
        p = m.positions[:, list(MIRROR_INDEX)].copy()
        p[..., 1] *= -1
        return Motion(p, m.fps)

    if (CMU / "18_01.bvh").is_file() and (CMU / "19_01.bvh").is_file():
        people = [load_motion(CMU / f, fps=30.0) for f in ("18_01.bvh", "19_01.bvh")]
        what = "CMU 18_01/19_01 whole, mirrored, first and last 1.5 s mirrored"
    else:
        from dualflow.synthetic import make_leader

        people = [make_leader(76 / 30.0, 30.0, seed) for seed in (1, 2)]
        what = "synthetic leaders (../shared/data absent)"
    clips = []
    for k, m in enumerate(people):
        mm = mirrored(m)
        clips += [
            (f"p{k}_whole", m),
            (f"p{k}_mirror", mm),
            (f"p{k}_mirror_head", mm.slice(0, 45)),
            (f"p{k}_mirror_tail", mm.slice(mm.n_frames - 45)),
        ]
    paths = []
    for name, m in clips[:n]:
        paths.append(folder / f"{name}.npz")
        save_motion(Motion(np.asarray(m.positions), m.fps), paths[-1])
    return paths, what


def timed_batch(files, cfg, engine: str, workers: int):
    """(wall seconds, rows) of one batch, started afresh (its output folder emptied, no robot
    cached in this process: forked workers load it as Ray's workers do)."""
    from ros_free_bridge.batch import clip_check
    from ros_free_bridge.batch.run import run_batch

    clip_check._ROBOT.clear()
    t0 = time.perf_counter()
    rows = run_batch(files, cfg, jobs=workers, progress=False, engine=engine)
    return time.perf_counter() - t0, rows


RAY_CHILD = """
import json, sys, time
from pathlib import Path
import ray
from ros_free_bridge.batch.config import BatchConfig
from ros_free_bridge.batch.ray_engine import start
from ros_free_bridge.batch.run import run_batch
files, out, robot, workers = [Path(f) for f in json.loads(sys.argv[1])], \
Path(sys.argv[2]), sys.argv[3], int(sys.argv[4])
t0 = time.perf_counter(); start(jobs=workers); up = time.perf_counter() - t0
t0 = time.perf_counter()
rows = run_batch(files, BatchConfig(robot=robot, out=out, video=False), jobs=workers, progress=False, engine="ray")
took = time.perf_counter() - t0
t0 = time.perf_counter(); ray.shutdown(); up += time.perf_counter() - t0
print(json.dumps({"wall": took, "start_stop": up, "rows": [r.row() for r in rows]}))
"""


def ray_batch(files, cfg, workers: int):
    """(wall seconds of the batch alone, Ray start + shutdown seconds, rows) of one Ray batch, run
    in a child process with its own local Ray instance: this process never loads Ray, whose
    gRPC threads do not survive the forks of the local engine's pool."""
    import json

    from ros_free_bridge.batch.results import ClipResult

    done = subprocess.run(
        [
            sys.executable,
            "-c",
            RAY_CHILD,
            json.dumps([str(f) for f in files]),
            str(cfg.out),
            str(cfg.robot),
            str(workers),
        ],
        capture_output=True,
        text=True,
        cwd=str(Path(__file__).resolve().parents[1]),
        check=False,
    )
    if done.returncode != 0:
        raise RuntimeError(f"the Ray batch failed: {done.stderr[-2000:]}")
    got = json.loads(done.stdout.strip().splitlines()[-1])
    return got["wall"], got["start_stop"], [ClipResult.from_row(r) for r in got["rows"]]


def comparable(rows) -> list[dict]:
    return [{k: v for k, v in r.row().items() if k != "seconds"} for r in rows]


def rows(quick: bool = False, argv: list[str] = ()) -> list[Row]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--robot", default="op3")
    ap.add_argument("--clips", type=int, default=8, help="how many of the 8 clips (default 8)")
    ap.add_argument("--video", action="store_true", help="also time the local engine with videos")
    ap.add_argument(
        "--repeats", type=int, default=1, help="best of this many runs of each engine, interleaved (default 1)"
    )
    args = parse_args(ap, argv, quick, QUICK)
    os.environ.setdefault("MUJOCO_GL", "egl")
    from ros_free_bridge.batch.config import BatchConfig

    tmp = Path(tempfile.mkdtemp(prefix="bench_rc_"))
    src = tmp / "clips"
    src.mkdir()
    files, what = make_clips(src, max(1, min(8, args.clips)))
    from dualflow.motion.io import load_motion

    frames = sum(load_motion(f).n_frames for f in files)
    n = len(files)
    cfg = lambda name, video=False: BatchConfig(robot=args.robot, out=tmp / name, video=video)  # noqa: E731
    # compile (or find cached) the robot's C code before any timing, in another process so that
    # the local engine's forked workers inherit nothing that Ray's workers must load themselves
    subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys; from pathlib import Path; "
            "from ros_free_bridge.batch.config import BatchConfig; "
            "from ros_free_bridge.batch.clip_check import check_clip; "
            "check_clip(Path(sys.argv[1]), BatchConfig(robot=sys.argv[2], out=Path(sys.argv[3]), video=False))",
            str(files[0]),
            args.robot,
            str(tmp / "warmup"),
        ],
        check=True,
        cwd=str(Path(__file__).resolve().parents[1]),
    )
    print(
        f"{n} clips ({what}), {frames} frames at 30 fps, robot {args.robot}; "
        f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}"
    )

    import importlib.util

    has_ray = importlib.util.find_spec("ray") is not None
    configs = [("local", 1), ("local", 2)] + ([("ray", 1), ("ray", 2)] if has_ray else [])
    configs += [("video", 2)] if args.video else []
    steal0 = cpu_counters()
    wall, results, ray_up = {}, {}, {}
    for rep in range(max(1, args.repeats)):  # interleaved, so that a burst of other load hits one run, not one engine
        for engine, w in configs:
            if engine == "ray":  # in a child: a fresh Ray instance, and none in this process (see ray_batch)
                took, up, results[(engine, w)] = ray_batch(files, cfg(f"ray{w}"), w)
                ray_up[w] = min(ray_up.get(w, float("inf")), up)
            else:
                took, results[(engine, w)] = timed_batch(
                    files, cfg(f"{engine}{w}", video=engine == "video"), "local", w
                )
            wall[(engine, w)] = min(wall.get((engine, w), float("inf")), took)
            print(
                f"  run {rep + 1}: {engine} engine{' (local, with videos)' if engine == 'video' else ''}, "
                f"{w} worker(s): {took:.1f} s"
            )
    ray_start_stop = min(ray_up.values()) if ray_up else float("nan")
    steal = steal_percent(steal0, cpu_counters())
    same = all(comparable(r) == comparable(results[("local", 1)]) for r in results.values())
    verdicts = ", ".join(f"{r.clip}: {r.status}" for r in results[("local", 1)])
    print(f"  rows identical across engines: {same}; {verdicts}; {steal:.1f} % of CPU time stolen")

    per_min = {k: 60.0 * n / v for k, v in wall.items()}
    label = f"{n} clips, {frames} frames, {args.robot}, no video"
    out = [
        Row(f"clips per minute, local engine, 1 worker ({label})", per_min[("local", 1)]),
        Row("clips per minute, local engine, 2 workers", per_min[("local", 2)], per_min[("local", 1)]),
    ]
    for w in (1, 2):
        if ("ray", w) in wall:
            out.append(
                Row(
                    f"clips per minute, Ray, {w} worker{'s' if w > 1 else ''} (baseline: local, same workers)",
                    per_min[("ray", w)],
                    per_min[("local", w)],
                )
            )
            out.append(
                Row(
                    f"Ray overhead per clip, {w} worker{'s' if w > 1 else ''} (s, wall, vs local)",
                    (wall[("ray", w)] - wall[("local", w)]) / n,
                )
            )
        else:
            out.append(Row(f"clips per minute, Ray, {w} worker(s)", "Ray not installed", per_min[("local", w)]))
    if has_ray:
        out.append(Row("local Ray instance start + shutdown, once per batch (s)", ray_start_stop))
    if ("video", 2) in wall:
        out.append(
            Row("clips per minute, local engine, 2 workers, with videos", per_min[("video", 2)], per_min[("local", 2)])
        )
    # the dataset estimate from the steady state of one worker (the robot loaded: the median clip),
    # which other programs on the machine disturb less than the 2-worker walls, plus Ray's overhead
    import statistics

    per_clip = statistics.median(r.seconds for r in results[("local", 1)])
    overhead = max(0.0, (wall[("ray", 1)] - wall[("local", 1)]) / n) if ("ray", 1) in wall else 0.0
    core_hours = DATASET_CLIPS * (per_clip + overhead) / 3600.0
    seconds = frames / n / 30.0
    out.append(Row("retarget + check, one worker, whole batch (frames per second)", frames / wall[("local", 1)]))
    out.append(Row(f"compute per clip, median, one worker ({seconds:.1f} s clips, robot loaded; s)", per_clip))
    out.append(Row(f"{DATASET_CLIPS:,} such clips with Ray (core-hours: divide by the cluster's cores)", core_hours))
    out.append(Row("rows identical across engines", "yes" if same else "NO", "", "", NA))
    print(
        f"  estimate: {DATASET_CLIPS:,} clips of {seconds:.1f} s = {DATASET_CLIPS:,} x ({per_clip:.2f} s per clip + "
        f"{overhead:.2f} s Ray overhead) = {core_hours:.1f} core-hours; on N nodes of C cores about "
        f"{core_hours:.1f} h / (N C) + {ray_start_stop:.0f} s to start Ray "
        f"({per_clip / seconds / 30:.3f} core-seconds per frame)"
    )
    return out


def main(argv: list[str] | None = None) -> int:
    return script_main(rows, argv)


if __name__ == "__main__":
    raise SystemExit(main())
