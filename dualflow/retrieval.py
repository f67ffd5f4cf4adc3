"""Multi-modal motion retrieval (RAG) for DualFlow (paper sec. 3.2).

Pieces, in the order data flows through them
--------------------------------------------
:class:`RetrievalDatabase`  N two-person clips: motions (N, T_max, 2, 262) float32 (normalised
    InterGen features, zero-padded after ``lengths[i]`` frames) and one unit-norm embedding
    table per cue: ``spatial``, ``body``, ``rhythm`` (text embeddings of the decomposed text,
    :mod:`dualflow.decompose` + :mod:`dualflow.text`) and ``music`` (clip-level music
    embedding, :func:`music_embedding`). Built from a dataset with :meth:`RetrievalDatabase.build`,
    saved/loaded as one npz (no pickle).
:func:`similarity_scores`   s_i = cos(f_i, f_p) · exp(−λ·|l_i − l_p| / max(l_i, l_p))   (eq. 1),
    vectorised over all entries and a batch of queries: one (Q, D)·(D, N) product.
:meth:`RetrievalDatabase.query`   top-k per cue (k = 5 interactive, 3 reactive by default,
    :data:`DEFAULT_K`), the query's own entry excluded at training time (``exclude``).
:class:`RetrievalEncoder`   retrieved motions -> retrieval latent z_R (B, R, width), the
    ``Conditions.retrieval`` tokens of :class:`dualflow.model.DualFlow`.

Choices where the paper is silent: the music embedding of a clip is the mean and standard
deviation over its frames of the per-frame music features, z-scored with the database's
statistics (the paper uses Jukebox embeddings: pass those per-frame features to get the same
treatment). Cue tables for absent modalities are simply not built.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import nn

from dualflow.errors import DualFlowError
from dualflow.model import sinusoidal_encoding

TEXT_CUES = ("spatial", "body", "rhythm")
CUES = TEXT_CUES + ("music",)
DEFAULT_K = {"interactive": 5, "reactive": 3}
DEFAULT_LAMBDA = 0.1
FORMAT = "dualflow-retrieval-db-v1"


def _unit(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float32)
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.where(n > 0, x / np.maximum(n, 1e-12), 0.0).astype(np.float32)


def similarity_scores(db_emb: np.ndarray, db_len: np.ndarray, query_emb: np.ndarray, query_len,
                      lam: float = DEFAULT_LAMBDA) -> np.ndarray:
    """Eq. 1 for Q queries against N entries -> (Q, N) float32.

    db_emb (N, D) unit-norm rows; db_len (N,) frames; query_emb (Q, D) or (D,) (normalised here);
    query_len (Q,) or scalar frames; lam: λ >= 0. cos = E q̂ because the rows are unit norm;
    the length factor exp(−λ·|l_i − l_p| / max(l_i, l_p)) lies in (e^−λ, 1].
    """
    q = _unit(np.atleast_2d(query_emb))
    if q.shape[1] != db_emb.shape[1]:
        raise DualFlowError(f"query embedding has {q.shape[1]} dims, the database {db_emb.shape[1]}; "
                            "use the same encoder for queries and database")
    lp = np.broadcast_to(np.asarray(query_len, dtype=np.float32).reshape(-1, 1), (q.shape[0], 1))
    li = np.asarray(db_len, dtype=np.float32)[None, :]
    # (Q, D)·(D, N) through torch (zero-copy views): its CPU GEMV is ~10x faster here than
    # numpy's OpenBLAS call on a busy machine (bench/retrieval_speed.py measures both paths).
    e = torch.from_numpy(np.ascontiguousarray(db_emb, dtype=np.float32))
    cos = torch.mm(torch.from_numpy(q), e.T).numpy()
    return cos * np.exp(-float(lam) * np.abs(li - lp) / np.maximum(np.maximum(li, lp), 1.0))


def top_k(scores: np.ndarray, k: int, exclude: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Indices and scores (Q, k') of the k highest scores per row, best first; k' = min(k, N − 1 if
    excluding else N). exclude (Q,) int: the entry to skip in each row (−1 = none)."""
    s = np.array(scores, dtype=np.float32, copy=True)
    q, n = s.shape
    if exclude is not None:
        ex = np.asarray(exclude, dtype=np.int64).reshape(-1)
        rows = np.flatnonzero(ex >= 0)
        s[rows, ex[rows]] = -np.inf
    kk = min(int(k), n - (1 if exclude is not None else 0))
    if kk < 1:
        return np.zeros((q, 0), np.int64), np.zeros((q, 0), np.float32)
    part = np.argpartition(-s, kk - 1, axis=1)[:, :kk]
    part_scores = np.take_along_axis(s, part, 1)
    order = np.argsort(-part_scores, axis=1, kind="stable")
    return np.take_along_axis(part, order, 1), np.take_along_axis(part_scores, order, 1)


