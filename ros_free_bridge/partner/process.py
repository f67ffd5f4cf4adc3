"""The partner generator (DualFlow + streaming retarget) in a child process: the parent's handle.

:class:`GeneratorProcess` has the partner core's interface (``feed`` / ``finish_stream`` /
``idle`` / ``close``), so :class:`~ros_free_bridge.partner.pipeline.PartnerPipeline` runs it
unchanged; ``feed`` never waits for the generator. The child is
:mod:`ros_free_bridge.partner.child`, the pipe protocol :mod:`ros_free_bridge.partner.wire`.
Why a process, and how it ends: docs/partner_pipeline.md.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from ros_free_bridge.errors import BridgeError
from ros_free_bridge.partner.wire import Channel, decode_target, encode_actor

CHILD_MODULE = "ros_free_bridge.partner.child"  #: what the parent runs with ``python -m``


class WorkerDied(BridgeError):
    """The generator process ended without being asked to."""


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
    device: str = "cpu"  #: where the model runs (ReactorStage); on CUDA full windows, not incremental ones


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
    def start(self) -> GeneratorProcess:
        self._spawn()
        self._chan.send_json(
            b"C",
            {
                k: (str(v) if k in ("checkpoint", "music") and v is not None else v)
                for k, v in self.config.__dict__.items()
            },
        )
        deadline = time.monotonic() + self.start_timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                self.close()
                raise BridgeError(
                    f"generator process: not ready within {self.start_timeout:g} s (loading the model); "
                    "check the machine's load or the checkpoint"
                )
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
                raise WorkerDied(
                    f"generator process exited while starting (exit code {self.process.wait()}); "
                    "see its error output above"
                )

    def _spawn(self) -> None:
        """Start the child with one pipe each way (its ends passed as inherited descriptors)."""
        from ros_free_bridge.lifeline import parent_thread_lives_on

        p2c_r, p2c_w = os.pipe()
        c2p_r, c2p_w = os.pipe()
        env = dict(os.environ)
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            env[var] = str(max(1, int(self.config.threads)))
        try:
            argv = [sys.executable, "-m", CHILD_MODULE, "--fds", f"{p2c_r},{c2p_w}", "--parent", str(os.getpid())] + (
                ["--pdeathsig"] if parent_thread_lives_on() else []
            )
            self.process = subprocess.Popen(
                argv,
                pass_fds=(p2c_r, c2p_w),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                env=env,
            )
        finally:
            os.close(p2c_r)
            os.close(c2p_w)
        self._chan = Channel(c2p_r, p2c_w)

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
        """End the child: Q and EOF on its input, then wait, then kill. Idempotent. Records
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
        return self._take()

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
                yield self._take()
        yield self._take()

    # -- internals ------------------------------------------------------------------------
    def _take(self) -> tuple[list, list[dict]]:
        """The targets and events received so far, handed over once."""
        out = (self._targets, self._events)
        self._targets, self._events = [], []
        return out

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
