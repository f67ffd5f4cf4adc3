"""Retrieval-augmented generation for DualFlow (paper sec. 3.2, eq. 1): databases, scoring, encoder, wiring.

Contract: a :class:`RetrievalDatabase` (npz, no pickle) holds normalised two-person clips
(N, T_max, 2, 262) and one unit-norm embedding table per cue (spatial / body / rhythm text,
music); :meth:`RetrievalDatabase.query` returns the top-k per cue by eq. 1; the trainable
:class:`RetrievalEncoder` turns retrieved clips into z_R (B, 2K, width), the model's
``Conditions.retrieval``. For training: :class:`RagConfig` (the config's ``retrieval``
section), :func:`build_training_database`, :class:`NeighbourTable` (precomputed neighbours,
the query's own clip excluded) and :class:`RetrievalConditioner`; for checkpoints:
:func:`save_rag_files` / :func:`load_rag`. How it works: docs/model.md.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

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


def similarity_scores(
    db_emb: np.ndarray, db_len: np.ndarray, query_emb: np.ndarray, query_len, lam: float = DEFAULT_LAMBDA
) -> np.ndarray:
    """Eq. 1 for Q queries against N entries -> (Q, N) float32.

    db_emb (N, D) unit-norm rows; db_len (N,) frames; query_emb (Q, D) or (D,) (normalised here);
    query_len (Q,) or scalar frames; lam: λ >= 0. cos = E q̂ because the rows are unit norm;
    the length factor exp(−λ·|l_i − l_p| / max(l_i, l_p)) lies in (e^−λ, 1].
    """
    q = _unit(np.atleast_2d(query_emb))
    if q.shape[1] != db_emb.shape[1]:
        raise DualFlowError(
            f"query embedding has {q.shape[1]} dims, the database {db_emb.shape[1]}; "
            "use the same encoder for queries and database"
        )
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
        cue_ids = (
            np.concatenate([np.full(self.indices[c].shape[1], CUES.index(c)) for c in cues])
            if cues
            else np.zeros(0, np.int64)
        )
        return idx, cue_ids.astype(np.int64)


@dataclass
class RetrievalDatabase:
    """Clips to retrieve from, one embedding table per cue.

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
    def build(
        motions: np.ndarray,
        lengths: Sequence[int],
        texts: Sequence[str] | None = None,
        music: Sequence[np.ndarray] | None = None,
        *,
        text_encoder=None,
        decomposer=None,
        ids: Sequence[str] | None = None,
        genre: str | None = None,
    ) -> RetrievalDatabase:
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
                raise DualFlowError(
                    "retrieval build: texts given but no text_encoder (see dualflow.text.make_text_encoder)"
                )
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
            raw = np.stack([music_embedding(m, n_frames) for m, n_frames in zip(music, lengths)])
            std = raw.std(0)
            stats = (raw.mean(0), np.where(std > 1e-6, std, 1.0).astype(np.float32))  # constant dims stay 0
            emb["music"] = (raw - stats[0]) / stats[1]
        if not emb:
            raise DualFlowError("retrieval build: give texts and/or music; a database needs at least one cue")
        return RetrievalDatabase(
            np.asarray(motions, np.float32),
            np.asarray(lengths),
            emb,
            list(ids) if ids is not None else [f"clip{i:06d}" for i in range(n)],
            list(texts) if texts is not None else [],
            stats,
            meta,
        )

    def music_query(self, features: np.ndarray, length: int | None = None) -> np.ndarray:
        """Query embedding (2·D,) of per-frame music features, z-scored like the database's."""
        if self.music_stats is None:
            raise DualFlowError("this retrieval database has no music cue; rebuild it with music")
        return (music_embedding(features, length) - self.music_stats[0]) / self.music_stats[1]

    # -- querying ------------------------------------------------------------------------------

    def query(
        self,
        queries: dict[str, np.ndarray],
        lengths,
        k: int = DEFAULT_K["interactive"],
        exclude: np.ndarray | None = None,
        lam: float = DEFAULT_LAMBDA,
    ) -> RetrievalResult:
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

    def query_training(
        self, batch_indices: np.ndarray, k: int = DEFAULT_K["interactive"], lam: float = DEFAULT_LAMBDA
    ) -> RetrievalResult:
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
        arrays = {
            "motions": self.motions,
            "lengths": self.lengths,
            "ids": np.array(self.ids, dtype=str),
            "texts": np.array(self.texts, dtype=str),
            "meta": np.array(json.dumps(self.meta)),
        }
        for cue, e in self.embeddings.items():
            arrays[f"emb_{cue}"] = e
        if self.music_stats is not None:
            arrays["music_mean"], arrays["music_std"] = self.music_stats
        tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp.npz")
        np.savez(tmp, **arrays)
        os.replace(tmp, p)
        return p

    @staticmethod
    def load(path: str | Path) -> RetrievalDatabase:
        p = Path(path)
        if not p.is_file():
            raise DualFlowError(
                f"{p}: retrieval database not found; build one with RetrievalDatabase.build(...).save(path)"
            )
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
        return RetrievalDatabase(
            data["motions"],
            data["lengths"],
            emb,
            [str(s) for s in data["ids"]],
            [str(s) for s in data.get("texts", [])],
            stats,
            meta,
        )


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

    def __init__(
        self,
        width: int,
        n_layers: int = 2,
        n_heads: int = 4,
        ff_dim: int | None = None,
        dropout: float = 0.1,
        motion_dim: int = 262,
        frame_stride: int = 1,
    ):
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
        layer = nn.TransformerEncoderLayer(
            width, n_heads, ff_dim or 2 * width, dropout, activation="gelu", batch_first=True, norm_first=True
        )
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
        h = (
            h
            + sinusoidal_encoding(torch.arange(t, device=dev) * s, self.width)[:, None, :]
            + self.person.weight
            + self.cue(cue_ids)[:, :, None, None, :]
        )
        h = h.transpose(2, 3).reshape(b * k, 2 * t, self.width)  # person-major tokens
        key_valid = valid[:, :, None, :].expand(b, k, 2, t).reshape(b * k, 2 * t)
        h = self.encoder(h, src_key_padding_mask=~key_valid)
        h = h.view(b, k, 2, t, self.width)
        w = valid[:, :, None, :, None].to(h.dtype)
        pooled = (h * w).sum(3) / w.sum(3).clamp(min=1.0)  # (B, K, 2, W)
        return self.norm(pooled.reshape(b, 2 * k, self.width))


