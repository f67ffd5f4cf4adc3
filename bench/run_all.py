"""Run every benchmark and print one table: figure, our value, baseline (same run), target, verdict.

    python bench/run_all.py [--quick] [--only NAME ...] [--out results.md|results.csv]
    python -m bench [same options]

The benchmarks, each defined by an issue (its targets are the issue's):

    #2 motion_io            BVH forward kinematics and stick-figure preview speed
    #3 sim_speed            MuJoCo check speed (x real time) and offscreen rendering
    #4 retarget_speed       CasADi retargeting speed and quality vs a GMR-style mink/daqp IK
    #4 retarget_balance     balance-aware streaming retargeting: speed, CoM over the feet, sim check
    #5 servo_bus            Dynamixel sync write + fast sync read cycles, sustained 250 Hz
    #6 dualflow_generation  10 s reactive generation (the paper's AITS setting), streaming
    #6 bench_streaming      streaming compute per frame, seam continuity, reactor error
    #7 retrieval_speed      one retrieval query against 10,000 entries
    #8 bridge_loop          control-loop jitter, skipped ticks, loop CPU, end-to-end latency
    #9 demo_time            wall time of `dualflow-bridge demo` on the embedded defaults
    #26 retarget_check_engines  retarget-check clips per minute: local engine vs Ray (1 and 2 workers)

(``bench/partner_motion.py`` is not among them: it is a quality check of the bundled model's
streamed partner, with no target from an issue; run it on its own.)

Each runs in its own fresh Python process (``--child``), so one benchmark's state (threads,
torch settings, CPU affinity, a GL context) cannot change another's figures, and a crash or a
timeout becomes a row saying so instead of ending the run. The child calls the module's
``rows(quick=...)`` and hands the rows back as JSON in a temporary file; its own output is shown
with ``-v``, and its last lines are printed when it fails.

``--quick`` shortens every benchmark (fewer repeats, shorter clips) for a smoke run: its figures
are noisier and some targets are defined for the full length, so judge targets on a full run.
On a shared, loaded machine every timing is pessimistic; the baselines run under the same load.

Exit code: 0 when every benchmark ran to the end (whatever the verdicts), 1 when one crashed or
timed out, 2 for bad options.
"""

from __future__ import annotations

import argparse
import collections
import datetime
import importlib
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.table import NOT_MET, Row, print_table, write_table  # noqa: E402

#: (module, issue) in the order they run.
BENCHES: tuple[tuple[str, int], ...] = (
    ("bench.motion_io", 2),
    ("bench.sim_speed", 3),
    ("bench.retarget_speed", 4),
    ("bench.retarget_balance", 4),
    ("bench.servo_bus", 5),
    ("bench.dualflow_generation", 6),
    ("bench.bench_streaming", 6),
    ("bench.retrieval_speed", 7),
    ("bench.bridge_loop", 8),
    ("bench.demo_time", 9),
    ("bench.retarget_check_engines", 26),
)

DEFAULT_TIMEOUT_S = 1800.0
QUICK_TIMEOUT_S = 600.0
TAIL_LINES = 30
DID_NOT_FINISH = "benchmark did not finish"
FAILURE_CHARS = 100


def short_name(module: str) -> str:
    return module.rsplit(".", 1)[-1]


def _child(module: str, quick: bool, out: Path) -> int:
    """Child process: run one benchmark module's rows() and write them to ``out`` as JSON."""
    rows = importlib.import_module(module).rows(quick=quick)
    out.write_text(json.dumps([r.to_dict() for r in rows]), encoding="utf-8")
    return 0


def _failure_row(name: str, what: str, tail: Sequence[str]) -> Row:
    """The row standing for a benchmark that crashed or timed out: what happened and its last
    output line (shortened; the full tail goes to stderr)."""
    last = next((line.strip() for line in reversed(tail) if line.strip()), "")
    if len(last) > FAILURE_CHARS:
        last = last[: FAILURE_CHARS - 3] + "..."
    return Row(
        figure=DID_NOT_FINISH,
        value=f"{what}: {last}" if last else what,
        baseline="",
        target="runs to the end",
        verdict=NOT_MET,
        bench=name,
    )


def is_failure(row: Row) -> bool:
    """Whether ``row`` is the one row standing for a benchmark that crashed or timed out."""
    return row.figure == DID_NOT_FINISH and row.verdict == NOT_MET


