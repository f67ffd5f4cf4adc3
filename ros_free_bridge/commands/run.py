"""``dualflow-bridge run``: a person moves, the robot partner answers, live.

    dualflow-bridge run --robot op3 --actor synthetic --transport sim
    dualflow-bridge run --actor udp://127.0.0.1:9870 --transport dynamixel --port /dev/ttyUSB0
    dualflow-bridge run --actor dance.bvh --transport dynamixel --emulate   # no hardware

The actor's motion goes through the partner generator (DualFlow in reactive mode, or the
robot imitating the actor) and the streaming retargeter to the control loop, which sends
each command through the safety filter to the transport at --rate Hz. A status line shows
the state, latency and safety interventions while it runs.

Stop with Ctrl-C (or SIGTERM): an e-stop that applies the e-stop policy at once. On a
terminal, q or the space bar does the same. A recorded actor stops by itself at its end
(the stop policy: hold or limp after a ramp).

A live actor (udp://) listens on the loopback interface only, unless --allow-remote-actor
(then it warns: any host that reaches the port can move the robot). It locks onto one
sender; packets it drops (garbage, out of range, out of order, forged sequence jumps,
another sender's) are counted by kind in the status line, the summary and the telemetry
events.

Writes into --out: telemetry.dftl (+ .events.jsonl; every control tick, flushed even on a
crash), actor.npz and partner.npz (the two people), robot.npz (the simulated robot's
measured motion, sim transports) or commands.npz (record transport), and the video with
--video.

Exit codes: 0 the run ended normally (the motion's end, --max-duration, a stop request);
1 a fault, e-stop or watchdog stop (a bus error, an overheated servo, a failed generator,
no frames arriving, Ctrl-C / SIGTERM / q); 2 bad options or a bad input file (one line
naming it and the fix).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

from ros_free_bridge.session import ADAPTIVE_MARGIN, MOTION_FPS, PARTNERS, TRANSPORTS, SessionOptions


def add_stabilizer_option(p) -> None:
    p.add_argument(
        "--no-stabilizer",
        action="store_true",
        help="no balance stabilizer in the loop (on by default for a free-standing robot whose transport "
        "reads an IMU: IMU and joint readings -> bounded corrections on the legs' joints)",
    )


def add_generator_options(p) -> None:
    """The partner generator's options, shared by ``run`` and ``demo``; defaults are SessionOptions'."""
    d = SessionOptions()
    p.add_argument("--model", help="DualFlow checkpoint directory (default: the bundled one)")
    p.add_argument("--steps", type=int, default=d.steps, help=f"ODE steps per generated window (default {d.steps})")
    p.add_argument(
        "--hop",
        type=int,
        default=d.hop,
        help=f"generate the partner every HOP frames (default {d.hop}; 1 = lowest delay, most compute)",
    )
    p.add_argument(
        "--window",
        type=int,
        default=d.window,
        help=f"frames per generation window (default {d.window}, the training clip length)",
    )
    p.add_argument(
        "--partner-device",
        default=d.partner_device,
        metavar="DEVICE",
        help="where DualFlow runs: cpu (default) or a CUDA device (cuda, cuda:1), for a model too large to "
        "stream in real time on the CPU",
    )
    p.add_argument(
        "--generator",
        choices=("process", "thread"),
        default=d.generator,
        help="run DualFlow + retargeting in a child process (default) or in a thread of this one",
    )
    p.add_argument(
        "--playback-margin",
        type=_margin_ms,
        default=None,
        metavar="MS",
        help=f"reserve between a partner frame's arrival and its playback, on top of the frames' measured "
        f"delays (default {ADAPTIVE_MARGIN * 1e3:g} ms). More: the loop extrapolates less often and "
        f"follows the generated motion more closely, at a higher latency (README: real time and latency)",
    )
    p.add_argument(
        "--playback-quantile",
        type=_quantile,
        default=d.playback_quantile,
        metavar="Q",
        help=f"share of recent partner frames that must be in by their playback time (default "
        f"{d.playback_quantile}); lower: lower latency, more extrapolation",
    )
    p.add_argument(
        "--smoothing",
        type=_omega,
        default=d.revision_smoothing,
        metavar="RAD_S",
        help=f"how fast the commands join the partner's curve when a late frame changes it (rad/s, default "
        f"{d.revision_smoothing:g}: within about {4 / d.revision_smoothing * 1e3:.0f} ms); higher: closer "
        f"to the curve, rougher; 0: no smoothing",
    )


def _number(text: str, ok, expected: str) -> float:
    """``text`` as a float for which ``ok`` holds (NaN never does), else one argparse error
    saying what was ``expected``."""
    try:
        x = float(text)
    except ValueError:
        x = float("nan")
    if not ok(x):
        raise argparse.ArgumentTypeError(f"must be {expected}, got {text!r}")
    return x


def _margin_ms(text: str) -> float:
    """--playback-margin in ms -> seconds, >= 0."""
    return _number(text, lambda ms: ms >= 0, "a number of milliseconds >= 0") / 1e3


def _omega(text: str) -> float:
    """--smoothing in rad/s, >= 0 and finite."""
    return _number(text, lambda w: 0 <= w < float("inf"), "a rate in rad/s >= 0 (0: off), e.g. 15")


def _quantile(text: str) -> float:
    """--playback-quantile, a share in (0, 1]."""
    return _number(text, lambda q: 0 < q <= 1, "a share in (0, 1], e.g. 0.9")


def generator_options(args) -> dict:
    """The SessionOptions fields set by :func:`add_generator_options`."""
    return dict(
        model=args.model,
        steps=args.steps,
        hop=args.hop,
        window=args.window,
        partner_device=args.partner_device,
        generator=args.generator,
        playback_margin=args.playback_margin,
        playback_quantile=args.playback_quantile,
        revision_smoothing=args.smoothing,
    )


def register(sub) -> None:
    p = sub.add_parser(
        "run",
        help="stream a robot partner from a live or recorded actor",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--robot",
        default="op3",
        metavar="NAME|DIR",
        help="the robot: a bundled name (op3, ub14), a robot folder (see `robot init`) or its hardware.yaml; "
        "sim and record need no hardware config (default: op3)",
    )
    p.add_argument(
        "--actor",
        default="synthetic",
        help="motion file (BVH, npz, InterGen npy), udp://127.0.0.1:PORT (live), or 'synthetic' (default)",
    )
    p.add_argument(
        "--allow-remote-actor",
        action="store_true",
        help="let a udp:// actor listen on a non-loopback address (e.g. udp://0.0.0.0:9870); anyone who "
        "reaches the port can then move the robot: trusted networks only",
    )
    p.add_argument("--seconds", type=float, default=10.0, help="length of the synthetic actor (default 10 s)")
    p.add_argument("--seed", type=int, default=0, help="synthetic actor seed (default 0)")
    p.add_argument(
        "--partner",
        choices=PARTNERS,
        default="dualflow",
        help="dualflow: generate the partner (default); imitate: the robot copies the actor",
    )
    add_generator_options(p)
    p.add_argument("--text", help="a text cue for the generated partner, e.g. 'the partner mirrors the leader'")
    p.add_argument("--music", help="an audio file (wav/ogg/mp3) aligned with the actor's clock (loops if shorter)")
    p.add_argument("--transport", choices=TRANSPORTS, default="sim", help="where commands go (default: sim)")
    p.add_argument("--port", help="serial port, overriding the hardware config's (e.g. /dev/ttyUSB0)")
    p.add_argument(
        "--emulate", action="store_true", help="dynamixel/serial: use the byte-level bus emulator, no hardware"
    )
    p.add_argument("--rate", type=float, default=100.0, help="control rate in Hz (default 100)")
    p.add_argument(
        "--realtime-priority",
        type=int,
        default=0,
        metavar="N",
        help="run the control loop at SCHED_FIFO priority N (1-99; needs root, CAP_SYS_NICE or an rtprio "
        "limit; refused: normal scheduling, said in the telemetry's 'realtime' event). Default 0: normal",
    )
    p.add_argument("--max-duration", type=float, help="stop after this many seconds of streaming")
    add_stabilizer_option(p)
    p.add_argument(
        "--stop-policy", choices=("hold", "limp"), help="after the stop ramp (default: the hardware config's)"
    )
    p.add_argument(
        "--estop-policy", choices=("hold", "limp"), default="limp", help="on e-stop and errors (default: limp)"
    )
    p.add_argument(
        "--sim-clock",
        choices=("realtime", "lockstep"),
        default="realtime",
        help="sim transports: physics paced by the wall clock (default) or one control period per command",
    )
    p.add_argument("-o", "--out", default="runs/latest", help="output folder (telemetry, motions; default runs/latest)")
    p.add_argument("--video", help="sim transports: render the run to this .mp4 afterwards")
    p.add_argument("--quiet", action="store_true", help="no live status line")
    p.set_defaults(func=run)


def fault_names(faults) -> str:
    """The Fault flags by name, e.g. "starved, deadline_miss", or "none". EXTRAPOLATED (the
    loop continued the newest frame while the next was on its way) is how a hop-1 run keeps its
    latency low, not a fault, and is left out."""
    from ros_free_bridge.control.loop import Fault

    flags = Fault(int(faults))
    return ", ".join(f.name.lower() for f in Fault if f and f in flags and f is not Fault.EXTRAPOLATED) or "none"


class StatusLine:
    """A one-line live status on stderr: state, rate, latency, interventions, faults."""

    def __init__(self, stream=None, every_s: float = 0.5):
        self._stream = stream  # None: whatever sys.stderr is when writing
        self.every_s = every_s
        self._last = 0.0
        self._ticks0 = 0

    def __call__(self, loop, tick, faults) -> None:
        now = time.monotonic()
        if now - self._last < self.every_s:
            return
        rate = (loop.summary.ticks - self._ticks0) / (now - self._last) if self._last else 0.0
        self._last, self._ticks0 = now, loop.summary.ticks
        lat = loop.summary.e2e_latency[-1] * 1e3 if loop.summary.e2e_latency else float("nan")
        stream = self._stream or sys.stderr
        stats = getattr(loop, "source_stats", None)
        drops = f" udp {stats.describe()} " if stats is not None and stats.dropped else ""
        stream.write(
            f"\r{loop.state.name:<8} {rate:6.1f} Hz  frame {loop.summary.frames_played:5d}  latency {lat:6.1f} ms  "
            f"interventions {loop.summary.interventions:5d}  misses {loop.deadline_misses:3d}  "
            f"faults {fault_names(faults)} {drops}"
        )
        stream.flush()


def watch_keys(loop) -> None:
    """On a terminal, q or space triggers the e-stop (a daemon thread; the terminal mode is restored)."""
    if not sys.stdin.isatty():
        return
    import termios
    import tty

    fd = sys.stdin.fileno()
    old = termios.tcgetattr(fd)

    def reader():
        try:
            tty.setcbreak(fd)
            while True:
                ch = sys.stdin.read(1)
                if ch in ("q", " ", "\x1b"):
                    loop.estop(f"key {ch!r}")
                    return
        finally:
            termios.tcsetattr(fd, termios.TCSADRAIN, old)

    threading.Thread(target=reader, daemon=True).start()
    import atexit

    atexit.register(termios.tcsetattr, fd, termios.TCSADRAIN, old)


def print_summary(result, stream=None) -> None:
    stream = stream or sys.stdout
    from ros_free_bridge.control.loop import Fault

    s = result.summary
    g = getattr(result, "pipeline_info", {})
    lat = s.latency_percentiles()
    ahead = g.get("frames_ahead")
    # the loop measures from the arrival of the newest actor frame a partner frame needs; for the
    # generated partner that is actor frame i + L, so the look-ahead itself comes on top
    what = (
        f"latency beyond the {ahead}-frame look-ahead ({ahead / MOTION_FPS * 1e3:.0f} ms more from actor frame i)"
        if ahead
        else "end-to-end latency"
    )
    flags = Fault(s.faults)
    lines = [
        f"robot {result.files.name}: {s.end_state} ({s.reason})",
        f"ticks {s.ticks}, deadline misses {s.deadline_misses}, late ticks {s.late_ticks}",
        f"partner frames played {s.frames_played}"
        + (
            f" (the last {g['settle_s']:.1f} s returning to stand, {g['settle_steps']} "
            + ("step)" if g["settle_steps"] == 1 else "steps)")
            if g.get("settle_s")
            else ""
        ),
        what + " " + (f"p50 {lat['p50'] * 1e3:.0f} ms, p99 {lat['p99'] * 1e3:.0f} ms" if lat else "n/a"),
        f"safety interventions on {s.interventions} ticks, faults: {fault_names(s.faults)}"
        + ("; targets extrapolated while a frame was on its way" if Fault.EXTRAPOLATED in flags else ""),
    ]
    if g.get("generator") in ("process", "thread"):
        warm = f"; a full window took {g['warmup_window_ms']:.0f} ms at start" if "warmup_window_ms" in g else ""
        cpu = f"; it used {g['generator_cpu_per_s']:.2f} CPU s per s of motion" if "generator_cpu_per_s" in g else ""
        cpu += f"; playback margin {g['playback_margin_ms']:.0f} ms" if "playback_margin_ms" in g else ""
        lines.append(
            f"generator: {g['generator']} ({g['steps']} steps, hop {g['hop']}, window {g['window']}{warm}{cpu}), "
            f"partner frames dropped to keep up: {g['frames_dropped']} in {g['catch_ups']} catch-ups"
        )
    stats = getattr(result, "source_stats", None)
    if stats is not None:
        lines.append(
            f"udp input: {stats.received} packets, {stats.accepted} frames accepted, {stats.describe()}"
            + (f", {stats.estops} e-stop packets" if stats.estops else "")
            + (f", {stats.flooded} polls flooded" if stats.flooded else "")
        )
    for k, v in result.transport_info.items():
        lines.append(f"{k}: {v}")
    lines.append(f"outputs in {result.out}")
    stream.write("\n".join(lines) + "\n")


def remote_actor_warning(actor: str, allow_remote: bool) -> str | None:
    """The warning printed when a udp:// actor listens beyond loopback (--allow-remote-actor)."""
    from ros_free_bridge.session import check_udp_actor
    from ros_free_bridge.sources.udp import is_loopback

    where = check_udp_actor(actor, allow_remote)
    if where is None or is_loopback(where[0]):
        return None
    return (
        f"warning: the UDP actor listens on {where[0]}:{where[1]}, not on loopback: any host that reaches this "
        "port can move the robot (--allow-remote-actor)"
    )


