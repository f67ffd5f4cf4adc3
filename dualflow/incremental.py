"""Incremental reactive inference: each new frame computed once per ODE step, not a whole window.

Why: a streamed window of W frames recomputes every context frame at every ODE step to
emit a few new ones; on a CPU that is most of the partner's latency (a 60-frame window at
2 Euler steps: ~80 ms for one new frame). The reactive network is causal (``dualflow.model``:
causal self-attention, left-padded convolutions, the reactor reads actor frames j <= i + L),
so inside one window a frame's activations depend only on earlier frames. With trajectory
context (``dualflow.streaming``: a context frame's state at grid time t_k is replayed as it
was generated) the activations of the frames already emitted are therefore the same in
every later window *with the same start*, and can be kept.

The positional encoding is absolute within a window (position p - s for a window starting
at frame s, 0 <= p - s < W), so a window start cannot move; a :class:`WindowCache` is one
fixed start s. It holds, per block:

* the block input z of every frame so far (the causal convolutions read k - 1 frames back);
* the self-attention keys and values K_j = W_K LN(z'_j), V_j = W_V LN(z'_j);
* for the actor stream also its motion keys LN0(z^(2)_a) through the reactor's motion
  cross-attention projections (they do not depend on t: computed once);

for the actor stream once and for the reactor once per ODE grid time t_k (the adaptive
LayerNorms depend on t). Generating frames [p0, p1) runs only those rows through the
network at each step, attending to the cached keys: for new row i (frame p),

    self-attention keys: frames s .. p,   motion cross-attention keys: actor s .. p + L,

exactly the rows a full window [s, s + W) would let it see (tests/test_incremental.py
checks equality with the full forward). Cost per frame: about one network pass of one row
per step instead of one of W rows.

A start serves frames p with p + L - s <= W - 1, i.e. P = W - L of them. The streamer keeps
``bases`` staggered starts D = P / bases apart: the oldest generates (its context is the
longest, P - D .. P - 1 frames), the others are fed every emitted frame's recorded states
(teacher forcing, outputs unused; ``WindowCache.feed``: every grid step's rows in one pass,
like the shared-weight products below) so that they are ready when the oldest runs out.
Cost: ``bases`` times the rows per frame and step; context never shorter than P - D.
The music latent of a start is computed once over its frames [s, s + W) (the stream's
music track is known ahead); text, retrieval and the time embeddings once per start.

A CPU spends most of a one-row pass on per-operation overhead, so a pass does the same
arithmetic in fewer operations (equal to the full forward up to float rounding):

* the adaptive LayerNorms' (scale, shift) = W SiLU(z_d) + b depend only on z_d: once per
  start and grid time;
* the music and retrieval keys/values do not depend on the motion: once per start; with a
  single key (the learned null token) attention returns that key's value whatever the query
  (softmax over one logit is 1), so the whole sub-layer is a constant;
* the three causal convolutions (kernels k_1 < k_2 < k_3): one matrix product each over
  the last k block inputs, laid out tap-major so that each reads a contiguous slice of one
  history matrix: y_k(p) = sum_{d < k} W_k[:, :, d] z(p - k + 1 + d). (A one-row pass is
  bound by reading the weights from memory; an earlier single product with the smaller
  kernels zero-padded to k_3 read 1.6x the bytes.)
* the self-attention's query and key/value projections are one (3W, W) product;
* the generating start's new actor rows and its first grid step's reactor rows go through
  the blocks in one pass (``reactor_rows(actor=...)``): the products with the shared
  weights (convolutions, self-attention projections, feed-forward) run once over both row
  sets stacked; the attention and the modulated norms stay per stream. The actor stream of
  a block is computed before the reactor's motion cross-attention reads its keys, so this
  equals a separate ``sync_actor`` followed by ``reactor_rows``;
* in idle time before a frame (``WindowCache.prefetch``), the convolutions' products over the
  frames before the next rows are made: the frame's pass then multiplies only the newest one
  or two taps of each kernel (about a fifth of a block's weights were the rest of the taps).

Limits: Euler steps, ``cfg_scale`` 1 (one conditional pass), trajectory context, no
per-window canonical frames (``ReactiveStreamer`` checks and says so).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from dualflow.model import MODES, Conditions, DualFlow, sinusoidal_encoding


class _StreamCache:
    """Per-block caches of one stream (the actor, or the reactor at one grid time)."""

    def __init__(self, n_blocks: int):
        self.z_in: list[torch.Tensor | None] = [None] * n_blocks  # (1, N, W) block inputs
        self.k: list[torch.Tensor | None] = [None] * n_blocks  # (1, H, N, dh) self-attention
        self.v: list[torch.Tensor | None] = [None] * n_blocks
        self.n = 0  # frames cached
        #: ``WindowCache.prefetch``: the first row b it was made for (None: none made), and per
        #: block the convolutions' products over the frames before b for rows b, b + 1, ...
        self.pre_base: int | None = None
        self.pre: list[torch.Tensor | None] = [None] * n_blocks

    def truncate(self, n: int) -> None:
        """Forget frames >= n (positions relative to the window start)."""
        if self.pre_base is not None and self.pre_base > n:  # it summed frames that are gone
            self.pre, self.pre_base = [None] * len(self.pre), None
        if n >= self.n:
            return
        for j in range(len(self.z_in)):
            if self.z_in[j] is not None:
                self.z_in[j] = self.z_in[j][:, :n]
                self.k[j] = self.k[j][:, :, :n]
                self.v[j] = self.v[j][:, :, :n]
        self.n = n


def _heads(x: torch.Tensor, n_heads: int) -> torch.Tensor:
    """(1, T, W) -> (1, H, T, W / H)."""
    b, t, w = x.shape
    return x.view(b, t, n_heads, w // n_heads).transpose(1, 2)


def _stack(parts: list[torch.Tensor], dim: int) -> torch.Tensor:
    """torch.cat, without a copy for a single part."""
    return parts[0] if len(parts) == 1 else torch.cat(parts, dim)


def _taps(hist: torch.Tensor, n: int, k: int) -> torch.Tensor:
    """The last k frames up to each of the last n rows of ``hist`` (m, W), m <= n + k - 1, one
    row each, tap-major: (n, k * W), row r = hist rows r - k + 1 .. r of the window ending at
    the last one. Rows before the start of ``hist`` are zeros."""
    if hist.shape[0] < n + k - 1:
        hist = F.pad(hist, (0, 0, n + k - 1 - hist.shape[0], 0))
    return hist.reshape(1, -1) if n == 1 else hist.unfold(0, k, 1).transpose(1, 2).reshape(n, -1)


def _kv(attn, context: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Keys and values (1, H, T, dh) of ``dualflow.model.Attention`` over context (1, T, W)."""
    k, v = attn.kv(context).view(1, context.shape[1], 2, attn.n_heads, -1).permute(2, 0, 3, 1, 4)
    return k, v


