"""The SYNTHETIC duets (:mod:`dualflow.synthetic`): the trainer's arrays and a DuetSet loader.

Nothing here is captured motion. Clip ``i`` of a split is
``make_duet(rules[i % len(rules)], seconds=(frames + 1) / fps, fps, seed)`` with the split's
seed ``seed·10⁶ + offset + i`` (offsets: train 0, val 500000, test 750000, so splits never
share a clip); with ``data.crop`` a share of the training clips is instead a window cut at a
random offset from a longer clip (:func:`crop_draw`, :func:`cropped_duet`), so the model also
sees windows that start mid-dance, as a live stream's do. :func:`build_split` gives the
trainer's raw arrays (:class:`SyntheticSplit`, optionally cached as npz); :func:`load_synthetic`
gives the whole clips as :class:`DuetSample` objects (template sentence, (T, 4) beat track as
"beats4" music, rule as ``style``).
numpy only (librosa is imported only for :func:`click_track_music`).
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dualflow.datasets.collection import DuetSet
from dualflow.datasets.sample import DuetSample
from dualflow.errors import DualFlowError
from dualflow.motion.features import encode_pair
from dualflow.synthetic import RULES, make_duet

if TYPE_CHECKING:  # the config imports this package's loader registry, which imports this module
    from dualflow.datasets.config import TrainingDataConfig

SPLIT_OFFSETS = {"train": 0, "val": 500_000, "test": 750_000}


@dataclass
class SyntheticSplit:
    """Raw (un-normalised) features of one split, the layout the trainer reads.

    features (N, T, 2, 262) float32; texts: N sentences; beats (N, T, 4) float32
    [beat impulse, sin 2π·phase, cos 2π·phase, downbeat impulse]; rules (N,) int64 index into
    the config's rules; seeds (N,) int64; music (N, T, D) float32 per-frame music features of
    kind ``music_kind`` (dualflow.music) or None; offsets (N,) int64: first frame of each clip
    in its longer source clip (0: a whole clip from the start of the dance; empty when unknown).
    """

    features: np.ndarray
    texts: list[str]
    beats: np.ndarray
    rules: np.ndarray
    seeds: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    music: np.ndarray | None = None
    music_kind: str | None = None
    offsets: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


@dataclass(frozen=True)
class CropDraw:
    """How one training clip is cut: ``offset`` frames into a longer clip played ``speed``
    times as fast (1 = as generated), reflected left-right when ``mirrored``."""

    offset: int
    speed: float = 1.0
    mirrored: bool = False


def crop_draw(config: TrainingDataConfig, split: str, seed: int, any_split: bool = False) -> CropDraw | None:
    """The crop of the clip with ``seed`` (None: a whole clip from the start of the dance).

    Only training clips are cropped (any_split: validation clips too, for a held-out figure
    on windows that start mid-dance), a share ``config.crop`` of them; offset uniform in
    [1, crop_max_s·fps] frames, speed uniform in 1 ± crop_speed, mirrored with probability
    crop_mirror; all drawn from the clip's seed, so a split is reproducible."""
    share = float(getattr(config, "crop", 0.0))
    if (split != "train" and not any_split) or share <= 0.0:
        return None
    rng = np.random.default_rng([int(seed), 28])
    if rng.uniform() >= share:
        return None
    offset = int(rng.integers(1, max(1, int(round(float(config.crop_max_s) * float(config.fps)))) + 1))
    spread = float(config.crop_speed)
    speed = float(rng.uniform(1.0 - spread, 1.0 + spread)) if spread > 0 else 1.0
    return CropDraw(offset, speed, bool(rng.uniform() < float(config.crop_mirror)))


def _swap_sides(text: str) -> str:
    return " ".join({"left": "right", "right": "left"}.get(w, w) for w in text.split(" "))


def cropped_duet(rule: str, n_frames: int, fps: float, seed: int, draw: CropDraw, varied: bool = False):
    """Motion frames [offset, offset + n_frames) of ``make_duet(rule, ..., seed)`` generated
    long enough and at fps / speed (so it plays ``speed`` times as fast at ``fps``), both
    persons cut at the same frames; mirrored: both reflected in the vertical plane y = 0
    (left and right joints, contacts and the text's sides swapped). meta["beats"] is cut with
    them; meta gains "crop_offset", "speed" and "crop_mirrored"."""
    from dualflow.motion.container import TwoPersonMotion
    from dualflow.synthetic import _CONTACT_MIRROR, _reflect

    gen_fps = float(fps) / draw.speed
    total = draw.offset + int(n_frames)
    pair = make_duet(rule, seconds=total / gen_fps, fps=gen_fps, seed=seed, varied=varied)
    if len(pair.actor.positions) != total:
        raise DualFlowError(f"cropped synthetic clip: expected {total} frames, got {len(pair.actor.positions)}")
    cut = slice(draw.offset, total)
    people = []
    for person in (pair.actor, pair.reactor):
        pos, contacts = person.positions[cut], None if person.contacts is None else person.contacts[cut]
        if draw.mirrored:
            n = len(pos)
            pos = _reflect(pos, np.zeros((n, 2)), np.broadcast_to(np.array([0.0, 1.0]), (n, 2)))
            contacts = None if contacts is None else contacts[:, _CONTACT_MIRROR]
        people.append(person.replace(positions=pos, contacts=contacts, fps=float(fps)))
    meta = dict(pair.meta)
    meta.update(beats=pair.meta["beats"][cut], crop_offset=draw.offset, speed=draw.speed, crop_mirrored=draw.mirrored)
    meta["beat_frames"] = np.flatnonzero(meta["beats"][:, 0] > 0.5)
    text = _swap_sides(pair.text) if draw.mirrored else pair.text
    return TwoPersonMotion(people[0], people[1], text, meta)


