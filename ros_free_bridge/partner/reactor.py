"""DualFlow's reactive mode over world positions: actor frames (22, 3) m in, partner frames out.

:class:`ReactorStage` wraps :class:`dualflow.streaming.ReactiveStreamer` (feature encoding,
provisional newest row, decoding, body cleaning) and offers the streamer's catch-up work
(:class:`dualflow.streaming.CatchUpWork`) under ``torch.inference_mode``. This is the one
module of the bridge that imports torch (lazily, when a stage is built; DESIGN.md).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ros_free_bridge.errors import BridgeError
from ros_free_bridge.sources.udp import ActorFrame


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
class Cues:
    """What the partner is conditioned on for the whole run. ``text``: a cue (None: none).
    ``music``: an audio file (or a Jukebox .npy) whose frames are aligned with the actor clock
    (actor frame k ↔ music frame k); it loops when the run is longer than the track.
    ``music_frames``: how many frames the run may last (the track is tiled to cover them)."""

    text: str | None = None
    music: object = None
    music_frames: int = 30 * 60 * 30


def partner_device(device: str, check_torch: bool = True) -> str:
    """``device`` checked: "cpu", or a CUDA device name that (with ``check_torch``) torch can
    use; BridgeError naming the fix. Without ``check_torch`` only the name is checked and torch
    is not imported (the bridge's process leaves torch to the generator)."""
    name = str(device)
    if name == "cpu":
        return name
    head, _, index = name.partition(":")
    if head != "cuda" or (index and not index.isdigit()):
        raise BridgeError(f"partner device {name!r}: choose 'cpu' or a CUDA device ('cuda', 'cuda:1')")
    if not check_torch:
        return name
    import torch

    if not torch.cuda.is_available():
        raise BridgeError(
            f"partner device {name!r}: torch sees no CUDA device here (a CPU-only torch build, or no GPU); "
            "use --partner-device cpu"
        )
    count = torch.cuda.device_count()
    if int(index or 0) >= count:
        raise BridgeError(
            f"partner device {name!r}: torch sees {count} CUDA device(s); choose cuda:0 .. cuda:{count - 1}"
        )
    return name


class ReactorStage:
    """Generate the partner (reactor) from actor world positions, causally, frame by frame.

    checkpoint: a checkpoint directory (None: the bundled one). cues: :class:`Cues` (None: no
    text, no music). threads: torch threads (1 leaves a core to the control loop). device:
    where the model runs, "cpu" or a CUDA device ("cuda", "cuda:1"; see :func:`partner_device`).

    ``predict_next`` (default): an actor frame's 262-d row needs the next frame (its velocity
    p[n+1] - p[n] and the foot contacts from it), which would add one frame (33 ms) to the
    delay. Instead the newest frame's row is encoded with the constant-velocity prediction
    p^[n+1] = 2 p[n] - p[n-1] and pushed as provisional; when p[n+1] arrives the row is
    revised (``ReactiveStreamer.push(revise=1)``). Partner frame i then needs actor frames up
    to i + L only (``frames_ahead`` = L); False: up to i + L + 1, every row exact.
    ``clean``: each partner frame through :class:`dualflow.body.BodyCleaner` (bone lengths,
    planted feet, jitter).

    The streamer runs under ``torch.inference_mode`` (no autograd bookkeeping: ~10 % less
    per-operation overhead in the one-row passes); its tensors are only read outside it.
    """

    def __init__(
        self,
        fps: float = 30.0,
        checkpoint=None,
        stream_config=None,
        cues: Cues | None = None,
        threads: int = 1,
        predict_next: bool = True,
        clean: bool = True,
        device: str = "cpu",
    ):
        import torch

        from dualflow.body import BodyCleaner
        from dualflow.checkpoint import BUNDLED_CHECKPOINT, load_checkpoint
        from dualflow.streaming import ReactiveStreamer, StreamConfig

        torch.set_num_threads(max(1, int(threads)))  # leave a core to the control loop
        ckpt = load_checkpoint(checkpoint or BUNDLED_CHECKPOINT)
        self.stats = ckpt.stats
        self.model = ckpt.build_model(partner_device(device))
        self.fps = float(fps)
        cues = cues or Cues()
        self._cond = self._conditions(ckpt, cues) if (cues.text or cues.music is not None) else None
        if self._cond is not None:
            self._cond = self._cond.to(self.model.out_b.weight.device)
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
        self.cleaner = BodyCleaner(self.fps) if clean else None

    @staticmethod
    def _conditions(ckpt, cues: Cues):
        import torch

        from dualflow.conditioning import ConditionBuilder
        from dualflow.model import Conditions

        builder = ConditionBuilder.from_checkpoint(ckpt)
        cond = Conditions()
        if cues.text:
            if builder.text_encoder is None:
                raise BridgeError(f"{ckpt.path}: this model was trained without text; drop --text or use another model")
            cond.text = builder.text_condition(cues.text)
        if cues.music is not None:
            if builder.music_kind is None:
                raise BridgeError(
                    f"{ckpt.path}: this model was trained without music; drop --music or use another model"
                )
            track = builder.music_array(cues.music, None)
            reps = int(np.ceil(cues.music_frames / len(track)))
            cond.music = torch.from_numpy(np.tile(track, (reps, 1))[: cues.music_frames])[None]
        return cond

    # -- generation ----------------------------------------------------------------------
    def push(self, actor_positions: np.ndarray, arrival: float, actor_index: int) -> list[ReactorFrame]:
        """Add one actor frame (22, 3) m; returns the partner frames this completed (often none).

        Feature rows are encoded in chunks of the streamer's hop (the inverse kinematics of
        the 262-d rotation part costs mostly per call, not per frame); the streamer would not
        generate before a hop's worth of rows anyway, so chunking adds no delay.
        """
        return self.push_many([ActorFrame(actor_index, actor_positions, arrival)])

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
            self.predict_next and frames and self._rows_ready() - self.look_ahead - self._n_emitted >= hop
        ):
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

    # -- catch-up work (dualflow.streaming.CatchUpWork, for the current stream) ---------------
    def idle_jobs(self) -> list[str]:
        """The kinds of catch-up work due now, first to be done first."""
        return self.streamer.idle_jobs()

    @property
    def urgent_jobs(self) -> tuple[str, ...]:
        """The kinds worth doing in any idle gap, fitting or not."""
        return self.streamer.urgent_jobs

    def prepare(self, max_passes: int = 1, kinds=None) -> bool:
        """Do up to ``max_passes`` pieces of catch-up work, of ``kinds`` only if given; returns
        whether more is due."""
        with self._torch.inference_mode():
            return self.streamer.prepare(max_passes, kinds)

    @property
    def has_catch_up(self) -> bool:
        """Catch-up work is due (``idle_jobs`` is not empty)."""
        return self.streamer.has_catch_up

    # -- features --------------------------------------------------------------------------
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
