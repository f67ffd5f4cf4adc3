"""``dualflow-bridge demo``: the whole system on the embedded defaults, in a few minutes.

A leader dances (the synthetic leader, or ``--actor FILE``) to music (``--music FILE``, or
a click track synthesised on the leader's beats: the synthetic leader's own, or a file
actor's motion beats, the minima of its joint speed); the bundled DualFlow checkpoint generates the partner in
reactive mode, streamed causally; the streaming retargeter puts it on the bundled op3 humanoid;
the bridge's control loop drives the MuJoCo virtual robot and, at the same time, an emulated
20-servo Dynamixel bus (byte-level, over a pseudo-terminal). Outputs, in one folder:

- ``demo.mp4``: the human leader, the generated partner and the robot, side by side;
- ``check.json`` / ``check.md`` (+ plots): the physics check of the commands the robot received;
- ``telemetry.dftl`` (+ ``.events.jsonl``): every control tick;
- ``actor.npz``, ``partner.npz`` (with the foot contacts the robot's retargeter was given, so
  that retargeting it again gives the robot's run), ``robot.npz``, ``music.wav``; and a printed
  summary (frames, latency, safety interventions, the physics check's PASS/FAIL).

Progress is shown for each of the three steps. No downloads, no hardware, no GPU; about a
minute on a 2-core CPU with the defaults.

Exit code 0 when the run stopped normally, the emulated bus saw no out-of-limit command
and the physics check passed; 1 otherwise; 2 for bad options or files.
"""

from __future__ import annotations

import argparse
import sys
import time
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np


def register(sub) -> None:
    from ros_free_bridge.commands.run import add_generator_options, add_stabilizer_option

    p = sub.add_parser(
        "demo",
        help="the main job: a dancing leader, a generated robot partner, video and reports",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--robot",
        default="op3",
        metavar="NAME|DIR",
        help="the robot partner: a bundled name (op3, ub14) or a robot folder (see `robot init`); a robot "
        "without hardware.yaml runs without the emulated bus (default op3)",
    )
    p.add_argument("--actor", default="synthetic", help="a motion file for the leader (default: the synthetic leader)")
    p.add_argument("--music", help="an audio file, wav/ogg/mp3 (default: a click track on the leader's beats)")
    p.add_argument("--text", help="a text cue for the partner (default: none)")
    p.add_argument("--seconds", type=float, default=8.0, help="length of the synthetic leader (default 8 s)")
    p.add_argument("--seed", type=int, default=0, help="synthetic leader seed (default 0)")
    add_generator_options(p)
    p.add_argument("--no-bus", action="store_true", help="drive the virtual robot only, without the emulated bus")
    p.add_argument("--no-video", action="store_true", help="skip the video")
    add_stabilizer_option(p)
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
            audio[i : i + len(t)] += (0.9 if k % 4 == 0 else 0.5) * click
    sf.write(path, audio, sr)
    return path


def demo(args) -> int:
    from dualflow.checkpoint import BUNDLED_CHECKPOINT, load_checkpoint
    from ros_free_bridge.commands.run import StatusLine, generator_options
    from ros_free_bridge.robots import resolve_robot
    from ros_free_bridge.run_video import render_video
    from ros_free_bridge.session import SessionOptions, run_session
    from sim.report import write_report

    files = resolve_robot(args.robot)
    if files.hardware is None and not args.no_bus:
        print(
            f"note: robot {files.ref} has no hardware.yaml; driving the virtual robot without the emulated bus",
            file=sys.stderr,
        )
        args.no_bus = True
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    music = _demo_music(args, load_checkpoint(args.model or BUNDLED_CHECKPOINT).meta, out)

    print(
        f"[1/3] streaming: leader -> DualFlow partner -> retarget -> virtual robot"
        f"{'' if args.no_bus else ' + emulated Dynamixel bus'}",
        file=sys.stderr,
    )
    opts = SessionOptions(
        robot=args.robot,
        actor=args.actor,
        seconds=args.seconds,
        seed=args.seed,
        **generator_options(args),
        transport="sim" if args.no_bus else "sim+dynamixel",
        emulate=not args.no_bus,
        out=out,
        text=args.text,
        music=music,
        stabilizer=not args.no_stabilizer,
    )
    result = run_session(opts, on_status=StatusLine())
    sys.stderr.write("\n")

    check = _check_commands(result, out, stabilizer=not args.no_stabilizer)
    reports = write_report(check, out, "check")

    video = None
    if not args.no_video:
        with motion_progress("[3/3] rendering the video", result.robot_motion.duration) as tick:
            video = render_video(result, out / "demo.mp4", on_tick=tick)

    _print_demo_summary(result, check, reports, video)
    print(steps_line(out / "partner.npz", check, result.pipeline_info.get("settle_steps", 0), planted_note(args.robot)))
    fell, line = live_robot_line(result.robot_motion, check.config.fall_tilt_deg)
    print(line)
    print(f"done in {time.monotonic() - t_start:.0f} s")
    ok = result.summary.ok and result.transport_info.get("bus_violations", 0) == 0 and check.passed and not fell
    return 0 if ok else 1


