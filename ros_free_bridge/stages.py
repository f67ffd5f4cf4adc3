"""The slow stages between the actor and the control loop, and the thread that runs them.

- :class:`ReactorStage`: DualFlow's reactive mode over world positions. Actor frames
  (22, 3) m in, reactor frames (22, 3) m + foot contacts out, through
  :class:`dualflow.streaming.ReactiveStreamer`. This is the one place outside
  ``dualflow`` that imports torch (DESIGN.md).
- :class:`RetargetStage`: :class:`retarget.streaming.StreamingRetargeter`, one frame at a
  time, robot joint angles in the transport's joint order out.
- :class:`PartnerCore`: both stages behind one call, ``feed(new actor frames) -> targets``,
  with the real-time policy: a backlog of due partner frames is generated in wider windows
  (one window per call, so the lag is checked between windows); if it still grows beyond
  ``max_lag`` frames (the generator fell behind the actor's clock), the stale work is
  dropped, the stream restarts at the newest actor frames and the skipped frames hold the
  last pose; a ``generator_behind`` event says so. Latency stays bounded instead of growing.
- :class:`PartnerPipeline`: a thread that polls the actor source, runs a
  :class:`PartnerCore` and pushes :class:`~ros_free_bridge.control.targets.TargetFrame` s to the
  control loop's buffer. It never touches the transport, so a slow or failed stage can only
  starve the loop (which then holds and stops, see :mod:`ros_free_bridge.control.loop`), never
  block it. :mod:`ros_free_bridge.generator_process` runs the same core in its own process
  (the default for generated partners: torch's Python then never competes with the
  control loop for the GIL).

Delay: reactor frame i needs actor rows up to i + L. An actor frame's 262-d feature row
needs the next frame (its velocity); by default the newest row is encoded with a predicted
next frame and revised later (``ReactorStage(predict_next=True)``), so reactor frame i is
produced when actor frame c(i) = i + L arrives (i + L + 1 with ``predict_next=False``),
plus the streamer's hop - 1 frames and the compute time. Its target is stamped with that
frame's arrival (:class:`PartnerCore`).
"""

from __future__ import annotations

import sys
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from ros_free_bridge.errors import BridgeError
from ros_free_bridge.idle_slots import IdleSlots
from ros_free_bridge.control.targets import TargetBuffer, TargetFrame


@dataclass(frozen=True)
class ReactorFrame:
    """One generated reactor pose: positions (22, 3) m (world, Z up), contacts (4,) bool."""

    index: int
    positions: np.ndarray
    contacts: np.ndarray
    source_arrival: float  #: monotonic arrival of the actor frame whose push produced it
    actor_frame: int
    latency: float  #: seconds the generator spent on the push that produced it


@dataclass(frozen=True)
class _Frame:
    index: int
    positions: np.ndarray
    arrival: float


