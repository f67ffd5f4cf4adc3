"""``dualflow-bridge demo``: the whole system on the embedded defaults, in a few minutes.

A leader dances (the synthetic leader, or ``--actor FILE``) to music (a click track on the
leader's beats, or ``--music FILE``); the bundled DualFlow checkpoint generates the partner in
reactive mode, streamed causally; the streaming retargeter puts it on the bundled op3 humanoid;
the bridge's control loop drives the MuJoCo virtual robot and, at the same time, an emulated
20-servo Dynamixel bus (byte-level, over a pseudo-terminal). Outputs, in one folder:

- ``demo.mp4``: the human leader, the generated partner and the robot, side by side;
- ``check.json`` / ``check.md`` (+ plots): the physics check of the commands the robot received;
- ``telemetry.dftl`` (+ ``.events.jsonl``): every control tick;
- ``actor.npz``, ``partner.npz``, ``robot.npz``, ``music.wav``; and a printed summary.

No downloads, no hardware, no GPU.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np


def register(sub) -> None:
    from ros_free_bridge.commands.run import add_generator_options

    p = sub.add_parser("demo", help="the main job: a dancing leader, a generated robot partner, video and reports",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("--actor", default="synthetic", help="a motion file for the leader (default: the synthetic leader)")
    p.add_argument("--music", help="an audio file (default: a click track on the synthetic leader's beats)")
    p.add_argument("--text", help="a text cue for the partner (default: none)")
    p.add_argument("--seconds", type=float, default=8.0, help="length of the synthetic leader (default 8 s)")
    p.add_argument("--seed", type=int, default=0, help="synthetic leader seed")
    add_generator_options(p)
    p.add_argument("--no-bus", action="store_true", help="drive the virtual robot only, without the emulated bus")
    p.add_argument("--no-video", action="store_true", help="skip the video")
    p.add_argument("-o", "--out", default="demo_out", help="output folder (default demo_out)")
    p.set_defaults(func=demo)


def click_track(beat_times: np.ndarray, seconds: float, path: Path, sr: int = 22050) -> Path:
    """A wav of short decaying 1 kHz clicks on ``beat_times`` (s), louder on every 4th beat."""
    import soundfile as sf

    t = np.arange(int(0.06 * sr)) / sr
    click = np.sin(2 * np.pi * 1000 * t) * np.exp(-t / 0.012)
    audio = np.zeros(int(seconds * sr) + len(t), np.float32)
    for k, b in enumerate(beat_times):
        i = int(b * sr)
        if 0 <= i < len(audio) - len(t):
            audio[i:i + len(t)] += (0.9 if k % 4 == 0 else 0.5) * click
    sf.write(path, audio, sr)
    return path


def demo(args) -> int:
    from dualflow.checkpoint import BUNDLED_CHECKPOINT, load_checkpoint
    from ros_free_bridge.commands.run import StatusLine, generator_options, print_summary, render_video
    from ros_free_bridge.session import SessionOptions, run_session
    from ros_free_bridge.telemetry import read_telemetry
    from sim.check import CheckConfig, check_trajectory
    from sim.report import write_report

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    ckpt = load_checkpoint(args.model or BUNDLED_CHECKPOINT)
    music = args.music
    if str(ckpt.meta.get("music", "none")) == "none":
        if music:
            print("note: this model was trained without music; --music is ignored", file=sys.stderr)
        music = None
    elif music is None and args.actor == "synthetic":
        from dualflow.synthetic import make_leader_clip

        clip = make_leader_clip(args.seconds, 30.0, args.seed)
        music = str(click_track(clip.beat_times, args.seconds, out / "music.wav"))
        print(f"music: a click track at {clip.bpm:.0f} bpm on the leader's beats ({out / 'music.wav'})", file=sys.stderr)

    print(f"[1/3] streaming: leader -> DualFlow partner -> retarget -> virtual robot"
          f"{'' if args.no_bus else ' + emulated Dynamixel bus'}", file=sys.stderr)
    opts = SessionOptions(actor=args.actor, seconds=args.seconds, seed=args.seed, **generator_options(args),
                          transport="sim" if args.no_bus else "sim+dynamixel", emulate=not args.no_bus, out=out,
                          text=args.text, music=music)
    result = run_session(opts, on_status=StatusLine())
    sys.stderr.write("\n")

    print("[2/3] checking the robot's commands in physics", file=sys.stderr)
    tel = read_telemetry(out / "telemetry.dftl")
    check = check_trajectory(tel.commands_trajectory(result.files.name), CheckConfig(control_hz=tel.rate_hz),
                             robot=result.files.name)
    reports = write_report(check, out, "check")

    video = None
    if not args.no_video:
        print("[3/3] rendering the video", file=sys.stderr)
        video = render_video(result, out / "demo.mp4")

    print_summary(result)
    print(f"physics check: {'PASS' if check.passed else 'FAIL'}"
          + ("" if check.passed else f" ({check.reason}, first at {check.first_failure_time} s)"))
    for name, path in reports.items():
        print(f"{name}: {path}")
    if video is not None:
        print(f"video: {video}")
    print(f"done in {time.monotonic() - t_start:.0f} s")
    ok = result.summary.end_state == "STOPPED" and result.transport_info.get("bus_violations", 0) == 0
    return 0 if ok else 1