def music_embedding(features: np.ndarray, length: int | None = None) -> np.ndarray:
    """Clip-level music embedding (2·D,) = [mean_t f_t, std_t f_t] over the first ``length`` frames
    of per-frame features (T, D) (any music feature set: EDGE 35, Duolando 54, Jukebox 4800)."""
    f = np.asarray(features, dtype=np.float64)
    if f.ndim != 2 or f.shape[0] < 1:
        raise DualFlowError(f"music features must be (T, D) with T >= 1, got {f.shape}")
    f = f[: int(length)] if length else f
    return np.concatenate([f.mean(0), f.std(0)]).astype(np.float32)


@dataclass
class RetrievalResult:
    """Per cue: indices (Q, k) into the database and their scores (Q, k), best first."""

    indices: dict[str, np.ndarray]
    scores: dict[str, np.ndarray]

    def flat(self) -> tuple[np.ndarray, np.ndarray]:
        """(Q, K) indices and (K,) cue ids (position in CUES), cues concatenated in CUES order."""
        cues = [c for c in CUES if c in self.indices]
        idx = np.concatenate([self.indices[c] for c in cues], axis=1) if cues else np.zeros((0, 0), np.int64)
        cue_ids = np.concatenate([np.full(self.indices[c].shape[1], CUES.index(c)) for c in cues]) if cues \
            else np.zeros(0, np.int64)
        return idx, cue_ids.astype(np.int64)


