"""Retrieval-augmented generation (RAG) in training and at inference (paper sec. 3.2, eq. 1).

:mod:`dualflow.retrieval` holds the pieces (databases, eq. 1 scoring, top-k, the retrieval
encoder); this module wires them into a training run and into a checkpoint:

1. :func:`build_training_database`: one :class:`RetrievalDatabase` from the *training*
   windows: their normalised motions (N, T, 2, 262), the spatial / body / rhythm text cues
   (the window's text decomposed by :class:`dualflow.decompose.KeywordDecomposer`, each
   description embedded by the run's text encoder) and the music cue (clip-level
   statistics of the run's per-frame music condition; absent when the run has no music).
2. :meth:`NeighbourTable.compute`: for each training window and each cue, the top-k
   database entries by s_i = cos(f_i, f_p) · exp(−λ·|l_i − l_p| / max(l_i, l_p)), computed
   once before training. The query's own clip is excluded: every window cut from the
   same source clip (``DuetDataset.groups``), not only the window itself, since windows of
   one clip share its text and music and would be retrieved first.
3. :class:`RetrievalConditioner.tokens`: per batch, the first k of each cue's list
   (k = 5 interactive, 3 reactive, :class:`RagConfig`), gathered and encoded by the
   trainable :class:`dualflow.retrieval.RetrievalEncoder` into z_R = ``Conditions.retrieval``.
   Classifier-free-guidance drop (:func:`drop_retrieval_tokens`): the tokens retrieved by a
   text cue are replaced by the model's learned null retrieval token when the sample's text
   is dropped, the music-cue tokens when its music is dropped; with both dropped the sample
   sees only null tokens, which the retrieval cross-attention reads exactly as "absent"
   (attention over identical tokens equals attention over one).
4. :func:`save_rag_files` / :func:`load_rag`: ``retrieval_encoder.safetensors`` and
   ``retrieval_db.npz`` inside the checkpoint directory, the :class:`RagConfig` under
   ``"retrieval"`` in its config.json; :class:`dualflow.conditioning.ConditionBuilder`
   and the evaluation load them with the checkpoint.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from dualflow.errors import DualFlowError
from dualflow.retrieval import (CUES, DEFAULT_K, DEFAULT_LAMBDA, TEXT_CUES, RetrievalDatabase, RetrievalEncoder,
                                similarity_scores)

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
        return RetrievalEncoder(int(width), n_layers=int(self.layers), n_heads=int(self.heads or model_heads),
                                dropout=float(self.dropout), frame_stride=int(self.frame_stride))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["cues"] = list(self.cues)
        return d

    @staticmethod
    def from_dict(d: dict | None, where: str = "retrieval") -> "RagConfig":
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
# database and queries
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
    """(N, T, 2, 262) float32 normalised motions of a :class:`dualflow.data.DuetDataset`."""
    return torch.stack([dataset.actor, dataset.reactor], dim=2).numpy()


def build_training_database(dataset, config: RagConfig, text_encoder=None, music: np.ndarray | None = None,
                            decomposer=None) -> RetrievalDatabase:
    """The retrieval database of a run's training windows (module docstring, step 1).

    dataset: a DuetDataset (normalised motions, texts, sources); text_encoder: the run's
    :class:`dualflow.text.TextEncoder` (None: no text cues); music: (N, T, D) per-frame music
    condition of every window, or None (no music cue). Only ``config.cues`` are kept.
    """
    n = len(dataset)
    want_text = any(c in config.cues for c in TEXT_CUES) and text_encoder is not None and any(dataset.texts)
    want_music = "music" in config.cues and music is not None
    if not (want_text or want_music):
        raise DualFlowError(f"retrieval: none of the cues {list(config.cues)} can be built (text cues need texts "
                            "and a text encoder, the music cue needs a music condition); set retrieval.cues or "
                            "retrieval.enabled: false")
    frames = int(dataset.n_frames)
    db = RetrievalDatabase.build(dataset_motions(dataset), np.full(n, frames),
                                 texts=list(dataset.texts) if want_text else None,
                                 music=np.asarray(music, dtype=np.float32) if want_music else None,
                                 text_encoder=_Deduplicated(text_encoder) if want_text else None, decomposer=decomposer,
                                 ids=list(dataset.sources))
    for cue in list(db.embeddings):
        if cue not in config.cues:
            del db.embeddings[cue]
    db.meta["groups"] = [int(g) for g in dataset.groups]
    return db


def cue_queries(db: RetrievalDatabase, texts: Sequence[str] | None, music: np.ndarray | None, text_encoder=None,
                decomposer=None) -> dict[str, np.ndarray]:
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
    def compute(db: RetrievalDatabase, queries: dict[str, np.ndarray], lengths, depth: int,
                lam: float = DEFAULT_LAMBDA, query_groups: np.ndarray | None = None,
                db_groups: np.ndarray | None = None, chunk: int = 1024) -> "NeighbourTable":
        """Eq. 1 top-``depth`` for every query (module docstring, step 2).

        query_groups (Q,) / db_groups (N,): entries whose group equals the query's are never
        returned (training: a window's own clip). depth is cut to the fewest allowed entries
        of any query; a DualFlowError when some query has none.
        """
        if not queries:
            raise DualFlowError("retrieval: no query cue matches the database's cues "
                                f"({', '.join(db.cues)}); give texts and/or music")
        q_len = np.broadcast_to(np.asarray(lengths, dtype=np.float32).reshape(-1), (len(next(iter(queries.values()))),))
        allowed = len(db)
        if query_groups is not None:
            qg, dg = np.asarray(query_groups, np.int64), np.asarray(db_groups, np.int64)
            counts = np.bincount(dg, minlength=int(max(dg.max(), qg.max())) + 1)
            allowed = int(len(db) - counts[qg].max())
            if allowed < 1:
                raise DualFlowError("retrieval: every training window comes from one clip, so nothing is left "
                                    "to retrieve once the query's own clip is excluded; use more clips")
        depth = min(int(depth), allowed)
        out = {}
        for cue, q in queries.items():
            rows = []
            for s0 in range(0, len(q), chunk):
                s = similarity_scores(db.embeddings[cue], db.lengths, q[s0:s0 + chunk], q_len[s0:s0 + chunk], lam)
                if query_groups is not None:
                    s = np.where(qg[s0:s0 + chunk, None] == dg[None, :], -np.inf, s)
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


def drop_retrieval_tokens(z: torch.Tensor, cue_ids: np.ndarray, null: torch.Tensor,
                          drop_text: torch.Tensor | None = None, drop_music: torch.Tensor | None = None) -> torch.Tensor:
    """CFG drop of z_R (B, 2K, W) per cue (module docstring, step 3): tokens 2j, 2j + 1 come from
    retrieved clip j with cue ``cue_ids[j]``; null (1, 1, W) is the model's null retrieval token."""
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
    """z_R for batches of queries with precomputed neighbours (module docstring, step 3).

    db: the database; table: NeighbourTable of the queries (rows = query indices); config: RagConfig.
    """

    def __init__(self, db: RetrievalDatabase, table: NeighbourTable, config: RagConfig):
        self.db, self.table, self.config = db, table, config

    def retrieved(self, rows, mode: str) -> tuple[np.ndarray, np.ndarray]:
        """(indices (B, K), cue ids (K,)) for query rows in ``mode``."""
        return self.table.select(rows, self.config.depth(mode))

    def tokens(self, encoder, rows, mode: str, device, null: torch.Tensor | None = None,
               drop_text: torch.Tensor | None = None, drop_music: torch.Tensor | None = None) -> torch.Tensor | None:
        """z_R (B, 2K, width) through ``encoder`` (gradients flow into it), dropped per cue when
        ``null`` and drop masks are given."""
        idx, cue_ids = self.retrieved(rows, mode)
        motions, lengths = self.db.gather(idx)
        z = encoder(torch.from_numpy(motions).to(device), torch.from_numpy(lengths).to(device),
                    torch.from_numpy(cue_ids).to(device))
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


def save_rag_files(directory: str | Path, encoder_state: dict[str, torch.Tensor],
                   db: RetrievalDatabase | None = None, ema_state: dict[str, torch.Tensor] | None = None) -> None:
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
        raise DualFlowError(f"{ckpt.path / ENCODER_FILE}: does not match retrieval config {section} "
                            f"({str(exc).splitlines()[0]})") from None
    return LoadedRag(config, encoder.to(device).eval(), RetrievalDatabase.load(Path(ckpt.path) / DB_FILE))