def _attend(attn, query: torch.Tensor, k: torch.Tensor, v: torch.Tensor, mask) -> torch.Tensor:
    """``dualflow.model.Attention.forward`` with precomputed keys/values (1, H, Tk, dh)."""
    b, tq, w = query.shape
    q = _heads(attn.q(query), attn.n_heads)
    y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
    return attn.out(y.transpose(1, 2).reshape(b, tq, w))


class _Fixed:
    """A cross-attention sub-layer whose keys do not change: cached keys/values, or the
    constant output when there is a single key."""

    def __init__(self, attn, context: torch.Tensor):
        self.attn = attn
        self.k, self.v = _kv(attn, context)
        self.const = None
        if context.shape[1] == 1:  # softmax over one key is 1: the output is that key's value
            self.const = attn.out(self.v.transpose(1, 2).reshape(1, 1, -1))

    def __call__(self, query) -> torch.Tensor:
        """query: (1, n, W), or a function returning it (not called when the output is constant)."""
        if self.const is not None:
            return self.const
        return _attend(self.attn, query() if callable(query) else query, self.k, self.v, None)


class IncrementalModel:
    """A ``DualFlow`` (eval mode) with its convolutions laid out for one-matrix-per-kernel passes.

    Per block and kernel k: the weight (W_out, W_in, k) as (W_out, k * W_in), tap-major, so
    that it multiplies the last k block inputs z(p - k + 1) .. z(p) laid out one after the
    other (a contiguous slice of the block-input history). No zero padding to the largest
    kernel: a one-row pass reads the weights from memory once and multiplies only real taps.
    """

    def __init__(self, model: DualFlow):
        self.model = model
        self.kmax = max(model.config.conv_kernels)
        self.width = model.config.width
        #: per block: [(k, weight (W, k * W) tap-major, bias (W,))] in the block's kernel order
        self.conv: list[list[tuple[int, torch.Tensor, torch.Tensor]]] = []
        #: per block: the self-attention's query and key/value projections as one (3W, W) product
        self.qkv: list[tuple[torch.Tensor, torch.Tensor]] = []
        #: per block: the feed-forward's (W1, b1, W2, b2) (dropout is the identity in eval mode)
        self.ffn: list[tuple[torch.Tensor, ...]] = []
        for block in model.blocks:
            attn, net = block.self_attn, block.ffn.net
            self.qkv.append(
                (
                    torch.cat([attn.q.weight, attn.kv.weight], 0).detach().contiguous(),
                    torch.cat([attn.q.bias, attn.kv.bias], 0).detach(),
                )
            )
            self.ffn.append(
                (net[0].weight.detach(), net[0].bias.detach(), net[3].weight.detach(), net[3].bias.detach())
            )
            self.conv.append(
                [
                    (
                        int(k),
                        c.weight.detach().permute(0, 2, 1).reshape(c.weight.shape[0], -1).contiguous(),
                        c.bias.detach(),
                    )
                    for c, k in zip(block.conv.convs, block.conv.kernels)
                ]
            )
        self._last_taps: dict[tuple[int, int], torch.Tensor] = {}

    def conv_products(self, j: int, windows: torch.Tensor) -> torch.Tensor:
        """Block j's convolutions before their GELU, (n, K * W) for K kernels, of rows of the
        last ``kmax`` frames (n, kmax * W) tap-major: y_k(p) = b_k + sum_{d < k} W_k[:, :, d]
        z(p - k + 1 + d), the kernels side by side."""
        width = self.width
        return torch.cat([F.linear(windows[:, (self.kmax - k) * width :], w, b) for k, w, b in self.conv[j]], 1)

    def last_taps(self, j: int, m: int) -> torch.Tensor:
        """Block j's convolution weights of their last m taps, every kernel side by side, as the
        right factor of a product with rows of the last m frames: (m * W, K * W) (a kernel
        shorter than m padded with zeros in front)."""
        key = (j, m)
        if key not in self._last_taps:
            width, parts = self.width, []
            for k, w, _ in self.conv[j]:
                taps = w[:, max(0, k - m) * width :]
                parts.append(F.pad(taps, ((m - min(k, m)) * width, 0)))
            self._last_taps[key] = torch.cat(parts, 0).t().contiguous()
        return self._last_taps[key]


