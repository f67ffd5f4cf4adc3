"""The fixed-rate control loop and its safety supervisor.

:class:`ControlLoop` drives a transport from a :class:`~ros_free_bridge.control.targets.TargetBuffer`
at ``LoopConfig.rate_hz``: each tick reads the transport, checks e-stop, watchdogs and health,
picks the target (start ramp, interpolated stream, hold, stop ramp), passes it through the
balance stabilizer (free robots with an IMU) and the safety filter, writes it and records the
tick. It never blocks on the slow stages, and any exit applies the stop or e-stop policy.
The tick, the life cycle and the timing: docs/bridge_timing.md.
"""

from __future__ import annotations

import atexit
import signal
import threading
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from enum import IntEnum, IntFlag
from typing import NamedTuple

import numpy as np

from ros_free_bridge.control.clock import FixedRateClock
from ros_free_bridge.control.playback import PlaybackClock, PlaybackPolicy
from ros_free_bridge.control.realtime import LoopGc, realtime_priority, switch_interval
from ros_free_bridge.control.safety import JointLimits, SafetyFilter, min_jerk, min_jerk_duration
from ros_free_bridge.control.targets import RevisionSmoother, TargetBuffer
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.telemetry.log import TelemetryWriter
from ros_free_bridge.transports.base import STOP_POLICIES


class State(IntEnum):
    STARTING = 0
    RAMP_IN = 1
    WAITING = 2  #: at the rest pose, waiting for the first target frame
    RUNNING = 3
    HOLD = 4  #: the actor stream or the generator went quiet: holding the last command
    RAMP_OUT = 5
    STOPPED = 6
    ESTOP = 7


class Fault(IntFlag):
    NONE = 0
    ACTOR_TIMEOUT = 1
    STARVED = 2  #: the next target frame was not ready in time
    GENERATOR_ERROR = 4
    NONFINITE = 8
    DEADLINE_MISS = 16
    OVERHEAT = 32
    VOLTAGE = 64
    HARDWARE_ERROR = 128
    BUS_ERROR = 256
    ESTOP = 512
    DEGRADED = 1024  #: running with reduced velocity limits (warm servos)
    EXTRAPOLATED = 2048  #: the target continued the newest frame's velocity (next frame not there yet)


