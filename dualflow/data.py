"""Training data for DualFlow built from the SYNTHETIC duet generator.

Nothing here is captured motion: every clip comes from :mod:`dualflow.synthetic`
(a procedural leader and a rule-driven follower). Real dataset loaders are a
later issue; they should produce the same sample layout.

Pipeline, per clip ``i`` of a split:

1. ``make_duet(rule_i, seconds=(frames + 1) / fps, fps, seed_i)`` with the rules
   cycling through ``config.rules`` and seeds disjoint between splits
   (train: ``seed·10⁶ + i``, val: ``seed·10⁶ + 500000 + i``);
2. :func:`dualflow.motion.features.encode_pair` → (frames, 2, 262) float32 in the
   actor's canonical Y-up frame (InterGen's convention drops the last frame);
3. normalisation with :class:`NormStats` fitted on the *training* split (both
   persons pooled): ``x = (features − mean) / std``;
4. the text embedding of the clip's template sentence
   (:func:`template_text_embedding`) and the beat track (T, 4).

One sample (and one batch, stacked) is a dict of float32 tensors::

    actor    (T, 262)   normalised features of person A (the leader)
    reactor  (T, 262)   normalised features of person B (the follower)
    text     (D_text,)  sentence embedding
    beats    (T, 4)     [beat impulse, sin 2π·phase, cos 2π·phase, downbeat impulse]
    rule     ()         int64 index into ``config.rules``

Text embedding: until a real text encoder exists (the encoders are another
issue), :func:`template_text_embedding` is a documented, deterministic stand-in
(a random projection of the bag of words). Checkpoints record its id
(:data:`TEXT_ENCODER_ID`) so that inference embeds prompts the same way; a later
encoder replaces this one function and gets a new id.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from dualflow.errors import DualFlowError
from dualflow.motion.features import FEATURE_SLICES, encode_pair
from dualflow.motion.normalization import NormStats
from dualflow.synthetic import RULES, make_duet

#: Id of the text embedding below, stored in checkpoints (config.json "text_encoder").
TEXT_ENCODER_ID = "hashed_bag_of_words_v1"

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


#: data.dataset value of the built-in synthetic duets (the default); any other name is a
#: :data:`dualflow.datasets.LOADERS` entry read from ``data.root``.
SYNTHETIC = "synthetic"
#: The fields that describe the synthetic clips (the data cache key uses only these).
SYNTHETIC_FIELDS = ("n_clips", "val_clips", "frames", "fps", "rules", "seed", "varied")


@dataclass(frozen=True)
class SyntheticDataConfig:
    """Which training data: the synthetic duets (default) or a dataset by name.

    dataset: "synthetic" (generated here) or a loader of :mod:`dualflow.datasets`
    ("interhuman", "interhuman_as", "dd100", "mdd", "bvh_pairs"); root: that dataset's
    folder (required for every dataset but "synthetic"); splits: [train split] or
    [train split, validation split] (default: ["train"], for bvh_pairs ["all"]);
    stride: frames between window starts (default: frames, no overlap); options: keyword
    options of the loader (e.g. {music: jukebox} for MDD, {limit: 100}).

    Synthetic clips: n_clips training clips; val_clips validation clips (disjoint seeds);
    frames: feature rows per clip or window (the model's window, T); fps: frame rate;
    rules: follower rules to cycle through; seed: base seed of the split seeds; varied: share
    of clips (0-1) drawn from the wider repertoire of :mod:`dualflow.synthetic_varied` (leaders
    that walk up, turn and reach out a hand, responsive followers, mirrored duets); 0 = the
    classic clips only (what every checkpoint before it was trained on).
    """

    n_clips: int = 512
    val_clips: int = 32
    frames: int = 60
    fps: float = 30.0
    rules: tuple[str, ...] = RULES
    seed: int = 0
    dataset: str = SYNTHETIC
    root: str | None = None
    splits: tuple[str, ...] | None = None
    stride: int | None = None
    options: dict = field(default_factory=dict)
    varied: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "rules", tuple(self.rules))
        object.__setattr__(self, "options", dict(self.options or {}))
        bad = [r for r in self.rules if r not in RULES]
        if bad or not self.rules:
            raise DualFlowError(f"data.rules: unknown or empty rules {bad or '[]'}; choose from {', '.join(RULES)}")
        for name in ("n_clips", "frames"):
            if int(getattr(self, name)) < 1:
                raise DualFlowError(f"data.{name} must be >= 1, got {getattr(self, name)!r}")
        if int(self.val_clips) < 0:
            raise DualFlowError(f"data.val_clips must be >= 0, got {self.val_clips!r}")
        if not float(self.fps) > 0:
            raise DualFlowError(f"data.fps must be > 0, got {self.fps!r}")
        if not 0.0 <= float(self.varied) <= 1.0:
            raise DualFlowError(f"data.varied is a share of clips, 0 to 1; got {self.varied!r}")
        self._check_dataset()

    def _check_dataset(self) -> None:
        from dualflow.datasets import LOADERS

        if self.dataset not in LOADERS:
            raise DualFlowError(f"data.dataset: unknown dataset {self.dataset!r}; choose one of {', '.join(LOADERS)}")
        if self.splits is not None:
            splits = (self.splits,) if isinstance(self.splits, str) else tuple(self.splits)
            if not 1 <= len(splits) <= 2 or not all(isinstance(x, str) and x for x in splits):
                raise DualFlowError(f"data.splits must be [train] or [train, validation] split names, got {self.splits!r}")
            object.__setattr__(self, "splits", splits)
        if self.stride is not None and int(self.stride) < 1:
            raise DualFlowError(f"data.stride must be >= 1 frames (or null = data.frames), got {self.stride!r}")
        if self.dataset == SYNTHETIC:
            if self.root is not None or self.splits is not None or self.options:
                raise DualFlowError("data.dataset 'synthetic' is generated (n_clips, val_clips, rules, seed); "
                                    "data.root, data.splits and data.options are for a real dataset")
            return
        if self.root is None or not str(self.root).strip():
            raise DualFlowError(f"data.root: dataset {self.dataset!r} needs its folder; set data.root: /path/to/{self.dataset}")
        if not Path(self.root).expanduser().is_dir():
            raise DualFlowError(f"data.root: {self.root} is not a folder (dataset {self.dataset!r}); "
                                "point data.root at the dataset's top folder")

    @property
    def is_synthetic(self) -> bool:
        return self.dataset == SYNTHETIC

    def split_names(self) -> tuple[str, str | None]:
        """(train split, validation split or None) of a real dataset."""
        default = ("all",) if self.dataset == "bvh_pairs" else ("train",)
        splits = self.splits or default
        return splits[0], (splits[1] if len(splits) > 1 else None)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["rules"] = list(self.rules)
        d["splits"] = None if self.splits is None else list(self.splits)
        return d

    def synthetic_dict(self) -> dict:
        """The synthetic-clip fields only (the data cache key)."""
        d = self.to_dict()
        return {k: d[k] for k in SYNTHETIC_FIELDS}

    @staticmethod
    def from_dict(d: dict, where: str = "data") -> "SyntheticDataConfig":
        known = {f.name for f in fields(SyntheticDataConfig)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise DualFlowError(f"{where}: unknown field(s) {unknown}; valid fields: {sorted(known)}")
        return SyntheticDataConfig(**d)


#: The training-data config under its general name (it describes any dataset, not only synthetic clips).
DataConfig = SyntheticDataConfig


@dataclass
class SyntheticSplit:
    """Raw (un-normalised) features of one split.

    features (N, T, 2, 262) float32; texts: N sentences; beats (N, T, 4) float32;
    rules (N,) int64 index into the config's rules; seeds (N,) int64; music (N, T, D)
    float32 per-frame music features of kind ``music_kind`` (dualflow.music) or None.
    """

    features: np.ndarray
    texts: list[str]
    beats: np.ndarray
    rules: np.ndarray
    seeds: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    music: np.ndarray | None = None
    music_kind: str | None = None


def clip_seed(config: SyntheticDataConfig, split: str, index: int) -> int:
    """Seed of clip ``index`` of ``split`` ('train' or 'val'); the splits never share a seed."""
    if split not in ("train", "val"):
        raise DualFlowError(f"split must be 'train' or 'val', got {split!r}")
    return int(config.seed) * 1_000_000 + (500_000 if split == "val" else 0) + int(index)


def is_varied_clip(config: SyntheticDataConfig, index: int) -> bool:
    """Whether clip ``index`` comes from the varied repertoire: a share ``config.varied`` of the
    clips, spread evenly over the rule cycle (clips of one cycle agree)."""
    share = float(getattr(config, "varied", 0.0))
    return share > 0 and ((index // len(config.rules)) * 0.6180339887498949) % 1.0 < share


def _cache_file(config: SyntheticDataConfig, split: str, cache_dir: Path) -> Path:
    """Cache name from the config, the split and the source of the generator and encoder
    (editing either invalidates the cache)."""
    import dualflow.motion.features as features_module
    import dualflow.synthetic as synthetic_module
    import dualflow.synthetic_varied as varied_module

    h = hashlib.sha1(json.dumps([config.synthetic_dict(), split], sort_keys=True).encode())
    for module in (synthetic_module, varied_module, features_module):
        h.update(Path(module.__file__).read_bytes())
    return cache_dir / f"synthetic_{split}_{h.hexdigest()[:16]}.npz"


def build_split(config: SyntheticDataConfig, split: str = "train", cache_dir: str | os.PathLike | None = None) -> SyntheticSplit:
    """Generate and encode the clips of one split (about 30 ms per 2 s clip on one core).

    cache_dir: when given, the split is read from / written to an npz there (no pickle:
    texts are stored as a unicode array), keyed by the config and the generator's source.
    """
    if cache_dir is not None:
        path = _cache_file(config, split, Path(cache_dir))
        if path.is_file():
            with np.load(path, allow_pickle=False) as z:
                return SyntheticSplit(z["features"], [str(t) for t in z["texts"]], z["beats"], z["rules"], z["seeds"])
        out = build_split(config, split)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".partial.npz")
        np.savez(tmp, features=out.features, texts=np.array(out.texts, dtype=np.str_), beats=out.beats,
                 rules=out.rules, seeds=out.seeds)
        os.replace(tmp, path)
        return out
    n = int(config.n_clips if split == "train" else config.val_clips)
    frames = int(config.frames)
    seconds = (frames + 1) / float(config.fps)
    feats = np.empty((n, frames, 2, 262), dtype=np.float32)
    beats = np.empty((n, frames, 4), dtype=np.float32)
    texts: list[str] = []
    rules = np.empty(n, dtype=np.int64)
    seeds = np.empty(n, dtype=np.int64)
    for i in range(n):
        rule_index = i % len(config.rules)
        seed = clip_seed(config, split, i)
        pair = make_duet(config.rules[rule_index], seconds=seconds, fps=float(config.fps), seed=seed,
                         varied=is_varied_clip(config, i))
        f, _ = encode_pair(pair)
        if f.shape[0] != frames:
            raise DualFlowError(f"synthetic clip {i}: expected {frames} feature rows, got {f.shape[0]} (fps/frames mismatch)")
        feats[i] = f
        beats[i] = pair.meta["beats"][:frames]
        texts.append(pair.text)
        rules[i] = rule_index
        seeds[i] = seed
    return SyntheticSplit(feats, texts, beats, rules, seeds)


class DuetDataset(torch.utils.data.Dataset):
    """Normalised two-person windows as float32 tensors (see the module docstring).

    features (N, T, 2, 262) raw; texts N sentences; beats (N, T, 4); rules (N,);
    stats: the training split's NormStats; text_dim: D_text of the model;
    text_embedder(texts, dim) -> (N, dim): default :func:`template_text_embedding`.

    Also kept: ``music`` (N, T, D) float32 tensor of the split's per-frame music features
    (``music_kind``) or None; ``groups`` (N,) int64: windows cut from the same clip share a
    group (retrieval never returns a window of the query's own clip); ``sources``: names.
    """

    def __init__(
        self,
        split: SyntheticSplit,
        stats: NormStats,
        text_dim: int,
        text_embedder: TextEmbedder = template_text_embedding,
    ):
        self.stats = stats
        x = torch.from_numpy(stats.normalize(split.features).astype(np.float32))
        self.actor = x[:, :, 0].contiguous()
        self.reactor = x[:, :, 1].contiguous()
        self.text = torch.from_numpy(np.asarray(text_embedder(split.texts, int(text_dim)), dtype=np.float32))
        self.beats = torch.from_numpy(split.beats)
        self.rule = torch.from_numpy(split.rules)
        self.texts = list(split.texts)
        music = getattr(split, "music", None)
        self.music = None if music is None else torch.from_numpy(np.ascontiguousarray(music, dtype=np.float32))
        self.music_kind = getattr(split, "music_kind", None) if music is not None else None
        sources = getattr(split, "sources", None)
        self.sources = list(sources) if sources is not None else [f"clip{i:06d}" for i in range(len(self.texts))]
        groups = getattr(split, "groups", None)
        self.groups = (np.arange(len(self.texts), dtype=np.int64) if groups is None
                       else np.asarray(groups, dtype=np.int64))
        if self.text.shape != (len(self.texts), int(text_dim)):
            raise DualFlowError(f"text embedder returned {tuple(self.text.shape)}, expected ({len(self.texts)}, {text_dim})")

    def __len__(self) -> int:
        return int(self.actor.shape[0])

    @property
    def n_frames(self) -> int:
        return int(self.actor.shape[1])

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        out = {"actor": self.actor[i], "reactor": self.reactor[i], "text": self.text[i],
               "beats": self.beats[i], "rule": self.rule[i]}
        if self.music is not None:
            out["music"] = self.music[i]
        return out

    def batch(self, indices: torch.Tensor) -> dict[str, torch.Tensor]:
        """Stacked samples for a (B,) index tensor (no DataLoader overhead); "index" is ``indices``."""
        out = {"actor": self.actor[indices], "reactor": self.reactor[indices], "text": self.text[indices],
               "beats": self.beats[indices], "rule": self.rule[indices], "index": indices}
        if self.music is not None:
            out["music"] = self.music[indices]
        if getattr(self, "_pin", False):  # a gathered batch is pageable again: pin it for a non-blocking copy
            out = {k: v.pin_memory() for k, v in out.items()}
        return out

    def place(self, device: torch.device, max_bytes: int = 4 << 30) -> None:
        """Keep the samples on ``device`` (a GPU) so that ``batch`` gathers there, without a host
        copy per step; a set larger than ``max_bytes`` stays on the host in pinned memory
        (its batches are then pinned too, for asynchronous copies)."""
        names = [n for n in ("actor", "reactor", "text", "beats", "rule", "music") if getattr(self, n) is not None]
        size = sum(getattr(self, n).numel() * getattr(self, n).element_size() for n in names)
        self._pin = size > max_bytes
        for n in names:
            t = getattr(self, n)
            setattr(self, n, t.pin_memory() if self._pin else t.to(device))

    def music_of(self, kind: str) -> torch.Tensor:
        """(N, T, D) per-frame music of ``kind`` ("beats4": the beat track), or a DualFlowError
        naming what the data has."""
        if kind == "beats4":
            return self.beats
        if self.music is None or self.music_kind != kind:
            have = self.music_kind or "only the beat track"
            raise DualFlowError(f"music {kind!r}: this training data has {have}; set music to what the data has "
                                "(beats, or the dataset's own feature kind)")
        return self.music


def make_datasets(
    config: SyntheticDataConfig,
    text_dim: int,
    text_embedder: TextEmbedder = template_text_embedding,
    cache_dir: str | os.PathLike | None = None,
    music_kind: str | None = None,
    stats: NormStats | None = None,
) -> tuple[DuetDataset, DuetDataset | None, NormStats]:
    """(train, val or None, NormStats fitted on the train split's raw features); cache_dir: see build_split.
    stats: normalise with these instead (fine-tuning keeps the checkpoint's statistics; synthetic data only).

    ``config.dataset`` other than "synthetic": the named dataset read from ``config.root``
    (:func:`dualflow.datasets.windows.make_training_sets`). music_kind "edge35" / "duolando54"
    on the synthetic duets: spectral features of a rendered click track (:func:`click_track_music`).
    """
    if not config.is_synthetic:
        from dualflow.datasets.windows import make_training_sets

        train_split, val_split = config.split_names()
        return make_training_sets(config.dataset, config.root, frames=int(config.frames), text_dim=text_dim,
                                  text_embedder=text_embedder, train_split=train_split, val_split=val_split,
                                  stride=config.stride, **config.options)
    if music_kind == "jukebox":
        raise DualFlowError("music 'jukebox': Jukebox features are precomputed 4800-d .npy files from the audio; "
                            "the synthetic duets have no audio to run Jukebox on (only beat times). Use a dataset "
                            "that ships them (e.g. data.dataset: mdd with data.options: {music: jukebox}) or, here, "
                            "music: beats / edge35 / duolando54")

    def split_of(name: str) -> SyntheticSplit:
        out = build_split(config, name, cache_dir)
        return with_click_music(out, music_kind, float(config.fps)) if music_kind in ("edge35", "duolando54") else out

    train = split_of("train")
    fitted = NormStats.from_features(train.features)
    stats = fitted if stats is None else widen_stats(stats, fitted)
    train_ds = DuetDataset(train, stats, text_dim, text_embedder)
    val_ds = None
    if int(config.val_clips) > 0:
        val_ds = DuetDataset(split_of("val"), stats, text_dim, text_embedder)
    return train_ds, val_ds, stats


def widen_stats(kept: NormStats, fitted: NormStats, factor: float = 3.0) -> NormStats:
    """``kept`` statistics, except in the columns where the new data spreads more than ``factor``
    times their std (a column the old data held constant, e.g. a shoulder rotation component the
    classic clips never use): there the new data's mean and std. Fine-tuning keeps every other
    column's scale, so the starting model sees the inputs it was trained on."""
    wide = np.asarray(fitted.std) > factor * np.asarray(kept.std)
    return NormStats(np.where(wide, fitted.mean, kept.mean), np.where(wide, fitted.std, kept.std))


def click_track_music(beats: np.ndarray, kind: str = "edge35", fps: float = 30.0) -> np.ndarray:
    """Spectral music features (T, D) of a click track rendered from a (T, 4) beat track.

    The synthetic duets have no audio, only beat times; to train and evaluate the *spectral*
    music path (EDGE 35-d / Duolando 54-d, :func:`dualflow.music.analyse_waveform`) on them,
    each beat impulse (column 0) becomes a 1 kHz click (librosa.clicks, 0.1 s), downbeats
    (column 3) a louder 1.5 kHz click, at sr = fps · 512, and the audio is analysed like a song.
    """
    import librosa

    from dualflow.music import analyse_waveform, analysis_rate

    b = np.asarray(beats, dtype=np.float64)
    if b.ndim != 2 or b.shape[1] != 4:
        raise DualFlowError(f"click_track_music: expected a (T, 4) beat track, got {b.shape}")
    sr = analysis_rate(fps)
    n = len(b)
    length = int(round(n / fps * sr))
    times = np.flatnonzero(b[:, 0] > 0.5) / float(fps)
    down = np.flatnonzero(b[:, 3] > 0.5) / float(fps)
    y = librosa.clicks(times=times, sr=sr, length=length, click_freq=1000.0) if len(times) else np.zeros(length)
    if len(down):
        y = y + librosa.clicks(times=down, sr=sr, length=length, click_freq=1500.0)
    y = y + 1e-4 * np.random.default_rng(n).standard_normal(length)  # a noise floor keeps chroma/MFCC finite
    import warnings

    with warnings.catch_warnings():  # librosa warns about its low CQT octaves on clips of a few seconds
        warnings.filterwarnings("ignore", message="n_fft=.*is too large", category=UserWarning)
        return analyse_waveform(y.astype(np.float32), sr, kind, fps, n_frames=n).features


def with_click_music(split: SyntheticSplit, kind: str, fps: float) -> SyntheticSplit:
    """The same split with ``music`` = :func:`click_track_music` of every clip's beat track."""
    music = np.stack([click_track_music(b, kind, fps) for b in split.beats]).astype(np.float32)
    return SyntheticSplit(split.features, split.texts, split.beats, split.rules, split.seeds, music, kind)


def positions_from_normalized(x: torch.Tensor | np.ndarray, stats: NormStats) -> np.ndarray:
    """Normalised features (..., T, 262) -> joint positions (..., T, 22, 3) in metres
    (the position block of the de-normalised feature, canonical Y-up frame)."""
    arr = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    raw = stats.denormalize(arr.astype(np.float64))
    pos = raw[..., FEATURE_SLICES["positions"]]
    return pos.reshape(pos.shape[:-1] + (22, 3))
