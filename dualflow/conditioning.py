"""Any subset of (actor motion, text, music file) -> DualFlow inputs, and a generator on top.

The rest of the system (CLI, bridge, evaluation) hands the generator whatever it has:

=================  ==================================================================
given               what is generated
=================  ==================================================================
actor               the reactor, reactive mode (paper app. D.3), as long as the actor
actor + text/music  the same, conditioned on them
text and/or music   both persons, interactive mode; length from the music, else n_frames
nothing             an unconditional interactive duet of ``n_frames`` (default 120)
=================  ==================================================================

:class:`ConditionBuilder` does the conversion. Absent inputs are None in
:class:`dualflow.model.Conditions`, which the network reads as its learned null (the same
null classifier-free guidance trains), so no input is ever faked.

* text -> ``text_encoder.encode([text])`` (1, D_text); the encoder must be the one the model
  was trained with (:func:`text_encoder_for` resolves a checkpoint's ``text_encoder`` id).
* music file (wav/ogg/mp3, or a Jukebox .npy) -> (1, T, D_music) with
  :func:`dualflow.music.music_features` of the model's music kind (checkpoint meta
  ``music``: "beats" -> "beats4", "none" -> music is ignored with a note).
* actor :class:`~dualflow.motion.Motion` -> resampled to ``fps``, encoded in its own canonical
  frame (:func:`dualflow.motion.features.encode_person`), normalised with the model's NormStats
  -> (1, T-1, 262); the canonical frame maps the generated reactor back to the actor's world.
* retrieval (optional; needs a :class:`dualflow.retrieval.RetrievalDatabase` and a trained
  :class:`dualflow.retrieval.RetrievalEncoder`): text decomposed into spatial/body/rhythm
  queries and the music embedding, top-k per cue (5 interactive, 3 reactive) -> z_R.

:class:`DuetGenerator` samples with :func:`dualflow.flow.generate` and decodes to a
:class:`~dualflow.motion.TwoPersonMotion` in world coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from dualflow.errors import DualFlowError
from dualflow.model import Conditions, DualFlow, DualFlowConfig
from dualflow.motion.container import Motion, TwoPersonMotion
from dualflow.motion.features import CanonicalFrame, canonical_frame, decode_person, encode_person
from dualflow.motion.normalization import NormStats
from dualflow.music import MUSIC_DIMS, MUSIC_KINDS, music_features
from dualflow.retrieval import CUES, DEFAULT_K, DEFAULT_LAMBDA, TEXT_CUES, RetrievalDatabase

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
        raise DualFlowError(f"the model was trained with text encoder {encoder_id!r}; pass "
                            "text_encoder=dualflow.text.ClipTextEncoder('<local ViT-L-14 weights>')")
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
    ignored); fps: the model's frame rate; retrieval_db / retrieval_encoder / decomposer / k /
    lam: optional RAG (both db and encoder, or neither); k: one depth for both tasks, a
    {mode: depth} dict, or None (5 interactive, 3 reactive). :meth:`from_checkpoint` loads a
    RAG checkpoint's database, encoder and depths (:func:`dualflow.rag.load_rag`).
    """

    def __init__(self, model_config: DualFlowConfig, stats: NormStats, *, text_encoder=None,
                 music_kind: str | None = "edge35", fps: float = 30.0,
                 retrieval_db: RetrievalDatabase | None = None, retrieval_encoder=None, decomposer=None,
                 k: int | dict | None = None, lam: float = DEFAULT_LAMBDA):
        self.config = model_config
        self.stats = stats
        self.text_encoder = text_encoder
        if text_encoder is not None and int(text_encoder.dim) != model_config.text_dim:
            raise DualFlowError(f"text encoder {text_encoder.encoder_id!r} gives {text_encoder.dim}-d embeddings, "
                                f"the model's text_dim is {model_config.text_dim}; use the model's encoder")
        if music_kind is not None:
            if music_kind not in MUSIC_DIMS:
                raise DualFlowError(f"unknown music kind {music_kind!r}; choose one of {', '.join(MUSIC_KINDS)}")
            if MUSIC_DIMS[music_kind] != model_config.music_dim:
                raise DualFlowError(f"music kind {music_kind!r} is {MUSIC_DIMS[music_kind]}-d but the model's "
                                    f"music_dim is {model_config.music_dim}; pick the kind it was trained with")
        self.music_kind = music_kind
        self.fps = float(fps)
        if (retrieval_db is None) != (retrieval_encoder is None):
            raise DualFlowError("retrieval needs both retrieval_db and retrieval_encoder (or neither)")
        self.retrieval_db, self.retrieval_encoder = retrieval_db, retrieval_encoder
        if decomposer is None and retrieval_db is not None:
            from dualflow.decompose import KeywordDecomposer

            decomposer = KeywordDecomposer()
        self.decomposer = decomposer
        self.k, self.lam = k, float(lam)

    @classmethod
    def from_checkpoint(cls, ckpt, **overrides) -> "ConditionBuilder":
        """Builder matching a :class:`dualflow.checkpoint.Checkpoint` (its text encoder and music kind)."""
        music_meta = str(ckpt.meta.get("music", "none"))
        if music_meta not in MUSIC_FROM_META:
            raise DualFlowError(f"{ckpt.path}: unknown music setting {music_meta!r} in config.json")
        data = ckpt.meta.get("data") if isinstance(ckpt.meta.get("data"), dict) else {}
        kw = {"music_kind": MUSIC_FROM_META[music_meta], "fps": float(data.get("fps", 30.0))}
        if "text_encoder" not in overrides:
            kw["text_encoder"] = text_encoder_for(ckpt.text_encoder, ckpt.config.text_dim)
        if "retrieval_db" not in overrides and "retrieval_encoder" not in overrides:
            from dualflow.rag import load_rag

            rag = load_rag(ckpt)
            if rag is not None:
                kw.update(retrieval_db=rag.db, retrieval_encoder=rag.encoder, lam=rag.config.lam,
                          k={m: rag.config.depth(m) for m in ("interactive", "reactive")})
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

    def retrieval_condition(self, text: str | None, music: np.ndarray | None, n_frames: int,
                            mode: str) -> tuple[torch.Tensor | None, list[str]]:
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
        depth = self.k.get(mode, DEFAULT_K[mode]) if isinstance(self.k, dict) else (self.k or DEFAULT_K[mode])
        res = db.query(queries, n_frames, k=int(depth), lam=self.lam)
        idx, cue_ids = res.flat()
        motions, lengths = db.gather(idx)
        param = next(self.retrieval_encoder.parameters())
        with torch.no_grad():
            z = self.retrieval_encoder(torch.from_numpy(motions).to(param), torch.from_numpy(lengths),
                                       torch.from_numpy(cue_ids))
        return z, [db.ids[i] for i in idx[0]]

    # -- everything -------------------------------------------------------------------------------

    def build(self, *, actor: Motion | None = None, text: str | None = None, music=None,
              n_frames: int | None = None) -> GeneratorInputs:
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
                raise DualFlowError(f"n_frames={n_frames} but the actor gives {x_actor.shape[1]} feature rows "
                                    "(its frames - 1); leave n_frames out with an actor")
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
            retrieval, retrieved = self.retrieval_condition(text if text_t is not None else None, music_arr,
                                                            n_frames, mode)
        cond = Conditions(text=text_t,
                          music=None if music_arr is None else torch.from_numpy(music_arr)[None],
                          retrieval=retrieval)
        used_in_order = tuple(name for name in ("actor", "text", "music") if name in used)
        return GeneratorInputs(cond, mode, n_frames, x_actor, frame, used_in_order, notes, retrieved)


