"""Causal streaming reactive inference: actor frames in, reactor frames out, delay L frames.

``ReactiveStreamer`` is fed the actor's motion one frame at a time (or in chunks) and emits
the reactor's motion as soon as it may: reactor frame i needs actor frames up to i + L
(the look-ahead of the reactive mode), so it is emitted when actor frame i + L arrives,
a fixed delay of L frames plus the compute time of one window.

Inputs and outputs
------------------
* ``push(frames)``: actor frames as normalised 262-d features (the model's input space,
  ``NormStats.normalize`` of ``dualflow.motion.features.encode_person``'s rows), shape
  (262,) or (n, 262), numpy or torch. Returns the newly emitted reactor frames (m, 262)
  (m may be 0), normalised the same way; ``on_frame(index, frame)`` is also called per frame.
* ``flush()`` at the end of the stream emits the last L frames with whatever look-ahead
  remains (the actor has stopped).
* ``emitted`` (N, 262): everything emitted so far; ``timing``: compute time per emitted frame.
* Input and output share one frame (e.g. the actor's canonical frame at the stream's first
  frame). With ``StreamConfig(recanonicalize=True)`` and the normalisation statistics
  (``stats=``), every window is generated in its own canonical frame and moved back
  (``WindowFrame``), so the model sees what it was trained on: clips that start at the
  origin facing +Z (opt-in; see ``StreamConfig``).

How a window is generated (inpainting with a causal network)
-----------------------------------------------------------
Let n be the number of actor frames received and e = n - 1 - L the last emittable frame.
When at least ``hop`` frames in [n_emitted, e] are pending, one window of W frames is
generated over the frames [s, s + W), s = max(0, u + L - W), where u (<= e + 1) is the end of
the frames to emit:

* actor: the received frames [s, u + L), clean (reactive mode);
* reactor: frames [s, n_emitted) are already emitted and are kept fixed as context: at every
  ODE grid time t_k their state is overwritten (``project`` of ``dualflow.flow.ode_solve``)
  with either
    - ``context="trajectory"`` (default): the state x_{t_k} they had at that grid time when
      they were generated. The reactor stream is causal, so while the stream fits in one
      window (s = 0) this reproduces *exactly* the single-pass generation of the whole
      sequence: no seam at all (tests/test_streaming.py checks it). Once the window slides,
      the context is the model's own trajectory, shifted by the window start;
    - ``context="path"``: their point on the straight rectified path,
      x_t = (1 - t) eps + t x_known, with the eps that started them (classic inpainting;
      used with ``recanonicalize``, where stored noisy states cannot be moved rigidly);
  frames [n_emitted, u) are generated and emitted; the frames
  [u, u + L) are generated too but discarded: they exist only because both streams of the
  network have one length, and by the causality of the reactive network (see
  ``dualflow.model``) they cannot influence the frames before them.
* noise: eps of absolute frame i is row i of ``stream_noise(seed, ...)`` (blocks of 64 frames
  from generators seeded with (seed, block)), so a stream is reproducible and a frame's noise
  depends neither on the windows nor on how the actor frames were pushed.

Causality: the emitted frame i is computed from actor frames <= i + L, the already-emitted
reactor frames (< i, themselves causal by induction) and noise; actor frames > i + L are not
in the window or are masked by the network (tests/test_streaming.py checks it end to end).

Incremental windows (``StreamConfig(incremental=True)``, ``dualflow.incremental``): the
same inpainting, but each frame's network activations are kept per fixed window start and
ODE step, so a window runs only its new frames through the network (about W times less
work at hop 1); window starts are staggered so that a frame still sees P - P / bases .. P - 1
frames of context (P = W - L). The other starts' catch-up can be done ahead, in a caller's
idle time: the catch-up protocol, ``CatchUpWork``.

Continuity: the new frames attend (causal self-attention, causal convolutions) to the context
frames at every ODE step, so the motion continues across window seams. ``seam_report``
measures the velocity jump at seams against the jump inside windows; bench/bench_streaming.py
prints it for trajectory context, straight-path context, per-window frames and no context.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np
import torch

from dualflow.errors import DualFlowError
from dualflow.flow import PRECISIONS, RectifiedPath, bf16_velocity, guided_velocity, ode_solve, precision_context
from dualflow.model import Conditions, DualFlow
from dualflow.motion.features import FEATURE_SLICES
from dualflow.motion.skeleton import FACE_JOINTS, N_JOINTS


class WindowFrame:
    """The ground-plane frame of one window, from the actor's first frame of the window.

    Training clips are canonicalised at their first frame (``dualflow.motion.features``: the
    actor's root over the origin, facing +Z, Y-up), so a window deep into a stream -- the actor
    metres away, turned -- would be out of distribution. Each window is therefore moved into
    its own canonical frame before generation and the result moved back:

        local = R (p - o),  p = R^T local + o    for joint positions (metres),
        local = R v,        v = R^T local        for joint velocities (metres per frame),

    with o = (root_x, 0, root_z) of the actor's first window frame and R the yaw about +Y
    taking its facing (up x across, across = (r_hip - l_hip) + (r_sho - l_sho)) to +Z. The
    6D rotations are parent-relative and the contacts scalar, so they do not change. Only the
    window's first actor frame is used, so the reactive causality is kept.
    raw: de-normalised features (T, 262).
    """

    def __init__(self, first_actor_raw: torch.Tensor):
        p = first_actor_raw[FEATURE_SLICES["positions"]].double().reshape(N_JOINTS, 3)
        r_hip, l_hip, r_sho, l_sho = FACE_JOINTS
        across = (p[r_hip] - p[l_hip]) + (p[r_sho] - p[l_sho])
        up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
        forward = torch.linalg.cross(up, across)
        forward[1] = 0.0
        norm = torch.linalg.vector_norm(forward)
        if norm < 1e-9:
            self.rotation = torch.eye(3, dtype=torch.float64)
        else:
            f = forward / norm
            self.rotation = torch.stack([torch.linalg.cross(up, f), up, f])  # rows: x', y, z'
        self.origin = torch.tensor([float(p[0, 0]), 0.0, float(p[0, 2])], dtype=torch.float64)

    def _apply(self, raw: torch.Tensor, inverse: bool) -> torch.Tensor:
        out = raw.double().clone()
        pos = out[..., FEATURE_SLICES["positions"]].reshape(*out.shape[:-1], N_JOINTS, 3)
        vel = out[..., FEATURE_SLICES["velocities"]].reshape(*out.shape[:-1], N_JOINTS, 3)
        if inverse:
            pos = pos @ self.rotation + self.origin
            vel = vel @ self.rotation
        else:
            pos = (pos - self.origin) @ self.rotation.T
            vel = vel @ self.rotation.T
        out[..., FEATURE_SLICES["positions"]] = pos.reshape(*out.shape[:-1], 3 * N_JOINTS)
        out[..., FEATURE_SLICES["velocities"]] = vel.reshape(*out.shape[:-1], 3 * N_JOINTS)
        return out.to(raw.dtype)

    def to_local(self, raw: torch.Tensor) -> torch.Tensor:
        return self._apply(raw, inverse=False)

    def to_global(self, raw: torch.Tensor) -> torch.Tensor:
        return self._apply(raw, inverse=True)


#: Frames per noise block: the noise of frames [64 b, 64 b + 64) comes from one generator
#: seeded with (seed, b), so a frame's noise never depends on how the stream was pushed.
NOISE_BLOCK = 64


def _noise_block(seed: int, block: int, dim: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(int(seed) * 1_000_003 + int(block))
    return torch.randn((NOISE_BLOCK, dim), generator=gen)


def stream_noise(seed: int, n_frames: int, dim: int = 262) -> torch.Tensor:
    """The initial noise eps (n_frames, dim) a ``ReactiveStreamer`` with this seed uses."""
    blocks = [_noise_block(seed, b, dim) for b in range(-(-n_frames // NOISE_BLOCK))]
    return torch.cat(blocks, 0)[:n_frames] if blocks else torch.zeros(0, dim)


@dataclass(frozen=True)
class StreamConfig:
    """window: frames per generation window W (actor and reactor); must exceed L + hop.
    hop: generate once at least this many frames are pending (1 = emit every frame as soon as
    its look-ahead arrives: delay exactly L frames; larger hops amortise the compute and add
    up to hop - 1 frames of delay). max_new: cap on frames emitted by one window (chunks).
    steps / method / cfg_scale: the ODE sampler (``dualflow.flow``). look_ahead: L (None =
    the model's). inpaint: keep emitted frames as context (False only for ablations: each
    window then starts from noise everywhere and the seams jump). context: "trajectory"
    (replay the emitted frames' own ODE states) or "path" (straight-line re-noising); see the
    module docstring. seed: noise seed.
    incremental: keep each frame's activations in fixed-start windows and compute only the
    new frames (``dualflow.incremental``; same model, each frame computed once per step and
    start instead of once per step and window; Euler, cfg_scale 1, trajectory context only).
    bases: how many staggered window starts it keeps (context P - P / bases .. P - 1 frames,
    P = window - L; cost proportional to bases). prefetch: in idle time (``prepare``), make
    the part of the next pass's convolutions that reads only older frames, so that a frame
    waits for fewer products (``WindowCache.prefetch``; the same results to float rounding).
    cuda_graph: on a CUDA device, a full window (not incremental) of a shape seen before is
    replayed from a CUDA graph: the actor stream, every ODE step and the context's inpainting
    in one launch (``dualflow.cuda_graph``; the same kernels). The second window of a shape
    captures it, which costs that window about three windows' time (once per shape and
    streamer; a live caller that restarts its streamer pays it again). precision: the matrix
    products on CUDA, as ``dualflow.flow.SamplingSettings.precision`` ("bf16": full windows only).
    """

    window: int = 60
    hop: int = 1
    recanonicalize: bool = False
    max_new: int | None = None
    steps: int = 20
    method: str = "euler"
    cfg_scale: float = 1.0
    look_ahead: int | None = None
    inpaint: bool = True
    context: str = "trajectory"
    seed: int = 0
    incremental: bool = False
    bases: int = 2
    prefetch: bool = True
    cuda_graph: bool = True
    precision: str = "tf32"


@dataclass
class StreamTiming:
    """Compute time of the generation windows: per emitted frame and per window (seconds)."""

    windows: list[tuple[int, int, float]] = field(default_factory=list)  # (first frame, n new, s)

    @property
    def total_s(self) -> float:
        return sum(w[2] for w in self.windows)

    @property
    def frames(self) -> int:
        return sum(w[1] for w in self.windows)

    @property
    def per_frame_s(self) -> float:
        """Average compute time per emitted reactor frame."""
        return self.total_s / max(self.frames, 1)

    @property
    def max_window_s(self) -> float:
        """Longest window: the worst added latency beyond the L-frame delay."""
        return max((w[2] for w in self.windows), default=0.0)


class CatchUpWork(Protocol):
    """The catch-up protocol: work a streamer can do ahead, in its caller's idle time.

    An incremental stream has work that no emitted frame waits for yet: feeding emitted
    frames' recorded states to the window starts that take over later, making the next
    start, and the next pass's convolution prefetch. The window that needs a piece does it
    itself if it is still left, so doing it earlier only moves compute off a frame's
    critical path. The streamer says what work exists; its caller decides when it runs.

    The caller may use, on the streamer's thread between ``push`` / ``flush`` calls:

    * ``idle_jobs() -> list[str]``: the kinds of work due now, in the order to do them
      (``ReactiveStreamer.IDLE_JOBS``). Bookkeeping only, no network pass. Empty when
      nothing is due, and always for a stream that is not incremental. What is due changes
      with every ``push``: ask again after each.
    * ``urgent_jobs``: the kinds that the next window would do in full itself if left
      ("takeover", "start"): started in a gap too short for it, such a piece delays the next
      frame by less than its own cost, which that frame would otherwise pay whole. The
      other kinds only pay off when they end before the caller's next input.
    * ``prepare(max_passes=1, kinds=None) -> bool``: do up to ``max_passes`` pieces, each
      the first kind due (among ``kinds`` if given); returns whether work is still due.
      One piece, in one-row network passes (every ODE step in the same pass): "takeover"
      about one (the frames the start about to take over lacks), "start" about one (a new
      start caching its actor rows), "feed" about 1.5 (``FEED_BATCH`` or more rows per step
      for a background start), "prefetch" a fraction of one. The costs differ several-fold,
      so a caller timing pieces should time each kind on its own.

    Guarantees: the emitted frames are the same, to float rounding, whether catch-up work
    is done, when and how much (tests/test_incremental.py); each piece is complete, so the
    caller may stop after any one. ``has_catch_up`` is ``bool(idle_jobs())``.
    """

    urgent_jobs: tuple[str, ...]

    def idle_jobs(self) -> list[str]: ...

    def prepare(self, max_passes: int = 1, kinds: Iterable[str] | None = None) -> bool: ...


class ReactiveStreamer:
    """Feed actor frames, get reactor frames (module docstring). One stream, batch 1.
    Offers its catch-up work through ``CatchUpWork``.

    model: a DualFlow (its reactive mode). cond: Conditions for the whole stream with batch 1:
    text (1, D_text), music (1, T_track, D_music) covering every frame the stream will reach
    (sliced per window; a live track must be known L frames ahead too), retrieval (1, R, width).
    on_frame(index, frame (262,) tensor): called for each emitted frame, in order.
    stats: the normalisation statistics of the model's training data (a ``NormStats`` or any
    object with ``mean`` and ``std`` (262,)); needed for ``config.recanonicalize``.
    """

    def __init__(
        self,
        model: DualFlow,
        config: StreamConfig = StreamConfig(),
        cond: Conditions | None = None,
        on_frame: Callable[[int, torch.Tensor], None] | None = None,
        stats=None,
    ):
        self.model = model
        self.config = config
        self.cond = cond or Conditions()
        self.on_frame = on_frame
        self.look_ahead = model.config.look_ahead if config.look_ahead is None else int(config.look_ahead)
        self.max_new = config.max_new or max(config.hop, (config.window - self.look_ahead) // 2)
        if config.incremental:
            self._check_incremental(config)
            # the newest start, at most one stagger old, must hold every frame of a window
            span = config.window - self.look_ahead
            self._stagger = max(1, span // max(1, int(config.bases)))
            self.max_new = max(1, min(self.max_new, span - self._stagger))
            if config.hop > self.max_new:
                raise DualFlowError(
                    f"StreamConfig: hop {config.hop} exceeds the {self.max_new} new frames an incremental "
                    f"window can take (window {config.window} - look-ahead {self.look_ahead}, "
                    f"{config.bases} starts); lower hop or bases, or raise window"
                )
        if config.precision not in PRECISIONS or (config.incremental and config.precision == "bf16"):
            raise DualFlowError(
                f"StreamConfig.precision must be one of {PRECISIONS} ('bf16' with incremental=False only), "
                f"got {config.precision!r}"
            )
        if config.context not in ("trajectory", "path"):
            raise DualFlowError(f"StreamConfig.context must be 'trajectory' or 'path', got {config.context!r}")
        if config.hop < 1:
            raise DualFlowError(f"StreamConfig.hop must be >= 1 frame, got {config.hop}")
        if config.window < self.look_ahead + self.max_new + 1:
            raise DualFlowError(
                f"StreamConfig.window ({config.window}) must be at least look_ahead ({self.look_ahead}) + "
                f"max_new ({self.max_new}) + 1 so a window holds context, new frames and look-ahead; "
                "raise window or lower hop/max_new"
            )
        for name in ("text", "music", "retrieval"):
            value = getattr(self.cond, name)
            if value is not None and value.shape[0] != 1:
                raise DualFlowError(f"streaming conditions: {name} must have batch size 1, got {tuple(value.shape)}")
        param = next(model.parameters())
        self.device, self.dtype = param.device, param.dtype
        self.dim = model.config.motion_dim
        self._actor = torch.zeros(0, self.dim, dtype=self.dtype, device=self.device)
        self._emitted = torch.zeros(0, self.dim, dtype=self.dtype, device=self.device)
        self._noise = torch.zeros(0, self.dim)
        self.timing = StreamTiming()
        self.path = RectifiedPath()
        # ODE states of the last emitted frames at every grid time: (n, steps + 1, 262), frame
        # index of row 0 = self._traj_start (only the last `window` frames are kept).
        # (incremental mode: the states at t_0 .. t_{S-1} only, for feeding the other window starts)
        self._traj = torch.zeros(
            0, config.steps + (0 if config.incremental else 1), self.dim, dtype=self.dtype, device=self.device
        )
        self._traj_start = 0
        self._graphs: dict = {}  # full windows on CUDA: GraphedCall (None: seen once) per shape (``_window_graph``)
        self._graphs_weights = None  # the model's weights the graphs were captured with (``_weights_key``)
        self._inc = None  # incremental mode: dualflow.incremental.IncrementalModel, built on first use
        self._bases: list = []  # incremental mode: dualflow.incremental.WindowCache, oldest first
        self._mean = self._std = None
        if stats is not None and config.recanonicalize:
            self._mean = torch.tensor(np.array(stats.mean), dtype=self.dtype, device=self.device)
            self._std = torch.tensor(np.array(stats.std), dtype=self.dtype, device=self.device)
            if self._mean.shape != (self.dim,) or self._std.shape != (self.dim,):
                raise DualFlowError(f"streaming stats: mean and std must have shape ({self.dim},)")

    # -- state ---------------------------------------------------------------------------

    @property
    def emitted(self) -> torch.Tensor:
        """All reactor frames emitted so far, (N, 262) normalised features."""
        return self._emitted

    @property
    def n_actor(self) -> int:
        return self._actor.shape[0]

    @property
    def delay_frames(self) -> int:
        """Frames between receiving actor frame i + L and emitting reactor frame i: L + hop - 1 at most."""
        return self.look_ahead + self.config.hop - 1

    # -- input ---------------------------------------------------------------------------

    @property
    def pending(self) -> int:
        """Reactor frames whose look-ahead has arrived but that are not generated yet."""
        return max(0, self.n_actor - self.look_ahead - self._emitted.shape[0])

    def push(self, frames, max_windows: int | None = None, revise: int = 0) -> torch.Tensor:
        """Append actor frames (262,) or (n, 262) and return the newly emitted reactor frames (m, 262).

        ``max_windows``: generate at most this many windows now (None: every window that is
        due). A real-time caller passes 1 and pushes again (possibly zero frames, shape
        (0, 262)) while ``pending >= hop``, so that it can look at newer input between windows.
        ``revise``: the first ``revise`` of ``frames`` replace the last ``revise`` actor rows
        pushed before. For provisional rows: the newest actor frame's 262-d row needs the
        next frame (its velocity), so a live caller may push it encoded with a predicted next
        frame and revise it when the true one arrives. Reactor frames already emitted stay as
        they are (they were computed from what had arrived then); later windows read the
        revised rows.
        """
        x = torch.as_tensor(np.asarray(frames) if not torch.is_tensor(frames) else frames)
        if x.ndim == 1:
            x = x[None]
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise DualFlowError(
                f"actor frames must have shape ({self.dim},) or (n, {self.dim}) (normalised features), "
                f"got {tuple(x.shape)}"
            )
        if not torch.isfinite(x).all():
            raise DualFlowError("actor frames contain NaN or inf; drop or repair those frames before pushing")
        revise = int(revise)
        if not 0 <= revise <= min(x.shape[0], self.n_actor):
            raise DualFlowError(
                f"push(revise={revise}): can replace between 0 and min(new rows {x.shape[0]}, "
                f"rows pushed {self.n_actor}) rows"
            )
        for b in self._bases:
            b.forget_actor(self.n_actor - revise)
        kept = self._actor[: self.n_actor - revise]
        self._actor = torch.cat([kept, x.to(self.device, self.dtype)], 0)
        return self._drain(final=False, max_windows=max_windows)

    def flush(self, max_windows: int | None = None) -> torch.Tensor:
        """End of stream: emit the remaining frames (their look-ahead is cut at the last actor frame);
        ``max_windows`` as in ``push`` (call again until it returns no frames)."""
        return self._drain(final=True, max_windows=max_windows)

    # -- generation ----------------------------------------------------------------------

    def _denorm(self, x: torch.Tensor) -> torch.Tensor:
        return x * self._std + self._mean

    def _norm(self, raw: torch.Tensor) -> torch.Tensor:
        return (raw - self._mean) / self._std

    def _drain(self, final: bool, max_windows: int | None = None) -> torch.Tensor:
        out = []
        while max_windows is None or len(out) < max_windows:
            n_done = self._emitted.shape[0]
            limit = self.n_actor if final else self.n_actor - self.look_ahead  # frames [0, limit) emittable
            pending = limit - n_done
            if pending <= 0 or (pending < self.config.hop and not final):
                break
            upto = n_done + min(pending, self.max_new)
            out.append(self._generate(n_done, upto))
        if not out:
            return self._emitted[:0]
        return torch.cat(out, 0)

    def _noise_rows(self, stop: int) -> torch.Tensor:
        """eps of absolute frames [0, stop) (``stream_noise``), extended block by block."""
        have = self._noise.shape[0]
        if stop > have:
            n_blocks = -(-stop // NOISE_BLOCK)
            first = have // NOISE_BLOCK
            fresh = [_noise_block(self.config.seed, b, self.dim) for b in range(first, n_blocks)]
            self._noise = torch.cat([self._noise[: first * NOISE_BLOCK]] + fresh, 0)
        return self._noise[:stop]

    def _check_music(self, stop: int) -> None:
        """The music track must cover frames [0, stop) of the stream."""
        music = self.cond.music
        if music is not None and music.shape[1] < stop:
            raise DualFlowError(
                f"streaming conditions: the music track has {music.shape[1]} frames but the stream reached "
                f"frame {stop}; give a track covering the whole stream (or no music)"
            )

    def _window_conditions(self, start: int, stop: int) -> Conditions:
        self._check_music(stop)
        return self.cond.slice_frames(start, stop)

    @staticmethod
    def _check_incremental(config: StreamConfig) -> None:
        bad = [
            f"{name} {value!r}"
            for name, value, ok in (
                ("method", config.method, config.method == "euler"),
                ("cfg_scale", config.cfg_scale, config.cfg_scale == 1.0),
                ("context", config.context, config.context == "trajectory"),
                ("inpaint", config.inpaint, config.inpaint),
                ("recanonicalize", config.recanonicalize, not config.recanonicalize),
                ("bases", config.bases, config.bases >= 1),
            )
            if not ok
        ]
        if bad:
            raise DualFlowError(
                "StreamConfig(incremental=True) supports Euler steps, cfg_scale 1, trajectory context "
                f"with inpainting, no recanonicalize and bases >= 1; got {', '.join(bad)}"
            )

    def _emit(self, first_new: int, new: torch.Tensor, tic: float) -> torch.Tensor:
        self._emitted = torch.cat([self._emitted, new], 0)
        self.timing.windows.append((first_new, new.shape[0], time.perf_counter() - tic))
        if self.on_frame is not None:
            for k in range(new.shape[0]):
                self.on_frame(first_new + k, new[k])
        return new

    @torch.no_grad()
    def _generate_incremental(self, first_new: int, upto: int) -> torch.Tensor:
        """Frames [first_new, upto) in the oldest cached window start that holds them; every
        other live start is fed their states (``dualflow.incremental``)."""
        from dualflow.flow import time_grid
        from dualflow.incremental import IncrementalModel, WindowCache

        tic = time.perf_counter()
        grid = time_grid(self.config.steps)
        W, L = self.config.window, self.look_ahead
        self._check_music(max(upto, min(upto + L, self.n_actor)))  # the frames these rows condition on
        if self._inc is None:
            self._inc = IncrementalModel(self.model)
        if not self._bases:
            self._bases.append(WindowCache(self._inc, first_new, W, L, self.cond, grid[:-1]))
        elif first_new >= self._next_start():  # normally made in idle time already (``prepare``)
            self._add_start()
        self._bases = [b for b in self._bases if b.can_generate(upto - 1)]
        if not self._bases:  # cannot happen with max_new as set in __init__; a fresh start is still correct
            self._bases = [WindowCache(self._inc, first_new, W, L, self.cond, grid[:-1])]
        gen = self._bases[0]
        while self._feed(gen):  # frames it has not seen yet (normally fed while idle)
            pass
        x = self._noise_rows(upto)[first_new:upto].to(self.device, self.dtype)[None]
        states = []
        for k in range(len(grid) - 1):
            states.append(x[0])
            # the new actor rows go through the network with step 0's rows, in one pass
            x = x + (grid[k + 1] - grid[k]) * gen.reactor_rows(k, x, actor=self._actor if k == 0 else None)
        # every step's state of the new frames, for the other starts (``prepare``)
        self._traj = torch.cat([self._traj, torch.stack(states, 1)], 0)
        drop = max(0, self._traj.shape[0] - self.config.window)
        self._traj, self._traj_start = self._traj[drop:], self._traj_start + drop
        return self._emit(first_new, x[0], tic)

    def _next_start(self) -> int:
        """Where the next cached window start goes: one stagger after the newest."""
        return self._bases[-1].start + self._stagger

    def _add_start(self) -> None:
        from dualflow.flow import time_grid
        from dualflow.incremental import WindowCache

        grid = time_grid(self.config.steps)
        self._bases.append(
            WindowCache(self._inc, self._next_start(), self.config.window, self.look_ahead, self.cond, grid[:-1])
        )

    def _feed(self, base, batch: int = 1) -> bool:
        """One pass of catch-up work for a cached start: the recorded states of the emitted
        frames it has not seen, at every grid step that lacks at least ``batch`` of them, all
        in one pass (``WindowCache.feed``), with the actor rows it has not cached yet.
        Returns False when it had nothing to do (actor rows alone are never worth a pass:
        the generating start takes them with its first step's rows).

        ``batch`` > 1 (idle-time catch-up): a start is fed only once it lags that many
        frames, so that its passes carry several rows each (on a CPU a pass is mostly
        per-operation overhead: 8 rows per step cost about 1.5 times 1 row)."""
        n_done = self._emitted.shape[0]
        rows = []
        for k, cache in enumerate(base.reactor):
            lo = base.start + cache.n
            if n_done - lo >= batch:
                rows.append((k, self._traj[lo - self._traj_start : n_done - self._traj_start, k][None]))
        if rows:
            base.feed(rows, actor=self._actor)
        return bool(rows)

    #: incremental mode: a window start that is not generating is fed once it lags this many
    #: emitted frames (a pass over 8 rows costs about 1.5 times one over 1 row on a CPU); what is left
    #: when it takes over is fed then
    FEED_BATCH = 8
    #: ... except the start that takes over within this many frames: fed everything it lacks
    #: (still in idle time), so that the window that switches to it has only its own passes
    TAKEOVER_FRAMES = 3

    #: the kinds of catch-up work (``CatchUpWork``), in the order ``prepare`` takes them when several are due
    IDLE_JOBS = ("takeover", "start", "feed", "prefetch")
    #: ``CatchUpWork.urgent_jobs``: the kinds that a frame within ``TAKEOVER_FRAMES`` does itself,
    #: in full, if they were left
    urgent_jobs: tuple[str, ...] = ("takeover", "start")

    def idle_jobs(self) -> list[str]:
        """``CatchUpWork.idle_jobs``. "takeover": one pass of the frames that the start taking
        over within ``TAKEOVER_FRAMES`` has not seen (usually one row per grid step); "start":
        make the next window start and cache the actor rows it holds; "feed": one pass of
        ``FEED_BATCH`` or more rows per grid step for a background start; "prefetch": the next
        generator's share of its next pass's convolutions."""
        return [kind for kind, _ in self._idle_work()]

    def _idle_work(self) -> list[tuple[str, object]]:
        """(kind, what it works on) for each kind of catch-up work due now, in ``IDLE_JOBS``
        order: "takeover" and "feed" the first (start, batch) of ``_due`` with their batch,
        "start" None, "prefetch" the start to prefetch for."""
        if not self.config.incremental:
            return []
        starts = self._due()
        work: dict[str, object] = {}
        for base, batch in starts:
            work.setdefault("takeover" if batch == 1 else "feed", (base, batch))
        if self._start_due():
            work["start"] = None
        gen = self._prefetch_target(starts)
        if gen is not None:
            work["prefetch"] = gen
        return [(kind, work[kind]) for kind in self.IDLE_JOBS if kind in work]

    @torch.no_grad()
    def prepare(self, max_passes: int = 1, kinds=None) -> bool:
        """``CatchUpWork.prepare``: up to ``max_passes`` pieces of catch-up work now (each the
        first kind due, among ``kinds`` if given), so that a window has only its own passes to
        do. Returns whether more catch-up work is due."""
        for _ in range(max(0, int(max_passes))):
            work = [(kind, on) for kind, on in self._idle_work() if kinds is None or kind in kinds]
            if not work:
                break
            kind, on = work[0]
            if kind == "start":
                self._add_start()
                self._bases[-1].sync_actor(self._actor)
            elif kind == "prefetch":
                on.prefetch(rows=self.config.hop + 1)
            else:
                self._feed(*on)
        return self.has_catch_up

    def _next_generator(self):
        """The cached window start that will generate the next frames (None: none can yet)."""
        n_done = self._emitted.shape[0]
        return next((b for b in self._bases if b.can_generate(n_done + self.config.hop - 1)), None)

    def _prefetch_target(self, due: list):
        """The window start whose ``prefetch`` is due: the next generator, once it has been
        fed every frame it lacks (not among ``due``, the ``_due()`` list: a feed moves its
        streams on), else None."""
        gen = self._next_generator() if self.config.prefetch else None
        if gen is None or not gen.prefetch_due() or any(b is gen for b, _ in due):
            return None
        return gen

    def _start_due(self) -> bool:
        """Whether the next window start should be made now: its first frame is at most
        ``TAKEOVER_FRAMES`` away (making one costs about a pass; not in a window that needs it)."""
        return bool(self._bases) and self._emitted.shape[0] + self.TAKEOVER_FRAMES > self._next_start()

    def _due(self) -> list:
        """The window starts whose catch-up work is due, with the batch to feed them in (see
        ``FEED_BATCH`` and ``TAKEOVER_FRAMES``)."""
        if not self._bases:
            return []
        n_done = self._emitted.shape[0]
        due = []
        for i, b in enumerate(self._bases[1:], 1):
            lag = n_done - (b.start + min(c.n for c in b.reactor))
            if i == 1 and not self._bases[0].can_generate(n_done + self.TAKEOVER_FRAMES - 1):
                if lag > 0:
                    due.append((b, 1))
            elif lag >= self.FEED_BATCH:
                due.append((b, self.FEED_BATCH))
        return due

    @property
    def has_catch_up(self) -> bool:
        """Whether ``prepare`` has work due (``idle_jobs`` is not empty)."""
        return bool(self.idle_jobs())

    @torch.no_grad()
    def _generate(self, first_new: int, upto: int) -> torch.Tensor:
        """Generate and emit reactor frames [first_new, upto) in one window."""
        with precision_context(self.device, self.config.precision):
            if self.config.incremental:
                return self._generate_incremental(first_new, upto)
            return self._generate_window(first_new, upto)

    @torch.no_grad()
    def _generate_window(self, first_new: int, upto: int) -> torch.Tensor:
        """One full window over the frames [first_new - context, upto + L) (module docstring)."""
        tic = time.perf_counter()
        stop = min(upto + self.look_ahead, self.n_actor)
        stop = max(stop, upto)
        start = max(0, stop - self.config.window)
        n_ctx = first_new - start  # already-emitted frames kept as context
        actor = self._actor[start:stop]
        eps = self._noise_rows(stop)[start:stop].to(self.device, self.dtype)[None]
        known = self._emitted[start:first_new]
        frame = None
        if self._mean is not None:  # move the window into its own canonical frame
            frame = WindowFrame(self._denorm(actor[0]))
            actor = self._norm(frame.to_local(self._denorm(actor)))
            known = self._norm(frame.to_local(self._denorm(known)))
        actor, known = actor[None], known[None]
        n_new = upto - first_new
        use_traj = self.config.context == "trajectory" and frame is None
        ctx_traj = None
        if use_traj and n_ctx > 0:
            ctx_traj = self._traj[start - self._traj_start : first_new - self._traj_start]  # (n_ctx, S+1, D)
        cond = self._window_conditions(start, stop)
        # Module.train()/eval() walk every submodule (~3 ms each for the small model): switch only
        # when needed, not twice per window
        was_training = self.model.training
        if was_training:
            self.model.eval()
        try:
            # (a model in training mode changes between windows: no graph of its weights)
            graphed = (
                self._window_graph(stop - start, n_ctx, n_new) if ctx_traj is not None and not was_training else None
            )
            if graphed is not None:
                music = () if cond.music is None else (cond.music,)
                new, record = graphed(actor, eps, ctx_traj, *music)
            else:
                new, record = self._solve_window(cond, n_ctx, n_new, actor, eps, ctx_traj, known)
        finally:
            if was_training:
                self.model.train(True)
        if use_traj:
            self._traj = torch.cat([self._traj, record], 0)
            drop = max(0, self._traj.shape[0] - self.config.window)
            self._traj, self._traj_start = self._traj[drop:], self._traj_start + drop
        if frame is not None:
            new = self._norm(frame.to_global(self._denorm(new)))
        return self._emit(first_new, new, tic)

    def _solve_window(self, cond, n_ctx, n_new, actor, eps, ctx_traj, known=None):
        """The window's ODE solve: (its new frames (n_new, D), their state at every grid time
        (n_new, S + 1, D)). Context frames are held at ``ctx_traj``'s states (trajectory
        context) or on the straight path to ``known`` (see ``StreamConfig.context``)."""
        steps = self.config.steps
        record = torch.zeros(n_new, steps + 1, self.dim, dtype=self.dtype, device=self.device)

        def project(x: torch.Tensor, t: float) -> torch.Tensor:
            k = int(round(t * steps))
            if n_ctx > 0 and self.config.inpaint:
                x = x.clone()
                if ctx_traj is not None:
                    x[:, :n_ctx] = ctx_traj[:, k]  # the context's own state at t_k
                else:
                    x[:, :n_ctx] = (1 - t) * eps[:, :n_ctx] + t * known  # x_t on the straight path
            record[:, k] = x[0, n_ctx : n_ctx + n_new]  # the last write at t_k is the state
            return x

        velocity = guided_velocity(
            self.model,
            cond,
            mode="reactive",
            x_actor=actor,
            cfg_scale=self.config.cfg_scale,
            look_ahead=self.look_ahead,
        )
        if self.config.precision == "bf16" and self.device.type == "cuda":
            velocity = bf16_velocity(velocity, self.dtype)
        x = ode_solve(velocity, eps, steps=steps, method=self.config.method, project=project)
        return x[0, n_ctx : n_ctx + n_new], record

    #: at most this many window shapes get a CUDA graph (a steady stream uses one; the rest,
    #: the first and last windows, run eagerly)
    MAX_WINDOW_GRAPHS = 4

    def _window_graph(self, width: int, n_ctx: int, n_new: int):
        """The ``GraphedCall`` of a window of this shape with trajectory context, or None
        (``StreamConfig.cuda_graph`` off, not on CUDA, or a window not worth a graph: one not
        yet full, the first of its shape (a shape seen once, like the last window's, would cost
        a capture and two warm-up runs), or more shapes than ``MAX_WINDOW_GRAPHS``). Its inputs: the actor rows, the
        noise, the context's trajectory and the music rows (when the stream has music);
        text and retrieval are the stream's, the same for every window."""
        if not (self.config.cuda_graph and self.device.type == "cuda" and width == self.config.window):
            return None
        weights = _weights_key(self.model)
        if weights != self._graphs_weights:  # a graph replays the weights it was captured with
            self._graphs, self._graphs_weights = {}, weights
        key = (width, n_ctx, n_new)
        graphed = self._graphs.get(key)
        if graphed is None and key not in self._graphs:  # a shape's first window runs eagerly
            self._graphs[key] = None
        elif graphed is None and sum(g is not None for g in self._graphs.values()) < self.MAX_WINDOW_GRAPHS:
            from dualflow.cuda_graph import GraphedCall

            def solve(actor, eps, ctx_traj, music=None):
                cond = self.cond if music is None else replace(self.cond, music=music)
                return self._solve_window(cond, n_ctx, n_new, actor, eps, ctx_traj)

            graphed = self._graphs[key] = GraphedCall(solve, names=("actor", "noise", "context", "music"))
        return graphed


