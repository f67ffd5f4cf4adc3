"""The SYNTHETIC duet dataset (:mod:`dualflow.synthetic`) as :class:`DuetSample` objects.

Nothing here is captured motion. Clip ``i`` of a split is
``make_duet(rules[i % len(rules)], seconds=(frames + 1) / fps, fps, seed)`` with the
seeds of :func:`dualflow.data.clip_seed` for "train" and "val" (so these samples are
the clips the trainer sees) and ``seed·10⁶ + 750000 + i`` for "test". Each sample
carries the template sentence, the (T, 4) beat track as ``music`` ("beats4"), the
follower rule as ``style`` and the rule index in ``meta["rule"]``.
"""

from __future__ import annotations

from dualflow.datasets.collection import DuetSet
from dualflow.datasets.sample import DuetSample
from dualflow.errors import DualFlowError
from dualflow.synthetic import RULES, make_duet

SPLIT_OFFSETS = {"train": 0, "val": 500_000, "test": 750_000}


def load_synthetic(root=None, split: str = "train", *, n_clips: int = 64, frames: int = 60, fps: float = 30.0,
                   rules: tuple[str, ...] = RULES, seed: int = 0, limit: int | None = None) -> DuetSet:
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
        clip_seed = int(seed) * 1_000_000 + SPLIT_OFFSETS[split] + i
        pair = make_duet(rule, seconds=(int(frames) + 1) / float(fps), fps=float(fps), seed=clip_seed)
        samples.append(DuetSample(source="synthetic", name=f"{split}_{i:05d}", motion=pair, texts=(pair.text,),
                                  music=pair.meta["beats"], music_kind="beats4", style=rule,
                                  roles=("leader", "follower"),
                                  meta={"rule": RULES.index(rule), "seed": clip_seed, "bpm": pair.meta["bpm"],
                                        "beat_frames": pair.meta["beat_frames"]}))
    return DuetSet("synthetic", split, None, samples, {})
