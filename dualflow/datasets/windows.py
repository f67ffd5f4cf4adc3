"""Fixed-length training windows from any :class:`DuetSet` (the trainer's data layout).

The trainer (:mod:`dualflow.train`) reads :class:`dualflow.data.SyntheticSplit`
arrays: features (N, T, 2, 262), texts, beats (N, T, 4) and an int label per
window. :func:`window_split` cuts every clip of a DuetSet into windows of
``frames + 1`` motion frames (so ``frames`` feature rows, InterGen drops the
last) every ``stride`` frames, encodes each window on its own (canonical frame
of the window's first actor frame, as InterGen crops then canonicalises), and
fills the other arrays:

* beats: the sample's (T, 4) beat track when ``music_kind == "beats4"``; else,
  from the beat one-hot column of Duolando's 54-d (column 53) or EDGE's 35-d
  (column 34) features, :func:`beat_track`; zeros when the clip has no beats.
* label: the index of the sample's style, else its genre, in the sorted set of
  labels over the DuetSet (0 for all when neither exists), for the triplet loss.
* music: the window's rows of the sample's per-frame music features when every
  clip of the split carries the same kind (``music_kind``), else None.
* groups: the index of the source clip of each window (retrieval at training
  time excludes every window of the query's own clip).

:func:`make_training_sets` loads a dataset by name, windows the train and
validation splits and returns what :func:`dualflow.data.make_datasets` returns,
so the trainer can take any loader by name (``data: {dataset: dd100, root: ...}``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualflow.datasets import load_dataset
from dualflow.datasets.collection import DuetSet
from dualflow.errors import DualFlowError

#: music kind -> column of the beat one-hot
BEAT_COLUMNS = {"duolando54": 53, "edge35": 34}


def beat_track(impulses: np.ndarray) -> np.ndarray:
    """(T,) beat one-hot -> (T, 4) [impulse, sin 2πφ, cos 2πφ, downbeat] like :mod:`dualflow.synthetic`.

    φ ∈ [0, 1) is the fraction of the current inter-beat interval elapsed (linear
    between consecutive beats, extrapolated with the nearest interval before the
    first and after the last beat); every 4th beat, from the first, is a downbeat.
    """
    imp = np.asarray(impulses, dtype=np.float64).reshape(-1) > 0.5
    n = len(imp)
    out = np.zeros((n, 4), dtype=np.float32)
    beats = np.flatnonzero(imp)
    out[beats, 0] = 1.0
    out[beats[::4], 3] = 1.0
    if len(beats) < 2:
        out[:, 2] = 1.0
        return out
    t = np.arange(n, dtype=np.float64)
    k = np.clip(np.searchsorted(beats, t, side="right") - 1, 0, len(beats) - 2)
    phase = np.mod((t - beats[k]) / (beats[k + 1] - beats[k]), 1.0)
    out[:, 1] = np.sin(2 * np.pi * phase)
    out[:, 2] = np.cos(2 * np.pi * phase)
    return out


@dataclass
class WindowSplit:
    """Arrays of :class:`dualflow.data.SyntheticSplit` plus where each window came from."""

    features: np.ndarray
    texts: list[str]
    beats: np.ndarray
    rules: np.ndarray
    seeds: np.ndarray
    sources: list[str]
    labels: tuple[str, ...]
    music: np.ndarray | None = None
    music_kind: str | None = None
    groups: np.ndarray | None = None


def _sample_beats(sample, n: int) -> np.ndarray:
    rows = sample.music_rows(n)
    if rows is None:
        return np.zeros((n, 4), dtype=np.float32)
    if sample.music_kind == "beats4":
        return rows.astype(np.float32)
    col = BEAT_COLUMNS.get(sample.music_kind)
    if col is None:
        return np.zeros((n, 4), dtype=np.float32)
    return beat_track(rows[:, col])


def window_split(dset: DuetSet, frames: int, stride: int | None = None, labels: tuple[str, ...] | None = None) -> WindowSplit:
    """Cut ``dset`` into windows of ``frames`` feature rows (module docstring)."""
    frames = int(frames)
    stride = int(stride or frames)
    if frames < 1 or stride < 1:
        raise DualFlowError(f"windows: frames and stride must be >= 1, got {frames}, {stride}")
    if labels is None:
        labels = tuple(sorted({s.style or s.genre for s in dset if (s.style or s.genre)}))
    kinds = {s.music_kind for s in dset}
    music_kind = kinds.pop() if len(kinds) == 1 else None
    feats, texts, beats, rules, sources, music, groups = [], [], [], [], [], [], []
    for clip, sample in enumerate(dset):
        if sample.n_frames < frames + 1:
            continue
        rows = sample.music_rows(sample.n_frames) if music_kind is not None else None
        for start in range(0, sample.n_frames - frames, stride):
            w = sample.window(start, frames + 1)
            feats.append(w.features())
            texts.append(w.text)
            beats.append(_sample_beats(sample, sample.n_frames)[start:start + frames])
            if rows is not None:
                music.append(rows[start:start + frames])
            label = sample.style or sample.genre
            rules.append(labels.index(label) if label in labels else 0)
            sources.append(w.name)
            groups.append(clip)
    if not feats:
        raise DualFlowError(f"{dset.name}/{dset.split}: no clip has the {frames + 1} frames a window needs; "
                            "lower data.frames")
    return WindowSplit(np.stack(feats).astype(np.float32), texts, np.stack(beats).astype(np.float32),
                       np.asarray(rules, dtype=np.int64), np.arange(len(feats), dtype=np.int64), sources, labels,
                       np.stack(music).astype(np.float32) if music else None, music_kind if music else None,
                       np.asarray(groups, dtype=np.int64))


def make_training_sets(name: str, root=None, *, frames: int = 60, text_dim: int, text_embedder=None,
                       train_split: str = "train", val_split: str | None = "val", stride: int | None = None,
                       **options):
    """(train DuetDataset, val DuetDataset | None, NormStats) from dataset ``name`` (module docstring).

    The NormStats are fitted on the training windows; ``options`` go to the loader.
    """
    from dualflow.data import DuetDataset, template_text_embedding
    from dualflow.motion.normalization import NormStats

    embed = text_embedder or template_text_embedding
    train_set = load_dataset(name, root, train_split, **options)
    if len(train_set) == 0:
        raise DualFlowError(f"dataset {name!r} at {root}: split {train_split!r} has no usable clips "
                            f"({len(train_set.skipped)} skipped, e.g. {dict(list(train_set.skipped.items())[:2])}); "
                            "check data.root and data.splits")
    train = window_split(train_set, frames, stride)
    stats = NormStats.from_features(train.features)
    train_ds = DuetDataset(train, stats, text_dim, embed)
    val_ds = None
    if val_split:
        val = window_split(load_dataset(name, root, val_split, **options), frames, stride, train.labels)
        val_ds = DuetDataset(val, stats, text_dim, embed)
    return train_ds, val_ds, stats