# ---------------------------------------------------------------------------------------------
# Retrieval in a training run and in a checkpoint
# ---------------------------------------------------------------------------------------------


ENCODER_FILE = "retrieval_encoder.safetensors"
ENCODER_EMA_FILE = "retrieval_encoder_ema.safetensors"
DB_FILE = "retrieval_db.npz"
MUSIC_CUE = CUES.index("music")


@dataclass(frozen=True)
class RagConfig:
    """The ``retrieval`` section of a training config.

    enabled: train with retrieval (False = the paper's "w/o RAG"); k: retrieval depth for both
    tasks (None = k_interactive / k_reactive, the paper's 5 / 3); lam: λ of eq. 1; cues: which
    databases to retrieve from (spatial, body, rhythm, music); layers / heads / dropout: the
    retrieval encoder (heads None = the model's n_heads); frame_stride: the encoder reads every
    s-th frame of a retrieved clip (1 = all; a compute saving for CPU runs).
    """

    enabled: bool = False
    k: int | None = None
    k_interactive: int = DEFAULT_K["interactive"]
    k_reactive: int = DEFAULT_K["reactive"]
    lam: float = DEFAULT_LAMBDA
    cues: tuple[str, ...] = CUES
    layers: int = 2
    heads: int | None = None
    dropout: float = 0.1
    frame_stride: int = 1

    def __post_init__(self) -> None:
        object.__setattr__(self, "cues", tuple(self.cues))
        bad = [c for c in self.cues if c not in CUES]
        if bad or not self.cues:
            raise DualFlowError(f"retrieval.cues: unknown or empty {bad or '[]'}; choose from {', '.join(CUES)}")
        for name in ("k_interactive", "k_reactive", "layers", "frame_stride"):
            if int(getattr(self, name)) < 1:
                raise DualFlowError(f"retrieval.{name} must be >= 1, got {getattr(self, name)!r}")
        if self.k is not None and int(self.k) < 1:
            raise DualFlowError(f"retrieval.k must be >= 1 (or null = 5 interactive / 3 reactive), got {self.k!r}")
        if self.heads is not None and int(self.heads) < 1:
            raise DualFlowError(f"retrieval.heads must be >= 1 or null, got {self.heads!r}")
        if float(self.lam) < 0 or not 0 <= float(self.dropout) < 1:
            raise DualFlowError("retrieval.lam must be >= 0 and retrieval.dropout in [0, 1)")

    def depth(self, mode: str) -> int:
        """k for a task: ``k`` when set, else k_interactive / k_reactive."""
        if self.k is not None:
            return int(self.k)
        return int(self.k_interactive if mode == "interactive" else self.k_reactive)

    @property
    def max_depth(self) -> int:
        return max(self.depth("interactive"), self.depth("reactive"))

    def encoder(self, width: int, model_heads: int) -> RetrievalEncoder:
        return RetrievalEncoder(
            int(width),
            n_layers=int(self.layers),
            n_heads=int(self.heads or model_heads),
            dropout=float(self.dropout),
            frame_stride=int(self.frame_stride),
        )

    def to_dict(self) -> dict:
        d = asdict(self)
        d["cues"] = list(self.cues)
        return d

    @staticmethod
    def from_dict(d: dict | None, where: str = "retrieval") -> RagConfig:
        d = dict(d or {})
        known = {f.name for f in fields(RagConfig)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise DualFlowError(f"{where}: unknown field(s) {unknown}; valid fields: {sorted(known)}")
        try:
            return RagConfig(**d)
        except (TypeError, ValueError) as exc:
            raise DualFlowError(f"{where}: {exc}") from None


# ---------------------------------------------------------------------------------------------
# training database and neighbour tables
# ---------------------------------------------------------------------------------------------


class _Deduplicated:
    """A text encoder that embeds each distinct sentence once (training texts repeat a lot)."""

    def __init__(self, encoder):
        self.inner = encoder
        self.encoder_id = encoder.encoder_id
        self.dim = encoder.dim

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        texts = [str(t) for t in texts]
        unique = sorted(set(texts))
        emb = np.asarray(self.inner.encode(unique), dtype=np.float32)
        where = {t: i for i, t in enumerate(unique)}
        return emb[[where[t] for t in texts]]


def dataset_motions(dataset) -> np.ndarray:
    """(N, T, 2, 262) float32 normalised motions of a :class:`dualflow.datasets.training.DuetDataset`."""
    return torch.stack([dataset.actor, dataset.reactor], dim=2).numpy()


def build_training_database(
    dataset, config: RagConfig, text_encoder=None, music: np.ndarray | None = None, decomposer=None
) -> RetrievalDatabase:
    """The retrieval database of a run's training windows: their normalised motions, the text
    cues (each window's text decomposed into spatial / body / rhythm descriptions, each embedded
    by the run's text encoder) and the music cue (clip statistics of the music condition).

    dataset: a DuetDataset (normalised motions, texts, sources); text_encoder: the run's
    :class:`dualflow.text.TextEncoder` (None: no text cues); music: (N, T, D) per-frame music
    condition of every window, or None (no music cue). Only ``config.cues`` are kept.
    """
    n = len(dataset)
    want_text = any(c in config.cues for c in TEXT_CUES) and text_encoder is not None and any(dataset.texts)
    want_music = "music" in config.cues and music is not None
    if not (want_text or want_music):
        raise DualFlowError(
            f"retrieval: none of the cues {list(config.cues)} can be built (text cues need texts "
            "and a text encoder, the music cue needs a music condition); set retrieval.cues or "
            "retrieval.enabled: false"
        )
    frames = int(dataset.n_frames)
    db = RetrievalDatabase.build(
        dataset_motions(dataset),
        np.full(n, frames),
        texts=list(dataset.texts) if want_text else None,
        music=np.asarray(music, dtype=np.float32) if want_music else None,
        text_encoder=_Deduplicated(text_encoder) if want_text else None,
        decomposer=decomposer,
        ids=list(dataset.sources),
    )
    for cue in list(db.embeddings):
        if cue not in config.cues:
            del db.embeddings[cue]
    db.meta["groups"] = [int(g) for g in dataset.groups]
    return db


def cue_queries(
    db: RetrievalDatabase, texts: Sequence[str] | None, music: np.ndarray | None, text_encoder=None, decomposer=None
) -> dict[str, np.ndarray]:
    """Query embeddings {cue: (Q, D)} for the database's cues from texts and per-frame music (Q, T, D)."""
    out: dict[str, np.ndarray] = {}
    text_cues = [c for c in TEXT_CUES if c in db.embeddings]
    if text_cues and texts is not None and text_encoder is not None:
        if decomposer is None:
            from dualflow.decompose import KeywordDecomposer

            decomposer = KeywordDecomposer()
        parts = [decomposer.decompose(t).as_tuple() for t in texts]
        encoder = _Deduplicated(text_encoder)
        for cue in text_cues:
            j = TEXT_CUES.index(cue)
            out[cue] = np.asarray(encoder.encode([p[j] for p in parts]), dtype=np.float32)
    if "music" in db.embeddings and music is not None:
        out["music"] = np.stack([db.music_query(m) for m in np.asarray(music)]).astype(np.float32)
    return out


@dataclass
class NeighbourTable:
    """Top-``depth`` database indices per query and cue, best first: {cue: (Q, depth) int64}."""

    indices: dict[str, np.ndarray]

    @property
    def depth(self) -> int:
        return min(v.shape[1] for v in self.indices.values()) if self.indices else 0

    @staticmethod
    def compute(
        db: RetrievalDatabase,
        queries: dict[str, np.ndarray],
        lengths,
        depth: int,
        lam: float = DEFAULT_LAMBDA,
        query_groups: np.ndarray | None = None,
        db_groups: np.ndarray | None = None,
        chunk: int = 1024,
    ) -> NeighbourTable:
        """Eq. 1 top-``depth`` for every query and cue, computed once before training.

        query_groups (Q,) / db_groups (N,): entries whose group equals the query's are never
        returned (training: a window's own clip). depth is cut to the fewest allowed entries
        of any query; a DualFlowError when some query has none.
        """
        if not queries:
            raise DualFlowError(
                f"retrieval: no query cue matches the database's cues ({', '.join(db.cues)}); give texts and/or music"
            )
        q_len = np.broadcast_to(np.asarray(lengths, dtype=np.float32).reshape(-1), (len(next(iter(queries.values()))),))
        allowed = len(db)
        if query_groups is not None:
            qg, dg = np.asarray(query_groups, np.int64), np.asarray(db_groups, np.int64)
            counts = np.bincount(dg, minlength=int(max(dg.max(), qg.max())) + 1)
            allowed = int(len(db) - counts[qg].max())
            if allowed < 1:
                raise DualFlowError(
                    "retrieval: every training window comes from one clip, so nothing is left "
                    "to retrieve once the query's own clip is excluded; use more clips"
                )
        depth = min(int(depth), allowed)
        out = {}
        for cue, q in queries.items():
            rows = []
            for s0 in range(0, len(q), chunk):
                s = similarity_scores(db.embeddings[cue], db.lengths, q[s0 : s0 + chunk], q_len[s0 : s0 + chunk], lam)
                if query_groups is not None:
                    s = np.where(qg[s0 : s0 + chunk, None] == dg[None, :], -np.inf, s)
                part = np.argpartition(-s, depth - 1, axis=1)[:, :depth]
                order = np.argsort(-np.take_along_axis(s, part, 1), axis=1, kind="stable")
                rows.append(np.take_along_axis(part, order, 1))
            out[cue] = np.concatenate(rows).astype(np.int64)
        return NeighbourTable(out)

    def select(self, rows, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(indices (B, K), cue ids (K,)) of the first k entries of every cue for query ``rows``;
        K = k · cues, cues in :data:`CUES` order."""
        r = np.asarray(rows, dtype=np.int64).reshape(-1)
        k = min(int(k), self.depth)
        cues = [c for c in CUES if c in self.indices]
        idx = np.concatenate([self.indices[c][r, :k] for c in cues], axis=1)
        cue_ids = np.repeat([CUES.index(c) for c in cues], k).astype(np.int64)
        return idx, cue_ids


def drop_retrieval_tokens(
    z: torch.Tensor,
    cue_ids: np.ndarray,
    null: torch.Tensor,
    drop_text: torch.Tensor | None = None,
    drop_music: torch.Tensor | None = None,
) -> torch.Tensor:
    """Classifier-free-guidance drop of z_R (B, 2K, W) per cue: tokens 2j, 2j + 1 come from
    retrieved clip j with cue ``cue_ids[j]``; null (1, 1, W) is the model's null retrieval token.
    A sample's dropped text replaces its text-cue tokens with null, its dropped music the
    music-cue tokens (both dropped: all null, which attention reads as "absent")."""
    token_music = torch.from_numpy(np.repeat(np.asarray(cue_ids) == MUSIC_CUE, 2)).to(z.device)
    drop = torch.zeros(z.shape[:2], dtype=torch.bool, device=z.device)
    if drop_text is not None:
        drop |= drop_text.to(z.device)[:, None] & ~token_music[None]
    if drop_music is not None:
        drop |= drop_music.to(z.device)[:, None] & token_music[None]
    if not bool(drop.any()):
        return z
    return torch.where(drop[..., None], null.to(z.dtype).expand_as(z), z)


class RetrievalConditioner:
    """z_R for batches of queries with precomputed neighbours: per batch, the first k of each
    cue's list (k by mode, :meth:`RagConfig.depth`), gathered and encoded by the retrieval encoder.

    db: the database; table: NeighbourTable of the queries (rows = query indices); config: RagConfig.
    """

    def __init__(self, db: RetrievalDatabase, table: NeighbourTable, config: RagConfig):
        self.db, self.table, self.config = db, table, config

    def retrieved(self, rows, mode: str) -> tuple[np.ndarray, np.ndarray]:
        """(indices (B, K), cue ids (K,)) for query rows in ``mode``."""
        return self.table.select(rows, self.config.depth(mode))

    def tokens(
        self,
        encoder,
        rows,
        mode: str,
        device,
        null: torch.Tensor | None = None,
        drop_text: torch.Tensor | None = None,
        drop_music: torch.Tensor | None = None,
    ) -> torch.Tensor | None:
        """z_R (B, 2K, width) through ``encoder`` (gradients flow into it), dropped per cue when
        ``null`` and drop masks are given."""
        idx, cue_ids = self.retrieved(rows, mode)
        motions, lengths = self.db.gather(idx)
        z = encoder(
            torch.from_numpy(motions).to(device),
            torch.from_numpy(lengths).to(device),
            torch.from_numpy(cue_ids).to(device),
        )
        if z is None or null is None:
            return z
        return drop_retrieval_tokens(z, cue_ids, null, drop_text, drop_music)


# ---------------------------------------------------------------------------------------------
# checkpoint files
# ---------------------------------------------------------------------------------------------


def _chmod_public(path: Path) -> None:
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o644 & ~umask)


def save_rag_files(
    directory: str | Path,
    encoder_state: dict[str, torch.Tensor],
    db: RetrievalDatabase | None = None,
    ema_state: dict[str, torch.Tensor] | None = None,
) -> None:
    """Write the retrieval encoder (and its EMA state, and the database) into a checkpoint directory
    that is not yet published (the caller renames the directory into place afterwards)."""
    from safetensors.torch import save_file

    d = Path(directory)
    files = [(ENCODER_FILE, encoder_state), (ENCODER_EMA_FILE, ema_state)]
    for name, state in files:
        if state is not None:
            save_file({k: v.detach().cpu().float().contiguous() for k, v in state.items()}, str(d / name))
            _chmod_public(d / name)
    if db is not None:
        _chmod_public(db.save(d / DB_FILE))


@dataclass
class LoadedRag:
    """What a RAG checkpoint carries: its config, the encoder (eval mode) and the database."""

    config: RagConfig
    encoder: RetrievalEncoder
    db: RetrievalDatabase


def load_rag(ckpt, device: str | torch.device = "cpu") -> LoadedRag | None:
    """The retrieval parts of a loaded :class:`dualflow.checkpoint.Checkpoint`, or None when it was
    trained without retrieval. Missing or mismatched files raise DualFlowError naming them."""
    from safetensors.torch import load_file

    section = ckpt.meta.get("retrieval")
    if not isinstance(section, dict) or not section.get("enabled"):
        return None
    config = RagConfig.from_dict(section, f"{ckpt.path}/config.json 'retrieval'")
    for name in (ENCODER_FILE, DB_FILE):
        if not (Path(ckpt.path) / name).is_file():
            raise DualFlowError(f"{ckpt.path}: trained with retrieval but lacks {name}; re-export the checkpoint")
    encoder = config.encoder(ckpt.config.width, ckpt.config.n_heads)
    try:
        encoder.load_state_dict(load_file(str(Path(ckpt.path) / ENCODER_FILE)))
    except RuntimeError as exc:
        raise DualFlowError(
            f"{ckpt.path / ENCODER_FILE}: does not match retrieval config {section} ({str(exc).splitlines()[0]})"
        ) from None
    return LoadedRag(config, encoder.to(device).eval(), RetrievalDatabase.load(Path(ckpt.path) / DB_FILE))
