"""The DualFlow network: a two-person velocity field v_theta(x_t, t, c) (paper sec. 3.3, app. D).

Contract: ``DualFlow(config)(x_a, x_b, t, cond, mode=, look_ahead=, frame_mask=)`` with x_a,
x_b (B, T, 262) normalised features of actor and reactor, t (B,) or float in [0, 1] (0 = noise),
``cond`` a :class:`Conditions` (text (B, D_text), music (B, T, D_music), retrieval (B, R, width),
drop masks; None = the learned null), mode "interactive" | "reactive" → (v_a, v_b), each
(B, T, 262); in reactive mode x_a is the clean actor and v_a is exactly 0, and reactor frame i
depends on actor frames <= i + L only. :class:`DualFlowConfig` has presets "paper" / "small" /
"tiny"; :func:`sample_condition_drop` draws the guidance drop masks. Design choices where the
paper is silent: docs/model.md. Read top to bottom: config, conditioning, blocks, model.
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass, fields, replace

import torch
import torch.nn.functional as F
from torch import nn

from dualflow.errors import DualFlowError

MOTION_DIM = 262  # InterGen's per-person feature size (22 joints).
MODES = ("interactive", "reactive")
#: What the output linears predict (``DualFlowConfig.prediction``): the velocity v, or the
#: clean motion x0 from which v is formed (see ``DualFlow._velocity``).
PREDICTIONS = ("velocity", "x0")
#: Smallest 1 - t used when forming v from an x0 prediction (caps the 1 / (1 - t) gain at 20).
X0_MIN_GAP = 0.05


# ---------------------------------------------------------------------------------------------
# Configuration
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DualFlowConfig:
    """Hyper-parameters of the network. ``preset(name)`` gives the named configurations.

    width: latent size of motion, conditions and attention; n_heads must divide it.
    conv_kernels: the multi-scale temporal convolution kernel sizes (odd).
    look_ahead: default L (frames) of the reactive causal cross-attention (paper: 10).
    prediction: "velocity" (the output linears give v, as in the paper) or "x0" (they give the
        clean motion and v is formed from it; use it when width < 262, see DualFlow._velocity).
    """

    motion_dim: int = MOTION_DIM
    width: int = 512
    n_blocks: int = 20
    n_heads: int = 8
    ff_dim: int = 1024
    dropout: float = 0.1
    text_dim: int = 384
    music_dim: int = 35
    music_layers: int = 2
    conv_kernels: tuple[int, ...] = (7, 11, 21)
    look_ahead: int = 10
    prediction: str = "velocity"

    def __post_init__(self) -> None:
        for f in fields(self):  # the types first: a config read from a file may hold anything
            value, default = getattr(self, f.name), f.default
            if isinstance(default, bool) or not isinstance(default, (int, float, str, tuple)):
                continue
            if isinstance(default, tuple):
                ok = isinstance(value, (tuple, list)) and all(
                    isinstance(v, int) and not isinstance(v, bool) for v in value
                )
            elif isinstance(default, int):
                ok = isinstance(value, int) and not isinstance(value, bool)
            elif isinstance(default, float):
                ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            else:
                ok = isinstance(value, str)
            if not ok:
                raise DualFlowError(f"DualFlowConfig.{f.name} must be {type(default).__name__}, got {value!r:.40}")
        if self.prediction not in PREDICTIONS:
            raise DualFlowError(f"DualFlowConfig.prediction must be one of {PREDICTIONS}, got {self.prediction!r}")
        if self.width % self.n_heads:
            raise DualFlowError(f"DualFlowConfig: width ({self.width}) must be divisible by n_heads ({self.n_heads})")
        if any(k < 1 or k % 2 == 0 for k in self.conv_kernels):
            raise DualFlowError(f"DualFlowConfig.conv_kernels must be odd positive sizes, got {self.conv_kernels}")
        if self.look_ahead < 0:
            raise DualFlowError(f"DualFlowConfig.look_ahead must be >= 0, got {self.look_ahead}")
        for name in ("motion_dim", "width", "n_blocks", "n_heads", "ff_dim", "text_dim", "music_dim"):
            if getattr(self, name) < 1:
                raise DualFlowError(f"DualFlowConfig.{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 <= self.dropout < 1.0:
            raise DualFlowError(f"DualFlowConfig.dropout must be in [0, 1), got {self.dropout}")

    @staticmethod
    def preset(name: str, **overrides) -> DualFlowConfig:
        """``paper`` (the published model), ``small`` (CPU training in minutes), ``tiny`` (tests)."""
        if name not in PRESETS:
            raise DualFlowError(f"unknown DualFlow preset {name!r}; choose one of {', '.join(PRESETS)}")
        return replace(PRESETS[name], **overrides)

    def to_dict(self) -> dict:
        """JSON-friendly dict (tuples become lists); inverse of ``from_dict``."""
        d = asdict(self)
        d["conv_kernels"] = list(self.conv_kernels)
        return d

    @staticmethod
    def from_dict(d: dict) -> DualFlowConfig:
        known = {f.name for f in fields(DualFlowConfig)}
        unknown = set(d) - known
        if unknown:
            raise DualFlowError(f"DualFlowConfig: unknown field(s) {sorted(unknown)}; valid fields: {sorted(known)}")
        d = dict(d)
        if "conv_kernels" in d:
            d["conv_kernels"] = tuple(d["conv_kernels"])
        return DualFlowConfig(**d)


PRESETS: dict[str, DualFlowConfig] = {
    # Sec. 4 "Implementation details": 20 blocks, 8 heads, dropout 0.1, width 512, FFN 1024.
    "paper": DualFlowConfig(),
    # Trains on a 2-core CPU in minutes (a few hundred steps on 60-frame clips).
    "small": DualFlowConfig(width=128, n_blocks=4, n_heads=4, ff_dim=256, music_layers=1),
    # Unit tests: forward + backward in milliseconds.
    "tiny": DualFlowConfig(width=32, n_blocks=2, n_heads=2, ff_dim=64, dropout=0.0, music_layers=1, look_ahead=2),
}


# ---------------------------------------------------------------------------------------------
# Conditioning
# ---------------------------------------------------------------------------------------------


@dataclass
class Conditions:
    """Conditioning tensors for one batch; every field may be None (= absent, learned null).

    text (B, D_text); music (B, T, D_music) aligned with the motion frames; retrieval
    (B, R, width) tokens; drop_text / drop_music (B,) bool masks (True = use the null).
    """

    text: torch.Tensor | None = None
    music: torch.Tensor | None = None
    retrieval: torch.Tensor | None = None
    drop_text: torch.Tensor | None = None
    drop_music: torch.Tensor | None = None

    def unconditional(self) -> Conditions:
        """The classifier-free-guidance null: text, music and retrieval dropped, as training drops
        them together (dualflow/retrieval.py: a sample with both cues dropped equals one without
        retrieval)."""
        return Conditions()

    def slice_frames(self, start: int, stop: int) -> Conditions:
        """The same conditions restricted to motion frames [start, stop) (music is per frame)."""
        music = None if self.music is None else self.music[:, start:stop]
        return replace(self, music=music)

    def to(self, device) -> Conditions:
        """The same conditions with every tensor on ``device``."""
        moved = {f.name: getattr(self, f.name) for f in fields(self)}
        return Conditions(**{k: None if v is None else v.to(device) for k, v in moved.items()})


def sample_condition_drop(
    batch: int,
    generator: torch.Generator | None = None,
    device: torch.device | str = "cpu",
    p_both: float = 0.10,
    p_text: float = 0.20,
    p_music: float = 0.20,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Classifier-free-guidance drop masks (paper sec. 4): both 10 %, text 20 %, music 20 %.

    One uniform u per sample: u < p_both drops both; the next p_text drops text alone; the next
    p_music drops music alone; otherwise nothing is dropped. Returns (drop_text, drop_music),
    each (batch,) bool on ``device``.
    """
    if p_both + p_text + p_music > 1.0 or min(p_both, p_text, p_music) < 0:
        raise DualFlowError("condition drop probabilities must be >= 0 and sum to <= 1")
    u = torch.rand(batch, generator=generator, device=None if generator is None else generator.device).to(device)
    both = u < p_both
    text_only = (u >= p_both) & (u < p_both + p_text)
    music_only = (u >= p_both + p_text) & (u < p_both + p_text + p_music)
    return both | text_only, both | music_only


