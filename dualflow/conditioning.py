"""Any subset of (actor motion, text, music) -> the network's inputs (:class:`GeneratorInputs`).

Contract: :meth:`ConditionBuilder.build` takes what the caller has (None = absent) and returns
the :class:`dualflow.model.Conditions` plus the mode: an actor makes it reactive (the reactor
is generated as long as the actor), otherwise interactive (both persons; length from the music,
else ``n_frames``, default 120). Absent inputs stay None, which the network reads as its learned
null; given inputs the model cannot use are listed in ``notes``, never faked. The builder must
match the checkpoint (text encoder, music kind, fps): :meth:`ConditionBuilder.from_checkpoint`.
The generator on top is :class:`dualflow.duet_generator.DuetGenerator`; details: docs/model.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from dualflow.errors import DualFlowError
from dualflow.model import Conditions, DualFlowConfig
from dualflow.motion.container import Motion
from dualflow.motion.features import CanonicalFrame, canonical_frame, encode_person
from dualflow.motion.normalization import NormStats
from dualflow.music import MUSIC_DIMS, MUSIC_KINDS, music_features
from dualflow.retrieval import CUES, TEXT_CUES, RagConfig, RetrievalDatabase, load_rag

DEFAULT_FRAMES = 120
#: Checkpoint meta "music" -> music feature kind (None: the model never heard music).
MUSIC_FROM_META = {"none": None, "beats": "beats4", **{k: k for k in MUSIC_KINDS}}


def text_encoder_for(encoder_id: str, dim: int):
    """The text encoder a checkpoint was trained with, from its id (config.json "text_encoder").

    "hashed_bag_of_words_v1…" -> :class:`dualflow.text.HashedBagOfWordsEncoder`; the MiniLM id ->
    :class:`dualflow.text.MiniLMEncoder`; an open_clip id needs the local weights, so it raises
    with the fix (pass ``text_encoder=ClipTextEncoder(path)``). An empty id (old checkpoints)
    means MiniLM when dim is 384.
    """
    from dualflow import text as T

    if encoder_id.startswith("hashed_bag_of_words_v1"):
        return T.HashedBagOfWordsEncoder(dim)
    if encoder_id == T.MINILM_ID or (not encoder_id and dim == T.MINILM_DIM):
        return T.MiniLMEncoder()
    if encoder_id.startswith("open_clip/"):
        raise DualFlowError(
            f"the model was trained with text encoder {encoder_id!r}; pass "
            "text_encoder=dualflow.text.ClipTextEncoder('<local ViT-L-14 weights>')"
        )
    raise DualFlowError(f"unknown text encoder id {encoder_id!r} in the checkpoint; pass text_encoder= explicitly")


@dataclass
class GeneratorInputs:
    """What the network gets for one request (batch 1).

    cond: Conditions; mode: 'reactive' (actor given) or 'interactive'; n_frames: T feature rows;
    actor: (1, T, 262) normalised actor features or None; canonical: the actor's canonical
    frame or None; used: the inputs that made it into ``cond`` or ``actor``; notes: inputs
    that were given but not used, and why; retrieved: ids of retrieved clips.
    """

    cond: Conditions
    mode: str
    n_frames: int
    actor: torch.Tensor | None = None
    canonical: CanonicalFrame | None = None
    used: tuple[str, ...] = ()
    notes: list[str] = field(default_factory=list)
    retrieved: list[str] = field(default_factory=list)


class ConditionBuilder:
    """Builds :class:`GeneratorInputs` from any subset of actor / text / music (module docstring).

    model_config: the network's DualFlowConfig (text_dim, music_dim, width); stats: its NormStats;
    text_encoder: a TextEncoder with ``dim == text_dim`` (None: text is ignored with a note);
    music_kind: a dualflow.music kind with ``MUSIC_DIMS[kind] == music_dim``, or None (music
    ignored); fps: the model's frame rate; retrieval_db / retrieval_encoder: optional RAG (both
    or neither); retrieval_config: its depths per mode and λ (None: :class:`RagConfig` defaults,
    5 interactive, 3 reactive); ``decomposer`` (attribute): splits a text into the three cue
    queries. :meth:`from_checkpoint` loads a RAG checkpoint's database, encoder and config
    (:func:`dualflow.retrieval.load_rag`).
    """

    def __init__(
        self,
        model_config: DualFlowConfig,
        stats: NormStats,
        *,
        text_encoder=None,
        music_kind: str | None = "edge35",
        fps: float = 30.0,
        retrieval_db: RetrievalDatabase | None = None,
        retrieval_encoder=None,
        retrieval_config: RagConfig | None = None,
    ):
        self.config = model_config
        self.stats = stats
        self.text_encoder = text_encoder
        if text_encoder is not None and int(text_encoder.dim) != model_config.text_dim:
            raise DualFlowError(
                f"text encoder {text_encoder.encoder_id!r} gives {text_encoder.dim}-d embeddings, "
                f"the model's text_dim is {model_config.text_dim}; use the model's encoder"
            )
        if music_kind is not None:
            if music_kind not in MUSIC_DIMS:
                raise DualFlowError(f"unknown music kind {music_kind!r}; choose one of {', '.join(MUSIC_KINDS)}")
            if MUSIC_DIMS[music_kind] != model_config.music_dim:
                raise DualFlowError(
                    f"music kind {music_kind!r} is {MUSIC_DIMS[music_kind]}-d but the model's "
                    f"music_dim is {model_config.music_dim}; pick the kind it was trained with"
                )
        self.music_kind = music_kind
        self.fps = float(fps)
        if (retrieval_db is None) != (retrieval_encoder is None):
            raise DualFlowError("retrieval needs both retrieval_db and retrieval_encoder (or neither)")
        self.retrieval_db, self.retrieval_encoder = retrieval_db, retrieval_encoder
        self.retrieval_config = retrieval_config or RagConfig()
        self.decomposer = None
        if retrieval_db is not None:
            from dualflow.decompose import KeywordDecomposer

            self.decomposer = KeywordDecomposer()

    @classmethod
    def from_checkpoint(cls, ckpt, **overrides) -> ConditionBuilder:
        """Builder matching a :class:`dualflow.checkpoint.Checkpoint` (its text encoder and music kind)."""
        music_meta = str(ckpt.meta.get("music", "none"))
        if music_meta not in MUSIC_FROM_META:
            raise DualFlowError(f"{ckpt.path}: unknown music setting {music_meta!r} in config.json")
        data = ckpt.meta.get("data") if isinstance(ckpt.meta.get("data"), dict) else {}
        kw = {"music_kind": MUSIC_FROM_META[music_meta], "fps": float(data.get("fps", 30.0))}
        if "text_encoder" not in overrides:
            kw["text_encoder"] = text_encoder_for(ckpt.text_encoder, ckpt.config.text_dim)
        if "retrieval_db" not in overrides and "retrieval_encoder" not in overrides:
            rag = load_rag(ckpt)
            if rag is not None:
                kw.update(retrieval_db=rag.db, retrieval_encoder=rag.encoder, retrieval_config=rag.config)
        kw.update(overrides)
        return cls(ckpt.config, ckpt.stats, **kw)

    # -- one input each -------------------------------------------------------------------------

    def text_condition(self, text: str) -> torch.Tensor:
        """(1, D_text) float32 embedding of one sentence."""
        if not isinstance(text, str) or not text.strip():
            raise DualFlowError(f"text must be a non-empty string, got {text!r}")
        return torch.from_numpy(np.asarray(self.text_encoder.encode([text]), dtype=np.float32))

    def music_array(self, music, n_frames: int | None) -> np.ndarray:
        """(T, D_music) per-frame features from a file path or a ready (T, D_music) array."""
        if isinstance(music, (str, Path)):
            return music_features(music, self.music_kind, self.fps, n_frames)
        arr = np.asarray(music, dtype=np.float32)
        if arr.ndim != 2 or arr.shape[1] != self.config.music_dim:
            raise DualFlowError(f"music array must be (T, {self.config.music_dim}), got {arr.shape}")
        if n_frames is not None:
            if arr.shape[0] < n_frames:
                raise DualFlowError(f"music array has {arr.shape[0]} frames, the clip needs {n_frames}")
            arr = arr[:n_frames]
        return arr

    def actor_condition(self, actor: Motion) -> tuple[torch.Tensor, CanonicalFrame]:
        """(1, T-1, 262) normalised actor features in its own canonical frame, and that frame."""
        if not isinstance(actor, Motion):
            raise DualFlowError(f"actor must be a dualflow.motion.Motion, got {type(actor).__name__}")
        if abs(actor.fps - self.fps) > 1e-6:
            actor = actor.resample(self.fps)
        frame = canonical_frame(actor)
        feats = self.stats.normalize(encode_person(actor, frame)).astype(np.float32)
        return torch.from_numpy(feats)[None], frame

    def retrieval_condition(
        self, text: str | None, music: np.ndarray | None, n_frames: int, mode: str
    ) -> tuple[torch.Tensor | None, list[str]]:
        """z_R (1, R, width) from the text's three focused descriptions and the music, or None."""
        db = self.retrieval_db
        queries: dict[str, np.ndarray] = {}
        if text is not None and self.text_encoder is not None and all(c in db.embeddings for c in TEXT_CUES):
            parts = self.decomposer.decompose(text).as_tuple()
            emb = self.text_encoder.encode(list(parts))
            queries.update({c: emb[i] for i, c in enumerate(TEXT_CUES)})
        if music is not None and "music" in db.embeddings:
            queries["music"] = db.music_query(music, n_frames)
        if not queries:
            return None, []
        config = self.retrieval_config
        res = db.query(queries, n_frames, k=config.depth(mode), lam=float(config.lam))
        idx, cue_ids = res.flat()
        motions, lengths = db.gather(idx)
        param = next(self.retrieval_encoder.parameters())
        with torch.no_grad():
            z = self.retrieval_encoder(
                torch.from_numpy(motions).to(param), torch.from_numpy(lengths), torch.from_numpy(cue_ids)
            )
        return z, [db.ids[i] for i in idx[0]]

    # -- everything -------------------------------------------------------------------------------

    def build(
        self, *, actor: Motion | None = None, text: str | None = None, music=None, n_frames: int | None = None
    ) -> GeneratorInputs:
        """GeneratorInputs for any subset of the three inputs (None = absent).

        n_frames: feature rows to generate when there is no actor (default: the music's length,
        else 120); with an actor it is the actor's T - 1 and must not be given differently.
        """
        used: list[str] = []
        notes: list[str] = []
        x_actor = frame = None
        if actor is not None:
            x_actor, frame = self.actor_condition(actor)
            if n_frames is not None and int(n_frames) != x_actor.shape[1]:
                raise DualFlowError(
                    f"n_frames={n_frames} but the actor gives {x_actor.shape[1]} feature rows "
                    "(its frames - 1); leave n_frames out with an actor"
                )
            n_frames = x_actor.shape[1]
            used.append("actor")
        mode = "reactive" if x_actor is not None else "interactive"

        music_arr = None
        if music is not None:
            if self.music_kind is None:
                notes.append("music ignored: this model was trained without music")
            else:
                music_arr = self.music_array(music, n_frames)
                if n_frames is None:
                    n_frames = music_arr.shape[0]
                used.append("music")
        n_frames = int(n_frames if n_frames is not None else DEFAULT_FRAMES)
        if n_frames < 1:
            raise DualFlowError(f"n_frames must be >= 1, got {n_frames}")

        text_t = None
        if text is not None:
            if self.text_encoder is None:
                notes.append("text ignored: no text encoder for this model")
            else:
                text_t = self.text_condition(text)
                used.append("text")

        retrieval, retrieved = None, []
        if self.retrieval_db is not None:
            retrieval, retrieved = self.retrieval_condition(
                text if text_t is not None else None, music_arr, n_frames, mode
            )
        cond = Conditions(
            text=text_t, music=None if music_arr is None else torch.from_numpy(music_arr)[None], retrieval=retrieval
        )
        used_in_order = tuple(name for name in ("actor", "text", "music") if name in used)
        return GeneratorInputs(cond, mode, n_frames, x_actor, frame, used_in_order, notes, retrieved)


__all__ = ["ConditionBuilder", "GeneratorInputs", "text_encoder_for", "CUES"]