@dataclass
class LoopConfig:
    """Timing and safety settings of a run. Times in seconds, temperatures in °C, volts."""

    rate_hz: float = 100.0
    rest_pose: np.ndarray | None = None  #: (n,) rad; None: the measured start pose
    stop_policy: str = "hold"  #: after the stop ramp: 'hold' or 'limp'
    estop_policy: str = "limp"  #: on e-stop and on errors
    start_timeout: float = 20.0  #: waiting for the first target frame, then stop
    actor_timeout: float = 0.5  #: no new target frame for this long: hold
    rest_after: float = 3.0  #: holding for this long: ramp to rest and stop
    playback_margin: float = 0.05  #: extra delay before playing a frame, to absorb jitter
    #: playback clock (ros_free_bridge.control.playback): adapt t0 to the frames' recent arrivals
    #: (True) or keep it where the first frame put it (False)
    adaptive_playback: bool = True
    playback_lead_frames: float = 1.0  #: adaptive: frame k + 1 is due when frame k plays (interpolation)
    #: adaptive: the share of recent frames that must have arrived by their play time (the
    #: rest is played as it comes, the buffer extrapolating meanwhile)
    playback_quantile: float = 0.9
    #: ω (rad/s) of the critically damped offset that carries the command across a revision of
    #: the target curve (a frame that came after the loop had extrapolated past its
    #: predecessor: targets.RevisionSmoother); position and velocity stay continuous and the
    #: command joins the new curve within a few 1 / ω. 0: sample the curve as it is
    revision_smoothing: float = 15.0
    #: s: the shortest blend from the pose the loop holds onto the stream, when streaming starts
    #: (from the rest pose to the first frame) and when it resumes after a hold: the command
    #: starts where it was and the offset to the curve fades along a minimum-jerk profile, over
    #: this long or longer where half the joints' velocity and acceleration limits need it
    #: (targets.RevisionSmoother.join). 0: jump onto the curve (the safety filter spreads the jump)
    stream_join_s: float = 0.5
    #: the playback clock never runs more frames past the newest frame than the buffer
    #: extrapolates (and not past the first frame alone): a stalled stream stops the motion
    #: instead of the clock running on and the motion skipping ahead when the frames come
    #: (PlaybackPolicy.run_ahead). False: the clock runs on (as before)
    playback_waits: bool = True
    min_ramp: float = 1.0  #: shortest start / stop ramp
    max_duration: float | None = None  #: stop after this long streaming (None: until the stream ends)
    temperature_warn: float = 65.0  #: degrade (slow down) above this
    temperature_stop: float = 75.0  #: ramp out and stop above this
    voltage_min: float = 9.5
    voltage_max: float = 16.0
    degrade_factor: float = 0.5  #: velocity-limit scale while degraded
    handle_signals: bool = True  #: SIGINT / SIGTERM → e-stop (main thread only)
    gc_in_slack: bool = True  #: freeze the heap, collect young objects only in a tick's slack (realtime.LoopGc)
    switch_interval_s: float = 0.0005  #: GIL switch interval while running (the default 5 ms exceeds a 250 Hz period)
    realtime_priority: int = 0  #: SCHED_FIFO priority of the loop thread (1-99; needs privileges); 0: normal
    #: "clock": frame k is played at its time on the playback clock (live streams: a late tick
    #: skips ahead, the motion keeps to the wall clock); "ticks": one frame period per executed
    #: tick from the first frame on, so every frame of a recorded stream is played whatever the
    #: load (a late or skipped tick delays the rest instead of dropping frames; ``replay``)
    pace: str = "clock"
    #: split-phase bus cycle where the transport offers one (``pipeline(True)``, the Dynamixel
    #: transport): a tick's write also sends the position read and the next tick takes its
    #: reply, so no tick waits for the bus; measured positions are then one tick old
    split_phase_bus: bool = True
    #: balance stabilizer (sim.stabilizer) for a free-standing robot whose transport gives IMU
    #: readings (JointState.imu); it acts only where the loop is given the robot's BalanceModel
    stabilizer: bool = True
    #: sim.stabilizer.StabilizerGains overriding the robot-scaled defaults (None: the defaults)
    stabilizer_gains: object = None

    def __post_init__(self) -> None:
        for name in ("stop_policy", "estop_policy"):
            if getattr(self, name) not in STOP_POLICIES:
                raise BridgeError(f"loop config: {name} must be one of {STOP_POLICIES}, got {getattr(self, name)!r}")
        if not self.rate_hz > 0:
            raise BridgeError(f"loop config: rate_hz must be > 0, got {self.rate_hz}")
        if self.pace not in ("clock", "ticks"):
            raise BridgeError(f"loop config: pace must be 'clock' or 'ticks', got {self.pace!r}")
        if not self.playback_margin >= 0:
            raise BridgeError(f"loop config: playback_margin must be >= 0 s, got {self.playback_margin}")
        if not 0 < self.playback_quantile <= 1:
            raise BridgeError(f"loop config: playback_quantile must be in (0, 1], got {self.playback_quantile}")
        if not 0 <= self.revision_smoothing < float("inf"):
            raise BridgeError(
                f"loop config: revision_smoothing must be >= 0 rad/s (0: off), got {self.revision_smoothing}"
            )
        join = self.stream_join_s
        if isinstance(join, bool) or not isinstance(join, (int, float)) or not 0 <= join < float("inf"):
            raise BridgeError(f"loop config: stream_join_s must be a number >= 0 s (0: no blend), got {join!r}")
        if not isinstance(self.playback_waits, bool):
            raise BridgeError(f"loop config: playback_waits must be true or false, got {self.playback_waits!r}")
        if not 0 <= self.realtime_priority <= 99:
            raise BridgeError(
                f"loop config: realtime_priority must be 0 (normal scheduling) or a SCHED_FIFO "
                f"priority 1-99, got {self.realtime_priority} (CLI: --realtime-priority)"
            )