@dataclass
class RetrievalDatabase:
    """Clips to retrieve from (see the module docstring).

    motions (N, T_max, 2, 262) float32; lengths (N,) int64 frames; embeddings {cue: (N, D_cue)}
    unit-norm float32; ids (N,) clip names; texts (N,) original texts; music_stats: (mean, std)
    of raw music embeddings (z-scoring) or None; meta: JSON-able dict (encoder ids, …).
    """

    motions: np.ndarray
    lengths: np.ndarray
    embeddings: dict[str, np.ndarray]
    ids: list[str]
    texts: list[str] = field(default_factory=list)
    music_stats: tuple[np.ndarray, np.ndarray] | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        m = np.asarray(self.motions)
        if m.ndim != 4 or m.shape[2] != 2 or m.shape[3] != 262:
            raise DualFlowError(f"retrieval database motions must be (N, T, 2, 262), got {m.shape}")
        n = m.shape[0]
        self.motions = m.astype(np.float32, copy=False)
        self.lengths = np.asarray(self.lengths, dtype=np.int64).reshape(-1)
        if self.lengths.shape != (n,) or (n and (self.lengths.min() < 1 or self.lengths.max() > m.shape[1])):
            raise DualFlowError(f"retrieval database lengths must be (N,) = ({n},) in [1, {m.shape[1]}]")
        for cue, e in self.embeddings.items():
            if cue not in CUES:
                raise DualFlowError(f"unknown retrieval cue {cue!r}; cues are {', '.join(CUES)}")
            if e.ndim != 2 or e.shape[0] != n:
                raise DualFlowError(f"retrieval embeddings[{cue!r}] must be (N={n}, D), got {e.shape}")
            self.embeddings[cue] = _unit(e)
        if len(self.ids) != n:
            raise DualFlowError(f"retrieval database needs {n} ids, got {len(self.ids)}")

    def __len__(self) -> int:
        return int(self.motions.shape[0])

    @property
    def cues(self) -> tuple[str, ...]:
        return tuple(c for c in CUES if c in self.embeddings)

    # -- building ------------------------------------------------------------------------------

    @staticmethod
    def build(motions: np.ndarray, lengths: Sequence[int], texts: Sequence[str] | None = None,
              music: Sequence[np.ndarray] | None = None, *, text_encoder=None, decomposer=None,
              ids: Sequence[str] | None = None, genre: str | None = None) -> "RetrievalDatabase":
        """Embed a dataset's clips per cue.

        motions (N, T, 2, 262) normalised features; lengths (N,); texts: N strings (decomposed by
        ``decomposer``, default :class:`dualflow.decompose.KeywordDecomposer`, each description
        encoded by ``text_encoder``, required with texts); music: N per-frame feature arrays
        (T_i, D) or one (N, T, D) array, or None.
        """
        n = len(motions)
        emb: dict[str, np.ndarray] = {}
        meta: dict = {"format": FORMAT}
        if texts is not None:
            if len(texts) != n:
                raise DualFlowError(f"retrieval build: {len(texts)} texts for {n} motions")
            if text_encoder is None:
                raise DualFlowError("retrieval build: texts given but no text_encoder (see dualflow.text.make_text_encoder)")
            if decomposer is None:
                from dualflow.decompose import KeywordDecomposer

                decomposer = KeywordDecomposer()
            parts = [decomposer.decompose(t, genre).as_tuple() for t in texts]
            for j, cue in enumerate(TEXT_CUES):
                emb[cue] = text_encoder.encode([p[j] for p in parts])
            meta.update(text_encoder=text_encoder.encoder_id, decomposer=getattr(decomposer, "name", "?"))
        stats = None
        if music is not None:
            if len(music) != n:
                raise DualFlowError(f"retrieval build: {len(music)} music arrays for {n} motions")
            raw = np.stack([music_embedding(m, l) for m, l in zip(music, lengths)])
            std = raw.std(0)
            stats = (raw.mean(0), np.where(std > 1e-6, std, 1.0).astype(np.float32))  # constant dims stay 0
            emb["music"] = (raw - stats[0]) / stats[1]
        if not emb:
            raise DualFlowError("retrieval build: give texts and/or music; a database needs at least one cue")
        return RetrievalDatabase(np.asarray(motions, np.float32), np.asarray(lengths), emb,
                                 list(ids) if ids is not None else [f"clip{i:06d}" for i in range(n)],
                                 list(texts) if texts is not None else [], stats, meta)

    def music_query(self, features: np.ndarray, length: int | None = None) -> np.ndarray:
        """Query embedding (2·D,) of per-frame music features, z-scored like the database's."""
        if self.music_stats is None:
            raise DualFlowError("this retrieval database has no music cue; rebuild it with music")
        return (music_embedding(features, length) - self.music_stats[0]) / self.music_stats[1]

    # -- querying ------------------------------------------------------------------------------

    def query(self, queries: dict[str, np.ndarray], lengths, k: int = DEFAULT_K["interactive"],
              exclude: np.ndarray | None = None, lam: float = DEFAULT_LAMBDA) -> RetrievalResult:
        """Top-k per cue for Q queries.

        queries {cue: (Q, D_cue) or (D_cue,)}: any subset of the database's cues (absent cues are
        skipped); lengths (Q,) or scalar frames; exclude (Q,) database index of each query's own
        clip (training) or None; lam: λ of eq. 1.
        """
        idx, sc = {}, {}
        for cue, q in queries.items():
            if q is None:
                continue
            if cue not in self.embeddings:
                raise DualFlowError(f"retrieval cue {cue!r} is not in this database (it has {', '.join(self.cues)})")
            s = similarity_scores(self.embeddings[cue], self.lengths, q, lengths, lam)
            idx[cue], sc[cue] = top_k(s, k, exclude)
        return RetrievalResult(idx, sc)

    def query_training(self, batch_indices: np.ndarray, k: int = DEFAULT_K["interactive"],
                       lam: float = DEFAULT_LAMBDA) -> RetrievalResult:
        """Queries from the database's own entries ``batch_indices`` (B,), each excluding itself."""
        b = np.asarray(batch_indices, dtype=np.int64).reshape(-1)
        return self.query({c: self.embeddings[c][b] for c in self.cues}, self.lengths[b], k, exclude=b, lam=lam)

    def gather(self, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Motions (Q, K, T_max, 2, 262) and lengths (Q, K) of retrieved indices (Q, K)."""
        idx = np.asarray(indices, dtype=np.int64)
        return self.motions[idx], self.lengths[idx]

    # -- files ---------------------------------------------------------------------------------

    def save(self, path: str | Path) -> Path:
        """Write one npz (temp file + rename): motions, lengths, ids, texts, emb_<cue>, music stats, meta JSON."""
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        arrays = {"motions": self.motions, "lengths": self.lengths,
                  "ids": np.array(self.ids, dtype=str), "texts": np.array(self.texts, dtype=str),
                  "meta": np.array(json.dumps(self.meta))}
        for cue, e in self.embeddings.items():
            arrays[f"emb_{cue}"] = e
        if self.music_stats is not None:
            arrays["music_mean"], arrays["music_std"] = self.music_stats
        tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp.npz")
        np.savez(tmp, **arrays)
        os.replace(tmp, p)
        return p

    @staticmethod
    def load(path: str | Path) -> "RetrievalDatabase":
        p = Path(path)
        if not p.is_file():
            raise DualFlowError(f"{p}: retrieval database not found; build one with RetrievalDatabase.build(...).save(path)")
        try:
            with np.load(p, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except Exception as exc:
            raise DualFlowError(f"{p}: not a readable npz retrieval database ({exc})") from exc
        missing = [k for k in ("motions", "lengths", "ids", "meta") if k not in data]
        if missing:
            raise DualFlowError(f"{p}: retrieval database lacks {missing}; rebuild it")
        meta = json.loads(str(data["meta"]))
        if meta.get("format") != FORMAT:
            raise DualFlowError(f"{p}: format {meta.get('format')!r}, expected {FORMAT!r}; rebuild it")
        emb = {c: data[f"emb_{c}"] for c in CUES if f"emb_{c}" in data}
        stats = (data["music_mean"], data["music_std"]) if "music_mean" in data else None
        return RetrievalDatabase(data["motions"], data["lengths"], emb, [str(s) for s in data["ids"]],
                                 [str(s) for s in data.get("texts", [])], stats, meta)


# ---------------------------------------------------------------------------------------------
# Retrieval encoder (torch): retrieved motions -> z_R
# ---------------------------------------------------------------------------------------------


class RetrievalEncoder(nn.Module):
    """Retrieved two-person motions -> retrieval latent z_R (B, 2K, width).

    motions (B, K, T, 2, 262) normalised features, lengths (B, K) valid frames, cue_ids (K,)
    or (B, K) positions in CUES. Per retrieved clip: tokens h_{t,p} = W x_{t,p} + b (one
    linear shared by every clip, person and cue) + PE(t) + e_person[p] + e_cue; a small
    transformer encoder over the clip's 2T tokens (padded frames masked out as keys); then a
    masked mean over each person's valid frames gives one token per (clip, person), and a
    final LayerNorm. K = 0 (nothing retrieved) gives None, which the model reads as absent.
    frame_stride s >= 1: encode every s-th frame of the retrieved clips (positions keep the
    original frame index t·s), which divides the encoder's tokens by s and its attention by s².
    """

    def __init__(self, width: int, n_layers: int = 2, n_heads: int = 4, ff_dim: int | None = None,
                 dropout: float = 0.1, motion_dim: int = 262, frame_stride: int = 1):
        super().__init__()
        if width % n_heads:
            raise DualFlowError(f"RetrievalEncoder: width ({width}) must be divisible by n_heads ({n_heads})")
        if int(frame_stride) < 1:
            raise DualFlowError(f"RetrievalEncoder: frame_stride must be >= 1, got {frame_stride}")
        self.frame_stride = int(frame_stride)
        self.width = int(width)
        self.proj = nn.Linear(motion_dim, width)
        self.person = nn.Embedding(2, width)
        self.cue = nn.Embedding(len(CUES), width)
        layer = nn.TransformerEncoderLayer(width, n_heads, ff_dim or 2 * width, dropout, activation="gelu",
                                           batch_first=True, norm_first=True)
        self.encoder = nn.TransformerEncoder(layer, n_layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(width)

    def forward(self, motions: torch.Tensor, lengths: torch.Tensor, cue_ids: torch.Tensor):
        if motions.ndim != 5 or motions.shape[3] != 2:
            raise DualFlowError(f"retrieved motions must be (B, K, T, 2, 262), got {tuple(motions.shape)}")
        if motions.shape[1] == 0:
            return None
        s = self.frame_stride
        if s > 1:
            motions = motions[:, :, ::s]
            lengths = torch.div(torch.as_tensor(lengths) + (s - 1), s, rounding_mode="floor")
        b, k, t = motions.shape[:3]
        dev = motions.device
        cue_ids = torch.as_tensor(cue_ids, device=dev).long().expand(b, k)
        valid = torch.arange(t, device=dev)[None, None, :] < lengths.to(dev)[..., None]  # (B, K, T)
        h = self.proj(motions)  # (B, K, T, 2, W)
        h = (h + sinusoidal_encoding(torch.arange(t, device=dev) * s, self.width)[:, None, :]
             + self.person.weight + self.cue(cue_ids)[:, :, None, None, :])
        h = h.transpose(2, 3).reshape(b * k, 2 * t, self.width)  # person-major tokens
        key_valid = valid[:, :, None, :].expand(b, k, 2, t).reshape(b * k, 2 * t)
        h = self.encoder(h, src_key_padding_mask=~key_valid)
        h = h.view(b, k, 2, t, self.width)
        w = valid[:, :, None, :, None].to(h.dtype)
        pooled = (h * w).sum(3) / w.sum(3).clamp(min=1.0)  # (B, K, 2, W)
        return self.norm(pooled.reshape(b, 2 * k, self.width))
