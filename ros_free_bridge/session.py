"""One bridge session, assembled from options: robot, actor source, partner, transport,
telemetry. The ``run`` and ``demo`` commands are thin layers over :func:`run_session`.

Transports (``SessionOptions.transport``): ``sim`` (the MuJoCo virtual robot), ``record``
(dry run), ``dynamixel`` and ``serial`` (the robot's buses; ``emulate`` starts an emulator),
``sim+dynamixel`` (both; the demo). The generator runs in a child process by default
(:mod:`ros_free_bridge.partner.process`). Outputs in ``out``: ``telemetry.dftl``,
``actor.npz``, ``partner.npz``, ``robot.npz`` (sim) or ``commands.npz`` (record). The
latency budget and the defaults that keep it: docs/bridge_timing.md.
"""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ros_free_bridge.control.loop import ControlLoop, LoopConfig, RunSummary
from ros_free_bridge.control.targets import TargetBuffer
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.robots import RobotFiles, bridge_limits, model_limits, planning_robot, resolve_robot
from ros_free_bridge.telemetry.log import TelemetryWriter

TRANSPORTS = ("sim", "record", "dynamixel", "serial", "sim+dynamixel")
PARTNERS = ("dualflow", "imitate")
GENERATORS = ("process", "thread")
MOTION_FPS = 30.0
#: the adaptive playback clock's default reserve (s) on top of the measured arrival quantile
ADAPTIVE_MARGIN = 0.005


@dataclass
class SessionOptions:
    robot: str = "op3"
    actor: str = "synthetic"  #: a motion file, udp://HOST:PORT, or "synthetic"
    seconds: float = 10.0  #: length of the synthetic actor
    seed: int = 0
    partner: str = "dualflow"
    model: str | None = None  #: checkpoint directory (None: the bundled one)
    # Streaming generation on a 2-core CPU, tuned for latency (bench/bridge_loop.py,
    # bench/partner_motion.py): every frame as soon as its look-ahead is in (hop 1), 2 Euler
    # steps (the partner's error to the rule follower and its jitter as at 5 steps), windows of
    # 60 frames (the training clip length; shorter ones jitter more) computed incrementally
    # (only the new frame runs through the network). When the generator falls behind it
    # catches up with wider windows (up to 25 new frames); see partner.core.PartnerCore.
    steps: int = 2  #: ODE steps per streamed window
    hop: int = 1  #: generate once this many partner frames are due (adds hop - 1 frames of delay)
    window: int = 60  #: frames per generation window (context + new frames + look-ahead)
    #: "process": DualFlow + retarget in a child process (default: its Python never competes
    #: with the control loop for the GIL); "thread": in a thread of this process
    generator: str = "process"
    max_lag: int | None = (
        None  #: frames of generator backlog before dropping to the newest actor frames (None: hop + max_new)
    )
    #: encode the newest actor frame with a predicted next frame (revised when it arrives):
    #: partner frame i waits for actor frame i + L instead of i + L + 1 (partner.reactor.ReactorStage)
    predict_next: bool = True
    #: cache each frame's activations in fixed-start windows and compute only new frames
    #: (dualflow.incremental): ~3x less compute per frame than re-running 60-frame windows.
    #: On the CPU only: on a CUDA device full windows replayed from CUDA graphs are faster
    incremental: bool = True
    #: where DualFlow runs: "cpu", or a CUDA device ("cuda", "cuda:1") for a model too large for
    #: the CPU in real time (the paper preset streams at ~15 ms per frame on an H100)
    partner_device: str = "cpu"
    #: the loop's playback clock follows the frames' recent arrival times (ros_free_bridge.control.playback)
    #: instead of staying where the first frame put it
    adaptive_playback: bool = True
    #: reserve (s) between a frame's arrival and its playback on top of what the adaptive clock
    #: measured; None: 5 ms adaptive, the loop's 50 ms fixed
    playback_margin: float | None = None
    #: the adaptive clock plays a frame when this share of the recent frames had arrived by then
    #: (the median: half the frames come after their play time and the loop extrapolates toward
    #: them, the revisions smoothed by ``revision_smoothing``)
    playback_quantile: float = 0.5
    #: the loop may continue the newest frame for up to this many frames while the next is on
    #: its way, its speed fading to zero (then holds): frame k plays as soon as it arrives instead
    #: of when k + 1 does (interpolation needs it); 0: hold
    extrapolate_frames: float = 3.0
    #: ω (rad/s) of the offset that carries the command smoothly onto the curve when a late frame
    #: changes it (LoopConfig.revision_smoothing); 0: off
    revision_smoothing: float = 15.0
    transport: str = "sim"
    port: str | None = None
    emulate: bool = False
    rate_hz: float = 100.0
    #: SCHED_FIFO priority (1-99) of the control-loop thread; 0: normal scheduling. Needs root,
    #: CAP_SYS_NICE or an rtprio limit; when refused the loop runs normally and says why (telemetry event "realtime")
    realtime_priority: int = 0
    out: Path = Path("runs/latest")
    stop_policy: str | None = None  #: None: the hardware config's
    estop_policy: str = "limp"
    max_duration: float | None = None
    sim_clock: str = "realtime"
    handle_signals: bool = True
    text: str | None = None  #: a text cue for the generator
    music: str | None = None  #: an audio file aligned with the actor clock
    #: let a udp:// actor listen on a non-loopback address (anyone who reaches it moves the robot)
    allow_remote_actor: bool = False
    #: balance stabilizer in the loop for a free-standing robot whose transport reads an IMU
    #: (LoopConfig.stabilizer); False: open loop (--no-stabilizer)
    stabilizer: bool = True


