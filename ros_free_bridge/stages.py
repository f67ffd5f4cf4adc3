"""The slow stages between the actor and the control loop, and the thread that runs them.

- :class:`ReactorStage`: DualFlow's reactive mode over world positions. Actor frames
  (22, 3) m in, reactor frames (22, 3) m + foot contacts out, through
  :class:`dualflow.streaming.ReactiveStreamer`. This is the one place outside
  ``dualflow`` that imports torch (DESIGN.md).
- :class:`RetargetStage`: :class:`retarget.streaming.StreamingRetargeter`, one frame at a
  time, robot joint angles in the transport's joint order out.
- :class:`PartnerPipeline`: a thread that polls the actor source, runs both stages and
  pushes :class:`~ros_free_bridge.targets.TargetFrame` s to the control loop's buffer.
  It never touches the transport, so a slow or failed stage can only starve the loop
  (which then holds and stops, see :mod:`ros_free_bridge.loop`), never block it.

Delay: an actor frame's 262-d feature row needs the next frame (its velocity), and the
reactor frame i needs actor rows up to i + L; so reactor frame i is produced when actor
frame i + L + 1 arrives (plus the streamer's hop - 1 frames and the compute time).
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

from ros_free_bridge.errors import BridgeError
from ros_free_bridge.targets import TargetBuffer, TargetFrame


@dataclass(frozen=True)
class ReactorFrame:
    """One generated reactor pose: positions (22, 3) m (world, Z up), contacts (4,) bool."""

    index: int
    positions: np.ndarray
    contacts: np.ndarray
    source_arrival: float  #: monotonic arrival of the actor frame whose push produced it
    actor_frame: int
    latency: float  #: seconds the generator spent on the push that produced it


class ReactorStage:
    """Generate the partner (reactor) from actor world positions, causally, frame by frame.

    checkpoint: a checkpoint directory (None: the bundled one). text: a cue for the whole run.
    music: an audio file (or a Jukebox .npy) whose features are aligned with the actor clock
    (actor frame k ↔ music frame k); it loops when the run is longer than the track.
    ``music_frames``: how many frames the run may last (the track is tiled to cover them).
    """

    def __init__(self, fps: float = 30.0, checkpoint=None, stream_config=None, text: str | None = None,
                 music=None, music_frames: int = 30 * 60 * 30, threads: int = 1):
        import torch

        from dualflow.checkpoint import BUNDLED_CHECKPOINT, load_checkpoint
        from dualflow.streaming import ReactiveStreamer, StreamConfig

        torch.set_num_threads(max(1, int(threads)))  # leave a core to the control loop
        ckpt = load_checkpoint(checkpoint or BUNDLED_CHECKPOINT)
        self.stats = ckpt.stats
        self.model = ckpt.build_model("cpu")
        self.fps = float(fps)
        conditions = self._conditions(ckpt, text, music, music_frames) if (text or music is not None) else None
        self.streamer = ReactiveStreamer(self.model, stream_config or StreamConfig(), conditions)
        self.look_ahead = self.streamer.look_ahead
        self.delay_frames = self.streamer.delay_frames + 1  # + 1: a feature row needs the next frame
        self._canonical = None
        self._pending: list[np.ndarray] = []  # actor frames not yet encoded, plus the last encoded one
        self._n_out = 0
        self._torch = torch

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
        from dualflow.motion import Motion
        from dualflow.motion.features import canonical_frame

        pos = np.asarray(actor_positions, dtype=np.float64)
        if self._canonical is None:
            self._canonical = canonical_frame(Motion(pos[None], self.fps))
        self._pending.append(pos)
        if len(self._pending) - 1 < self.streamer.config.hop:
            return []
        return self._encode_and_push(arrival, actor_index)

    def flush(self, arrival: float, actor_index: int) -> list[ReactorFrame]:
        """End of the actor stream: generate the remaining partner frames."""
        frames = self._encode_and_push(arrival, actor_index) if len(self._pending) > 1 else []
        t0 = time.perf_counter()
        with self._torch.no_grad():
            out = self.streamer.flush()
        return frames + self._decode(out, arrival, actor_index, time.perf_counter() - t0)

    def _encode_and_push(self, arrival: float, actor_index: int) -> list[ReactorFrame]:
        """Rows for every pending frame but the last (a row needs the next frame's position)."""
        from dualflow.motion import Motion
        from dualflow.motion.features import encode_person

        rows = encode_person(Motion(np.stack(self._pending), self.fps), self._canonical)
        self._pending = self._pending[-1:]
        t0 = time.perf_counter()
        with self._torch.no_grad():
            out = self.streamer.push(self.stats.normalize(rows))
        return self._decode(out, arrival, actor_index, time.perf_counter() - t0)

    def _decode(self, rows, arrival: float, actor_index: int, latency: float) -> list[ReactorFrame]:
        from dualflow.motion.features import decode_person

        rows = rows.detach().cpu().numpy()
        if rows.shape[0] == 0:
            return []
        motion = decode_person(self.stats.denormalize(rows), self.fps, self._canonical)
        frames = []
        for k in range(rows.shape[0]):
            frames.append(ReactorFrame(self._n_out, motion.positions[k], motion.contacts[k], arrival, actor_index, latency))
            self._n_out += 1
        return frames


class RetargetStage:
    """Reactor world positions → robot joint angles (n,) rad in ``joint_names`` order."""

    def __init__(self, robot, fps: float, joint_names=None):
        from retarget.streaming import StreamingRetargeter

        self.robot = robot
        # its default keypoint scaler uses REST_POSE proportions: a live stream has no clip to measure
        self.streamer = StreamingRetargeter(robot, fps)
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


class PartnerPipeline:
    """Run source → reactor → retarget in a thread, feeding ``buffer``.

    ``start_event``: wait for it (the loop's ``ready``) before starting the actor clock;
    actor frames that arrive earlier (a live stream) are discarded. ``reactor`` None makes
    the robot retarget the actor itself (imitation). ``record``: keep every actor frame and
    every partner pose given to the retargeter (``actor_positions``, ``partner_positions``,
    lists of (22, 3) arrays) for videos and reports.
    """

    def __init__(self, source, reactor: ReactorStage | None, retarget: RetargetStage, buffer: TargetBuffer,
                 start_event: threading.Event | None = None, record: bool = False):
        self.source = source
        self.reactor = reactor
        self.retarget = retarget
        self.buffer = buffer
        self.start_event = start_event
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="partner-pipeline", daemon=True)
        self.frames_in = 0
        self.frames_out = 0
        self.record = record
        self.actor_positions: list[np.ndarray] = []
        self.partner_positions: list[np.ndarray] = []

    def start(self) -> None:
        # Short GIL slices so that the control-loop thread wakes on time while torch,
        # numpy and CasADi work here.
        sys.setswitchinterval(0.0005)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    def _run(self) -> None:
        try:
            while self.start_event is not None and not self.start_event.wait(0.01):
                if self._stop.is_set():
                    return
                if self.source.live:
                    self.source.poll()  # drop what a live stream sends before the robot is ready
            self.source.start()
            last_arrival, last_index = time.monotonic(), -1
            while not self._stop.is_set():
                frames = self.source.poll()
                for f in frames:
                    self.frames_in += 1
                    if self.record:
                        self.actor_positions.append(f.positions)
                    last_arrival, last_index = f.arrival, f.index
                    if self.reactor is None:
                        self._emit(f.positions, None, f.arrival, f.index, 0.0)
                    else:
                        for r in self.reactor.push(f.positions, f.arrival, f.index):
                            self._emit(r.positions, r.contacts, r.source_arrival, r.actor_frame, r.latency)
                if getattr(self.source, "finished", False):
                    if self.reactor is not None:
                        for r in self.reactor.flush(last_arrival, last_index):
                            self._emit(r.positions, r.contacts, r.source_arrival, r.actor_frame, r.latency)
                    break
                if not frames:
                    time.sleep(0.002)
        except BaseException as exc:  # noqa: BLE001 - handed to the control loop, which stops safely
            self.buffer.close(exc)
            return
        self.buffer.close()

    def _emit(self, positions, contacts, arrival, actor_index, gen_latency) -> None:
        if self.record:
            self.partner_positions.append(np.asarray(positions))
        t0 = time.perf_counter()
        q = self.retarget.step(positions, contacts)
        rt = time.perf_counter() - t0
        self.buffer.push(TargetFrame(self.frames_out, q, arrival, actor_index, gen_latency, rt))
        self.frames_out += 1
