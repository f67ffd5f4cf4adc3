"""A contrastive motion-text evaluator after InterGen's InterCLIP, trainable offline.

Contract: :func:`train_evaluator` (CLI ``dualflow-bridge eval train-evaluator``) learns the
metrics' embedding space, since no public evaluator weights can be downloaded here; a motion
transformer (both people's 262-d features) and a text transformer (hashed words) give
L2-normalised embeddings trained with a symmetric CLIP loss. Saved as a folder
(``evaluator.safetensors``, ``evaluator.json``, ``norm_stats.npz``) and loaded without pickle.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import tempfile
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file
from torch import nn

from dualflow.errors import DualFlowError
from dualflow.motion.features import FEATURE_DIM
from dualflow.motion.normalization import NormStats

WEIGHTS_FILE = "evaluator.safetensors"
CONFIG_FILE = "evaluator.json"
STATS_FILE = "norm_stats.npz"
FORMAT = "dualflow-evaluator-1"
_WORD = re.compile(r"[a-z0-9]+")


@dataclass(frozen=True)
class EvaluatorConfig:
    """width: transformer width; layers / heads / ff_dim per encoder; dim: embedding size;
    vocab: hashed word buckets; max_words: text tokens kept; max_frames: positions table size."""

    width: int = 128
    layers: int = 2
    heads: int = 4
    ff_dim: int = 256
    dim: int = 128
    vocab: int = 4096
    max_words: int = 48
    max_frames: int = 512
    dropout: float = 0.1

    def __post_init__(self) -> None:
        if self.width % self.heads:
            raise DualFlowError(f"evaluator: width {self.width} must be divisible by heads {self.heads}")
        for f in fields(self):
            if f.name != "dropout" and getattr(self, f.name) < 1:
                raise DualFlowError(f"evaluator: {f.name} must be >= 1")


def word_ids(texts: Sequence[str], vocab: int, max_words: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(ids (B, L) int64 in [1, vocab], mask (B, L) bool True = word) for hashed words; 0 pads."""
    rows = []
    for text in texts:
        words = _WORD.findall(str(text).lower())[:max_words]
        rows.append(
            [1 + int.from_bytes(hashlib.blake2b(w.encode(), digest_size=8).digest(), "little") % vocab for w in words]
            or [0]
        )
    length = max(len(r) for r in rows)
    ids = torch.zeros((len(rows), length), dtype=torch.long)
    for i, r in enumerate(rows):
        ids[i, : len(r)] = torch.tensor(r)
    return ids, ids > 0


def _sinusoid(n: int, dim: int) -> torch.Tensor:
    pos = torch.arange(n, dtype=torch.float32)[:, None]
    div = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-math.log(10000.0) / dim))
    pe = torch.zeros(n, dim)
    pe[:, 0::2] = torch.sin(pos * div)
    pe[:, 1::2] = torch.cos(pos * div)
    return pe