@dataclass
class SessionResult:
    summary: RunSummary
    out: Path
    files: RobotFiles
    actor: object = None  #: dualflow.motion.Motion of the actor frames received
    partner: object = None  #: Motion of the partner poses sent to the retargeter
    robot_motion: object = None  #: RobotTrajectory measured on the virtual robot (sim transports)
    transport_info: dict = field(default_factory=dict)
    #: monotonic arrival (s) of each actor frame received, by index (for latency figures)
    actor_arrivals: np.ndarray | None = None
    #: a live actor's input counters (UdpStats: received, accepted, dropped by kind), else None
    source_stats: object = None
    #: generator: where it ran; frames_dropped: partner frames skipped to keep up (held);
    #: warmup_window_ms: one generation window's compute measured at start (process only)
    pipeline_info: dict = field(default_factory=dict)


def load_actor_file(spec: str):
    """The actor Motion of a motion file (a duet's actor), or None for ``synthetic`` and
    ``udp://``: read and checked before anything starts, so a bad file is named at once."""
    if spec == "synthetic" or spec.startswith("udp://"):
        return None
    from dualflow.motion import TwoPersonMotion
    from dualflow.motion.io import load_any

    if not Path(spec).exists():
        raise BridgeError(f"actor {spec!r}: no such file; give a motion file, udp://127.0.0.1:PORT or 'synthetic'")
    motion = load_any(spec)
    return motion.actor if isinstance(motion, TwoPersonMotion) else motion


def check_udp_actor(spec: str, allow_remote: bool = False) -> tuple[str, int] | None:
    """(host, port) of a ``udp://HOST:PORT`` actor, checked before anything starts (a
    non-loopback host needs ``allow_remote``); None for other actors."""
    if not spec.startswith("udp://"):
        return None
    from ros_free_bridge.sources.udp import is_loopback

    host, _, port = spec[len("udp://") :].rpartition(":")
    if not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise BridgeError(f"actor {spec!r}: write a UDP source as udp://127.0.0.1:PORT")
    if not allow_remote and not is_loopback(host):
        raise BridgeError(
            f"actor {spec!r}: {host} is not a loopback address, and anyone who reaches it could move the "
            "robot; use udp://127.0.0.1:PORT, or add --allow-remote-actor to listen there on purpose"
        )
    return host, int(port)