def run(args) -> int:
    from ros_free_bridge.session import run_session

    opts = SessionOptions(
        robot=args.robot,
        actor=args.actor,
        seconds=args.seconds,
        seed=args.seed,
        partner=args.partner,
        **generator_options(args),
        transport=args.transport,
        port=args.port,
        emulate=args.emulate,
        rate_hz=args.rate,
        realtime_priority=args.realtime_priority,
        out=Path(args.out),
        stop_policy=args.stop_policy,
        estop_policy=args.estop_policy,
        max_duration=args.max_duration,
        sim_clock=args.sim_clock,
        text=args.text,
        music=args.music,
        allow_remote_actor=args.allow_remote_actor,
        stabilizer=not args.no_stabilizer,
    )
    warning = remote_actor_warning(args.actor, args.allow_remote_actor)
    if warning:
        print(warning, file=sys.stderr)
    status = None if args.quiet else StatusLine()

    def ready(loop, described):
        print(f"actor: {described}", file=sys.stderr)
        watch_keys(loop)

    result = run_session(opts, on_status=status, on_ready=ready)
    if status is not None:
        sys.stderr.write("\n")
    print_summary(result)
    if args.video:
        from ros_free_bridge.run_video import render_video

        print(f"video: {render_video(result, Path(args.video))}")
    return 0 if result.summary.ok else 1