class ReactorStage:
    """Generate the partner (reactor) from actor world positions, causally, frame by frame.

    checkpoint: a checkpoint directory (None: the bundled one). text: a cue for the whole run.
    music: an audio file (or a Jukebox .npy) whose features are aligned with the actor clock
    (actor frame k ↔ music frame k); it loops when the run is longer than the track.
    ``music_frames``: how many frames the run may last (the track is tiled to cover them).

    ``predict_next`` (default): an actor frame's 262-d row needs the next frame (its velocity
    p[n+1] - p[n] and the foot contacts from it), which would add one frame (33 ms) to the
    delay. Instead the newest frame's row is encoded with the constant-velocity prediction
    p^[n+1] = 2 p[n] - p[n-1] and pushed as provisional; when p[n+1] arrives the row is
    revised (``ReactiveStreamer.push(revise=1)``). Partner frame i then needs actor frames up
    to i + L only (``frames_ahead`` = L); False: up to i + L + 1, every row exact.

    The streamer runs under ``torch.inference_mode`` (no autograd bookkeeping: ~10 % less
    per-operation overhead in the one-row passes); its tensors are only read outside it.
    """

    def __init__(self, fps: float = 30.0, checkpoint=None, stream_config=None, text: str | None = None,
                 music=None, music_frames: int = 30 * 60 * 30, threads: int = 1, predict_next: bool = True,
                 clean: bool = True):
        import torch

        from dualflow.checkpoint import BUNDLED_CHECKPOINT, load_checkpoint
        from dualflow.streaming import ReactiveStreamer, StreamConfig

        torch.set_num_threads(max(1, int(threads)))  # leave a core to the control loop
        ckpt = load_checkpoint(checkpoint or BUNDLED_CHECKPOINT)
        self.stats = ckpt.stats
        self.model = ckpt.build_model("cpu")
        self.fps = float(fps)
        self._cond = self._conditions(ckpt, text, music, music_frames) if (text or music is not None) else None
        self._stream_config = stream_config or StreamConfig()
        self._streamer_type = ReactiveStreamer
        self.streamer = ReactiveStreamer(self.model, self._stream_config, self._cond)
        self.look_ahead = self.streamer.look_ahead
        self.predict_next = bool(predict_next)
        #: partner frame i depends on actor frames up to i + frames_ahead
        self.frames_ahead = self.look_ahead + (0 if self.predict_next else 1)
        #: frames between actor frame i + frames_ahead and partner frame i at most (the hop)
        self.delay_frames = self.streamer.delay_frames + (0 if self.predict_next else 1)
        self._canonical = None
        # actor frames not yet encoded exactly, after the last exactly encoded one; with
        # predict_next the first may be pushed already as a provisional row (_provisional)
        self._pending: list[np.ndarray] = []
        self._provisional = False
        self._before: np.ndarray | None = None  # the frame before _pending[0] (for the prediction)
        self._last_in = (0.0, -1)  # arrival and index of the newest actor frame pushed
        self._n_out = 0
        self._torch = torch
        # clean: each partner frame through dualflow.body.BodyCleaner (bone lengths, planted feet, jitter)
        from dualflow.body import BodyCleaner

        self.cleaner = BodyCleaner(self.fps) if clean else None

    @staticmethod
    def _conditions(ckpt, text, music, music_frames: int):
        import torch

        from dualflow.conditioning import ConditionBuilder
        from dualflow.model import Conditions

        builder = ConditionBuilder.from_checkpoint(ckpt)
        cond = Conditions()
        if text:
            if builder.text_encoder is None:
                raise BridgeError(f"{ckpt.path}: this model was trained without text; drop --text or use another model")
            cond.text = builder.text_condition(text)
        if music is not None:
            if builder.music_kind is None:
                raise BridgeError(f"{ckpt.path}: this model was trained without music; drop --music or use another model")
            track = builder.music_array(music, None)
            reps = int(np.ceil(music_frames / len(track)))
            cond.music = torch.from_numpy(np.tile(track, (reps, 1))[:music_frames])[None]
        return cond

    def push(self, actor_positions: np.ndarray, arrival: float, actor_index: int) -> list[ReactorFrame]:
        """Add one actor frame (22, 3) m; returns the partner frames this completed (often none).

        Feature rows are encoded in chunks of the streamer's hop (the inverse kinematics of
        the 262-d rotation part costs mostly per call, not per frame); the streamer would not
        generate before a hop's worth of rows anyway, so chunking adds no delay.
        """
        return self.push_many([_Frame(actor_index, actor_positions, arrival)])

    def push_many(self, frames, max_windows: int | None = None) -> list[ReactorFrame]:
        """Add several actor frames at once (objects with ``positions`` (22, 3) m, ``arrival``,
        ``index``; may be empty); one feature encoding, and the streamer generates the backlog
        in windows of up to ``max_new`` frames (a window costs about the same for 1 or
        ``max_new`` new frames). ``max_windows``: generate at most this many windows now; call
        again (with no frames) while ``backlog``."""
        for f in frames:
            pos = np.asarray(f.positions, dtype=np.float64)
            if self._canonical is None:
                from dualflow.motion import Motion
                from dualflow.motion.features import canonical_frame

                self._canonical = canonical_frame(Motion(pos[None], self.fps))
            self._pending.append(pos)
            self._last_in = (f.arrival, f.index)
        hop = self.streamer.config.hop
        revise = 0
        if self._rows_ready() - self.streamer.n_actor >= hop or (
                self.predict_next and frames and self._rows_ready() - self.look_ahead - self._n_emitted >= hop):
            rows, revise = self._encode_pending()
        elif self.streamer.pending >= hop:
            rows = np.zeros((0, self.streamer.dim), np.float32)
        else:
            return []
        t0 = time.perf_counter()
        with self._torch.inference_mode():
            out = self.streamer.push(rows, max_windows, revise=revise)
        return self._decode(out, *self._last_in, time.perf_counter() - t0)

    @property
    def _n_emitted(self) -> int:
        return self.streamer.emitted.shape[0]

    def _rows_ready(self) -> int:
        """Actor rows the streamer would hold if every pending frame were encoded now."""
        provisional = 1 if self._provisional else 0
        if self.predict_next:
            return self.streamer.n_actor - provisional + len(self._pending)
        return self.streamer.n_actor + max(0, len(self._pending) - 1)

    @property
    def backlog(self) -> bool:
        """True when a window could be generated now (at least ``hop`` frames are due)."""
        return self.streamer.pending >= self.streamer.config.hop

    @property
    def has_catch_up(self) -> bool:
        """Incremental streaming: catch-up work for idle time is waiting (``prepare``)."""
        return self.streamer.has_catch_up if self.streamer.config.incremental else False

    def idle_jobs(self) -> list[str]:
        """The kinds of catch-up work due now, first to be done first (``ReactiveStreamer.idle_jobs``)."""
        return self.streamer.idle_jobs()

    @property
    def urgent_jobs(self) -> tuple[str, ...]:
        """The kinds of catch-up work to do in any idle gap, fitting or not (``ReactiveStreamer.URGENT_JOBS``)."""
        return self.streamer.URGENT_JOBS

    def prepare(self, max_passes: int = 1, kinds=None) -> None:
        """Do up to ``max_passes`` pieces of the streamer's catch-up work (idle time), of
        ``kinds`` only if given."""
        with self._torch.inference_mode():
            self.streamer.prepare(max_passes, kinds)

    @property
    def next_index(self) -> int:
        """Index of the next partner frame this stage will emit (= its actor frame's index)."""
        return self._n_out

    def restart(self, first_index: int) -> None:
        """Drop the stream and start a new one whose frame 0 is actor frame ``first_index``.

        For catching up with the actor's clock: the frames before ``first_index`` are never
        generated. The canonical frame and the conditions stay (music is per actor frame, so
        the new stream's music starts at ``first_index``); the new stream has no partner
        context, like the start of a run.
        """
        cond = self._cond
        if cond is not None and cond.music is not None:
            from dataclasses import replace

            cond = replace(cond, music=cond.music[:, first_index:])
        self.streamer = self._streamer_type(self.model, self._stream_config, cond)
        self._pending, self._provisional, self._before = [], False, None
        self._n_out = int(first_index)

    def flush(self, arrival: float, actor_index: int, max_windows: int | None = None) -> list[ReactorFrame]:
        """End of the actor stream: generate the remaining partner frames (``max_windows`` at a
        time: call again until it returns nothing)."""
        if self._rows_ready() > self.streamer.n_actor:
            rows, revise = self._encode_pending()
            with self._torch.inference_mode():
                self.streamer.push(rows, max_windows=0, revise=revise)
        t0 = time.perf_counter()
        with self._torch.inference_mode():
            out = self.streamer.flush(max_windows)
        return self._decode(out, arrival, actor_index, time.perf_counter() - t0)

    def _encode_pending(self) -> tuple[np.ndarray, int]:
        """(normalised rows, how many of them revise provisional rows already pushed).

        Exact mode: rows for every pending frame but the last (a row needs the next frame's
        position). predict_next: rows for every pending frame, the last one provisional, encoded
        with p^[n+1] = 2 p[n] - p[n-1] (p[n] itself when no earlier frame exists)."""
        from dualflow.motion import Motion
        from dualflow.motion.features import encode_person

        frames = self._pending
        revise = 0
        if self.predict_next:
            prev = frames[-2] if len(frames) > 1 else self._before
            frames = frames + [2.0 * frames[-1] - prev if prev is not None else frames[-1]]
            revise = 1 if self._provisional else 0
        rows = encode_person(Motion(np.stack(frames), self.fps), self._canonical)
        if len(self._pending) > 1:
            self._before = self._pending[-2]
        self._pending = self._pending[-1:]
        self._provisional = self.predict_next
        return self.stats.normalize(rows), revise

    def _decode(self, rows, arrival: float, actor_index: int, latency: float) -> list[ReactorFrame]:
        from dualflow.motion.features import decode_person

        rows = rows.detach().cpu().numpy()
        if rows.shape[0] == 0:
            return []
        motion = decode_person(self.stats.denormalize(rows), self.fps, self._canonical)
        frames = []
        for k in range(rows.shape[0]):
            pos, contacts = motion.positions[k], motion.contacts[k]
            if self.cleaner is not None:
                pos, contacts = self.cleaner.step(pos)
            frames.append(ReactorFrame(self._n_out, pos, contacts, arrival, actor_index, latency))
            self._n_out += 1
        return frames