def open_actor_source(spec: str, seconds: float, seed: int, on_estop=None, motion=None, **udp_options):
    """(source, description) for a file path, ``udp://HOST:PORT`` or ``synthetic``; ``motion``:
    the file's motion when already read (:func:`load_actor_file`); ``udp_options`` go to
    :class:`~ros_free_bridge.sources.udp.UdpActorSource`."""
    from ros_free_bridge.sources.replay import MotionReplaySource

    if spec == "synthetic":
        from dualflow.synthetic import make_leader

        return MotionReplaySource(
            make_leader(seconds, MOTION_FPS, seed)
        ), f"synthetic leader ({seconds:g} s, seed {seed})"
    if spec.startswith("udp://"):
        from ros_free_bridge.sources.udp import UdpActorSource

        host, port = check_udp_actor(spec, allow_remote=udp_options.get("allow_remote", False))
        src = UdpActorSource(host, port, on_estop=on_estop, **udp_options)
        return src, f"UDP actor stream on {host}:{src.address[1]}"
    if motion is None:
        motion = load_actor_file(spec)
    return MotionReplaySource(motion.resample(MOTION_FPS)), f"{spec} ({motion.n_frames} frames at {motion.fps:g} fps)"


#: Transports that need only the robot's model, not its hardware config.
MODEL_ONLY_TRANSPORTS = ("sim", "record")


def open_transport(opts: SessionOptions, files: RobotFiles, hardware, names, rest, stack: ExitStack):
    """(transport, info) for ``opts.transport``, joints in the order ``names``; ``rest`` (n,) rad
    is the record transport's first reading. An emulator it starts is stopped by ``stack`` and
    is ``info["emulator"]``."""
    kind = opts.transport
    if kind not in TRANSPORTS:
        raise BridgeError(f"transport {kind!r}: choose one of {', '.join(TRANSPORTS)}")
    stop_policy = opts.stop_policy or (hardware.stop_policy if hardware is not None else "hold")
    info: dict = {"transport": kind}
    emu = None
    if kind == "sim":
        transport = _sim_transport(opts, files, names)
    elif kind == "record":
        from ros_free_bridge.transports.record import RecordTransport

        transport = RecordTransport(names, initial=rest)
    elif kind == "dynamixel":
        transport, emu = _dynamixel_transport(opts, files, hardware, names, stop_policy, stack)
    elif kind == "serial":
        transport, emu = _serial_transport(opts, files, hardware, names, stop_policy, stack)
    else:  # sim+dynamixel
        from ros_free_bridge.transports.tee import TeeTransport

        sim = _sim_transport(opts, files, names)
        dxl, emu = _dynamixel_transport(opts, files, hardware, names, stop_policy, stack)
        transport = TeeTransport(sim, dxl)
    if emu is not None:
        info["emulator"] = emu
    return transport, info


def _sim_transport(opts: SessionOptions, files: RobotFiles, names):
    """The MuJoCo virtual robot; its MJCF must list the joints in the hardware config's order."""
    from ros_free_bridge.transports.sim import SimTransport

    t = SimTransport(files.ref, control_hz=opts.rate_hz, clock=opts.sim_clock)
    if tuple(t.joint_names) != tuple(names):
        raise BridgeError(
            f"robot {files.name}: the MJCF's joint order {t.joint_names} differs from the hardware "
            f"config's {names}; list the servos in the MJCF's actuator order"
        )
    return t


def _dynamixel_transport(opts: SessionOptions, files: RobotFiles, hardware, names, stop_policy, stack: ExitStack):
    """(transport, emulator or None) on the hardware config's first Dynamixel bus; with
    ``opts.emulate`` the bus is an emulator in its own process."""
    from ros_free_bridge.dynamixel.transport import DynamixelTransport

    bus = next((b for b in hardware.buses if b.protocol in ("1.0", "2.0")), None)
    if bus is None:
        raise BridgeError(f"{files.hardware}: no Dynamixel bus (protocol 1.0 or 2.0) in the hardware config")
    port, emu = opts.port, None
    if opts.emulate:
        emu = _dynamixel_emulator(bus, stack)
        port = emu.port
    # An emulator is a process on a possibly busy machine, not a servo: allow it 100 ms to
    # answer (a real bus answers within the latency timer, 16 ms at worst). At 50 ms, demos
    # on a machine loaded to 5 and more ended in "no status packet" errors.
    transport = DynamixelTransport(
        bus, port=port, joint_names=names, stop_policy=stop_policy, latency_ms=100.0 if opts.emulate else 16.0
    )
    return transport, emu


