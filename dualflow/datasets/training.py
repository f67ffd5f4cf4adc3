"""The trainer's data: normalised two-person windows as float32 torch tensors.

:func:`make_datasets` turns a :class:`TrainingDataConfig` into (train, val or None,
NormStats fitted on the training windows); :class:`DuetDataset` holds one split. One
sample (and one batch, stacked) is a dict of float32 tensors::

    actor    (T, 262)   normalised features of person A (the leader), x = (f − mean) / std
    reactor  (T, 262)   normalised features of person B (the follower)
    text     (D_text,)  sentence embedding (the run's TextEmbedder)
    beats    (T, 4)     [beat impulse, sin 2π·phase, cos 2π·phase, downbeat impulse]
    rule     ()         int64 label (synthetic: index into data.rules; datasets: style/genre)
    music    (T, D)     per-frame music features, only when the split has them
"""

from __future__ import annotations

import os

import numpy as np
import torch

from dualflow.datasets import load_dataset
from dualflow.datasets.config import TrainingDataConfig
from dualflow.datasets.synthetic import SyntheticSplit, build_split, with_click_music
from dualflow.datasets.windows import WindowSplit, window_split
from dualflow.errors import DualFlowError
from dualflow.motion.features import FEATURE_SLICES
from dualflow.motion.normalization import NormStats
from dualflow.text import TextEmbedder, template_text_embedding