class RetargetStage:
    """Reactor world positions → robot joint angles (n,) rad in ``joint_names`` order."""

    def __init__(self, robot, fps: float, joint_names=None):
        from retarget.streaming import StreamingConfig, StreamingRetargeter

        self.robot = robot
        # its default keypoint scaler uses REST_POSE proportions: a live stream has no clip to measure;
        # a free-standing robot keeps its feet planted and its CoM over them (fixed bases ignore it)
        self.streamer = StreamingRetargeter(robot, fps, StreamingConfig(balance=True))
        names = tuple(joint_names) if joint_names is not None else tuple(robot.joint_names)
        missing = [n for n in names if n not in robot.joint_names]
        if missing:
            raise BridgeError(f"retarget stage: the robot model has no joints {missing}; the hardware config and the MJCF disagree")
        self.joint_names = names
        self._index = np.array([robot.joint_names.index(n) for n in names])

    def step(self, positions: np.ndarray, contacts: np.ndarray | None = None) -> np.ndarray:
        from retarget.targets import side_contacts

        side = (False, False) if contacts is None else tuple(bool(c) for c in side_contacts(np.asarray(contacts)[None])[0])
        q, _, _ = self.streamer.split(self.streamer.step_human(positions, side))
        return q[self._index]

@dataclass(frozen=True)
class PartnerTarget:
    """One robot target from :class:`PartnerCore`: q (n,) rad, the partner pose (22, 3) m it
    came from, and its timing. ``held``: a stand-in that repeats the previous pose for a frame
    the generator skipped to catch up (``gen_latency`` is NaN then)."""

    index: int
    q: np.ndarray
    positions: np.ndarray
    arrival: float
    actor_frame: int
    gen_latency: float
    rt_latency: float
    held: bool = False