def _dynamixel_emulator(bus, stack: ExitStack):
    """The emulated servos and devices of ``bus``, started (stopped by ``stack``). In its own
    process, like real hardware: its Python must not compete with the control loop for the
    GIL. It counts any goal outside the config's limits."""
    from firmware_cfg.servo_models import load_servo_model
    from ros_free_bridge.dynamixel.servos import servo_tick_limits
    from ros_free_bridge.emulators.process import EmulatorProcess

    allowed = {s.id: servo_tick_limits(s, load_servo_model(s.model)) for s in bus.servos}
    emu = EmulatorProcess(
        [(s.id, s.model) for s in bus.servos] + [(d.id, d.model) for d in bus.devices],
        bus.baud,
        int(float(bus.protocol)),
        wire_timing=False,
        allowed=allowed,
    )
    stack.callback(emu.stop)
    return emu


def _serial_transport(opts: SessionOptions, files: RobotFiles, hardware, names, stop_policy, stack: ExitStack):
    """(transport, emulator or None) on the hardware config's serial-link bus; with
    ``opts.emulate`` the MCU is emulated."""
    from ros_free_bridge.transports.serial_link import SerialLinkTransport

    bus = next((b for b in hardware.buses if b.protocol == "serial-link"), None)
    if bus is None:
        raise BridgeError(
            f"{files.hardware}: no serial-link bus in the hardware config; add one with protocol: serial-link"
        )
    port, emu = opts.port, None
    if opts.emulate:
        from ros_free_bridge.emulators.serial_mcu import SerialMcuEmulator

        emu = SerialMcuEmulator(n_channels=len(bus.servos)).start()
        stack.callback(emu.stop)
        port = emu.port
    return SerialLinkTransport(bus, port=port, joint_names=names, stop_policy=stop_policy), emu


def run_session(opts: SessionOptions, on_status=None, on_ready=None) -> SessionResult:
    """Build everything, run the control loop until the motion ends or a stop, save outputs.

    The generator starts first (a process that loads the model and answers ready, or a core
    in this process), so a bad checkpoint or condition fails before the robot moves."""
    if opts.partner not in PARTNERS:
        raise BridgeError(f"partner {opts.partner!r}: choose one of {', '.join(PARTNERS)}")
    if opts.generator not in GENERATORS:
        raise BridgeError(f"generator {opts.generator!r}: choose one of {', '.join(GENERATORS)}")
    if opts.partner == "dualflow":
        from ros_free_bridge.partner.reactor import partner_device

        # the name now; whether torch sees the GPU where the model runs: the generator process
        # says so when it starts, before the robot moves (this process does not import torch)
        partner_device(opts.partner_device, check_torch=opts.generator == "thread")
    actor_motion = load_actor_file(opts.actor)  # a bad file is named before anything starts
    check_udp_actor(opts.actor, opts.allow_remote_actor)
    files = resolve_robot(opts.robot)
    if files.hardware is None and opts.transport in MODEL_ONLY_TRANSPORTS:
        # a robot without hardware config (a model just brought in): the simulated robot
        # and recording need only the model's limits
        hardware = None
        robot = planning_robot(files.ref)
        limits = model_limits(robot)
    else:
        hardware = files.hardware_config()
        limits = bridge_limits(hardware)
        robot = planning_robot(files.ref, limits=limits)  # plans within the loop's limits
    names = limits.names
    out = Path(opts.out)
    out.mkdir(parents=True, exist_ok=True)
    with ExitStack() as stack:
        core, rest = _partner_core(opts, files, robot, names, limits, stack)
        return _run(opts, _Robot(files, hardware, limits, rest), out, core, on_status, on_ready, actor_motion)


