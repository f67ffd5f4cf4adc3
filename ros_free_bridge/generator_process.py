"""The partner generator (DualFlow + streaming retarget) in its own process.

Why a process: the generator is a small torch model, so most of its time is Python
(module calls, tensor dispatch) holding the GIL. In a thread it competes with the 100 Hz
control loop, the MuJoCo virtual robot and the bus I/O for that one lock, and on a 2-core
CPU it ran at a fraction of its stand-alone speed. In a child process it has its own
interpreter and core; the parent keeps only the loop and a light pipeline thread.

:class:`GeneratorProcess` is the parent's handle. It has the interface of
:class:`ros_free_bridge.stages.PartnerCore` (``feed`` / ``finish_stream`` / ``idle`` / ``close``), so
:class:`~ros_free_bridge.stages.PartnerPipeline` runs it unchanged: ``feed`` sends the new
actor frames and returns whatever targets the child has finished by then (it never waits
for the generator). The child (``python -m ros_free_bridge.generator_process``) runs a
``PartnerCore`` (with its drop-to-newest policy) over the frames it reads.

Wire format: two anonymous pipes (not stdin/stdout: libraries may print), little-endian
messages ``<u4 payload length><u1 type><payload>``; no pickle, only JSON and float64/int64
arrays:

====  ============  =================================================================
type  direction     payload
====  ============  =================================================================
C     parent→child  JSON config (checkpoint, stream settings, text, music, robot, joints)
A     parent→child  actor frame: <q index><d arrival> + 66 float64 (22 × 3 positions, m)
E     parent→child  end of the actor stream: generate the rest, then answer D
Q     parent→child  quit now (EOF means the same, but a process forked from the parent
                    after the child started holds a copy of the write end)
R     child→parent  JSON: ready (delay_frames, look_ahead, warm-up window time, objects frozen)
T     child→parent  target: <q index><q actor frame><d arrival><d gen s><d retarget s><B held>
                    + n float64 q (rad) + 66 float64 partner positions (m)
V     child→parent  JSON event (e.g. generator_behind)
X     child→parent  JSON error {type, message}; the child exits
D     child→parent  done (after E): every target was sent
====  ============  =================================================================

Shutdown: the parent sends Q and closes its write end, waits, then kills. The child also
exits on EOF, and it never outlives its parent, however that ends (SIGKILL included):
:func:`ros_free_bridge.lifeline.die_with_parent` (PR_SET_PDEATHSIG on Linux when the parent
started it from its main thread, and a parent-pid watch everywhere). SIGINT and SIGTERM
are ignored: a Ctrl-C reaches the whole process group, and the parent decides (an e-stop
with the signal as its reason), then ends the child. A child that
dies (or is killed) is seen as EOF on the parent's read end: ``feed`` raises
:class:`~ros_free_bridge.errors.BridgeError`, the pipeline closes the target buffer with
it, and the control loop ramps to rest and applies its stop policy.
"""

from __future__ import annotations

import argparse
import fcntl
import gc
import json
import math
import os
import select
import signal
import struct
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ros_free_bridge.errors import BridgeError

HEADER = struct.Struct("<IB")
ACTOR = struct.Struct("<qd")
TARGET = struct.Struct("<qqdddB")
N_POS = 22 * 3
PIPE_BYTES = 1 << 20  #: ask for 1 MiB pipes (~30 s of actor frames) so the parent never blocks writing


class WorkerDied(BridgeError):
    """The generator process ended without being asked to."""