def live_robot_line(motion, fall_tilt_deg: float) -> tuple[bool, str]:
    """(fell, a summary line) for the virtual robot that ran live (the video's robot): its
    torso tilt over the run. The physics check replays the commands in a simulation of its
    own; the live one differs by the run's timing, and near a fall the two can part."""
    if motion is None or motion.n_frames == 0:
        return False, "live virtual robot: not recorded"
    _, x, y, _ = np.asarray(motion.root_quat, dtype=np.float64).T
    tilt = np.degrees(np.arccos(np.clip(1.0 - 2.0 * (x * x + y * y), -1.0, 1.0)))
    over = np.flatnonzero(tilt > fall_tilt_deg)
    if len(over):
        return True, (
            f"live virtual robot: FELL at {over[0] / motion.fps:.2f} s (torso tilt beyond {fall_tilt_deg:g} deg; "
            "the physics check replays the commands in its own simulation)"
        )
    return False, f"live virtual robot: stayed up (largest torso tilt {tilt.max():.0f} deg)"


def _demo_music(args, model_meta: dict, out: Path) -> str | None:
    """The music the partner hears: ``--music``, else a click track on the leader's beats
    (written to ``out/music.wav``) when it has any; None for a model trained without music."""
    music = args.music
    if str(model_meta.get("music", "none")) == "none":
        if music:
            print("note: this model was trained without music; --music is ignored", file=sys.stderr)
        return None
    if music is None:
        beats = leader_beats(args.actor, args.seconds, args.seed)
        if beats is not None:
            music = str(click_track(beats[0], beats[1], out / "music.wav"))
            print(f"music: a click track {beats[2]} ({out / 'music.wav'})", file=sys.stderr)
    return music


def _check_commands(result, out: Path, stabilizer: bool):
    """The physics check (:class:`sim.check.CheckResult`) of the commands the run sent, read
    back from ``out/telemetry.dftl``."""
    from ros_free_bridge.telemetry.log import read_telemetry
    from sim.check import CheckConfig, check_trajectory

    tel = read_telemetry(out / "telemetry.dftl")
    cfg = CheckConfig(control_hz=tel.rate_hz, stabilizer=stabilizer)
    loop = tel.loop_replay(result.files.ref) if stabilizer else None
    if loop is not None:
        # the loop's order: its pre-stabilizer targets, the check's stabilizer on its own simulated
        # robot with readings as old as the run's, then the run's safety filter. (The filtered
        # open-loop commands with readings a tick old made another controller: the check passed
        # runs whose live robot fell in its balance feedback.)
        commands, make_filter, age = loop
        # (the loop's targets are samples, extrapolated at times, not a trajectory given: the
        # limits are judged on the commands the run sent)
        cfg = replace(cfg, reading_age=age, command_filter=make_filter, judge_reference=False)
    else:
        # the commands the loop sent without a stabilizer correction (Telemetry.open_loop_commands)
        commands = tel.commands_trajectory(result.files.ref, without_correction=True)
    with motion_progress("[2/3] checking the robot's commands in physics", commands.duration) as tick:
        return check_trajectory(commands, cfg, robot=result.files.ref, on_tick=tick)


def _print_demo_summary(result, check, reports: dict, video) -> None:
    """The run's summary, the check's verdict and the files written."""
    from ros_free_bridge.commands.run import print_summary
    from sim.report import stabilizer_line

    print_summary(result)
    print(
        f"physics check: {'PASS' if check.passed else 'FAIL'}"
        + ("" if check.passed else f" ({check.reason}, first at {check.first_failure_time} s)")
        + f"; {stabilizer_line(check)}"
    )
    for name, path in reports.items():
        print(f"{name}: {path}")
    if video is not None:
        print(f"video: {video}")