def _weights_key(model: torch.nn.Module) -> tuple:
    """Where each parameter's data is and how often it was changed in place: another key means
    other weights than a CUDA graph captured (moved, loaded or trained since)."""
    return tuple((p.data_ptr(), 0 if p.is_inference() else p._version) for p in model.parameters())


# ---------------------------------------------------------------------------------------------
# Seam continuity
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SeamReport:
    """Velocity jumps ||(p[i] - p[i-1]) - (p[i-1] - p[i-2])|| averaged over joints (units of p per
    frame), at window seams (frames i - 2, i - 1, i span two windows: i = s and s + 1 for a window
    starting at s) and inside windows (all three frames from one window).
    ratio = seam / within: about 1 means the seams are invisible."""

    seam_mean: float
    within_mean: float
    n_seams: int
    n_within: int

    @property
    def ratio(self) -> float:
        return self.seam_mean / self.within_mean if self.within_mean > 0 else float("inf")


def seam_report(positions: torch.Tensor | np.ndarray, window_starts: list[int]) -> SeamReport:
    """positions (N, J, 3) (or (N, D) features) of the emitted frames; window_starts: the first
    frame index of each window (``[w[0] for w in streamer.timing.windows]``)."""
    p = torch.as_tensor(np.asarray(positions) if not torch.is_tensor(positions) else positions).double()
    p = p.reshape(p.shape[0], -1, p.shape[-1]) if p.ndim == 3 else p.reshape(p.shape[0], 1, -1)
    if p.shape[0] < 3:
        raise DualFlowError(f"seam_report needs at least 3 frames, got {p.shape[0]}")
    acc = torch.linalg.vector_norm(p[2:] - 2 * p[1:-1] + p[:-2], dim=-1).mean(-1)  # jump at frame i = 2..N-1
    window_id = torch.zeros(p.shape[0], dtype=torch.long)
    for k, s in enumerate(sorted(window_starts)):
        window_id[s:] = k
    idx = torch.arange(2, p.shape[0])
    seam = window_id[idx] != window_id[idx - 2]  # the triple (i-2, i-1, i) spans a seam
    within = ~seam
    seam_vals, within_vals = acc[seam], acc[within]
    return SeamReport(
        seam_mean=float(seam_vals.mean()) if seam_vals.numel() else 0.0,
        within_mean=float(within_vals.mean()) if within_vals.numel() else 0.0,
        n_seams=int(seam_vals.numel()),
        n_within=int(within_vals.numel()),
    )