class _Encoder(nn.Module):
    """Query token + transformer encoder over (B, L, width) tokens -> (B, dim)."""

    def __init__(self, cfg: EvaluatorConfig):
        super().__init__()
        layer = nn.TransformerEncoderLayer(
            cfg.width, cfg.heads, cfg.ff_dim, cfg.dropout, activation="gelu", batch_first=True, norm_first=True
        )
        self.query = nn.Parameter(torch.zeros(1, 1, cfg.width))
        self.body = nn.TransformerEncoder(layer, cfg.layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(cfg.width)
        self.out = nn.Linear(cfg.width, cfg.dim)
        self.register_buffer("pe", _sinusoid(cfg.max_frames + 1, cfg.width), persistent=False)

    def forward(self, tokens: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        b, n, _ = tokens.shape
        x = torch.cat([self.query.expand(b, 1, -1), tokens], dim=1) + self.pe[: n + 1]
        pad = torch.cat([torch.zeros(b, 1, dtype=torch.bool, device=valid.device), ~valid], dim=1)
        return self.out(self.norm(self.body(x, src_key_padding_mask=pad)[:, 0]))


class MotionTextEvaluator(nn.Module):
    """InterCLIP-style evaluator (module docstring). Inputs are RAW (un-normalised) features."""

    def __init__(self, config: EvaluatorConfig, stats: NormStats):
        super().__init__()
        self.config = config
        self.stats = stats
        self.register_buffer("mean", torch.tensor(np.array(stats.mean), dtype=torch.float32), persistent=False)
        self.register_buffer("std", torch.tensor(np.array(stats.std), dtype=torch.float32), persistent=False)
        self.motion_in = nn.Linear(2 * FEATURE_DIM, config.width)
        self.motion = _Encoder(config)
        self.words = nn.Embedding(config.vocab + 1, config.width, padding_idx=0)
        self.text = _Encoder(config)
        self.latent_scale = nn.Parameter(torch.tensor(1.0))

    @property
    def device(self) -> torch.device:
        return self.latent_scale.device

    def _scaled(self, u: torch.Tensor) -> torch.Tensor:
        return F.normalize(u, dim=-1) * self.latent_scale

    def encode_motion(self, features: torch.Tensor, lengths: torch.Tensor | None = None) -> torch.Tensor:
        """(B, T, 2, 262) raw features (+ optional (B,) valid lengths) -> (B, dim)."""
        x = torch.as_tensor(features, dtype=torch.float32, device=self.device)
        if x.ndim != 4 or x.shape[2:] != (2, FEATURE_DIM):
            raise DualFlowError(f"evaluator: motion must be (B, T, 2, {FEATURE_DIM}) features, got {tuple(x.shape)}")
        if x.shape[1] > self.config.max_frames:
            raise DualFlowError(f"evaluator: clips of {x.shape[1]} frames exceed max_frames {self.config.max_frames}")
        x = ((x - self.mean) / self.std).flatten(2)
        t = torch.arange(x.shape[1], device=self.device)
        valid = (
            torch.ones(x.shape[:2], dtype=torch.bool, device=self.device)
            if lengths is None
            else t[None, :] < torch.as_tensor(lengths, device=self.device)[:, None]
        )
        return self._scaled(self.motion(self.motion_in(x), valid))

    def encode_text(self, texts: Sequence[str]) -> torch.Tensor:
        if isinstance(texts, str):
            raise DualFlowError("evaluator: texts must be a list of strings")
        ids, valid = word_ids(texts, self.config.vocab, self.config.max_words)
        ids, valid = ids.to(self.device), valid.to(self.device)
        return self._scaled(self.text(self.words(ids), valid))

    def clip_loss(self, motion_emb: torch.Tensor, text_emb: torch.Tensor) -> torch.Tensor:
        """½ [CE(s² U_m U_tᵀ, I) + CE(s² U_t U_mᵀ, I)] (module docstring)."""
        um, ut = F.normalize(motion_emb, dim=-1), F.normalize(text_emb, dim=-1)
        logits = self.latent_scale**2 * um @ ut.T
        target = torch.arange(len(um), device=um.device)
        return 0.5 * (F.cross_entropy(logits, target) + F.cross_entropy(logits.T, target))

    @torch.no_grad()
    def embed(self, features: np.ndarray, texts: Sequence[str] | None = None, batch_size: int = 256):
        """numpy (motion (N, dim), text (N, dim) | None) in eval mode, batched."""
        was = self.training
        self.eval()
        try:
            m = [
                self.encode_motion(torch.as_tensor(features[i : i + batch_size])).cpu().numpy()
                for i in range(0, len(features), batch_size)
            ]
            t = None
            if texts is not None:
                t = np.concatenate(
                    [
                        self.encode_text(list(texts[i : i + batch_size])).cpu().numpy()
                        for i in range(0, len(texts), batch_size)
                    ]
                )
        finally:
            self.train(was)
        return np.concatenate(m), t

    # -- persistence ----------------------------------------------------------------------

    def save(self, path: str | os.PathLike, summary: dict | None = None) -> Path:
        """Write the evaluator directory atomically (temp dir + rename)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
        save_file({k: v.detach().cpu().contiguous() for k, v in self.state_dict().items()}, str(tmp / WEIGHTS_FILE))
        (tmp / CONFIG_FILE).write_text(
            json.dumps({"format": FORMAT, "config": asdict(self.config), "summary": summary or {}}, indent=2)
        )
        self.stats.save(tmp / STATS_FILE)
        from dualflow.checkpoint import replace_directory

        replace_directory(tmp, path)
        return path

    @staticmethod
    def load(path: str | os.PathLike, device: str = "cpu") -> MotionTextEvaluator:
        path = Path(path)
        for name in (WEIGHTS_FILE, CONFIG_FILE, STATS_FILE):
            if not (path / name).is_file():
                raise DualFlowError(
                    f"{path / name}: missing; train an evaluator with `dualflow-bridge eval "
                    "train-evaluator --dataset NAME --out DIR`"
                )
        try:
            meta = json.loads((path / CONFIG_FILE).read_text())
        except json.JSONDecodeError as exc:
            raise DualFlowError(f"{path / CONFIG_FILE}: not valid json ({exc})") from None
        if meta.get("format") != FORMAT:
            raise DualFlowError(f"{path / CONFIG_FILE}: not a DualFlow evaluator (format {meta.get('format')!r})")
        model = MotionTextEvaluator(EvaluatorConfig(**meta["config"]), NormStats.load(path / STATS_FILE))
        model.load_state_dict(load_file(str(path / WEIGHTS_FILE)))
        model.summary = meta.get("summary", {})
        return model.to(device).eval()


@dataclass(frozen=True)
class EvaluatorTraining:
    """steps, batch_size (matched pairs per contrastive batch), lr, weight_decay, seed, threads."""

    steps: int = 400
    batch_size: int = 32
    lr: float = 3e-4
    weight_decay: float = 1e-4
    seed: int = 0


def train_evaluator(
    features: np.ndarray,
    texts: Sequence[str],
    *,
    config: EvaluatorConfig = EvaluatorConfig(),
    training: EvaluatorTraining = EvaluatorTraining(),
    stats: NormStats | None = None,
    device: str = "cpu",
    log=None,
) -> MotionTextEvaluator:
    """Train on (N, T, 2, 262) raw features and their N texts; returns the model in eval mode.

    Batches draw ``batch_size`` distinct clips; pairs with identical text in one batch are
    still treated as negatives (as InterCLIP does). ``log(step, loss)`` is called every 50 steps.
    """
    features = np.asarray(features, dtype=np.float32)
    if features.ndim != 4 or features.shape[2:] != (2, FEATURE_DIM):
        raise DualFlowError(f"train_evaluator: features must be (N, T, 2, {FEATURE_DIM}), got {features.shape}")
    if len(texts) != len(features) or len(features) < 2:
        raise DualFlowError(
            f"train_evaluator: need >= 2 clips with one text each, got {len(features)} clips, {len(texts)} texts"
        )
    torch.manual_seed(training.seed)
    stats = stats or NormStats.from_features(features)
    model = MotionTextEvaluator(config, stats).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=training.lr, weight_decay=training.weight_decay)
    rng = np.random.default_rng(training.seed)
    b = min(training.batch_size, len(features))
    t0 = time.perf_counter()
    loss_value = float("nan")
    model.train()
    for step in range(training.steps):
        idx = rng.choice(len(features), b, replace=False)
        loss = model.clip_loss(
            model.encode_motion(torch.from_numpy(features[idx])), model.encode_text([texts[i] for i in idx])
        )
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        loss_value = float(loss.detach())
        if log is not None and (step % 50 == 0 or step == training.steps - 1):
            log(step, loss_value)
    model.summary = {
        "steps": training.steps,
        "final_loss": loss_value,
        "clips": len(features),
        "frames": int(features.shape[1]),
        "seconds": round(time.perf_counter() - t0, 2),
    }
    return model.eval()