# ---------------------------------------------------------------------------------------------
# Building blocks
# ---------------------------------------------------------------------------------------------


def sinusoidal_encoding(positions: torch.Tensor, dim: int) -> torch.Tensor:
    """PE(p)[2i] = sin(p / 10000^(2i/dim)), PE(p)[2i+1] = cos(...); positions (...,) -> (..., dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=positions.device) / half)
    angles = positions.float()[..., None] * freqs
    pe = torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)
    if dim % 2:
        pe = F.pad(pe, (0, 1))
    return pe


#: Adaptive LayerNorms per DualFlow block (self-attn, music, motion, retrieval, feed-forward).
N_ADA = 5


def ada_norm(norm: nn.LayerNorm, x: torch.Tensor, mod: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """LN(x, z_d) = LayerNorm(x) * (1 + scale) + shift for one (scale, shift) of ``DualFlowBlock.modulations``."""
    scale, shift = mod
    if torch.is_grad_enabled():
        return norm(x) * (1 + scale) + shift
    return torch.addcmul(shift, norm(x), 1 + scale)  # inference: the same, in one kernel fewer


class Attention(nn.Module):
    """Multi-head attention Attn(Q, K, V) = softmax(Q K^T / sqrt(d)) V via scaled_dot_product_attention.

    query (N, Tq, W), context (N, Tk, W); mask broadcastable to (N, heads, Tq, Tk), bool,
    True = may attend (app. D.4's M_ij). Every query row must keep at least one key.
    is_causal (mask None, Tq == Tk): attend to j <= i without a mask tensor.
    """

    def __init__(self, width: int, n_heads: int, dropout: float):
        super().__init__()
        self.n_heads = n_heads
        self.q = nn.Linear(width, width)
        self.kv = nn.Linear(width, 2 * width)
        self.out = nn.Linear(width, width)
        self.dropout = dropout

    def forward(
        self,
        query: torch.Tensor,
        context: torch.Tensor | tuple[torch.Tensor, torch.Tensor],
        mask: torch.Tensor | None,
        is_causal: bool = False,
    ) -> torch.Tensor:
        """context: (N, Tk, W), or its keys and values as ``project(context)`` gives them."""
        n, tq, w = query.shape
        h = self.n_heads
        q = self.q(query).view(n, tq, h, w // h).transpose(1, 2)
        k, v = context if isinstance(context, tuple) else self.project(context)
        y = F.scaled_dot_product_attention(
            q, k, v, attn_mask=mask, dropout_p=self.dropout if self.training else 0.0, is_causal=is_causal
        )
        return self.out(y.transpose(1, 2).reshape(n, tq, w))

    def project(self, context: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Keys and values (N, heads, Tk, W / heads) of a context (N, Tk, W)."""
        n, tk, w = context.shape
        k, v = self.kv(context).view(n, tk, 2, self.n_heads, w // self.n_heads).permute(2, 0, 3, 1, 4)
        return k, v

    def single_key(self, context: torch.Tensor) -> torch.Tensor:
        """The output (N, 1, W) for a context of one key (N, 1, W), whatever the query: softmax
        over one logit is 1, so every query row gets that key's value through ``out``."""
        return self.out(self.kv(context)[..., context.shape[-1] :])


def _inference(module: nn.Module) -> bool:
    """No autograd and no dropout: where the inference-only shortcuts below may be taken (they
    compute the same values; in training they would change which weights get gradients)."""
    return not (module.training or torch.is_grad_enabled())


class MultiScaleConv(nn.Module):
    """z' = z + sum_k gamma_k GELU(Conv1D_k(z)), k in conv_kernels (app. D.1).

    causal=False: centred ("same") padding. causal=True: left padding by k - 1 so output frame i
    sees input frames i-k+1 .. i only. z (N, T, W); frame_mask (N, T) zeroes padded frames first.

    Two ways to compute the same sums (equal up to float rounding), chosen by ``gemm``:
    ``Conv1d`` per kernel (False), or one tap-major window matrix of the largest kernel (N, T,
    k_max * W) from which each kernel's taps are a contiguous column slice, multiplied by the
    kernel's weights laid out tap-major: one large matrix product per kernel, no convolution
    algorithm search (True). None (default): the matrix products on CUDA, where cuDNN's 1-D
    convolutions with kernels 11 and 21 were the slowest part of a training step (issue 28,
    bench/dualflow_gpu.py), and Conv1d elsewhere.
    """

    def __init__(self, width: int, kernels: tuple[int, ...], dropout: float):
        super().__init__()
        self.kernels = tuple(kernels)
        self.convs = nn.ModuleList(nn.Conv1d(width, width, k) for k in self.kernels)
        self.gates = nn.Parameter(torch.full((len(self.kernels),), 0.1))
        self.drop = nn.Dropout(dropout)
        self.gemm: bool | None = None
        #: inference: per kernel, (weight's data pointer, its version, the tap-major layout)
        self._tap_major: list[tuple | None] = [None] * len(self.kernels)

    def forward(self, z: torch.Tensor, causal: bool, frame_mask: torch.Tensor | None) -> torch.Tensor:
        x = z if frame_mask is None else z * frame_mask[..., None]
        gemm = z.is_cuda if self.gemm is None else self.gemm
        out = self._by_products(x, causal) if gemm else self._by_convolutions(x, causal)
        return z + self.drop(out)

    def _by_convolutions(self, x: torch.Tensor, causal: bool) -> torch.Tensor:
        x = x.transpose(1, 2)  # (N, W, T)
        out = None
        for gamma, conv, k in zip(self.gates, self.convs, self.kernels):
            pad = (k - 1, 0) if causal else ((k - 1) // 2, (k - 1) // 2)
            out = self._gated_sum(out, gamma, F.gelu(conv(F.pad(x, pad))))
        return out.transpose(1, 2)

    def _gated_sum(self, out: torch.Tensor | None, gamma: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """out + gamma y (out None: gamma y); in inference the multiply-add in one kernel."""
        if out is None:
            return gamma * y
        return torch.addcmul(out, y, gamma) if _inference(self) else out + gamma * y

    def _by_products(self, x: torch.Tensor, causal: bool) -> torch.Tensor:
        n, t, w = x.shape
        k_max = max(self.kernels)
        if torch.is_autocast_enabled(x.device.type):  # build the window matrix once, in the product dtype
            x = x.to(torch.get_autocast_dtype(x.device.type))
        pad = (k_max - 1, 0) if causal else ((k_max - 1) // 2, (k_max - 1) // 2)
        # windows[n, i, u, :] = x[n, i - pad_left + u, :], tap u of frame i's k_max window, tap-major
        windows = F.pad(x, (0, 0, *pad)).unfold(1, k_max, 1).transpose(2, 3).contiguous()
        out = None
        for i, (gamma, conv, k) in enumerate(zip(self.gates, self.convs, self.kernels)):
            first = k_max - k if causal else (k_max - k) // 2  # this kernel's taps within the window
            taps = windows[:, :, first : first + k].reshape(n, t, k * w)
            out = self._gated_sum(out, gamma, F.gelu(F.linear(taps, self._weight(i, conv), conv.bias)))
        return out

    def train(self, mode: bool = True):
        if mode:  # training changes the weights: keep no copy (eval() keeps it: a CUDA graph may read it)
            self._tap_major = [None] * len(self.kernels)
        return super().train(mode)

    def _weight(self, i: int, conv: nn.Conv1d) -> torch.Tensor:
        """Kernel i's weight (out, tap-major in) = (W, k W); in inference kept between calls
        while the weight's storage and version are the same (a sampler calls the network once
        per ODE step: otherwise every call copies all the convolution weights). The copy is
        made again when the weight is another tensor or was changed in place (its version
        counter; an edit through ``.data`` bypasses it); weights made under inference mode have
        no version counter and are not kept."""
        weight = conv.weight
        w, _, k = weight.shape
        if not _inference(self) or torch.compiler.is_compiling() or weight.is_inference():
            return weight.permute(0, 2, 1).reshape(w, k * w)  # (compiled: the compiler fuses the copy)
        key = (weight.data_ptr(), weight._version)  # moved (``.to``, ``load_state_dict``) or changed in place
        cached = self._tap_major[i]
        if cached is None or cached[0] is not weight or cached[1] != key:
            cached = self._tap_major[i] = (weight, key, weight.permute(0, 2, 1).reshape(w, k * w).contiguous())
        return cached[2]


class FeedForward(nn.Module):
    """FFN(x) = W2 dropout(GELU(W1 x)), width -> ff_dim -> width (eq. 15)."""

    def __init__(self, width: int, ff_dim: int, dropout: float):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(width, ff_dim), nn.GELU(), nn.Dropout(dropout), nn.Linear(ff_dim, width))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


# ---------------------------------------------------------------------------------------------
# The DualFlow block (app. D.1, eq. 11-15)
# ---------------------------------------------------------------------------------------------


@dataclass
class BlockMasks:
    """Boolean attention masks of one stream pass (True = may attend).

    self_mask: (N, 1, T, T), (T, T) or None (= full); cross_mask: the same for the motion
    cross-attention to the other person's keys; causal: left-padded convolutions;
    frame_mask: (N, T) float, 1 on real frames (zeroes padding before the convolutions);
    self_causal: self-attention is plain causal (j <= i) with no mask tensor, SDPA's
    ``is_causal`` (which keeps it on its fused kernels; a boolean mask tensor does not).
    """

    self_mask: torch.Tensor | None
    cross_mask: torch.Tensor | None
    causal: bool
    frame_mask: torch.Tensor | None
    self_causal: bool = False


class DualFlowBlock(nn.Module):
    """One DualFlow block, applied to each person with shared weights.

      z'      = z + sum_k gamma_k GELU(Conv_k(z))                       multi-scale conv
      z^(1)   = z' + Attn(LN(z', z_d))                                  self-attention   (11)
      z^(2)   = z^(1) + Attn(Q=LN(z^(1), z_d), K=V=z_m)                 music cross      (12)
      z^(3)_a = z^(2)_a + Attn(Q=LN(z^(2)_a, z_d), K=V=LN0(z^(2)_b))    motion cross     (13)
      z^(4)   = z^(3) + Attn(Q=LN(z^(3), z_d), K=V=z_R)                 retrieval cross  (14)
      z^(j+1) = z^(4) + FFN(LN(z^(4), z_d))                             feed-forward     (15)

    The three stages are separate methods so that the model can run the two persons stacked
    along the batch (interactive) or one after the other (reactive: the actor first, without
    motion cross-attention; then the reactor, whose causal cross-attention reads the actor's
    LN0(z^(2)_a) of the same block).
    """

    def __init__(self, cfg: DualFlowConfig):
        super().__init__()
        w = cfg.width
        self.conv = MultiScaleConv(w, cfg.conv_kernels, cfg.dropout)
        # the five adaptive LayerNorms' [scale, shift] = W SiLU(z_d) + b as ONE linear (W: 10 W x W,
        # rows [scale_0, shift_0, ..., scale_4, shift_4]); zero-initialised: plain LayerNorms at first
        self.norm = nn.LayerNorm(w, elementwise_affine=False)
        self.modulation = nn.Linear(w, 2 * N_ADA * w)
        nn.init.zeros_(self.modulation.weight)
        nn.init.zeros_(self.modulation.bias)
        self.register_load_state_dict_pre_hook(_fuse_old_modulations)
        self.self_attn = Attention(w, cfg.n_heads, cfg.dropout)
        self.music_attn = Attention(w, cfg.n_heads, cfg.dropout)
        self.motion_attn = Attention(w, cfg.n_heads, cfg.dropout)
        self.retrieval_attn = Attention(w, cfg.n_heads, cfg.dropout)
        self.other_norm = nn.LayerNorm(w)
        self.ffn = FeedForward(w, cfg.ff_dim, cfg.dropout)
        self.drop = nn.Dropout(cfg.dropout)

    def modulations(self, z_d: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """The five (scale, shift) pairs, each (N, 1, W), of the block's adaptive LayerNorms for
        the conditioning latent z_d (N, W): one matrix product for all five."""
        parts = self.modulation(F.silu(z_d)).unsqueeze(1).chunk(2 * N_ADA, dim=-1)
        return [(parts[2 * k], parts[2 * k + 1]) for k in range(N_ADA)]

    def temporal(self, z, mods, z_m, masks: BlockMasks) -> torch.Tensor:
        """Conv, self-attention (11) and music cross-attention (12): z^(j) -> z^(j,2).
        mods: ``modulations(z_d)``; z_m: the music latent or its ``Attention.project``."""
        z = self.conv(z, causal=masks.causal, frame_mask=masks.frame_mask)
        h = ada_norm(self.norm, z, mods[0])
        z = z + self.drop(self.self_attn(h, h, masks.self_mask, is_causal=masks.self_causal))
        return z + self.drop(self._cross(self.music_attn, z, mods[1], z_m))

    def _cross(self, attn: Attention, z, mod, context) -> torch.Tensor:
        """Unmasked cross-attention of LN(z, z_d) to ``context``; with a single key (the learned
        null music or retrieval token) in inference, that key's constant output (N, 1, W)
        without the norm, the query projection and the attention."""
        if not isinstance(context, tuple) and context.shape[1] == 1 and _inference(self):
            return attn.single_key(context)
        return attn(ada_norm(self.norm, z, mod), context, None)

    def keys_of(self, z2: torch.Tensor) -> torch.Tensor:
        """What the other person's motion cross-attention reads: LN0(z^(j,2))."""
        return self.other_norm(z2)

    def motion_cross(self, z2, mods, other_keys, mask) -> torch.Tensor:
        """z^(3) = z^(2) + Attn(Q=LN(z^(2), z_d), K=V=other_keys)  (13; causal in reactive mode);
        other_keys (N, T, W) or their ``Attention.project``."""
        return z2 + self.drop(self.motion_attn(ada_norm(self.norm, z2, mods[2]), other_keys, mask))

    def finish(self, z, mods, z_r) -> torch.Tensor:
        """Retrieval cross-attention (14) and feed-forward (15): z^(j,3) -> z^(j+1)."""
        z = z + self.drop(self._cross(self.retrieval_attn, z, mods[3], z_r))
        return z + self.drop(self.ffn(ada_norm(self.norm, z, mods[4])))

    def forward(self, z, z_d, z_m, z_r, masks: BlockMasks) -> torch.Tensor:
        """Interactive: stacked z (2B, T, W), rows [0, B) person A, [B, 2B) person B."""
        n = z.shape[0] // 2
        mods = self.modulations(z_d)
        z2 = self.temporal(z, mods, z_m, masks)
        keys = self.keys_of(z2)
        swapped = torch.cat([keys[n:], keys[:n]], dim=0)
        z3 = self.motion_cross(z2, mods, swapped, masks.cross_mask)
        return self.finish(z3, mods, z_r)


def _fuse_old_modulations(module, state_dict, prefix, *_args) -> None:
    """``load_state_dict`` hook: a block's weights from before the fused modulation (issue 28)."""
    _fuse_block(state_dict, prefix)


def _fuse_block(state_dict: dict, prefix: str) -> bool:
    old = [f"{prefix}norms.{k}.modulation." for k in range(N_ADA)]
    if f"{old[0]}weight" not in state_dict:
        return False
    for name in ("weight", "bias"):
        state_dict[f"{prefix}modulation.{name}"] = torch.cat([state_dict.pop(o + name) for o in old], 0)
    return True


def fuse_old_modulations(state_dict: dict) -> bool:
    """Convert, in place, weights from before the fused modulation (issue 28): each block's five
    per-norm linears ``blocks.j.norms.k.modulation.{weight,bias}`` (2W x W, 2W) are stacked into
    ``blocks.j.modulation`` (10W x W, 10W) in the same order, which computes the same (scale,
    shift) pairs. Works under any key prefix (an EMA's ``module.``). True if anything changed."""
    suffix = "norms.0.modulation.weight"
    prefixes = [k[: -len(suffix)] for k in list(state_dict) if k.endswith(suffix)]
    return any([_fuse_block(state_dict, p) for p in prefixes])


# ---------------------------------------------------------------------------------------------
# The model
# ---------------------------------------------------------------------------------------------


@dataclass
class ActorContext:
    """The reactive actor stream's per-block keys/values LN0(z^(j,2)_a), each (B, T, W), and the
    conditioning latents it was built with, which do not change over a sampler's steps either:
    text + task (B, W), music z_m and retrieval z_r, and per block the keys and values of the
    reactor's music and motion cross-attention (``Attention.project``; music None for a single
    null token). ``DualFlow.forward`` reuses them all."""

    keys: list[torch.Tensor]
    shape: tuple[int, int]
    cues: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
    projected: list[tuple[tuple | None, tuple]] | None = None
    #: the conditions' tensors it was built with: the latents are reused only for these very ones
    source: tuple | None = None


def _tensors(cond: Conditions) -> tuple:
    """The tensors ``cond`` holds (None for a missing one), in field order."""
    return tuple(getattr(cond, f.name) for f in fields(cond))


def _same_tensors(a: tuple | None, b: tuple) -> bool:
    """Whether ``a`` holds the very tensors of ``b`` (identity, not equal values)."""
    return a is not None and len(a) == len(b) and all(x is y for x, y in zip(a, b))


def look_ahead_mask(t_query: int, t_key: int, look_ahead: int, device=None) -> torch.Tensor:
    """M_ij = (j <= i + L), shape (t_query, t_key) bool (app. D.4); L = 0 is plain causal."""
    i = torch.arange(t_query, device=device)[:, None]
    j = torch.arange(t_key, device=device)[None, :]
    return j <= i + look_ahead


class DualFlow(nn.Module):
    """The two-person velocity field v_theta(x_t, t, c); see the module docstring for the API."""

    def __init__(self, config: DualFlowConfig):
        super().__init__()
        self.config = cfg = config
        w = cfg.width
        # Per-person input projections (sec. 3.3) and output linears (eq. 16).
        self.in_a = nn.Linear(cfg.motion_dim, w)
        self.in_b = nn.Linear(cfg.motion_dim, w)
        self.out_norm = nn.LayerNorm(w)
        self.out_a = nn.Linear(w, cfg.motion_dim)
        self.out_b = nn.Linear(w, cfg.motion_dim)
        for lin in (self.out_a, self.out_b):
            nn.init.zeros_(lin.weight)
            nn.init.zeros_(lin.bias)
        # Conditioning: flow time, text, task, music, retrieval (+ learned nulls).
        self.time_mlp = nn.Sequential(nn.Linear(w, w), nn.SiLU(), nn.Linear(w, w))
        self.text_mlp = nn.Sequential(nn.Linear(cfg.text_dim, w), nn.SiLU(), nn.Linear(w, w))
        self.null_text = nn.Parameter(torch.zeros(w))
        self.task_embed = nn.Embedding(len(MODES), w)
        self.music_in = nn.Linear(cfg.music_dim, w)
        layer = nn.TransformerEncoderLayer(
            w, cfg.n_heads, cfg.ff_dim, cfg.dropout, activation="gelu", batch_first=True, norm_first=True
        )
        self.music_encoder = nn.TransformerEncoder(layer, cfg.music_layers, enable_nested_tensor=False)
        self.music_norm = nn.LayerNorm(w)
        self.null_music = nn.Parameter(torch.randn(1, 1, w) * 0.02)
        self.null_retrieval = nn.Parameter(torch.randn(1, 1, w) * 0.02)
        self.blocks = nn.ModuleList(DualFlowBlock(cfg) for _ in range(cfg.n_blocks))

    # -- conditioning latents -------------------------------------------------------------

    def time_embedding(self, t: torch.Tensor) -> torch.Tensor:
        """t (N,) in [0, 1] -> (N, W): MLP(PE(1000 t))."""
        return self.time_mlp(sinusoidal_encoding(t * 1000.0, self.config.width))

    def text_latent(self, cond: Conditions, batch: int, device) -> torch.Tensor:
        """(B, W): MLP(sqrt(D_text) text / |text|), or the learned null where text is absent or dropped.

        Sentence encoders return unit-norm vectors (MiniLM, CLIP after normalising), whose
        components are ~1/sqrt(D_text) = 0.05: fed as they are, the text latent is ~20x smaller
        than the time embedding it is added to, and a small model learns text-dependent motion
        (e.g. which follower rule a prompt names) only very slowly. Rescaling to unit RMS per
        component fixes the scale whatever the encoder's norm (a zero vector stays zero).
        """
        null = self.null_text.expand(batch, -1)
        if cond.text is None:
            return null
        text = F.normalize(cond.text, dim=-1) * math.sqrt(cond.text.shape[-1])
        z = self.text_mlp(text)
        if cond.drop_text is not None:
            z = torch.where(cond.drop_text.to(device)[:, None], null, z)
        return z

    def music_latent(self, cond: Conditions, batch: int, n_frames: int) -> torch.Tensor:
        """z_m (B, T_m, W): transformer(Linear(music) + PE); the null token where absent/dropped."""
        null = self.null_music.expand(batch, 1, -1)
        if cond.music is None:
            return null
        m = cond.music
        pe = sinusoidal_encoding(torch.arange(m.shape[1], device=m.device), self.config.width)
        z = self.music_norm(self.music_encoder(self.music_in(m) + pe))
        if cond.drop_music is not None:
            z = torch.where(cond.drop_music.to(m.device)[:, None, None], null.expand_as(z), z)
        return z

    def retrieval_latent(self, cond: Conditions, batch: int) -> torch.Tensor:
        if cond.retrieval is None:
            return self.null_retrieval.expand(batch, 1, -1)
        return cond.retrieval

    # -- forward --------------------------------------------------------------------------

    def _check(self, x_a, x_b, cond: Conditions, mode: str, look_ahead: int, frame_mask) -> None:
        cfg = self.config
        if mode not in MODES:
            raise DualFlowError(f"mode must be one of {MODES}, got {mode!r}")
        if look_ahead < 0:
            raise DualFlowError(f"look_ahead must be >= 0 frames, got {look_ahead}")
        for name, x in (("x_a", x_a), ("x_b", x_b)):
            if x.ndim != 3 or x.shape[-1] != cfg.motion_dim:
                raise DualFlowError(f"{name} must have shape (B, T, {cfg.motion_dim}), got {tuple(x.shape)}")
        if x_a.shape != x_b.shape:
            raise DualFlowError(f"x_a {tuple(x_a.shape)} and x_b {tuple(x_b.shape)} must have the same shape")
        b, t = x_a.shape[:2]
        if cond.text is not None and tuple(cond.text.shape) != (b, cfg.text_dim):
            raise DualFlowError(
                f"Conditions.text must be (B, D_text) = ({b}, {cfg.text_dim}), got {tuple(cond.text.shape)}"
            )
        if cond.music is not None and tuple(cond.music.shape) != (b, t, cfg.music_dim):
            raise DualFlowError(
                f"Conditions.music must be (B, T, D_music) = ({b}, {t}, {cfg.music_dim}) (per motion frame), "
                f"got {tuple(cond.music.shape)}"
            )
        if cond.retrieval is not None and (
            cond.retrieval.ndim != 3 or cond.retrieval.shape[0] != b or cond.retrieval.shape[2] != cfg.width
        ):
            raise DualFlowError(
                f"Conditions.retrieval must be (B, R, width) = ({b}, R, {cfg.width}), got {tuple(cond.retrieval.shape)}"
            )
        if frame_mask is not None and tuple(frame_mask.shape) != (b, t):
            raise DualFlowError(f"frame_mask must be (B, T) = ({b}, {t}) bool, got {tuple(frame_mask.shape)}")

    def _pe(self, n_frames: int, device) -> torch.Tensor:
        return sinusoidal_encoding(torch.arange(n_frames, device=device), self.config.width)

    @staticmethod
    def _frame_mask(frame_mask, dtype):
        return None if frame_mask is None else frame_mask.to(dtype)

    def actor_context(
        self,
        x_a: torch.Tensor,
        cond: Conditions | None = None,
        *,
        frame_mask: torch.Tensor | None = None,
    ) -> ActorContext:
        """Run the clean actor through the reactive-mode actor stream once.

        x_a (B, T, 262) normalised clean actor motion. Returns, per block, the keys/values
        LN0(z^(j,2)_a) (B, T, W) the reactor's causal cross-attention reads. The actor stream
        is causal (self-attention j <= i, left-padded convolutions), never reads the reactor and
        sits at flow time 1, so it does not change over the ODE steps of a sample: samplers
        compute it once per conditioning (``forward(..., actor_context=...)``).
        """
        cond = cond or Conditions()
        self._check(x_a, x_a, cond, "reactive", 0, frame_mask)
        b, n_frames = x_a.shape[:2]
        device = x_a.device
        z_text = self.text_latent(cond, b, device) + self.task_embed.weight[MODES.index("reactive")]
        z_d = z_text + self.time_embedding(torch.ones(b, dtype=x_a.dtype, device=device))
        z_m = self.music_latent(cond, b, n_frames)
        z_r = self.retrieval_latent(cond, b)
        masks = self._reactive_masks(n_frames, 0, frame_mask, device, x_a.dtype)
        z = self.in_a(x_a) + self._pe(n_frames, device)
        keys, projected = [], []
        for block in self.blocks:
            mods = block.modulations(z_d)
            music = block.music_attn.project(z_m) if z_m.shape[1] > 1 else None
            z2 = block.temporal(z, mods, z_m if music is None else music, masks)
            keys.append(block.keys_of(z2))
            projected.append((music, block.motion_attn.project(keys[-1])))
            z = block.finish(z2, mods, z_r)
        return ActorContext(
            keys=keys, shape=(b, n_frames), cues=(z_text, z_m, z_r), projected=projected, source=_tensors(cond)
        )

    def _reactive_masks(self, n_frames, look_ahead, frame_mask, device, dtype) -> BlockMasks:
        cross = look_ahead_mask(n_frames, n_frames, look_ahead, device)
        if frame_mask is None:  # plain causal self-attention: SDPA's is_causal, no mask tensor
            return BlockMasks(None, cross, causal=True, frame_mask=None, self_causal=True)
        causal = look_ahead_mask(n_frames, n_frames, 0, device)
        key_mask = frame_mask.bool()[:, None, None, :]  # (B, 1, 1, T)
        causal, cross = causal & key_mask, cross & key_mask
        return BlockMasks(causal, cross, causal=True, frame_mask=self._frame_mask(frame_mask, dtype))

    def forward(
        self,
        x_a: torch.Tensor,
        x_b: torch.Tensor,
        t: torch.Tensor | float,
        cond: Conditions | None = None,
        *,
        mode: str = "interactive",
        look_ahead: int | None = None,
        frame_mask: torch.Tensor | None = None,
        actor_context: ActorContext | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Velocities (v_a, v_b), each (B, T, 262); v_a == 0 in reactive mode (app. D.3).

        actor_context (reactive only): the result of ``actor_context(x_a, cond, frame_mask=...)``
        for the same x_a, cond and frame_mask, to skip recomputing the actor stream.
        """
        cfg = self.config
        cond = cond or Conditions()
        look_ahead = cfg.look_ahead if look_ahead is None else int(look_ahead)
        self._check(x_a, x_b, cond, mode, look_ahead, frame_mask)
        b, n_frames = x_a.shape[:2]
        device = x_a.device
        t = torch.as_tensor(t, dtype=x_a.dtype, device=device).reshape(-1).expand(b)
        # z_d = text + time + task, the conditioning of every adaptive LayerNorm.
        same_cues = actor_context is not None and _same_tensors(actor_context.source, _tensors(cond))
        if same_cues and actor_context.cues is not None and mode == "reactive":
            z_text, z_m, z_r = actor_context.cues  # built from these very conditions
        else:
            z_text = self.text_latent(cond, b, device) + self.task_embed.weight[MODES.index(mode)]
            z_m = self.music_latent(cond, b, n_frames)
            z_r = self.retrieval_latent(cond, b)
        pe = self._pe(n_frames, device)

        if mode == "reactive":
            if actor_context is None:  # both streams in one pass (training): see _reactive_stacked
                z = self._reactive_stacked(x_a, x_b, t, z_text, (z_m, z_r), look_ahead, frame_mask)
                return torch.zeros_like(x_a), self._velocity(self.out_b(self.out_norm(z)), x_b, t)
            if actor_context.shape != (b, n_frames) or len(actor_context.keys) != len(self.blocks):
                raise DualFlowError(
                    f"actor_context was built for (B, T) = {actor_context.shape}, but x_a is {(b, n_frames)}; "
                    "rebuild it with model.actor_context(x_a, cond)"
                )
            z_d = z_text + self.time_embedding(t)
            masks = self._reactive_masks(n_frames, look_ahead, frame_mask, device, x_b.dtype)
            z = self.in_b(x_b) + pe
            projected = actor_context.projected if same_cues and actor_context.projected else None
            projected = projected or [(None, keys) for keys in actor_context.keys]
            for block, (music, motion) in zip(self.blocks, projected):
                mods = block.modulations(z_d)
                z2 = block.temporal(z, mods, z_m if music is None else music, masks)
                z3 = block.motion_cross(z2, mods, motion, masks.cross_mask)
                z = block.finish(z3, mods, z_r)
            return torch.zeros_like(x_a), self._velocity(self.out_b(self.out_norm(z)), x_b, t)

        # Interactive: both persons noised at the same t, stacked along the batch.
        z_d = (z_text + self.time_embedding(t)).repeat(2, 1)
        key_mask = None if frame_mask is None else frame_mask.bool()[:, None, None, :].repeat(2, 1, 1, 1)
        fm = self._frame_mask(frame_mask, x_a.dtype)
        masks = BlockMasks(key_mask, key_mask, causal=False, frame_mask=None if fm is None else fm.repeat(2, 1))
        z = torch.cat([self.in_a(x_a), self.in_b(x_b)], 0) + pe
        z_m, z_r = z_m.repeat(2, 1, 1), z_r.repeat(2, 1, 1)
        for block in self.blocks:
            z = block(z, z_d, z_m, z_r, masks)
        z = self.out_norm(z)
        return self._velocity(self.out_a(z[:b]), x_a, t), self._velocity(self.out_b(z[b:]), x_b, t)

    def _reactive_stacked(self, x_a, x_b, t, z_text, cues, look_ahead: int, frame_mask) -> torch.Tensor:
        """The reactor's last latent z (B, T, W) with the actor stream run alongside it.

        The same arithmetic as ``actor_context`` followed by the reactor pass, but block by block
        on the two streams stacked along the batch (rows [0, B) actor at flow time 1, [B, 2B)
        reactor at t): the convolutions, self- and music attention, retrieval attention and
        feed-forward run once over 2B rows instead of twice over B (half the kernel launches of
        a reactive training step), and only the reactor's rows take the causal motion
        cross-attention to the actor's keys of the same block. Equal to the two passes up to
        float rounding (tests/test_dualflow_fast_paths.py). cues: (z_m, z_r) of the batch.
        """
        b, n_frames = x_a.shape[:2]
        device = x_a.device
        ones = torch.ones(b, dtype=x_a.dtype, device=device)
        z_d = z_text.repeat(2, 1) + self.time_embedding(torch.cat([ones, t]))
        reactor = self._reactive_masks(n_frames, look_ahead, frame_mask, device, x_b.dtype)
        self_mask = reactor.self_mask
        both = BlockMasks(
            None if self_mask is None else self_mask.repeat(2, 1, 1, 1),
            None,
            causal=True,
            frame_mask=None if reactor.frame_mask is None else reactor.frame_mask.repeat(2, 1),
            self_causal=reactor.self_causal,
        )
        z_m, z_r = (cue.repeat(2, 1, 1) for cue in cues)
        z = torch.cat([self.in_a(x_a), self.in_b(x_b)], 0) + self._pe(n_frames, device)
        for block in self.blocks:
            mods = block.modulations(z_d)
            z2 = block.temporal(z, mods, z_m, both)
            keys = block.keys_of(z2[:b])
            z3 = block.motion_cross(z2[b:], [(scale[b:], shift[b:]) for scale, shift in mods], keys, reactor.cross_mask)
            z = block.finish(torch.cat([z2[:b], z3], 0), mods, z_r)
        return z[b:]

    def _velocity(self, out: torch.Tensor, x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """The output linear's result as a velocity (B, T, 262), per ``config.prediction``.

        "velocity": the output is v itself (the paper's parameterisation).
        "x0": the output is the clean motion x0_hat and v = (x0_hat - x_t) / max(1 - t, X0_MIN_GAP),
        the straight-path velocity through x_t and x0_hat (so x_t + (1 - t) v = x0_hat). Needed when
        width < 262: a velocity read from a width-d latent lies in a d-dimensional subspace and
        cannot cancel the 262-d noise at t = 0 (samples keep noise in the other 262 - d
        directions), whereas x0_hat only has to span the data, which is low-dimensional
        (Li & He 2025, "Back to Basics: Let Denoising Generative Models Denoise").
        """
        if self.config.prediction == "velocity":
            return out
        gap = (1 - t).clamp_min(X0_MIN_GAP).to(out.dtype)[:, None, None]
        return (out - x_t) / gap


# ---------------------------------------------------------------------------------------------
# Parameter counts
# ---------------------------------------------------------------------------------------------


def count_parameters(config: DualFlowConfig | str) -> int:
    """Number of trainable parameters of a config (built on the meta device: no memory used)."""
    if isinstance(config, str):
        config = DualFlowConfig.preset(config)
    return _count_parameters(config)


@functools.lru_cache(maxsize=16)
def _count_parameters(config: DualFlowConfig) -> int:
    with torch.device("meta"):
        model = DualFlow(config)
    return sum(p.numel() for p in model.parameters())


def parameter_breakdown(config: DualFlowConfig | str) -> dict[str, int]:
    """Parameters per part: convolutions, adaptive norms, attention, feed-forward, encoders, in/out."""
    if isinstance(config, str):
        config = DualFlowConfig.preset(config)
    with torch.device("meta"):
        model = DualFlow(config)
    parts = {
        "temporal convolutions": 0,
        "adaptive LayerNorms": 0,
        "attention (4 per block)": 0,
        "feed-forward": 0,
        "condition encoders (text, music, time, task, nulls)": 0,
        "input/output projections": 0,
    }
    for name, p in model.named_parameters():
        in_block = name.startswith("blocks.")
        if in_block and ".conv." in name:
            key = "temporal convolutions"
        elif in_block and ".modulation." in name:
            key = "adaptive LayerNorms"
        elif in_block and ("_attn." in name or ".other_norm." in name):
            key = "attention (4 per block)"
        elif in_block and ".ffn." in name:
            key = "feed-forward"
        elif name.startswith(("in_", "out_")):
            key = "input/output projections"
        else:
            key = "condition encoders (text, music, time, task, nulls)"
        parts[key] += p.numel()
    return parts


def parameter_report() -> str:
    """One line per preset (blocks, width, parameters) and the ``paper`` preset's breakdown.

    Ours vs the paper's 456M. Our ``paper`` preset has 368M parameters: the published block
    stack (20 blocks, width 512, 8 heads, FFN 1024) with the three temporal convolutions as
    full width-to-width Conv1d of kernels 7, 11, 21 (20 * 512^2 * 39 = 204M, over half the
    model), four attention layers, five adaptive LayerNorms (53M) and the FFN per block, with
    block weights shared by the two persons (app. D.1's "symmetric updates", as InterGen).
    The paper does not break its 456M down. What it has and we do not: a transformer encoder
    over CLIP ViT-L/14 token features (768-d) for the text, a 4800-d Jukebox input projection
    and its music transformer, and the retrieval encoder (positional encoding + a shared
    projection of the retrieved motions) -- these live in the encoder issue, and our model
    takes a pooled 384-d sentence embedding, 35-d music features and retrieval tokens already
    in the model width. The 88M gap is about the size of such encoders (one 12-layer width-768
    text transformer alone is ~85M); separate per-person block weights would instead give
    ~720M, so the paper's model cannot be duplicating the blocks per person. We cannot say more
    without the authors' configuration.
    """
    lines = []
    for name, cfg in PRESETS.items():
        n = count_parameters(cfg)
        lines.append(
            f"{name:6s} blocks={cfg.n_blocks:2d} width={cfg.width:4d} heads={cfg.n_heads} ff={cfg.ff_dim:5d} "
            f"params={n:>12,d} ({n / 1e6:.2f}M)"
        )
    lines.append("paper preset by part:")
    for part, n in parameter_breakdown("paper").items():
        lines.append(f"  {part:52s} {n / 1e6:8.2f}M")
    lines.append(
        "the paper reports 456M for its full model, including its text/music encoders "
        "(see dualflow.model.parameter_report's docstring)"
    )
    return "\n".join(lines)


if __name__ == "__main__":
    print(parameter_report())