@dataclass
class RunSummary:
    ticks: int = 0
    deadline_misses: int = 0
    late_ticks: int = 0
    interventions: int = 0  #: ticks on which the safety filter changed something
    faults: int = 0  #: OR of every Fault seen
    end_state: str = ""
    reason: str = ""
    frames_played: int = 0
    e2e_latency: list = field(default_factory=list)  #: seconds, one per played target frame
    #: the stop was forced by a fault or a watchdog (overheat, voltage, a servo's hardware error,
    #: a failed generator, no frames), not the motion's end, a requested stop or --max-duration
    fault_stop: bool = False

    @property
    def ok(self) -> bool:
        """The run ended normally: stopped (not e-stopped) for a normal reason. The commands'
        exit code is 0 when this holds, 1 otherwise (README: exit codes)."""
        return self.end_state == State.STOPPED.name and not self.fault_stop

    def latency_percentiles(self) -> dict:
        if not self.e2e_latency:
            return {}
        arr = np.asarray(self.e2e_latency)
        return {"p50": float(np.percentile(arr, 50)), "p99": float(np.percentile(arr, 99)), "max": float(arr.max())}


class TickPlayback:
    """Motion time advanced by one control period per call (one call per executed tick), from
    the first frame's time: LoopConfig ``pace="ticks"``. Same interface as PlaybackClock."""

    def __init__(self, fps: float, first_index: int, dt: float):
        self.t0 = first_index / float(fps)
        self.dt = float(dt)
        self.ticks = 0  #: motion time t0 + ticks * dt at the next call
        self.stalled = 0.0  #: never stops for a late frame (PlaybackClock.stalled)

    def arrived(self, newest_index: int, now: float, timed: bool = True) -> None:
        pass

    def motion_time(self, now: float) -> float:
        t = self.t0 + self.ticks * self.dt + 1e-9  # a hair past the frame: exact frame, not its predecessor's end
        self.ticks += 1
        return t


class _Sent(NamedTuple):
    """One tick's output: the target before the stabilizer, its correction (None: none), the
    command written, the safety filter's flags, the target frame used (None: none) and the
    tick's compute time (s)."""

    target: np.ndarray
    correction: np.ndarray | None
    command: np.ndarray
    flags: np.ndarray
    used: object
    compute: float


@dataclass
class _Stream:
    """The streaming state the loop carries between ticks: the buffer's ``curve`` (revisions
    smoothed), the ``playback`` clock (frame k is played at t0 + k / fps), when the stream
    started, when a new frame last arrived and its index, when waiting began, whether the
    next target joins the curve from the held pose, and how long the clock has waited."""

    curve: RevisionSmoother
    playback: object = None
    start: float = 0.0
    last_new: float = 0.0
    last_frame_index: int = -1
    wait_since: float = 0.0
    joining: bool = False  #: the next streamed target starts a blend from the held pose
    stalled: float = 0.0  #: the playback clock's stalled seconds at the last tick
    wait_began: float | None = None  #: its stalled seconds when the current wait began (None: not waiting)