class PartnerCore:
    """Actor frames in, robot targets out, keeping up with the actor's clock.

    ``feed(frames)`` takes every actor frame that arrived since the last call (objects with
    ``index``, ``positions`` (22, 3) m, ``arrival``) and returns the targets they completed
    and any events. ``reactor`` None: the robot retargets the actor itself (imitation).

    Timing stamp: partner frame i depends on actor frames up to c(i) = i + A, A =
    ``reactor.frames_ahead`` (the look-ahead L, + 1 when the last feature row waits for the
    next frame), so its target carries ``arrival`` = the arrival of actor frame c(i) and
    ``actor_frame`` = c(i). The control loop's end-to-end latency (bus write minus that
    arrival) is then the time the bridge adds on top of the look-ahead: batching (up to
    hop - 1 frames), compute, queueing and the loop's playback delay. Actor frame i to partner
    frame i on the bus takes A / fps more.

    Real-time policy. When actor frame N has arrived, the partner frames due are those up to
    N - A and

        overdue = N - A + 1 - next_index   (frames whose inputs are all here but not generated yet)

    is at most ``hop`` while the generator keeps up. A backlog is worked off in wider
    windows (``push_many``: up to the streamer's ``max_new`` frames per window, for about
    the cost of one: a window's compute hardly depends on its length on a CPU). If
    ``overdue`` still exceeds ``max_lag`` frames, queueing the stale frames would only make the
    latency grow, so the stream restarts at a = N - A + 1 - hop (the newest actor frames, so one hop
    is generated at once), frames [next_index, a) repeat the last pose (the loop holds within
    its limits), and a ``generator_behind`` event reports the frames dropped. The latency is
    then bounded by the model's delay + ``max_lag`` frames + one window's compute.
    """

    def __init__(self, reactor: ReactorStage | None, retarget: RetargetStage, max_lag: int | None = None):
        self.reactor = reactor
        self.retarget = retarget
        if reactor is not None:
            hop = reactor.streamer.config.hop
            self.max_lag = max(int(max_lag) if max_lag is not None else self.default_max_lag(reactor), hop + 1)
            self._recent: deque = deque(maxlen=reactor.look_ahead + hop + 2)
        self.frames_dropped = 0
        #: catch-up passes only in the gap before the next actor frame (the frames' rate: the reactor's fps)
        self.idle_slots = IdleSlots(1.0 / (reactor.fps if reactor is not None else 30.0),
                                    urgent=reactor.urgent_jobs if reactor is not None else ())
        self._arrivals: dict[int, float] = {}  # actor index -> arrival, for frames not yet used as c(i)
        self._last_q: np.ndarray | None = None
        self._last_pos: np.ndarray | None = None
        self._last: tuple[float, int] = (0.0, -1)

    @staticmethod
    def default_max_lag(reactor: ReactorStage) -> int:
        """hop + the streamer's max_new: one wide window can still clear such a backlog."""
        return reactor.streamer.config.hop + reactor.streamer.max_new

    @property
    def delay_frames(self) -> int | None:
        return None if self.reactor is None else self.reactor.delay_frames

    @property
    def frames_ahead(self) -> int:
        """Partner frame i is complete when actor frame i + frames_ahead has arrived (0: imitation)."""
        return 0 if self.reactor is None else self.reactor.frames_ahead

    @property
    def backlog(self) -> bool:
        """True when ``feed([])`` would generate (frames are due): call it again before waiting."""
        return self.reactor is not None and self.reactor.backlog

    def feed(self, frames) -> tuple[list[PartnerTarget], list[dict]]:
        """New actor frames (may be empty) → (targets, events). Generates at most one window per
        call, so that the lag is checked against the newest input between windows."""
        if frames:
            self._last = (frames[-1].arrival, frames[-1].index)
        if self.reactor is None:
            return [self._target(f.index, f.positions, None, f.arrival, f.index, 0.0) for f in frames], []
        self._recent.extend(frames)
        for f in frames:
            self._arrivals[f.index] = f.arrival
            self.idle_slots.arrived(f.arrival)
        out, events = self._catch_up()
        if events:
            frames = [f for f in self._recent if f.index >= self.reactor.next_index]
        out += self._targets(self.reactor.push_many(frames, max_windows=1))
        return out, events

    def _catch_up(self) -> tuple[list[PartnerTarget], list[dict]]:
        """The drop-to-newest policy (class docstring): held targets and an event, or nothing."""
        r = self.reactor
        arrival, newest = self._last
        overdue = newest - r.frames_ahead + 1 - r.next_index
        restart_at = newest - r.frames_ahead + 1 - r.streamer.config.hop
        if not (overdue > self.max_lag and restart_at > r.next_index and self._recent
                and restart_at >= self._recent[0].index):
            return [], []
        skipped = restart_at - r.next_index
        held = []
        if self._last_q is not None:
            held = [PartnerTarget(k, self._last_q, self._last_pos, arrival, newest, float("nan"), 0.0, True)
                    for k in range(r.next_index, restart_at)]
        self.frames_dropped += skipped
        event = {"kind": "generator_behind", "overdue_frames": int(overdue), "dropped_frames": int(skipped),
                 "restart_frame": int(restart_at), "max_lag": self.max_lag}
        r.restart(restart_at)
        return held, [event]

    def finish(self) -> list[PartnerTarget]:
        """End of the actor stream: the remaining partner frames (none for imitation)."""
        return [t for targets, _ in self.finish_stream() for t in targets]

    def finish_stream(self):
        """End of the actor stream: yield (targets, events) batches, one window at a time (so
        the loop plays them while the rest is generated), the catch-up policy first."""
        if self.reactor is None or self._last[1] < 0:
            return
        held, events = self._catch_up()
        if events:  # the restarted stream needs its actor frames again
            self.reactor.push_many([f for f in self._recent if f.index >= self.reactor.next_index], max_windows=0)
        if held or events:
            yield held, events
        while True:
            batch = self._targets(self.reactor.flush(*self._last, max_windows=1))
            if not batch:
                return
            yield batch, []

    def _targets(self, reactor_frames) -> list[PartnerTarget]:
        out = []
        for p in reactor_frames:
            c = p.index + self.reactor.frames_ahead  # the last actor frame partner frame i depends on
            if c in self._arrivals:
                arrival, actor = self._arrivals[c], c
            else:
                # the stream's end: actor frame c never came (the look-ahead was cut at the last
                # frame); stamp the arrival it would have had on the actor's clock, so that the
                # loop's figure stays "beyond the look-ahead" for these frames too
                last_arrival, last = self._last
                arrival, actor = last_arrival + (c - last) / self.reactor.fps, c
            out.append(self._target(p.index, p.positions, p.contacts, arrival, actor, p.latency))
        if out:
            done = out[-1].index + self.reactor.frames_ahead
            for k in [k for k in self._arrivals if k < done]:
                del self._arrivals[k]
        return out

    def _idle_jobs(self) -> list[str]:
        return [] if self.reactor is None else self.reactor.idle_jobs()

    def _fitting_job(self, now: float | None) -> str | None:
        """The first due kind of catch-up work whose piece fits before the next actor frame,
        or that is urgent (the reactor's ``urgent_jobs``, given to :class:`IdleSlots`)."""
        now = time.monotonic() if now is None else now
        return next((k for k in self._idle_jobs() if self.idle_slots.fits(now, k)), None)

    def idle_ready(self, now: float | None = None) -> bool:
        """Catch-up work is due and a piece of it fits before the next actor frame
        (:class:`IdleSlots`, each kind of work timed on its own) or is urgent."""
        return self._fitting_job(now) is not None

    def idle_wait(self, now: float | None = None) -> float | None:
        """Seconds until a piece of catch-up work may start if no actor frame comes first: 0
        now, None when there is no catch-up work."""
        jobs = self._idle_jobs()
        if not jobs:
            return None
        now = time.monotonic() if now is None else now
        return min(self.idle_slots.wait(now, k) for k in jobs)

    def idle_step(self, now: float | None = None) -> None:
        """One short piece of the reactor's catch-up work (a few ms): the first due kind that
        fits before the next actor frame or is urgent, timed for that kind."""
        job = self._fitting_job(now)
        if job is not None:
            t0 = time.monotonic()
            self.reactor.prepare(1, kinds=(job,))
            self.idle_slots.ran(time.monotonic() - t0, job)

    def idle(self, seconds: float) -> None:
        """Nothing arrived: do a piece of catch-up work if it fits before the next actor frame,
        else wait up to ``seconds`` (the process variant waits on its pipe instead)."""
        wait = self.idle_wait()
        if wait == 0.0:
            self.idle_step()
        else:
            time.sleep(seconds if wait is None else min(seconds, wait))

    def close(self) -> None:
        """Nothing to release in-process (the process variant ends its worker)."""

    def _target(self, index, positions, contacts, arrival, actor_frame, gen_latency) -> PartnerTarget:
        t0 = time.perf_counter()
        q = self.retarget.step(positions, contacts)
        rt = time.perf_counter() - t0
        self._last_q, self._last_pos = q, np.asarray(positions)
        return PartnerTarget(index, q, np.asarray(positions), arrival, actor_frame, gen_latency, rt)