def _partner_core(opts: SessionOptions, files: RobotFiles, robot, names, limits, stack: ExitStack):
    """(core, rest pose): a PartnerCore here, or the generator process (started, model loaded)."""
    from ros_free_bridge.partner.core import PartnerCore
    from ros_free_bridge.partner.retarget_stage import RetargetStage

    stand = np.asarray(robot.x_stand)[robot.n_root :]
    rest = limits.clip(stand[[robot.joint_names.index(n) for n in names]])
    if opts.partner == "dualflow" and opts.generator == "process":
        from ros_free_bridge.partner.process import GeneratorConfig, GeneratorProcess

        gen = GeneratorProcess(
            GeneratorConfig(
                robot=opts.robot,
                joint_names=list(names),
                fps=MOTION_FPS,
                checkpoint=opts.model,
                window=opts.window,
                steps=opts.steps,
                hop=opts.hop,
                text=opts.text,
                music=opts.music,
                max_lag=opts.max_lag,
                predict_next=opts.predict_next,
                incremental=opts.incremental,
                device=opts.partner_device,
            )
        )
        stack.callback(gen.close)
        return gen.start(), rest
    retarget = RetargetStage(robot, MOTION_FPS, names)
    reactor = None
    if opts.partner == "dualflow":
        from dualflow.streaming import StreamConfig
        from ros_free_bridge.partner.reactor import Cues, ReactorStage

        stream = StreamConfig(
            window=opts.window,
            steps=opts.steps,
            hop=opts.hop,
            incremental=opts.incremental and opts.partner_device == "cpu",
        )
        reactor = ReactorStage(
            MOTION_FPS,
            opts.model,
            stream,
            Cues(opts.text, opts.music),
            predict_next=opts.predict_next,
            device=opts.partner_device,
        )
    return PartnerCore(reactor, retarget, opts.max_lag), rest


@dataclass(frozen=True)
class _Robot:
    """The robot a session drives: its folder's files, hardware config (None for a model-only
    transport), the limits the loop enforces (joint order = ``limits.names``) and the rest pose."""

    files: RobotFiles
    hardware: object
    limits: object
    rest: np.ndarray

    @property
    def names(self) -> tuple[str, ...]:
        return self.limits.names


def _loop_config(opts: SessionOptions, rb: _Robot, core) -> LoopConfig:
    hardware = rb.hardware
    margin = (
        {}
        if opts.playback_margin is None and not opts.adaptive_playback
        else {"playback_margin": ADAPTIVE_MARGIN if opts.playback_margin is None else opts.playback_margin}
    )
    config = LoopConfig(
        rate_hz=opts.rate_hz,
        rest_pose=rb.rest,
        stop_policy=opts.stop_policy or (hardware.stop_policy if hardware is not None else "hold"),
        adaptive_playback=opts.adaptive_playback,
        playback_lead_frames=max(0.0, 1.0 - opts.extrapolate_frames),
        playback_quantile=opts.playback_quantile,
        revision_smoothing=opts.revision_smoothing,
        **margin,
        estop_policy=opts.estop_policy,
        max_duration=opts.max_duration,
        handle_signals=opts.handle_signals,
        realtime_priority=opts.realtime_priority,
        stabilizer=opts.stabilizer,
    )
    if not config.adaptive_playback:  # the adaptive clock follows the measured delay itself
        config.playback_margin = playback_margin(config.playback_margin, core)
    return config