class DuetDataset(torch.utils.data.Dataset):
    """Normalised two-person windows as float32 tensors (see the module docstring).

    split: a SyntheticSplit or WindowSplit (raw features (N, T, 2, 262), texts, beats (N, T, 4),
    rules (N,)); stats: the training split's NormStats; text_dim: D_text of the model;
    text_embedder(texts, dim) -> (N, dim): default :func:`dualflow.text.template_text_embedding`.

    Also kept: ``music`` (N, T, D) float32 tensor of the split's per-frame music features
    (``music_kind``) or None; ``groups`` (N,) int64: windows cut from the same clip share a
    group (retrieval never returns a window of the query's own clip); ``sources``: names.
    """

    def __init__(
        self,
        split: SyntheticSplit | WindowSplit,
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
        self.groups = (
            np.arange(len(self.texts), dtype=np.int64) if groups is None else np.asarray(groups, dtype=np.int64)
        )
        if self.text.shape != (len(self.texts), int(text_dim)):
            raise DualFlowError(
                f"text embedder returned {tuple(self.text.shape)}, expected ({len(self.texts)}, {text_dim})"
            )

    def __len__(self) -> int:
        return int(self.actor.shape[0])

    @property
    def n_frames(self) -> int:
        return int(self.actor.shape[1])

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        out = {
            "actor": self.actor[i],
            "reactor": self.reactor[i],
            "text": self.text[i],
            "beats": self.beats[i],
            "rule": self.rule[i],
        }
        if self.music is not None:
            out["music"] = self.music[i]
        return out

    def batch(self, indices: torch.Tensor) -> dict[str, torch.Tensor]:
        """Stacked samples for a (B,) index tensor (no DataLoader overhead); "index" is ``indices``."""
        out = {
            "actor": self.actor[indices],
            "reactor": self.reactor[indices],
            "text": self.text[indices],
            "beats": self.beats[indices],
            "rule": self.rule[indices],
            "index": indices,
        }
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
            raise DualFlowError(
                f"music {kind!r}: this training data has {have}; set music to what the data has "
                "(beats, or the dataset's own feature kind)"
            )
        return self.music


def make_datasets(
    config: TrainingDataConfig,
    text_dim: int,
    text_embedder: TextEmbedder = template_text_embedding,
    cache_dir: str | os.PathLike | None = None,
    music_kind: str | None = None,
    stats: NormStats | None = None,
    workers: int = 0,
) -> tuple[DuetDataset, DuetDataset | None, NormStats]:
    """(train, val or None, NormStats fitted on the train split's raw features); cache_dir: see
    :func:`dualflow.datasets.synthetic.build_split`. stats: normalise with these instead
    (fine-tuning keeps the checkpoint's statistics; synthetic data only, :func:`widen_stats`).
    workers: processes that generate the synthetic clips (:func:`dualflow.datasets.synthetic.build_split`).

    ``config.dataset`` other than "synthetic": the named dataset read from ``config.root``
    (:func:`make_training_sets`). music_kind "edge35" / "duolando54" on the synthetic duets:
    spectral features of a rendered click track (:func:`dualflow.datasets.synthetic.click_track_music`).
    """
    if not config.is_synthetic:
        return make_training_sets(config, text_dim, text_embedder)
    if music_kind == "jukebox":
        raise DualFlowError(
            "music 'jukebox': Jukebox features are precomputed 4800-d .npy files from the audio; "
            "the synthetic duets have no audio to run Jukebox on (only beat times). Use a dataset "
            "that ships them (e.g. data.dataset: mdd with data.options: {music: jukebox}) or, here, "
            "music: beats / edge35 / duolando54"
        )

    def split_of(name: str) -> SyntheticSplit:
        out = build_split(config, name, cache_dir, workers=workers)
        return with_click_music(out, music_kind, float(config.fps)) if music_kind in ("edge35", "duolando54") else out

    train = split_of("train")
    fitted = NormStats.from_features(train.features)
    stats = fitted if stats is None else widen_stats(stats, fitted)
    train_ds = DuetDataset(train, stats, text_dim, text_embedder)
    val_ds = None
    if int(config.val_clips) > 0:
        val_ds = DuetDataset(split_of("val"), stats, text_dim, text_embedder)
    return train_ds, val_ds, stats


def make_training_sets(
    config: TrainingDataConfig,
    text_dim: int,
    text_embedder: TextEmbedder | None = None,
) -> tuple[DuetDataset, DuetDataset | None, NormStats]:
    """(train, val or None, NormStats) from the dataset ``config.dataset`` read from ``config.root``:
    its train and validation splits (``config.split_names()``) cut into windows of ``config.frames``
    rows every ``config.stride`` frames (:func:`dualflow.datasets.windows.window_split`).

    The NormStats are fitted on the training windows; ``config.options`` go to the loader.
    """
    embed = text_embedder or template_text_embedding
    name, root, frames = config.dataset, config.root, int(config.frames)
    train_split, val_split = config.split_names()
    train_set = load_dataset(name, root, train_split, **config.options)
    if len(train_set) == 0:
        raise DualFlowError(
            f"dataset {name!r} at {root}: split {train_split!r} has no usable clips "
            f"({len(train_set.skipped)} skipped, e.g. {dict(list(train_set.skipped.items())[:2])}); "
            "check data.root and data.splits"
        )
    train = window_split(train_set, frames, config.stride)
    stats = NormStats.from_features(train.features)
    train_ds = DuetDataset(train, stats, text_dim, embed)
    val_ds = None
    if val_split:
        val = window_split(load_dataset(name, root, val_split, **config.options), frames, config.stride, train.labels)
        val_ds = DuetDataset(val, stats, text_dim, embed)
    return train_ds, val_ds, stats


def widen_stats(kept: NormStats, fitted: NormStats, factor: float = 3.0) -> NormStats:
    """``kept`` statistics, except in the columns where the new data spreads more than ``factor``
    times their std (a column the old data held constant, e.g. a shoulder rotation component the
    classic clips never use): there the new data's mean and std. Fine-tuning keeps every other
    column's scale, so the starting model sees the inputs it was trained on."""
    wide = np.asarray(fitted.std) > factor * np.asarray(kept.std)
    return NormStats(np.where(wide, fitted.mean, kept.mean), np.where(wide, fitted.std, kept.std))


def positions_from_normalized(x: torch.Tensor | np.ndarray, stats: NormStats) -> np.ndarray:
    """Normalised features (..., T, 262) -> joint positions (..., T, 22, 3) in metres
    (the position block of the de-normalised feature, canonical Y-up frame)."""
    arr = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    raw = stats.denormalize(arr.astype(np.float64))
    pos = raw[..., FEATURE_SLICES["positions"]]
    return pos.reshape(pos.shape[:-1] + (22, 3))