class ControlLoop:
    """Drive ``transport`` from ``targets`` at ``config.rate_hz`` within ``limits``."""

    def __init__(
        self,
        transport,
        limits: JointLimits,
        targets: TargetBuffer,
        config: LoopConfig,
        telemetry: TelemetryWriter | None = None,
        on_status=None,
        balance=None,
    ):
        """``balance``: the robot's :class:`sim.stabilizer.BalanceModel` (None: no stabilizer,
        e.g. a fixed-base robot); the stabilizer runs when ``config.stabilizer`` is on and the
        transport's readings carry an IMU sample."""
        if tuple(transport.joint_names) != tuple(limits.names):
            raise BridgeError(
                f"control loop: transport joints {tuple(transport.joint_names)} differ from the limits' "
                f"joints {tuple(limits.names)}; both must come from the same robot config"
            )
        self.transport = transport
        self.limits = limits
        self.targets = targets
        self.config = config
        self.telemetry = telemetry
        self.on_status = on_status
        self.dt = 1.0 / config.rate_hz
        self.safety = SafetyFilter(limits, self.dt)
        self.state = State.STARTING
        self.ready = threading.Event()  #: set once the robot is at its rest pose, streaming may start
        self.summary = RunSummary()
        self._estop_reason: str | None = None
        self._stop_reason: str | None = None
        self._active = False
        self._faults = Fault.NONE
        self._degraded = False
        self._ramp_out: list[np.ndarray] | None = None  # the stop ramp, built when the stop begins
        self._settle_ticks = 0
        self._last_used: int | None = None  # index of the last target frame played
        self._clock: FixedRateClock | None = None
        self._realtime = ExitStack()  # GC, GIL and scheduling settings while ticking; closed by run()
        self.gc: LoopGc | None = None
        #: the live input's counters (sources.udp.UdpStats) when there is one: the status line shows its drops
        self.source_stats = None
        self.stabilizer = None
        if balance is not None and config.stabilizer:
            from sim.stabilizer import Stabilizer

            self.stabilizer = Stabilizer(balance.with_gains(config.stabilizer_gains))
        self._stabilizing = False  #: the stabilizer ran this run (an IMU was read)

    @property
    def deadline_misses(self) -> int:
        """Ticks skipped so far because the loop was more than a period late."""
        return 0 if self._clock is None else self._clock.missed

    # -- external requests (thread-safe: they only set flags) --------------
    def estop(self, reason: str = "e-stop") -> None:
        if self._estop_reason is None:
            self._estop_reason = reason

    def request_stop(self, reason: str = "stop requested") -> None:
        if self._stop_reason is None:
            self._stop_reason = reason

    # -- the run ------------------------------------------------------------
    def run(self) -> RunSummary:
        restore = self._install_signal_handlers()
        atexit.register(self._atexit)
        self._active = True
        try:
            self.transport.open()  # a port that cannot be opened is bad input: it propagates (exit 2)
            try:
                self._main()
            except (BridgeError, OSError) as exc:
                # the bus failed while the robot was under control (no reply, CRC errors, a
                # servo or the port gone): a fault, ended in the e-stop policy and reported in
                # the summary, not an exception. A signal that came first stays the reason: the
                # failed read was only its echo (e.g. a bus emulator hit by the same Ctrl-C).
                self._faults |= Fault.BUS_ERROR
                self.summary.fault_stop = True
                self._event("bus_error", error=str(exc), after_estop=self._estop_reason is not None)
                what = "bus error" if isinstance(exc, BridgeError) else "I/O error"
                self._emergency(self._estop_reason or f"{what}: {exc}")
        except BaseException as exc:
            self._emergency(f"{type(exc).__name__}: {exc}")
            raise
        finally:
            self._active = False
            self._realtime.close()
            try:
                self.transport.close()
            finally:
                atexit.unregister(self._atexit)
                restore()
                self.summary.deadline_misses = self.deadline_misses
                self.summary.late_ticks = 0 if self._clock is None else self._clock.late
                self.summary.end_state = self.state.name
                self.summary.faults = int(self._faults)
                if self.gc is not None:
                    self._event("gc", **self.gc.stats.__dict__)
                if self.telemetry is not None:
                    self.telemetry.event(
                        "end",
                        state=self.state.name,
                        reason=self.summary.reason,
                        summary={k: v for k, v in self.summary.__dict__.items() if k != "e2e_latency"},
                    )
                    self.telemetry.close()
        return self.summary

    def _main(self) -> None:
        start = self._start_up()
        ramp = list(
            min_jerk(
                start, self._rest, min_jerk_duration(start, self._rest, self.limits, self.config.min_ramp), self.dt
            )
        )
        stream = _Stream(RevisionSmoother(self.targets, self.config.revision_smoothing))
        while True:
            tick = self._clock.wait()
            faults = Fault.DEADLINE_MISS if tick.skipped else Fault.NONE
            state = self._read()
            faults |= self._check_health(state)
            if self._estop_reason is not None:
                self._emergency(self._estop_reason)
                return
            now = time.monotonic()
            ramping_out = self.state == State.RAMP_OUT  # a stop decided this tick ramps from the next one
            target, used = self._reference, None
            if self.state == State.RAMP_IN:
                target = ramp.pop(0)
                if not ramp:
                    self.state = State.WAITING
                    self.ready.set()
                    stream.wait_since = now
                    self._event("ready")
            elif self.state == State.WAITING:
                target = self._rest
                faults |= self._await_first_frame(stream, now)
            elif self.state in (State.RUNNING, State.HOLD):
                target, used, more = self._stream_target(stream, now, target, tick.index * self.dt)
                faults |= more
            if ramping_out:
                target = self._ramp_out_target()
            self._reference = target
            desired, correction = self._stabilize(target, state)
            command, flags = self.safety.step(desired)
            if ramping_out and not self._ramp_out:
                self._check_at_rest(target, desired, command)
            compute = time.monotonic() - tick.woke
            self.transport.write_goal(command)
            self._account(tick, faults, state, _Sent(target, correction, command, flags, used, compute))
            if self.state == State.STOPPED:
                self.transport.safe_stop(self.config.stop_policy)
                self._event("stopped", policy=self.config.stop_policy, reason=self.summary.reason)
                return

    def _start_up(self) -> np.ndarray:
        """From the present pose, torque on, to a started clock; returns the start pose (n,)."""
        cfg = self.config
        self._adopt_transport_limits()
        present = self._read().position
        if not np.all(np.isfinite(present)):
            raise BridgeError(f"start: could not read every joint's present position ({present}); check the bus")
        if not self.limits.contains(present, tol=0.05):
            bad = [
                n
                for n, q, lo, hi in zip(self.limits.names, present, self.limits.lower, self.limits.upper)
                if not lo - 0.05 <= q <= hi + 0.05
            ]
            self._event("start_outside_limits", joints=bad)
        start = self.safety.reset(present)
        # the filter's starting state and limits: with the targets recorded per tick they give
        # the commands the loop would have sent without its stabilizer (Telemetry.open_loop_commands)
        self._event(
            "safety_filter",
            dt=self.dt,
            start=start,
            lower=self.limits.lower,
            upper=self.limits.upper,
            max_velocity=self.limits.max_velocity,
            max_acceleration=self.limits.max_acceleration,
        )
        self.transport.write_goal(start)  # goal = present before torque on: no jump
        self.transport.set_torque(True)
        self._event("torque_on")
        if cfg.split_phase_bus and self.transport.pipeline(True):
            self._event(
                "split_phase_bus",
                measured="the reply to the previous tick's read request",
                stamp="JointState.stamp = when that request left",
            )
        self._rest = start if cfg.rest_pose is None else self.limits.clip(cfg.rest_pose)
        self._reference = start  # the last target before the stabilizer (what a hold keeps)
        if self.stabilizer is not None:
            self.stabilizer.reset()
        imu = self._last_state.imu if self._last_state is not None else None
        on = self.stabilizer is not None and imu is not None
        self._event(
            "stabilizer",
            on=on,
            why=(
                "on"
                if on
                else "turned off (--no-stabilizer)"
                if not cfg.stabilizer
                else "no balance model (fixed base, or legs not found)"
                if self.stabilizer is None
                else "the transport reads no IMU"
            ),
        )
        self._enter_realtime()
        self._clock = FixedRateClock(cfg.rate_hz)
        self._clock.start()
        self._t_start = time.monotonic()
        self.state = State.RAMP_IN
        return start

    def _await_first_frame(self, stream: _Stream, now: float) -> Fault:
        """While waiting at rest: start playing at the first target frame, or give up."""
        cfg = self.config
        first = self.targets.first()
        if self.targets.error is not None:
            self._begin_stop(f"generator failed before the first frame: {self.targets.error}", fault=True)
            return Fault.GENERATOR_ERROR
        if first is not None:
            if cfg.pace == "ticks":
                stream.playback = TickPlayback(self.targets.fps, first.index, self.dt)
            else:
                policy = PlaybackPolicy(
                    cfg.playback_margin,
                    cfg.playback_lead_frames,
                    quantile=cfg.playback_quantile,
                    fixed=not cfg.adaptive_playback,
                    run_ahead=self.targets.extrapolate if cfg.playback_waits else None,
                )
                stream.playback = PlaybackClock(self.targets.fps, first.index, now, policy)
            stream.start = stream.last_new = now
            stream.joining = True
            self.state = State.RUNNING
            self._event("streaming", first_frame=first.index)
        elif self.targets.closed or now - stream.wait_since > cfg.start_timeout:
            self._begin_stop(
                "no target frames arrived" + ("" if self.targets.closed else f" within {cfg.start_timeout:g} s"),
                fault=True,
            )
        return Fault.NONE

    def _stream_target(self, stream: _Stream, now: float, held: np.ndarray, clock: float):
        """(target, the frame used or None, faults) while streaming: the interpolated curve, a
        hold when the stream goes quiet, or the start of a stop. ``clock``: this tick's time (s,
        tick number x period), the time base of the blend onto the stream."""
        cfg = self.config
        newest = self.targets.newest()
        if newest is not None:
            # a frame without a source arrival (the return to stance after a stream) was not paced by one
            stream.playback.arrived(newest.index, now, timed=newest.source_arrival == newest.source_arrival)
        sample = stream.curve.sample(stream.playback.motion_time(now), now, clock)
        if self.targets.error is not None:
            self._begin_stop(f"generator failed: {self.targets.error}", fault=True)
            return held, None, Fault.GENERATOR_ERROR
        if sample.finished:
            self._begin_stop("the motion ended")
            if stream.joining:  # ended before the blend began: the stop ramp starts from the held pose
                return held, sample.newest, Fault.NONE
            return sample.q, sample.newest, Fault.NONE  # play the last frame, then ramp to rest
        if self._stop_reason is not None:
            self._begin_stop(self._stop_reason)
            return held, None, Fault.NONE
        if cfg.max_duration is not None and now - stream.start >= cfg.max_duration:
            self._begin_stop(f"max duration {cfg.max_duration:g} s reached")
            return held, None, Fault.NONE
        if (newest is not None and newest.index != stream.last_frame_index) or self.targets.closed:
            # a closed stream (every frame is in: a recording, or a source that ended) cannot go
            # quiet; it plays to its end (sample.finished)
            stream.last_frame_index, stream.last_new = (newest.index if newest is not None else -1), now
        quiet = now - stream.last_new
        faults = (Fault.STARVED if sample.starved else Fault.NONE) | (
            Fault.EXTRAPOLATED if sample.extrapolated else Fault.NONE
        )
        if quiet > cfg.rest_after:
            self._begin_stop(f"no new frames for {quiet:.1f} s", fault=True)
            return held, None, faults | Fault.ACTOR_TIMEOUT
        if quiet > cfg.actor_timeout or sample.q is None:
            if self.state != State.HOLD:
                self._event("hold", quiet_s=round(quiet, 3))
            self.state = State.HOLD
            stream.curve.reset()  # the command holds on its own: no offset to carry on resuming
            return held, None, faults | (Fault.ACTOR_TIMEOUT if quiet > cfg.actor_timeout else Fault.NONE)
        if self.state == State.HOLD:
            self._event("resume")
            stream.joining = True
        self.state = State.RUNNING
        if not np.all(np.isfinite(sample.q)):
            faults |= Fault.NONFINITE
            return sample.q, sample.newest, faults
        self._note_wait(stream, now)
        if stream.joining:
            stream.joining = False
            return self._join(stream, held, sample.q, clock), sample.newest, faults
        return sample.q, sample.newest, faults

    def _join(self, stream: _Stream, held: np.ndarray, q: np.ndarray, clock: float) -> np.ndarray:
        """Start following the curve (at ``q`` now) from the ``held`` pose: the offset between
        them fades over a minimum-jerk blend (LoopConfig.stream_join_s); returns this tick's
        target, ``held`` itself."""
        offset = np.asarray(held, float) - q
        if self.config.stream_join_s <= 0 or not np.any(offset):
            return q
        lim = self.safety.limits
        half = JointLimits(lim.names, lim.lower, lim.upper, 0.5 * lim.max_velocity, 0.5 * lim.max_acceleration)
        duration = min_jerk_duration(np.zeros_like(offset), offset, half, self.config.stream_join_s)
        stream.curve.join(offset, duration, clock)
        self._event("join", seconds=round(duration, 3), largest_offset=float(np.max(np.abs(offset))))
        return q + offset

    def _note_wait(self, stream: _Stream, now: float) -> None:
        """A ``playback_waited`` event when the playback clock resumes after waiting for a
        late frame (PlaybackPolicy.run_ahead)."""
        stalled = stream.playback.stalled
        if stalled > stream.stalled and stream.wait_began is None:
            stream.wait_began = stream.stalled
        elif stalled == stream.stalled and stream.wait_began is not None:
            self._event("playback_waited", seconds=round(stalled - stream.wait_began, 3))
            stream.wait_began = None
        stream.stalled = stalled

    def _ramp_out_target(self) -> np.ndarray:
        """The stop ramp's next target (built on its first tick), then the rest pose."""
        if self._ramp_out is None:
            # from the last reference when stabilizing (the command holds a correction the
            # stabilizer keeps adding): no jump by the correction at the ramp's start
            cur = self._reference if self._stabilizing else self.safety.last_command
            self._ramp_out = list(
                min_jerk(
                    cur, self._rest, min_jerk_duration(cur, self._rest, self.limits, self.config.min_ramp), self.dt
                )
            )
            self._settle_ticks = 0
        if self._ramp_out:
            return self._ramp_out.pop(0)
        self._settle_ticks += 1  # ramp done; the filter may still be braking a joint that was moving fast
        return self._rest

    def _stabilize(self, target: np.ndarray, state):
        """(the target with the balance stabilizer's correction, the correction or None)."""
        if self.stabilizer is None or state.imu is None or not np.all(np.isfinite(target)):
            return target, None
        desired = self.stabilizer.step(target, state.position, state.imu, self.dt)
        self._stabilizing = True
        return desired, desired - target

    def _check_at_rest(self, target: np.ndarray, desired: np.ndarray, command: np.ndarray) -> None:
        """After the stop ramp: stopped once the reference has arrived and the filter passes
        the command unchanged (or after 2 s of braking)."""
        if np.max(np.abs(target - self._rest)) < 1e-6 and np.max(np.abs(command - desired)) < 1e-6:
            self.state = State.STOPPED
        elif self._settle_ticks * self.dt > 2.0:
            self._event("rest_not_reached", error=float(np.max(np.abs(command - self._rest))))
            self.state = State.STOPPED

    def _account(self, tick, faults: Fault, state, sent: _Sent) -> None:
        """The tick's counters, latency, telemetry record, status callback and GC slack."""
        target, correction, command, flags, used, compute = sent
        write_time = time.monotonic()
        e2e = float("nan")
        if used is not None and used.index != self._last_used:
            self._last_used = used.index
            self.summary.frames_played += 1
            e2e = write_time - used.source_arrival
            if e2e == e2e:  # NaN: a frame no actor frame completed (the return to stance after a stream)
                self.summary.e2e_latency.append(e2e)
        if flags.any():
            self.summary.interventions += 1
        if self._degraded:
            faults |= Fault.DEGRADED
        self._faults |= faults
        self.summary.ticks += 1
        if self.telemetry is not None:
            imu = state.imu
            self.telemetry.record(
                t=tick.woke - self._t_start,
                tick=tick.index,
                lateness=tick.lateness,
                compute=compute,
                target=target,
                command=command,
                correction=0.0 if correction is None else correction,
                measured=state.position,
                imu_gyro=np.nan if imu is None else imu.gyro,
                imu_accel=np.nan if imu is None else imu.accel,
                imu_quat=np.nan if imu is None else imu.quat,
                intervention=flags,
                state=int(self.state),
                faults=int(faults),
                actor_frame=-1 if used is None else used.actor_frame,
                generator_latency=np.nan if used is None else used.generator_latency,
                retarget_latency=np.nan if used is None else used.retarget_latency,
                end_to_end=e2e,
            )
        if self.on_status is not None:
            self.on_status(self, tick, faults)
        if self.gc is not None:
            self.gc.collect_in_slack(tick.due + self.dt - time.monotonic())

    # -- helpers --------------------------------------------------------------
    def _enter_realtime(self) -> None:
        """GC in the ticks' slack, a short GIL switch interval and (if configured and
        permitted) SCHED_FIFO for this thread, until run() ends (ros_free_bridge.control.realtime)."""
        cfg = self.config
        if cfg.gc_in_slack:
            self.gc = self._realtime.enter_context(LoopGc())
        if cfg.switch_interval_s > 0:
            self._realtime.enter_context(switch_interval(cfg.switch_interval_s))
        note = self._realtime.enter_context(realtime_priority(cfg.realtime_priority))
        self._event("realtime", scheduling=note, gc_in_slack=cfg.gc_in_slack, switch_interval_s=cfg.switch_interval_s)

    def _adopt_transport_limits(self) -> None:
        found = self.transport.position_limits()
        if found is None:
            return
        lo = np.maximum(self.limits.lower, found[0])
        hi = np.minimum(self.limits.upper, found[1])
        if np.array_equal(lo, self.limits.lower) and np.array_equal(hi, self.limits.upper):
            return
        narrowed = [n for n, a, b in zip(self.limits.names, lo != self.limits.lower, hi != self.limits.upper) if a or b]
        self.limits = JointLimits(self.limits.names, lo, hi, self.limits.max_velocity, self.limits.max_acceleration)
        self.safety = SafetyFilter(self.limits, self.dt)
        self._event("limits_narrowed", joints=narrowed)

    def _begin_stop(self, reason: str, fault: bool = False) -> None:
        """Ramp to rest and stop; ``fault``: the stop is forced by a fault or a watchdog."""
        if self.state in (State.RAMP_OUT, State.STOPPED, State.ESTOP):
            return
        self.summary.reason = reason
        self.summary.fault_stop = fault
        self._event("stopping", reason=reason)
        self._ramp_out = None
        self.state = State.RAMP_OUT

    _last_state = None

    def _read(self):
        try:
            self._last_state = self.transport.read_state()
            return self._last_state
        except BridgeError:
            self._faults |= Fault.BUS_ERROR
            raise

    def _check_health(self, state) -> Fault:
        cfg = self.config
        faults = Fault.NONE
        temps = np.asarray(state.temperature, float)
        volts = np.asarray(state.voltage, float)
        if state.errors:
            faults |= Fault.HARDWARE_ERROR
            self._begin_stop("hardware error: " + ", ".join(f"{j}: {e}" for j, e in state.errors.items()), fault=True)
        if np.any(temps >= cfg.temperature_stop):
            j = self.limits.names[int(np.nanargmax(temps))]
            faults |= Fault.OVERHEAT
            self._begin_stop(
                f"{j} at {np.nanmax(temps):.0f} °C (stop threshold {cfg.temperature_stop:g} °C)", fault=True
            )
        elif np.any(temps >= cfg.temperature_warn) and not self._degraded:
            j = self.limits.names[int(np.nanargmax(temps))]
            self._degraded = True
            slow = JointLimits(
                self.limits.names,
                self.limits.lower,
                self.limits.upper,
                self.limits.max_velocity * cfg.degrade_factor,
                self.limits.max_acceleration,
            )
            self.safety.limits = slow
            self._event(
                "degraded",
                joint=j,
                temperature=float(np.nanmax(temps)),
                factor=cfg.degrade_factor,
                record=self.summary.ticks,  # the first tick record filtered with the slower limits
                max_velocity=slow.max_velocity,
            )
        finite_v = volts[np.isfinite(volts)]
        if finite_v.size and (finite_v.min() < cfg.voltage_min or finite_v.max() > cfg.voltage_max):
            faults |= Fault.VOLTAGE
            self._begin_stop(
                f"supply voltage {finite_v.min():.1f}-{finite_v.max():.1f} V outside "
                f"{cfg.voltage_min:g}-{cfg.voltage_max:g} V",
                fault=True,
            )
        return faults

    def _emergency(self, reason: str) -> None:
        """Apply the e-stop policy now; never raises (it runs on the error path)."""
        if self.state == State.ESTOP:
            return
        self.state = State.ESTOP
        self.summary.fault_stop = True
        self._faults |= Fault.ESTOP
        self.summary.reason = reason
        try:
            self.transport.safe_stop(self.config.estop_policy)
        except Exception as exc:  # noqa: BLE001 - the stop itself failed: report, keep going
            self._event("estop_failed", error=repr(exc))
        self._event("estop", reason=reason, policy=self.config.estop_policy)

    def _event(self, kind: str, **info) -> None:
        if self.telemetry is not None:
            self.telemetry.event(kind, **info)

    def _atexit(self) -> None:
        if self._active:
            self._emergency("process exit while running")
            try:
                self.transport.close()
            except Exception:  # noqa: BLE001
                pass

    def _install_signal_handlers(self):
        if not self.config.handle_signals or threading.current_thread() is not threading.main_thread():
            return lambda: None
        previous = {}

        def handler(signum, _frame):
            self.estop(f"signal {signal.Signals(signum).name}")

        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, handler)

        def restore():
            for sig, old in previous.items():
                signal.signal(sig, old)

        return restore