def _run(opts: SessionOptions, rb: _Robot, out: Path, core, on_status, on_ready, actor_motion=None) -> SessionResult:
    from ros_free_bridge.partner.pipeline import PartnerPipeline

    config = _loop_config(opts, rb, core)
    # cubic (Hermite, causal tangents) interpolation: linear would jump in velocity at every 30 fps frame,
    # which the safety filter's acceleration limit would then clip on every joint
    buffer = TargetBuffer(MOTION_FPS, interpolation="cubic", extrapolate=opts.extrapolate_frames)
    with ExitStack() as stack:
        transport, info = open_transport(opts, rb.files, rb.hardware, rb.names, rb.rest, stack)
        telemetry = _telemetry_writer(opts, rb, out)
        loop = ControlLoop(
            transport,
            rb.limits,
            buffer,
            config,
            telemetry,
            on_status=on_status,
            balance=_balance_model(rb.files, rb.names) if opts.stabilizer else None,
        )
        source, described = _open_source(opts, loop, telemetry, actor_motion, stack)
        stats = getattr(source, "stats", None)
        telemetry.event(
            "session",
            actor=described,
            delay_frames=core.delay_frames,
            frames_ahead=getattr(core, "frames_ahead", None),
            generator=_generator_info(opts, core),
            playback_margin_s=round(config.playback_margin, 4),
            playback_quantile=config.playback_quantile,
            extrapolate_frames=buffer.extrapolate,
            revision_smoothing=config.revision_smoothing,
        )
        pipeline = PartnerPipeline(
            source, None, None, buffer, loop.ready, record=True, on_event=telemetry.event, core=core
        )
        pipeline.start()
        stack.callback(pipeline.stop)
        if on_ready is not None:
            on_ready(loop, described)
        try:
            summary = loop.run()
        finally:
            # never leave the pipeline thread (or the generator in it) running while the process exits
            pipeline.stop()
            pipeline.join(30.0)
    result = SessionResult(summary, out, rb.files, transport_info={k: v for k, v in info.items() if k != "emulator"})
    if stats is not None:
        result.source_stats = stats
        _log_input_stats(out / "telemetry.dftl", stats)
    result.pipeline_info = _pipeline_info(opts, core, config, pipeline)
    _save_outputs(result, pipeline, transport, info.get("emulator"))
    return result


def _telemetry_writer(opts: SessionOptions, rb: _Robot, out: Path) -> TelemetryWriter:
    """``out/telemetry.dftl``, its header naming the robot, actor, partner, transport and model."""
    return TelemetryWriter(
        out / "telemetry.dftl",
        rb.names,
        opts.rate_hz,
        meta={
            "robot": rb.files.ref,
            "actor": opts.actor,
            "partner": opts.partner,
            "transport": opts.transport,
            "model": str(opts.model or "bundled"),
        },
    )


def _open_source(opts: SessionOptions, loop: ControlLoop, telemetry: TelemetryWriter, actor_motion, stack: ExitStack):
    """(source, description) of the actor's motion, closed by ``stack``; a UDP source's e-stop
    stops ``loop`` and its events go to ``telemetry``, its drop counters to the status line."""
    udp = {}
    if opts.actor.startswith("udp://"):
        udp = {"allow_remote": opts.allow_remote_actor, "on_event": telemetry.event}
    source, described = open_actor_source(
        opts.actor, opts.seconds, opts.seed, on_estop=loop.estop, motion=actor_motion, **udp
    )
    stack.callback(source.close)
    stats = getattr(source, "stats", None)
    if stats is not None:
        loop.source_stats = stats  # the status line shows its drop counters
    return source, described


def _log_input_stats(telemetry_path: Path, stats) -> None:
    """An ``input`` event with the actor source's packet counters, after the run."""
    telemetry_events_append(
        telemetry_path,
        "input",
        received=stats.received,
        accepted=stats.accepted,
        estops=stats.estops,
        flooded=stats.flooded,
        senders=stats.senders,
        dropped=stats.drops(),
    )


def _pipeline_info(opts: SessionOptions, core, config: LoopConfig, pipeline) -> dict:
    """The partner pipeline's figures for the summary: generator, playback margin (ms), frames
    dropped, catch-ups, frames ahead and the generator's CPU s per s of actor motion."""
    info = {
        **_generator_info(opts, core),
        "playback_margin_ms": round(1e3 * config.playback_margin, 1),
        "frames_dropped": pipeline.frames_dropped,
        "catch_ups": sum(e.get("kind") == "generator_behind" for e in pipeline.events),
        # the robot's return to its stance after the stream (retarget.settle): seconds, steps
        "settle_s": sum(e.get("seconds", 0.0) for e in pipeline.events if e.get("kind") == "settle"),
        "settle_steps": sum(e.get("steps", 0) for e in pipeline.events if e.get("kind") == "settle"),
        "frames_ahead": getattr(core, "frames_ahead", None),
    }
    cpu = getattr(core, "streaming_cpu_s", float("nan"))
    if np.isfinite(cpu) and len(pipeline.actor_positions):
        # CPU seconds the generator process used per second of actor motion: < 1 fits one core
        info["generator_cpu_per_s"] = round(cpu / (len(pipeline.actor_positions) / MOTION_FPS), 3)
    return info