def run_bench(
    module: str,
    quick: bool = False,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    *,
    label: str | None = None,
    pythonpath: Sequence[str | os.PathLike] = (),
    verbose: bool = False,
) -> list[Row]:
    """Run one benchmark module in a fresh process; its rows, or one row saying it failed.

    module:     importable name with a ``rows(quick=False)`` function (e.g. "bench.sim_speed").
    timeout_s:  wall seconds before the child (and its process group) is killed.
    label:      the bench column's text (default: the module's last name).
    pythonpath: extra import folders for the child (ahead of the repository root).
    verbose:    echo the child's output to stderr as it runs.
    """
    label = label or short_name(module)
    env = dict(os.environ)
    paths = [str(p) for p in pythonpath] + [str(ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])
    env["PYTHONPATH"] = os.pathsep.join(paths)
    env["PYTHONUNBUFFERED"] = "1"
    with tempfile.TemporaryDirectory(prefix="bench_") as tmp:
        out = Path(tmp) / "rows.json"
        cmd = [sys.executable, str(Path(__file__).resolve()), "--child", module, "--rows-json", str(out)]
        if quick:
            cmd.append("--quick")
        proc = subprocess.Popen(
            cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=env,
            cwd=str(ROOT),
            text=True,
            errors="replace",
            start_new_session=True,
        )
        tail: collections.deque[str] = collections.deque(maxlen=TAIL_LINES)

        def pump() -> None:
            for line in proc.stdout:
                tail.append(line.rstrip("\n"))
                if verbose:
                    sys.stderr.write(f"  {label}| {line}")
                    sys.stderr.flush()

        reader = threading.Thread(target=pump, daemon=True)
        reader.start()
        try:
            rc = proc.wait(timeout=timeout_s)
            failure = None if rc == 0 else (f"exit code {rc}" if rc > 0 else f"killed by signal {-rc}")
        except subprocess.TimeoutExpired:
            _kill_group(proc)
            failure = f"timed out after {timeout_s:g} s"
        reader.join(timeout=5)
        if failure is None:
            try:
                data = json.loads(out.read_text(encoding="utf-8"))
                return [Row.from_dict({**d, "bench": label}) for d in data]
            except (OSError, ValueError, TypeError) as exc:
                failure = f"no rows returned ({type(exc).__name__})"
        if not verbose:
            sys.stderr.write("".join(f"  {label}| {line}\n" for line in tail))
        return [_failure_row(label, failure, list(tail))]


def _kill_group(proc: subprocess.Popen) -> None:
    """Stop the child and whatever it started (its own session/process group)."""
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=10)
    except (ProcessLookupError, PermissionError):
        pass
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait()


def run_all(
    benches: Sequence[tuple[str, int | None]],
    quick: bool = False,
    timeout_s: float | None = None,
    pythonpath: Sequence[str | os.PathLike] = (),
    verbose: bool = False,
) -> list[Row]:
    """Run the benchmarks one after another, each in its own process; all their rows."""
    timeout_s = timeout_s or (QUICK_TIMEOUT_S if quick else DEFAULT_TIMEOUT_S)
    rows: list[Row] = []
    for i, (module, issue) in enumerate(benches, 1):
        label = (f"#{issue} " if issue else "") + short_name(module)
        sys.stderr.write(f"[{i}/{len(benches)}] {label} ...\n")
        sys.stderr.flush()
        t0 = time.perf_counter()
        got = run_bench(module, quick, timeout_s, label=label, pythonpath=pythonpath, verbose=verbose)
        ok = not any(is_failure(r) for r in got)
        sys.stderr.write(
            f"[{i}/{len(benches)}] {label}: {'done' if ok else 'FAILED'} in "
            f"{time.perf_counter() - t0:.0f} s, {len(got)} row(s)\n"
        )
        rows += got
    return rows


def machine_line() -> str:
    load = f", load average {os.getloadavg()[0]:.1f}" if hasattr(os, "getloadavg") else ""
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return f"{now}, {platform.node()}, {os.cpu_count()} CPUs{load}, Python {platform.python_version()}"


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python bench/run_all.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--quick", action="store_true", help="short smoke run of every benchmark")
    ap.add_argument(
        "--only",
        nargs="+",
        metavar="NAME",
        help="run only these benchmarks (names as listed above, e.g. sim_speed servo_bus)",
    )
    ap.add_argument("--out", type=Path, help="also write the table here: CSV for a .csv name, markdown otherwise")
    ap.add_argument(
        "--timeout",
        type=float,
        default=None,
        help=f"seconds per benchmark before it is stopped (default {DEFAULT_TIMEOUT_S:g}, "
        f"{QUICK_TIMEOUT_S:g} with --quick)",
    )
    ap.add_argument("-v", "--verbose", action="store_true", help="show each benchmark's own output as it runs")
    ap.add_argument("--child", metavar="MODULE", help=argparse.SUPPRESS)
    ap.add_argument("--rows-json", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return _child(args.child, args.quick, args.rows_json)

    benches = list(BENCHES)
    if args.only:
        known = {short_name(m): (m, n) for m, n in BENCHES}
        unknown = [n for n in args.only if n not in known]
        if unknown:
            ap.error(f"--only: unknown benchmark(s) {', '.join(unknown)}; choose from {', '.join(known)}")
        benches = [known[n] for n in args.only]

    started = machine_line()
    t0 = time.perf_counter()
    rows = run_all(benches, quick=args.quick, timeout_s=args.timeout, verbose=args.verbose)
    head = (
        f"Benchmarks{' (--quick smoke run)' if args.quick else ''}: {started}; {time.perf_counter() - t0:.0f} s in all"
    )
    print(head)
    print_table(rows)
    if args.out:
        write_table(rows, args.out, preamble=head + "\n\n")
        print(f"table written to {args.out}")
    return 1 if any(is_failure(r) for r in rows) else 0


if __name__ == "__main__":
    raise SystemExit(main())