class Channel:
    """Framed messages over a pair of pipe file descriptors (read side buffered)."""

    def __init__(self, rfd: int, wfd: int):
        self.rfd, self.wfd = rfd, wfd
        self._buf = bytearray()
        self.eof = False
        for fd in (rfd, wfd):
            try:
                fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
            except OSError:
                pass  # not Linux, or above the system's limit: the default 64 KiB pipe still works

    def send(self, kind: bytes, payload: bytes = b"") -> None:
        data = HEADER.pack(len(payload), kind[0]) + payload
        view = memoryview(data)
        while view:
            view = view[os.write(self.wfd, view):]

    def send_json(self, kind: bytes, obj) -> None:
        self.send(kind, json.dumps(obj).encode())

    def receive(self, timeout: float | None) -> list[tuple[bytes, bytes]]:
        """Every complete message available, waiting up to ``timeout`` s (None: forever) for the first."""
        out = self._parse()
        if out or self.eof:
            return out
        ready, _, _ = select.select([self.rfd], [], [], timeout)
        while ready:
            chunk = os.read(self.rfd, 1 << 16)
            if not chunk:
                self.eof = True
                break
            self._buf += chunk
            ready, _, _ = select.select([self.rfd], [], [], 0)
        return self._parse()

    def _parse(self) -> list[tuple[bytes, bytes]]:
        out, buf, pos = [], self._buf, 0
        while len(buf) - pos >= HEADER.size:
            n, kind = HEADER.unpack_from(buf, pos)
            if len(buf) - pos - HEADER.size < n:
                break
            out.append((bytes([kind]), bytes(buf[pos + HEADER.size: pos + HEADER.size + n])))
            pos += HEADER.size + n
        del buf[:pos]
        return out

    def close(self) -> None:
        for fd in (self.rfd, self.wfd):
            try:
                os.close(fd)
            except OSError:
                pass


def encode_actor(index: int, arrival: float, positions) -> bytes:
    pos = np.ascontiguousarray(positions, dtype="<f8").reshape(N_POS)
    return ACTOR.pack(int(index), float(arrival)) + pos.tobytes()


@dataclass(frozen=True)
class _Frame:
    index: int
    positions: np.ndarray
    arrival: float


def decode_actor(payload: bytes) -> _Frame:
    if len(payload) != ACTOR.size + 8 * N_POS:
        raise BridgeError(f"generator process: actor message of {len(payload)} bytes, expected {ACTOR.size + 8 * N_POS}")
    index, arrival = ACTOR.unpack_from(payload)
    pos = np.frombuffer(payload, "<f8", N_POS, ACTOR.size).reshape(22, 3).copy()
    return _Frame(index, pos, arrival)


def encode_target(t) -> bytes:
    q = np.ascontiguousarray(t.q, dtype="<f8")
    pos = np.ascontiguousarray(t.positions, dtype="<f8").reshape(N_POS)
    return TARGET.pack(t.index, t.actor_frame, t.arrival, t.gen_latency, t.rt_latency, int(t.held)) + q.tobytes() + pos.tobytes()


def decode_target(payload: bytes, n_joints: int):
    from ros_free_bridge.stages import PartnerTarget

    if len(payload) != TARGET.size + 8 * (n_joints + N_POS):
        raise BridgeError(f"generator process: target message of {len(payload)} bytes, expected "
                          f"{TARGET.size + 8 * (n_joints + N_POS)} for {n_joints} joints")
    index, actor_frame, arrival, gen, rt, held = TARGET.unpack_from(payload)
    q = np.frombuffer(payload, "<f8", n_joints, TARGET.size).copy()
    pos = np.frombuffer(payload, "<f8", N_POS, TARGET.size + 8 * n_joints).reshape(22, 3).copy()
    return PartnerTarget(index, q, pos, arrival, actor_frame, gen, rt, bool(held))


@dataclass
class GeneratorConfig:
    """What the child builds. ``robot``: a bundled robot name or hardware config (the MJCF and
    retarget profile are resolved from it); ``joint_names``: the transport's order.
    ``threads``: torch threads in the child (1 leaves the other core to the control loop and
    the bus; more threads only spin against each other on a busy 2-core machine).
    ``max_lag``: frames of backlog before dropping to the newest actor frames (None: hop +
    the streamer's max_new). ``nice``: how much lower the child's CPU priority is than the
    parent's: when the CPU is short, the control loop and the bus (emulator) must win; a
    generator that falls behind is caught up or dropped, a late bus write is a fault."""

    robot: str
    joint_names: list
    fps: float = 30.0
    checkpoint: str | None = None
    window: int = 60
    steps: int = 2
    hop: int = 1
    seed: int = 0
    text: str | None = None
    music: str | None = None
    music_frames: int = 30 * 60 * 30
    threads: int = 1
    max_lag: int | None = None
    warmup: bool = True
    nice: int = 5
    predict_next: bool = True  #: ReactorStage's provisional newest row (one frame less delay)
    incremental: bool = True  #: StreamConfig.incremental: cached activations, new frames only