def _save_outputs(result: SessionResult, pipeline, transport, emu) -> None:
    """The run's people (actor.npz, partner.npz), the simulated robot's motion (robot.npz), the
    recorded commands (commands.npz) and the emulated bus's counters, into ``result``."""
    from dualflow.motion import Motion
    from dualflow.motion.io import save_motion

    out = result.out
    result.actor_arrivals = np.asarray(pipeline.actor_arrivals, dtype=float)
    if pipeline.actor_positions:
        result.actor = Motion(np.asarray(pipeline.actor_positions), MOTION_FPS, name="actor")
        save_motion(result.actor, out / "actor.npz")
    if pipeline.partner_positions:
        # with the foot contacts the robot's retargeter was given, so that the file replays the run
        known = all(c is not None for c in pipeline.partner_contacts)
        contacts = np.asarray(pipeline.partner_contacts, dtype=bool) if known else None
        result.partner = Motion(np.asarray(pipeline.partner_positions), MOTION_FPS, contacts=contacts, name="partner")
        save_motion(result.partner, out / "partner.npz")
    sim_transport = transport.transports[0] if hasattr(transport, "transports") else transport
    if hasattr(sim_transport, "recorded_trajectory"):
        result.robot_motion = sim_transport.recorded_trajectory()
        if result.robot_motion is not None:
            result.robot_motion.save_npz(out / "robot.npz")
    if hasattr(transport, "save"):
        transport.save(out / "commands.npz")
    if emu is not None and getattr(emu, "stats", None):
        result.transport_info["bus_violations"] = emu.stats["violations"]
        result.transport_info["bus_goal_writes"] = emu.stats["goal_writes"]


def _balance_model(files, names):
    """The robot's sim.stabilizer.BalanceModel, or None for a fixed-base robot (or one whose legs
    are not found)."""
    from firmware_cfg.registry import resolve

    if resolve(files.ref).fixed_base:
        return None
    from sim.stabilizer import balance_model

    return balance_model(files.ref, joint_names=tuple(names))


def telemetry_events_append(telemetry_path: Path, kind: str, **info) -> None:
    """Append one event to a closed telemetry file's events (the loop closes the writer when it
    returns; what the session learns afterwards, e.g. the input's final counters, goes here)."""
    import json
    import time

    line = json.dumps({"kind": kind, "unix": time.time(), "monotonic": time.monotonic(), **info})
    with open(telemetry_path.with_name(telemetry_path.name + ".events.jsonl"), "a") as fh:
        fh.write(line + "\n")


def playback_margin(default: float, core) -> float:
    """Seconds the loop waits after the first partner frame before playing it (LoopConfig).

    The loop plays frame k at t0 + k / fps, with t0 fixed by the first frame, so a later
    frame is late (the loop holds, then jumps) whenever its window took longer than the first
    one by more than the margin. The first window is the shortest (no context yet), so the
    margin adds the difference, measured by the generator process at start on the same
    windows: margin = default + max(0, full window - first window). Latency grows by that
    once and stays flat instead of stuttering.
    """
    info = getattr(core, "ready_info", {})
    full, first = info.get("warmup_window_s"), info.get("warmup_first_window_s")
    if full is None or first is None or not (np.isfinite(full) and np.isfinite(first)):
        return default
    return default + max(0.0, full - first)


def _generator_info(opts: SessionOptions, core) -> dict:
    if opts.partner != "dualflow":
        return {"generator": "none (imitation)"}
    info = {
        "generator": opts.generator,
        "steps": opts.steps,
        "hop": opts.hop,
        "window": opts.window,
        "incremental": opts.incremental and opts.partner_device == "cpu",
        "partner_device": opts.partner_device,
        "predict_next": opts.predict_next,
    }
    ready = getattr(core, "ready_info", {})
    if "warmup_window_s" in ready:
        info["warmup_window_ms"] = round(1e3 * ready["warmup_window_s"], 1)
    return info