def clip_seed(config: TrainingDataConfig, split: str, index: int) -> int:
    """Seed of clip ``index`` of ``split`` ('train' or 'val'); the splits never share a seed."""
    if split not in ("train", "val"):
        raise DualFlowError(f"split must be 'train' or 'val', got {split!r}")
    return int(config.seed) * 1_000_000 + SPLIT_OFFSETS[split] + int(index)


def is_varied_clip(config: TrainingDataConfig, index: int) -> bool:
    """Whether clip ``index`` comes from the varied repertoire: a share ``config.varied`` of the
    clips, spread evenly over the rule cycle (clips of one cycle agree)."""
    share = float(getattr(config, "varied", 0.0))
    return share > 0 and ((index // len(config.rules)) * 0.6180339887498949) % 1.0 < share


def _cache_file(config: TrainingDataConfig, split: str, cache_dir: Path) -> Path:
    """Cache name from the config, the split and the source of the generator and encoder
    (editing either invalidates the cache)."""
    import dualflow.motion.features as features_module
    import dualflow.synthetic as synthetic_module
    import dualflow.synthetic_varied as varied_module

    h = hashlib.sha1(json.dumps([config.synthetic_dict(), split], sort_keys=True).encode())
    for module in (synthetic_module, varied_module, features_module):
        h.update(Path(module.__file__).read_bytes())
    return cache_dir / f"synthetic_{split}_{h.hexdigest()[:16]}.npz"


def _cached_split(config: TrainingDataConfig, split: str, cache_dir: Path, workers: int = 0) -> SyntheticSplit:
    path = _cache_file(config, split, cache_dir)
    if path.is_file():
        with np.load(path, allow_pickle=False) as z:
            offsets = z["offsets"] if "offsets" in z.files else np.zeros(0, dtype=np.int64)
            return SyntheticSplit(
                z["features"], [str(t) for t in z["texts"]], z["beats"], z["rules"], z["seeds"], offsets=offsets
            )
    out = build_split(config, split, workers=workers)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial.npz")
    np.savez(
        tmp,
        features=out.features,
        texts=np.array(out.texts, dtype=np.str_),
        beats=out.beats,
        rules=out.rules,
        seeds=out.seeds,
        offsets=out.offsets,
    )
    os.replace(tmp, path)
    return out


_CHUNK = 256  # clips per task of a parallel build (build_split's workers)


def build_split(
    config: TrainingDataConfig,
    split: str = "train",
    cache_dir: str | os.PathLike | None = None,
    crop_any_split: bool = False,
    workers: int = 0,
) -> SyntheticSplit:
    """Generate and encode the clips of one split (about 5 ms per 2 s clip on one core).

    Features come from :func:`dualflow.motion.features.encode_pair` (actor's canonical Y-up
    frame; InterGen drops the last motion frame, hence ``frames + 1`` generated frames).
    cache_dir: when given, the split is read from / written to an npz there (no pickle:
    texts are stored as a unicode array), keyed by the config and the generator's source.
    crop_any_split: crop validation clips too (:func:`crop_draw`; not cached).
    workers: generate in this many processes (0 or 1: in this one). Every clip depends only on
    its own seed, so the split is the same whatever the number.
    """
    if cache_dir is not None and not crop_any_split:
        return _cached_split(config, split, Path(cache_dir), workers)
    n = int(config.n_clips if split == "train" else config.val_clips)
    chunks = [range(a, min(n, a + _CHUNK)) for a in range(0, n, _CHUNK)] or [range(0)]
    if int(workers) > 1 and len(chunks) > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        # spawn: the trainer may already hold a CUDA context or torch threads, which fork does not survive
        with ProcessPoolExecutor(int(workers), mp_context=multiprocessing.get_context("spawn")) as pool:
            parts = list(pool.map(_build_clips, *zip(*[(config, split, c, crop_any_split) for c in chunks])))
    else:
        parts = [_build_clips(config, split, c, crop_any_split) for c in chunks]
    return SyntheticSplit(
        np.concatenate([q.features for q in parts]),
        [t for q in parts for t in q.texts],
        np.concatenate([q.beats for q in parts]),
        np.concatenate([q.rules for q in parts]),
        np.concatenate([q.seeds for q in parts]),
        offsets=np.concatenate([q.offsets for q in parts]),
    )


def _build_clips(config: TrainingDataConfig, split: str, indices: range, crop_any_split: bool) -> SyntheticSplit:
    """Clips ``indices`` of one split (:func:`build_split`)."""
    n, frames = len(indices), int(config.frames)
    seconds = (frames + 1) / float(config.fps)
    feats = np.empty((n, frames, 2, 262), dtype=np.float32)
    beats = np.empty((n, frames, 4), dtype=np.float32)
    texts: list[str] = []
    rules = np.empty(n, dtype=np.int64)
    seeds = np.empty(n, dtype=np.int64)
    offsets = np.zeros(n, dtype=np.int64)
    for k, i in enumerate(indices):
        rule_index = i % len(config.rules)
        seed = clip_seed(config, split, i)
        draw = crop_draw(config, split, seed, crop_any_split)
        if draw is not None:
            pair = cropped_duet(
                config.rules[rule_index], frames + 1, float(config.fps), seed, draw, varied=is_varied_clip(config, i)
            )
            offsets[k] = draw.offset
        else:
            pair = make_duet(
                config.rules[rule_index],
                seconds=seconds,
                fps=float(config.fps),
                seed=seed,
                varied=is_varied_clip(config, i),
            )
        f, _ = encode_pair(pair)
        if f.shape[0] != frames:
            raise DualFlowError(
                f"synthetic clip {i}: expected {frames} feature rows, got {f.shape[0]} (fps/frames mismatch)"
            )
        feats[k] = f
        beats[k] = pair.meta["beats"][:frames]
        texts.append(pair.text)
        rules[k] = rule_index
        seeds[k] = seed
    return SyntheticSplit(feats, texts, beats, rules, seeds, offsets=offsets)


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
    with warnings.catch_warnings():  # librosa warns about its low CQT octaves on clips of a few seconds
        warnings.filterwarnings("ignore", message="n_fft=.*is too large", category=UserWarning)
        return analyse_waveform(y.astype(np.float32), sr, kind, fps, n_frames=n).features


def with_click_music(split: SyntheticSplit, kind: str, fps: float) -> SyntheticSplit:
    """The same split with ``music`` = :func:`click_track_music` of every clip's beat track."""
    music = np.stack([click_track_music(b, kind, fps) for b in split.beats]).astype(np.float32)
    s = split
    return SyntheticSplit(s.features, s.texts, s.beats, s.rules, s.seeds, music, kind, s.offsets)


def load_synthetic(
    root=None,
    split: str = "train",
    *,
    n_clips: int = 64,
    frames: int = 60,
    fps: float = 30.0,
    rules: tuple[str, ...] = RULES,
    seed: int = 0,
    limit: int | None = None,
) -> DuetSet:
    """``n_clips`` synthetic duets of ``frames + 1`` motion frames (``frames`` feature rows)."""
    if root is not None:
        raise DualFlowError("synthetic dataset: it is generated, not read; pass no root folder")
    if split not in SPLIT_OFFSETS:
        raise DualFlowError(f"synthetic dataset: split must be one of {sorted(SPLIT_OFFSETS)}, got {split!r}")
    rules = tuple(rules)
    bad = [r for r in rules if r not in RULES]
    if bad or not rules:
        raise DualFlowError(f"synthetic dataset: unknown or empty rules {bad or '[]'}; choose from {', '.join(RULES)}")
    if int(n_clips) < 1 or int(frames) < 2:
        raise DualFlowError(f"synthetic dataset: n_clips must be >= 1 and frames >= 2, got {n_clips}, {frames}")
    n = int(n_clips) if limit is None else min(int(n_clips), int(limit))
    samples = []
    for i in range(n):
        rule = rules[i % len(rules)]
        seed_i = int(seed) * 1_000_000 + SPLIT_OFFSETS[split] + i
        pair = make_duet(rule, seconds=(int(frames) + 1) / float(fps), fps=float(fps), seed=seed_i)
        samples.append(
            DuetSample(
                source="synthetic",
                name=f"{split}_{i:05d}",
                motion=pair,
                texts=(pair.text,),
                music=pair.meta["beats"],
                music_kind="beats4",
                style=rule,
                roles=("leader", "follower"),
                meta={
                    "rule": RULES.index(rule),
                    "seed": seed_i,
                    "bpm": pair.meta["bpm"],
                    "beat_frames": pair.meta["beat_frames"],
                },
            )
        )
    return DuetSet("synthetic", split, None, samples, {})