def _ada(block, z_d: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(1 + scale, shift) of each of a block's five adaptive LayerNorms for the conditioning z_d (1, W)."""
    return [(1 + scale, shift) for scale, shift in block.modulations(z_d)]


class WindowCache:
    """One fixed window start ``start`` (absolute frame) over ``window`` frames: the actor
    stream's and the reactor's per-step caches (module docstring).

    cond: the stream's conditions (batch 1); the music of frames [start, start + window) is
    encoded once (what the track has of it). grid: the ODE grid times t_0 .. t_{S-1}.
    """

    def __init__(
        self, inc: IncrementalModel, start: int, window: int, look_ahead: int, cond: Conditions, grid: list[float]
    ):
        self.inc = inc
        self.model = model = inc.model
        self.start = int(start)
        self.window = int(window)
        self.look_ahead = int(look_ahead)
        self.grid = list(grid)
        cfg = model.config
        param = next(model.parameters())
        dev, dt = param.device, param.dtype
        self.n_blocks = len(model.blocks)
        stop = self.start + self.window
        if cond.music is not None:
            cond = cond.slice_frames(self.start, min(stop, cond.music.shape[1]))
        n_music = self.window if cond.music is None else cond.music.shape[1]
        z_text = model.text_latent(cond, 1, dev) + model.task_embed.weight[MODES.index("reactive")]
        z_actor = z_text + model.time_embedding(torch.ones(1, dtype=dt, device=dev))
        z_steps = [z_text + model.time_embedding(torch.full((1,), t, dtype=dt, device=dev)) for t in grid]
        z_m = model.music_latent(cond, 1, n_music)
        z_r = model.retrieval_latent(cond, 1)
        self.music = [_Fixed(b.music_attn, z_m) for b in model.blocks]
        self.retrieval = [_Fixed(b.retrieval_attn, z_r) for b in model.blocks]
        # per stream (actor, then each grid time) and block: the five norms' (1 + scale, shift)
        self.mod_actor = [_ada(b, z_actor) for b in model.blocks]
        self.mod_steps = [[_ada(b, z) for b in model.blocks] for z in z_steps]
        self.pe = sinusoidal_encoding(torch.arange(self.window, device=dev), cfg.width).to(dt)
        pos = torch.arange(self.window, device=dev)
        #: [r, c]: window position r may attend to position c in self-attention (c <= r) and in
        #: the motion cross-attention (c <= r + L); rows and columns are sliced per pass
        self.causal = pos[None, :] <= pos[:, None]
        self.cross = pos[None, :] <= pos[:, None] + self.look_ahead
        self.actor = _StreamCache(self.n_blocks)
        self.motion_k: list[torch.Tensor | None] = [None] * self.n_blocks  # actor keys through W_K, W_V
        self.motion_v: list[torch.Tensor | None] = [None] * self.n_blocks
        self.reactor = [_StreamCache(self.n_blocks) for _ in grid]

    # -- bookkeeping -----------------------------------------------------------------------
    def can_generate(self, last: int) -> bool:
        """Whether frame ``last`` (absolute) and its look-ahead fit in this window."""
        return last + self.look_ahead - self.start <= self.window - 1

    def forget_actor(self, first: int) -> None:
        """Actor rows from absolute frame ``first`` on were revised: drop them (and, the stream
        being causal, nothing else depends on them in the actor cache). Reactor rows already
        cached whose look-ahead reached the revised rows keep the activations computed with the
        provisional ones (recomputing them would undo the caching), so with revisions the
        stream can differ slightly from sliding windows over the final rows."""
        keep = max(0, first - self.start)
        if keep < self.actor.n:
            self.actor.truncate(keep)
            for j in range(self.n_blocks):
                self.motion_k[j] = self.motion_k[j][:, :, :keep]
                self.motion_v[j] = self.motion_v[j][:, :, :keep]

    def sync_actor(self, actor: torch.Tensor) -> None:
        """Cache the actor rows (absolute frames, all received so far; (N, 262)) that fit the window."""
        x_a = self._new_actor(actor)
        if x_a is not None:
            self._actor_rows(x_a)

    # -- idle-time work ---------------------------------------------------------------------
    def _prefetch_bases(self) -> list[tuple[_StreamCache, int]]:
        """(stream, b): the actor stream from its newest row (the next pass may revise it, as
        the streamer's predicted last feature row is), each grid step's reactor stream from
        its next row."""
        return [(self.actor, max(0, self.actor.n - 1))] + [(c, c.n) for c in self.reactor]

    def prefetch_due(self) -> bool:
        """Whether ``prefetch`` has work: a stream moved on since its last one."""
        return any(cache.pre_base != b for cache, b in self._prefetch_bases())

    @torch.no_grad()
    def prefetch(self, rows: int = 2) -> None:
        """Idle-time share of the next pass's convolutions. A convolution output row p sums
        W_k[:, :, d] z(p - k + 1 + d) over up to k_max = 21 past block inputs; all but the
        newest are known before the pass. Per stream (``_prefetch_bases``: from its row b) and
        block this keeps the sums over frames before b for rows b .. b + rows - 1, biases
        included; a pass whose new rows fall in that range then multiplies only the taps over
        frames b .. p (``IncrementalModel.last_taps``: one or two taps instead of 7 + 11 + 21)
        and adds these sums. The same arithmetic, a few times fewer weights read while a
        frame waits; a stream truncated before b (a revision) drops its sums."""
        kmax, width = self.inc.kmax, self.inc.width
        streams = self._prefetch_bases()
        for j in range(self.n_blocks):
            wins = []
            for cache, b in streams:
                z_in = cache.z_in[j]
                hist = z_in[0, max(0, b - kmax + 1) : b] if z_in is not None else self.pe.new_zeros(0, width)
                wins.append(_taps(F.pad(hist, (0, 0, 0, rows)), rows, kmax))  # frames >= b as zeros
            sums = self.inc.conv_products(j, torch.cat(wins, 0)).split(rows, 0)
            for (cache, _), part in zip(streams, sums):
                cache.pre[j] = part
        for cache, b in streams:
            cache.pre_base = b

    # -- network passes --------------------------------------------------------------------
    @staticmethod
    def _norm(block, i: int, z: torch.Tensor, mod) -> torch.Tensor:
        """Adaptive LayerNorm i of ``block``: LN(z) (1 + scale) + shift, in two operations."""
        scale, shift = mod[i]
        norm = block.norm
        return torch.addcmul(shift, F.layer_norm(z, norm.normalized_shape, None, None, norm.eps), scale)

    def _temporal(self, j: int, streams: list) -> list[torch.Tensor]:
        """``DualFlowBlock.temporal`` (causal) for new rows after the cached ones, of one or
        more streams at once: ``streams`` [(cache, z (1, n, W), mod)]; returns their z.

        The streams share the block's weights, so the convolution, the self-attention's
        projections run once over all new rows stacked (one weight read); the attention
        itself and the modulated norms stay per stream."""
        block = self.model.blocks[j]
        kmax, width = self.inc.kmax, self.inc.width
        rows, sizes = [], []  # per stream: (first new row p0, z_all (1, p0 + n, W), prefetched (b, P))
        for cache, z, _ in streams:
            p0, n = cache.n, z.shape[1]
            z_all = z if cache.z_in[j] is None else torch.cat([cache.z_in[j], z], 1)
            cache.z_in[j] = z_all
            b, sums = cache.pre_base, cache.pre[j]
            pre = (b, sums) if b is not None and b <= p0 and p0 + n <= b + sums.shape[0] else None
            rows.append((p0, z_all, pre))  # pre None: no prefetch, or made for other rows
            sizes.append(n)
        if all(pre is not None for *_, pre in rows):
            # the products over the frames before b were made in idle time (``prefetch``): only
            # the taps over frames b .. p0 + n - 1 are left, for every stream in one product
            m = max(p0 + n - pre[0] for (p0, _, pre), n in zip(rows, sizes))
            windows = _stack([_taps(z_all[0, pre[0] : p0 + n], n, m) for (p0, z_all, pre), n in zip(rows, sizes)], 0)
            before = _stack([pre[1][p0 - pre[0] : p0 - pre[0] + n] for (p0, _, pre), n in zip(rows, sizes)], 0)
            y = F.gelu(torch.addmm(before, windows, self.inc.last_taps(j, m)))
        else:
            # (n, kmax * W) tap-major: row r = z(p0 + r - kmax + 1), ..., z(p0 + r) one after the other
            windows = _stack(
                [_taps(z_all[0, max(0, p0 - kmax + 1) :], n, kmax) for (p0, z_all, _), n in zip(rows, sizes)], 0
            )
            y = F.gelu(self.inc.conv_products(j, windows))
        gates = block.conv.gates
        conv = (y.view(y.shape[0], len(gates), -1) * gates[:, None]).sum(1)[None].split(sizes, 1)
        zs = [z + c for (_, z, _), c in zip(streams, conv)]
        attn = block.self_attn
        h = _stack([self._norm(block, 0, z, mod) for z, (_, _, mod) in zip(zs, streams)], 1)
        qkv = F.linear(h, *self.inc.qkv[j])  # (1, N, 3W): q | k, v as attn.q and attn.kv give them
        ys = []
        for (cache, z, _), part in zip(streams, qkv.split(sizes, 1)):
            p0, n = cache.n, z.shape[1]
            q, kv = part[..., :width], part[..., width:]
            k_new, v_new = kv.reshape(1, n, 2, attn.n_heads, -1).permute(2, 0, 3, 1, 4)
            k_all = k_new if cache.k[j] is None else torch.cat([cache.k[j], k_new], 2)
            v_all = v_new if cache.v[j] is None else torch.cat([cache.v[j], v_new], 2)
            cache.k[j], cache.v[j] = k_all, v_all
            mask = self.causal[p0 : p0 + n, : p0 + n] if n > 1 else None  # row i: cached frames and new rows <= i
            y = F.scaled_dot_product_attention(_heads(q.reshape(1, n, -1), attn.n_heads), k_all, v_all, attn_mask=mask)
            ys.append(y.transpose(1, 2).reshape(1, n, -1))
        out = attn.out(_stack(ys, 1)).split(sizes, 1)
        zs = [z + o for z, o in zip(zs, out)]
        return [
            z + self.music[j](lambda z=z, mod=mod: self._norm(block, 1, z, mod)) for z, (_, _, mod) in zip(zs, streams)
        ]

    def _finish(self, j: int, streams: list) -> list[torch.Tensor]:
        """``DualFlowBlock.finish`` (retrieval cross-attention and feed-forward) of one or more
        streams [(z (1, n, W), mod)], the feed-forward over all rows stacked."""
        block = self.model.blocks[j]
        zs = [z + self.retrieval[j](lambda z=z, mod=mod: self._norm(block, 3, z, mod)) for z, mod in streams]
        w1, b1, w2, b2 = self.inc.ffn[j]
        h = _stack([self._norm(block, 4, z, mod) for z, (_, mod) in zip(zs, streams)], 1)
        ff = F.linear(F.gelu(F.linear(h, w1, b1)), w2, b2)  # block.ffn
        return [z + f for z, f in zip(zs, ff.split([z.shape[1] for z in zs], 1))]

    def _actor_rows(self, x_a: torch.Tensor) -> None:
        """Actor rows x_a (1, n, 262) at the next positions: their motion keys, cached."""
        self._rows(x_a, [], False)

    def _actor_keys(self, j: int, z2: torch.Tensor) -> None:
        block = self.model.blocks[j]
        k_new, v_new = _kv(block.motion_attn, block.keys_of(z2))
        self.motion_k[j] = k_new if self.motion_k[j] is None else torch.cat([self.motion_k[j], k_new], 2)
        self.motion_v[j] = v_new if self.motion_v[j] is None else torch.cat([self.motion_v[j], v_new], 2)

    def _new_actor(self, actor: torch.Tensor | None) -> torch.Tensor | None:
        """Of ``actor`` (all actor rows received, (N, 262)), those in this window not cached yet,
        (1, m, 262), or None."""
        if actor is None:
            return None
        stop = min(actor.shape[0], self.start + self.window)
        lo = self.start + self.actor.n
        return actor[lo:stop][None] if lo < stop else None

    def reactor_rows(
        self, step: int, x: torch.Tensor, need_output: bool = True, actor: torch.Tensor | None = None
    ) -> torch.Tensor | None:
        """The velocity (1, n, 262) of new reactor rows x (1, n, 262) at grid step ``step``
        (time ``grid[step]``), appended to that step's cache. The actor rows up to the new
        rows' look-ahead must be cached (``sync_actor``), or be among ``actor`` (all actor
        rows received, (N, 262), as for ``sync_actor``): those not cached yet then go through
        the network in the same pass as the reactor rows (the actor stream of a block comes
        first: the reactor's motion cross-attention reads its keys). ``need_output`` False:
        only cache (teacher forcing)."""
        return self._rows(self._new_actor(actor), [(step, x)], need_output)

    def feed(self, rows: list[tuple[int, torch.Tensor]], actor: torch.Tensor | None = None) -> None:
        """Teacher forcing of several grid steps in one pass: ``rows`` [(step, x (1, n, 262))],
        each step at most once, appended to those steps' caches (the same caches as one
        ``reactor_rows(step, x, need_output=False)`` per step; ``actor`` as there). The
        products with the shared weights run once over every step's rows stacked, so a pass
        over two steps costs far less than two passes."""
        if len({step for step, _ in rows}) != len(rows):
            raise ValueError(f"WindowCache.feed: a grid step given twice in {[step for step, _ in rows]}")
        self._rows(self._new_actor(actor), list(rows), False)

    def _rows(self, x_a: torch.Tensor | None, reactor: list, need_output: bool) -> torch.Tensor | None:
        """One pass through the blocks of new actor rows x_a (or None) and new reactor rows
        ``reactor`` [(step, x (1, n, 262))] at their grid steps; the velocity of the one reactor
        stream when ``need_output``, else None."""
        m = self.model
        actor = None
        if x_a is not None:
            pa, na = self.actor.n, x_a.shape[1]
            actor = [self.actor, m.in_a(x_a) + self.pe[pa : pa + na], None]
        n_keys = self.actor.n + (0 if x_a is None else x_a.shape[1])
        out_streams, cross = [], []  # per reactor stream: [cache, z, mod] and its motion mask
        for step, x in reactor:
            cache = self.reactor[step]
            p0, n = cache.n, x.shape[1]
            out_streams.append([cache, m.in_b(x) + self.pe[p0 : p0 + n], None])
            # None: every actor key lies within each row's look-ahead
            cross.append(self.cross[p0 : p0 + n, :n_keys] if n_keys > p0 + self.look_ahead + 1 else None)
        streams = ([actor] if actor is not None else []) + out_streams
        steps = [step for step, _ in reactor]
        for j, block in enumerate(m.blocks):
            if actor is not None:
                actor[2] = self.mod_actor[j]
            for st, step in zip(out_streams, steps):
                st[2] = self.mod_steps[step][j]
            out = self._temporal(j, streams)
            fin = []
            if actor is not None:
                z2a = out.pop(0)
                self._actor_keys(j, z2a)
                if j + 1 < self.n_blocks:  # the last block's output feeds nothing the reactor reads
                    fin.append((z2a, actor[2]))
            last = j + 1 == self.n_blocks
            for z2, st, mask in zip(out, out_streams, cross):
                q = self._norm(block, 2, z2, st[2])
                z3 = z2 + _attend(block.motion_attn, q, self.motion_k[j], self.motion_v[j], mask)
                if need_output or not last:  # teacher forcing: the last output is not needed
                    fin.append((z3, st[2]))
            zs = self._finish(j, fin) if fin else []
            if actor is not None and not last:
                actor[1] = zs.pop(0)
            for st, z in zip(out_streams, zs):
                st[1] = z
        if actor is not None:
            self.actor.n += x_a.shape[1]
        for (cache, _, _), (_, x) in zip(out_streams, reactor):
            cache.n += x.shape[1]
        if not need_output:
            return None
        (step, x), z = reactor[0], out_streams[0][1]
        tt = torch.full((1,), self.grid[step], dtype=x.dtype, device=x.device)
        return m._velocity(m.out_b(m.out_norm(z)), x, tt)
