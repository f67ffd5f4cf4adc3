"""Fixed-length training windows cut from any :class:`DuetSet` (numpy only).

:func:`window_split` cuts every clip into windows of ``frames + 1`` motion frames (``frames``
feature rows; InterGen drops the last) every ``stride`` frames, each encoded in its own
canonical frame, and returns a :class:`WindowSplit`: the arrays of
:class:`dualflow.datasets.synthetic.SyntheticSplit` plus each window's source clip. The torch
side is :mod:`dualflow.datasets.training`. How beats, labels and music are filled: docs/model.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
    """Arrays of :class:`dualflow.datasets.synthetic.SyntheticSplit` plus where each window came from.

    features (N, T, 2, 262) float32; texts N; beats (N, T, 4) (the sample's beat track, or one
    derived from the beat column of its music features, :func:`beat_track`, else zeros); rules
    (N,) int64 index of the sample's style, else genre, in ``labels``; seeds (N,) window index;
    sources: window names; music (N, T, D) when every clip has the same kind, else None;
    groups (N,) int64 index of the source clip (retrieval excludes the query's own clip).
    """

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


def window_split(
    dset: DuetSet, frames: int, stride: int | None = None, labels: tuple[str, ...] | None = None
) -> WindowSplit:
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
            beats.append(_sample_beats(sample, sample.n_frames)[start : start + frames])
            if rows is not None:
                music.append(rows[start : start + frames])
            label = sample.style or sample.genre
            rules.append(labels.index(label) if label in labels else 0)
            sources.append(w.name)
            groups.append(clip)
    if not feats:
        raise DualFlowError(
            f"{dset.name}/{dset.split}: no clip has the {frames + 1} frames a window needs; lower data.frames"
        )
    return WindowSplit(
        np.stack(feats).astype(np.float32),
        texts,
        np.stack(beats).astype(np.float32),
        np.asarray(rules, dtype=np.int64),
        np.arange(len(feats), dtype=np.int64),
        sources,
        labels,
        np.stack(music).astype(np.float32) if music else None,
        music_kind if music else None,
        np.asarray(groups, dtype=np.int64),
    )