class DuetGenerator:
    """The generator the rest of the system calls: any subset of (actor, text, music) in,
    a :class:`TwoPersonMotion` (Z-up world, metres, ``builder.fps``) out.

    With an actor the result's actor is the given motion (resampled to fps) and the reactor is
    generated in the actor's world; otherwise both persons are generated in a canonical world
    (person A starts at the origin facing +X).
    """

    def __init__(self, model: DualFlow, builder: ConditionBuilder):
        self.model = model.eval()
        self.builder = builder

    @classmethod
    def from_checkpoint(cls, path: str | Path | None = None, device: str = "cpu", **builder_kw) -> "DuetGenerator":
        from dualflow.checkpoint import load_model

        model, ckpt = load_model(path, device)
        return cls(model, ConditionBuilder.from_checkpoint(ckpt, **builder_kw))

    @torch.no_grad()
    def generate(self, *, actor: Motion | None = None, text: str | None = None, music=None,
                 n_frames: int | None = None, steps: int = 20, cfg_scale: float = 1.0, seed: int = 0,
                 method: str = "euler", clean: bool = True) -> tuple[TwoPersonMotion, GeneratorInputs]:
        """clean: pass the generated reactor through :func:`dualflow.body.clean_positions` (constant
        bone lengths, planted feet, less jitter; its contacts are the cleaner's); False: the raw
        decoded features, as before issue 28."""
        from dualflow.flow import generate

        inputs = self.builder.build(actor=actor, text=text, music=music, n_frames=n_frames)
        param = next(self.model.parameters())
        cond = Conditions(**{name: None if getattr(inputs.cond, name) is None else getattr(inputs.cond, name).to(param)
                             for name in ("text", "music", "retrieval")})
        x_a, x_b = generate(self.model, inputs.n_frames, cond, mode=inputs.mode,
                            x_actor=None if inputs.actor is None else inputs.actor.to(param),
                            steps=steps, method=method, cfg_scale=cfg_scale, seed=seed)
        fps = self.builder.fps
        stats = self.builder.stats
        a = stats.denormalize(x_a[0].cpu().numpy().astype(np.float64))
        b = stats.denormalize(x_b[0].cpu().numpy().astype(np.float64))
        reactor = decode_person(b, fps, inputs.canonical, append_last_frame=True, name="reactor")
        if clean:
            from dualflow.body import clean_positions

            pos, contacts = clean_positions(reactor.positions, fps)
            reactor = Motion(positions=pos, fps=fps, contacts=contacts, name="reactor")
        if actor is not None:
            actor_motion = actor if abs(actor.fps - fps) < 1e-6 else actor.resample(fps)
        else:
            actor_motion = decode_person(a, fps, None, append_last_frame=True, name="actor")
        return TwoPersonMotion(actor_motion, reactor, text or ""), inputs


__all__ = ["ConditionBuilder", "DuetGenerator", "GeneratorInputs", "text_encoder_for", "CUES"]