class PartnerPipeline:
    """Run source → :class:`PartnerCore` in a thread, feeding ``buffer``.

    ``start_event``: wait for it (the loop's ``ready``) before starting the actor clock;
    actor frames that arrive earlier (a live stream) are discarded. ``reactor`` None makes
    the robot retarget the actor itself (imitation). ``core``: anything with the core's
    ``feed`` / ``finish_stream`` / ``idle`` / ``close`` (e.g.
    :class:`ros_free_bridge.generator_process.GeneratorProcess`) instead of a core built from
    ``reactor`` and ``retarget``. ``record``: keep every actor frame and every partner pose
    given to the retargeter (``actor_positions``, ``partner_positions``, lists of (22, 3)
    arrays) for videos and reports. ``on_event(kind, **info)``: the core's events (e.g.
    ``generator_behind``), for telemetry.
    """

    def __init__(self, source, reactor: ReactorStage | None, retarget: RetargetStage | None, buffer: TargetBuffer,
                 start_event: threading.Event | None = None, record: bool = False, on_event=None, core=None):
        self.source = source
        self.core = core if core is not None else PartnerCore(reactor, retarget)
        self.buffer = buffer
        self.start_event = start_event
        self.on_event = on_event
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="partner-pipeline", daemon=True)
        self.frames_in = 0
        self.frames_out = 0
        self.events: list[dict] = []
        self.record = record
        self.actor_positions: list[np.ndarray] = []
        self.actor_arrivals: list[float] = []  #: record: monotonic arrival of each actor frame
        self.partner_positions: list[np.ndarray] = []

    @property
    def frames_dropped(self) -> int:
        """Partner frames skipped (held) to keep up with the actor's clock."""
        return self.core.frames_dropped

    def start(self) -> None:
        if isinstance(self.core, PartnerCore) and self.core.reactor is not None:
            # torch runs in this thread: short GIL slices so that the control-loop thread
            # wakes on time while torch, numpy and CasADi work here
            sys.setswitchinterval(0.0005)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def _run(self) -> None:
        try:
            while self.start_event is not None and not self.start_event.wait(0.01):
                if self._stop.is_set():
                    return
                if self.source.live:
                    self.source.poll()  # drop what a live stream sends before the robot is ready
            self.source.start()
            while not self._stop.is_set():
                frames = self.source.poll()
                self.frames_in += len(frames)
                if self.record:
                    self.actor_positions += [f.positions for f in frames]
                    self.actor_arrivals += [f.arrival for f in frames]
                targets, events = self.core.feed(frames)
                self._emit(targets, events)
                if getattr(self.source, "finished", False):
                    for targets, events in self.core.finish_stream():
                        self._emit(targets, events)
                        if self._stop.is_set():
                            break
                    break
                if not frames and not getattr(self.core, "backlog", False):
                    self.core.idle(self._poll_wait())
        except BaseException as exc:  # noqa: BLE001 - handed to the control loop, which stops safely
            self.buffer.close(exc)
        else:
            self.buffer.close()  # before the core's close, which may wait for a process to exit
        finally:
            self.core.close()

    POLL_S = 0.002  #: longest wait between polls of the actor source

    def _poll_wait(self) -> float:
        """Seconds to wait before polling the source again: ``POLL_S``, or less when the
        source says when its next frame is due (a replay: its frames are stamped with their
        due time, so a late poll would count in the latency)."""
        due = getattr(self.source, "next_due", None)
        due = due() if due is not None else None
        if due is None:
            return self.POLL_S
        return min(self.POLL_S, max(0.0, due - time.monotonic()))

    def _emit(self, targets: list[PartnerTarget], events: list[dict]) -> None:
        for e in events:
            self.events.append(e)
            if self.on_event is not None:
                self.on_event(**e)
        for t in targets:
            if self.record:
                self.partner_positions.append(t.positions)
            self.buffer.push(TargetFrame(t.index, t.q, t.arrival, t.actor_frame, t.gen_latency, t.rt_latency))
            self.frames_out += 1
