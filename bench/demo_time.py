"""Wall time of the main job, ``dualflow-bridge demo`` on the embedded defaults (issue 9, item 1).

Runs the README's first command after installation, ``python -m ros_free_bridge demo``, in a
fresh process into a temporary folder, exactly as a newcomer would (the bundled checkpoint,
the 8 s synthetic leader and its click track, the emulated Dynamixel bus, the video), and
reports its wall time next to the issue's target of under 3 minutes on a 2-core CPU.

Baseline, same run: the same command with ``--no-bus --no-video``, the pipeline alone
(generator, retargeting, control loop, virtual robot, physics check), to show what the byte-level
bus emulation and the video add. The share of CPU time the host stole during each run is
printed beside it (on a shared virtual machine, steal slows every figure here).

Run: python bench/demo_time.py [--seconds 8] [--quick]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.table import NA, Row, cpu_counters, parse_args, script_main, steal_percent, verdict  # noqa: E402

TARGET_S = 180.0
QUICK = ["--seconds", "3"]


def time_demo(extra: list[str], seconds: float) -> tuple[float, float, str]:
    """(wall s, host steal %, the physics verdict line) of one demo run in a fresh process."""
    with tempfile.TemporaryDirectory(prefix="bench_demo_") as tmp:
        cmd = [sys.executable, "-m", "ros_free_bridge", "demo", "--seconds", f"{seconds:g}", "-o", tmp, *extra]
        cpu0, t0 = cpu_counters(), time.monotonic()
        done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        wall = time.monotonic() - t0
        steal = steal_percent(cpu0, cpu_counters())
        if done.returncode not in (0, 1):
            raise RuntimeError(f"{' '.join(cmd)} exited with {done.returncode}:\n{done.stderr[-2000:]}")
        verdict_line = next((ln for ln in done.stdout.splitlines() if ln.startswith("physics check:")), "?")
        if not (Path(tmp) / "telemetry.dftl").stat().st_size or (
            "--no-video" not in extra and not (Path(tmp) / "demo.mp4").stat().st_size
        ):
            raise RuntimeError(f"{' '.join(cmd)}: an output is missing or empty")
    return wall, steal, verdict_line


def rows(quick: bool = False, argv: list[str] = ()) -> list[Row]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=8.0, help="length of the synthetic leader (demo default 8)")
    args = parse_args(ap, argv, quick, QUICK)
    full, full_steal, full_check = time_demo([], args.seconds)
    bare, bare_steal, _ = time_demo(["--no-bus", "--no-video"], args.seconds)
    print(
        f"demo, {args.seconds:g} s leader: {full:.1f} s wall ({full_check}; host steal {full_steal:.1f} %); "
        f"without bus and video: {bare:.1f} s (steal {bare_steal:.1f} %); {os.cpu_count()} CPUs"
    )
    default = args.seconds == 8.0
    return [
        Row(
            f"demo, embedded defaults, {args.seconds:g} s leader, bus + video (s wall)",
            round(full, 1),
            round(bare, 1),
            f"< {TARGET_S:g}" if default else "",
            verdict(full < TARGET_S) if default else NA,
        ),
    ]


def main(argv: list[str] | None = None) -> int:
    return script_main(rows, argv)


if __name__ == "__main__":
    raise SystemExit(main())