def planted_note(robot) -> str:
    """Why the robot does not step, where its profile keeps its feet planted (``streaming_steps:
    false``: robot init writes it for a robot that fell with steps in its probe); else ""."""
    from firmware_cfg.registry import resolve
    from retarget.profile import RetargetProfile

    path = resolve(robot).profile
    if path is None or RetargetProfile.load(path).streaming_steps:
        return ""
    return (
        f"the robot keeps its feet planted: {path} says streaming_steps: false (the comment above it "
        "says why; robot init writes it for a robot that fell with steps in its stepping probe)"
    )


def steps_line(partner_file: Path, check, settle_steps: int = 0, planted: str = "") -> str:
    """The partner's steps (touch-downs of its detected foot contacts) next to the robot's
    (its feet in the physics check, counted by the partner's rule scaled to the robot:
    :func:`sim.check.steps_as_a_person`; and how often they left the floor at all), less the
    ``settle_steps`` it took returning to its stance after the stream (named). Touch-downs
    that end a jump (both of the partner's feet up) are named: the robot keeps its feet down
    through a jump, so it has no step there to match. ``planted``: why the robot keeps its
    feet planted (:func:`planted_note`), added to the line."""
    from dualflow.motion.io import load_any
    from retarget.schedule import count_steps
    from retarget.targets import detect_contacts, side_contacts
    from sim.check import lift_offs, steps_taken

    robot = steps_taken(check.metrics) - settle_steps
    lifted = lift_offs(check.metrics) - settle_steps
    after = f", and {settle_steps} returning to its stance after the stream" if settle_steps else ""
    try:
        motion = load_any(partner_file)
        contacts = side_contacts(detect_contacts(motion))
    except Exception as exc:  # noqa: BLE001 - a summary line; the run's verdict is already made
        return f"steps: the robot {robot}{after} (the partner's not counted: {exc})"
    person = f"the partner {count_steps(contacts)}"
    jumps, landings, airborne = jump_landings(contacts, motion.fps)
    if jumps:
        person += (
            f" ({landings} of them landing from {jumps} jump{'s' if jumps > 1 else ''}, {airborne:.2f} s in the air,"
            " which the robot stands through)"
        )
    why = f"; {planted}" if planted else ""
    return (
        f"steps: {person}, the robot {robot} (its feet in physics, counted as the partner's are; "
        f"they left the floor {lifted} time{'' if lifted == 1 else 's'}){after}{why}"
    )


def jump_landings(contacts, fps: float) -> tuple[int, int, float]:
    """(jumps, touch-downs that end one, seconds in the air) of side contacts (T, 2): a jump is
    a run of frames with both feet up that ends with a foot down (retarget.schedule's flights)."""
    from retarget.schedule import keep_feet_down_in_flight

    c = np.asarray(contacts, dtype=bool)
    flights: list = []
    keep_feet_down_in_flight(c.copy(), fps, flights)
    ends = [round(f.end_s * fps) for f in flights]
    landed = [(f, e) for f, e in zip(flights, ends) if 0 < e < len(c)]
    landings = sum(int(c[e].sum()) for _, e in landed)
    return len(landed), landings, sum(f.end_s - f.start_s for f, _ in landed)


def leader_beats(actor: str, seconds: float, seed: int):
    """(beat times s, track length s, description) for the demo's click track: the synthetic
    leader's own beats, or a motion file's actor's motion beats; None for a live actor."""
    if actor == "synthetic":
        from dualflow.synthetic import make_leader_clip

        clip = make_leader_clip(seconds, 30.0, seed)
        return clip.beat_times, seconds, f"at {clip.bpm:.0f} bpm on the leader's beats"
    if actor.startswith("udp://"):
        return None
    from dualflow.evaluation.rhythm import motion_beats
    from dualflow.motion import TwoPersonMotion
    from dualflow.motion.io import load_any

    motion = load_any(actor)
    motion = motion.actor if isinstance(motion, TwoPersonMotion) else motion
    if motion.n_frames < 3:
        return None  # too short to have beats; the session says what is wrong with it
    return (
        motion_beats(motion.positions) / motion.fps,
        motion.duration,
        "on the actor's motion beats (its speed minima)",
    )


@contextmanager
def motion_progress(title: str, total_s: float):
    """A progress bar over seconds of motion for one demo step: ``with motion_progress(title,
    total_s) as tick: work(on_tick=tick)``; ``tick(t)`` reports that ``t`` seconds are done."""
    from tqdm import tqdm

    total = round(float(total_s), 2)
    print(title, file=sys.stderr)
    with tqdm(
        total=total,
        unit="s",
        leave=False,
        file=sys.stderr,
        bar_format="  {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} s of motion [{elapsed}<{remaining}]",
    ) as bar:
        yield lambda t: bar.update(min(float(t), total) - bar.n)