class GeneratorProcess:
    """Parent-side handle of the generator child (module docstring). ``start()`` blocks until
    the child has loaded the model and answered ready, or raises its error."""

    def __init__(self, config: GeneratorConfig, start_timeout: float = 600.0):
        self.config = config
        self.start_timeout = start_timeout
        self.n_joints = len(config.joint_names)
        self.process: subprocess.Popen | None = None
        self._chan: Channel | None = None
        self.ready_info: dict = {}
        self.frames_dropped = 0
        self.backlog = False  #: the child works off its own backlog; the pipeline may wait
        self.done = False
        self._targets: list = []
        self._events: list[dict] = []
        self._cpu_at_ready = float("nan")
        self.streaming_cpu_s = float("nan")  #: CPU seconds the child used from ready to close

    # -- life cycle ------------------------------------------------------------------------
    def start(self) -> "GeneratorProcess":
        p2c_r, p2c_w = os.pipe()
        c2p_r, c2p_w = os.pipe()
        env = dict(os.environ)
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            env[var] = str(max(1, int(self.config.threads)))
        try:
            from ros_free_bridge.lifeline import parent_thread_lives_on

            argv = [sys.executable, "-m", "ros_free_bridge.generator_process", "--fds", f"{p2c_r},{c2p_w}",
                    "--parent", str(os.getpid())] + (["--pdeathsig"] if parent_thread_lives_on() else [])
            self.process = subprocess.Popen(
                argv,
                pass_fds=(p2c_r, c2p_w), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, env=env,
            )
        finally:
            os.close(p2c_r)
            os.close(c2p_w)
        self._chan = Channel(c2p_r, p2c_w)
        self._chan.send_json(b"C", {k: (str(v) if k in ("checkpoint", "music") and v is not None else v)
                                    for k, v in self.config.__dict__.items()})
        deadline = time.monotonic() + self.start_timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                self.close()
                raise BridgeError(f"generator process: not ready within {self.start_timeout:g} s (loading the model); "
                                  "check the machine's load or the checkpoint")
            for kind, payload in self._chan.receive(min(left, 0.5)):
                if kind == b"R":
                    self.ready_info = json.loads(payload)
                    self._cpu_at_ready = self.cpu_seconds()
                    return self
                if kind == b"X":
                    self.close()
                    raise BridgeError(json.loads(payload)["message"])
            if self._chan.eof:
                self.close()
                raise WorkerDied(f"generator process exited while starting (exit code {self.process.wait()}); "
                                 "see its error output above")

    @property
    def pid(self) -> int | None:
        return None if self.process is None else self.process.pid

    @property
    def delay_frames(self) -> int | None:
        return self.ready_info.get("delay_frames")

    @property
    def frames_ahead(self) -> int | None:
        """Partner frame i is complete when actor frame i + frames_ahead has arrived."""
        return self.ready_info.get("frames_ahead")

    def cpu_seconds(self) -> float:
        """CPU seconds (user + system) the child has used so far (Linux /proc; NaN elsewhere or
        once it has been reaped)."""
        try:
            fields = Path(f"/proc/{self.pid}/stat").read_text().rsplit(")", 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except (OSError, ValueError, IndexError, TypeError):
            return float("nan")

    def close(self, timeout: float = 5.0) -> None:
        """End the child: EOF on its input, then wait, then kill. Idempotent. Records
        ``streaming_cpu_s``: the child's CPU seconds from ready to close."""
        if self.process is not None and self.process.poll() is None and math.isfinite(self._cpu_at_ready):
            self.streaming_cpu_s = self.cpu_seconds() - self._cpu_at_ready
        if self._chan is not None:
            try:  # say so: a process forked from ours since (the bus emulator) holds a copy of
                self._chan.send(b"Q")  # our write end, so the child may never read EOF
            except OSError:
                pass
            self._chan.close()
            self._chan = None
        if self.process is not None and self.process.poll() is None:
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- the PartnerCore interface -----------------------------------------------------------
    def feed(self, frames):
        """Send new actor frames; return (targets, events) the child has finished so far."""
        chan = self._channel()
        for f in frames:
            try:
                chan.send(b"A", encode_actor(f.index, f.arrival, f.positions))
            except BrokenPipeError:
                raise self._died() from None
        self._pump(0.0)
        out = (self._targets, self._events)
        self._targets, self._events = [], []
        return out

    def idle(self, seconds: float) -> None:
        """Wait up to ``seconds`` for the child's output (the pipeline calls it when no actor
        frame arrived); what came is returned by the next ``feed``."""
        self._pump(seconds)

    def finish_stream(self, timeout: float = 60.0):
        """End of the actor stream: yield (targets, events) batches as the child flushes,
        until it says done."""
        try:
            self._channel().send(b"E")
        except BrokenPipeError:
            raise self._died() from None
        deadline = time.monotonic() + timeout
        while not self.done:
            if time.monotonic() > deadline:
                raise BridgeError(f"generator process: no end of stream within {timeout:g} s")
            self._pump(0.05)
            if self._targets or self._events:
                out = (self._targets, self._events)
                self._targets, self._events = [], []
                yield out
        yield self._targets, self._events
        self._targets, self._events = [], []

    # -- internals ------------------------------------------------------------------------
    def _channel(self) -> Channel:
        if self._chan is None:
            raise BridgeError("generator process: not running (start() it first, or it was closed)")
        return self._chan

    def _died(self) -> WorkerDied:
        code = None if self.process is None else self.process.poll()
        if code is None and self.process is not None:
            try:
                code = self.process.wait(1.0)
            except subprocess.TimeoutExpired:
                code = "none yet"
        return WorkerDied(f"the generator process ended unexpectedly (exit code {code})")

    def _pump(self, timeout: float) -> None:
        """Read what the child sent (waiting up to ``timeout`` s) into the pending lists."""
        chan = self._channel()
        for kind, payload in chan.receive(timeout):
            if kind == b"T":
                self._targets.append(decode_target(payload, self.n_joints))
            elif kind == b"V":
                ev = json.loads(payload)
                self.frames_dropped += int(ev.get("dropped_frames", 0))
                self._events.append(ev)
            elif kind == b"D":
                self.done = True
            elif kind == b"X":
                raise BridgeError("generator process: " + json.loads(payload)["message"])
        if chan.eof and not self.done:
            raise self._died()


# ---------------------------------------------------------------------------------------------
# The child
# ---------------------------------------------------------------------------------------------


def build_core(cfg: GeneratorConfig):
    """The child's PartnerCore: the reactor (torch) and the retargeter (CasADi)."""
    import torch

    from dualflow.streaming import StreamConfig
    from retarget.robot import load_robot
    from ros_free_bridge.robots import resolve_robot
    from ros_free_bridge.stages import PartnerCore, ReactorStage, RetargetStage

    torch.set_num_threads(max(1, int(cfg.threads)))
    stream = StreamConfig(window=cfg.window, steps=cfg.steps, hop=cfg.hop, seed=cfg.seed, incremental=cfg.incremental)
    # the model first: a bad checkpoint or condition fails before the slower retargeter build
    reactor = ReactorStage(cfg.fps, cfg.checkpoint, stream, cfg.text, cfg.music, cfg.music_frames, threads=cfg.threads,
                           predict_next=cfg.predict_next)
    files = resolve_robot(cfg.robot)
    retarget = RetargetStage(load_robot(files.mjcf, files.profile), cfg.fps, cfg.joint_names)
    return PartnerCore(reactor, retarget, cfg.max_lag)


def warm_up(core) -> tuple[float, float]:
    """Generate throw-away windows (allocator, kernels) on a separate stream, as a run starts:
    the first window (no context, L + hop frames) and then full-width ones. Returns the seconds
    of the first and of the last (full) window: this machine's generation speed right now."""
    import torch

    from dualflow.streaming import ReactiveStreamer

    r = core.reactor
    streamer = ReactiveStreamer(r.model, r.streamer.config, r.streamer.cond)
    cfg = streamer.config
    with torch.inference_mode():
        streamer.push(torch.zeros(r.look_ahead + cfg.hop, streamer.dim))
        streamer.push(torch.zeros(cfg.window, streamer.dim))
    windows = streamer.timing.windows
    return windows[0][2], windows[-1][2]


def child_main(rfd: int, wfd: int) -> int:
    # Ctrl-C (or a SIGTERM to the group) reaches every process of the group; the parent
    # decides (e-stop, the signal as the reason), then ends this one
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    chan = Channel(rfd, wfd)
    try:
        msgs = []
        while not msgs and not chan.eof:
            msgs = chan.receive(None)
        if not msgs or msgs[0][0] != b"C":
            return 2
        cfg = GeneratorConfig(**json.loads(msgs[0][1]))
        if cfg.nice > 0:
            os.nice(int(cfg.nice))
        core = build_core(cfg)
        first_s, window_s = warm_up(core) if cfg.warmup else (float("nan"), float("nan"))
        # the model, the retargeter and the warm-up leave ~200 000 objects that live as long as
        # the process; a full collection scanning them took ~150 ms, and a frame waited for it.
        # Frozen, the collector scans only what is allocated while streaming.
        gc.collect()
        gc.freeze()
        chan.send_json(b"R", {"delay_frames": core.delay_frames, "look_ahead": core.reactor.look_ahead,
                              "gc_frozen_objects": gc.get_freeze_count(),
                              "frames_ahead": core.reactor.frames_ahead,
                              "max_lag": core.max_lag, "warmup_first_window_s": first_s,
                              "warmup_window_s": window_s, "pid": os.getpid()})
        while True:
            # more windows due: do not wait; catch-up work: wait only until a pass fits before
            # the next actor frame (stages.IdleSlots), or for that frame
            msgs = chan.receive(0.0 if core.backlog else core.idle_wait())
            if (chan.eof and not msgs) or any(k == b"Q" for k, _ in msgs):
                return 0
            frames = [decode_actor(p) for k, p in msgs if k == b"A"]
            if not msgs and not core.backlog:
                if core.idle_ready():
                    core.idle_step()  # one pass (a few ms), then look at the pipe again
                continue
            targets, events = core.feed(frames)
            for e in events:
                chan.send_json(b"V", e)
            for t in targets:
                chan.send(b"T", encode_target(t))
            if targets and not core.backlog and core.idle_ready():
                # a busy CPU leaves little idle time: one pass of catch-up work per window, after
                # its targets went out and if it ends before the next frame, rather than all of
                # it in the window that needs it
                core.idle_step()
            if any(k == b"E" for k, _ in msgs):
                for targets, events in core.finish_stream():
                    for e in events:
                        chan.send_json(b"V", e)
                    for t in targets:
                        chan.send(b"T", encode_target(t))
                chan.send(b"D")
    except BrokenPipeError:
        return 0  # the parent is gone
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which stops the robot safely
        try:
            msg = str(exc) if isinstance(exc, BridgeError) else f"{type(exc).__name__}: {exc}"
            chan.send_json(b"X", {"type": type(exc).__name__, "message": msg})
        except OSError:
            pass
        return 1
    finally:
        chan.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="the bridge's generator process (started by the bridge, not by hand)")
    ap.add_argument("--fds", required=True, help="READ_FD,WRITE_FD inherited from the parent")
    ap.add_argument("--parent", type=int, help="the parent's process id: end when it ends")
    ap.add_argument("--pdeathsig", action="store_true", help="also ask the kernel to kill this process with the parent")
    args = ap.parse_args(argv)
    if args.parent is not None:
        from ros_free_bridge.lifeline import die_with_parent

        die_with_parent(args.parent, pdeathsig=args.pdeathsig)
    rfd, wfd = (int(x) for x in args.fds.split(","))
    return child_main(rfd, wfd)


if __name__ == "__main__":
    raise SystemExit(main())
