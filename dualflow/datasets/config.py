"""The ``data`` section of a training config: which duets to train on and how to cut them.

:class:`TrainingDataConfig` names either the built-in synthetic duets (generated, no folder)
or a loader of :data:`dualflow.datasets.LOADERS` with its folder, splits and options. It
validates on construction and raises :class:`DualFlowError` naming the ``data.<field>``
at fault and the fix. numpy only (no torch).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from dualflow.datasets import LOADERS
from dualflow.errors import DualFlowError
from dualflow.synthetic import RULES

#: data.dataset value of the built-in synthetic duets (the default); any other name is a
#: :data:`dualflow.datasets.LOADERS` entry read from ``data.root``.
SYNTHETIC = "synthetic"
#: The fields that describe the synthetic clips (the data cache key uses only these).
SYNTHETIC_FIELDS = ("n_clips", "val_clips", "frames", "fps", "rules", "seed", "varied")
SYNTHETIC_FIELDS += ("crop", "crop_max_s", "crop_speed", "crop_mirror")


@dataclass(frozen=True)
class TrainingDataConfig:
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

    Crops (training split only; validation clips always start at the start of a dance, so
    held-out figures stay comparable): crop: share of training clips (0-1) cut at a random
    offset from a longer clip instead of starting at its first frame (the leader mid-dance,
    away from its start, the follower mid-response); crop_max_s: latest offset, seconds;
    crop_speed: the longer clip plays 1 ± up to this much faster (0 = real speed; beats scale
    with it); crop_mirror: share of cropped clips reflected left-right (both persons, text
    sides swapped). :func:`dualflow.datasets.synthetic.crop_draw` draws them.
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
    crop: float = 0.0
    crop_max_s: float = 6.0
    crop_speed: float = 0.0
    crop_mirror: float = 0.0

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
        for name in ("crop", "crop_mirror"):
            if not 0.0 <= float(getattr(self, name)) <= 1.0:
                raise DualFlowError(f"data.{name} is a share of clips, 0 to 1; got {getattr(self, name)!r}")
        if not float(self.crop_max_s) * float(self.fps) >= 1.0:
            raise DualFlowError(f"data.crop_max_s must be at least one frame (seconds > 0), got {self.crop_max_s!r}")
        if not 0.0 <= float(self.crop_speed) < 0.5:
            raise DualFlowError(f"data.crop_speed is a relative speed change in [0, 0.5), got {self.crop_speed!r}")
        self._check_dataset()

    def _check_dataset(self) -> None:
        if self.dataset not in LOADERS:
            raise DualFlowError(f"data.dataset: unknown dataset {self.dataset!r}; choose one of {', '.join(LOADERS)}")
        if self.splits is not None:
            splits = (self.splits,) if isinstance(self.splits, str) else tuple(self.splits)
            if not 1 <= len(splits) <= 2 or not all(isinstance(x, str) and x for x in splits):
                raise DualFlowError(
                    f"data.splits must be [train] or [train, validation] split names, got {self.splits!r}"
                )
            object.__setattr__(self, "splits", splits)
        if self.stride is not None and int(self.stride) < 1:
            raise DualFlowError(f"data.stride must be >= 1 frames (or null = data.frames), got {self.stride!r}")
        if self.dataset == SYNTHETIC:
            if self.root is not None or self.splits is not None or self.options:
                raise DualFlowError(
                    "data.dataset 'synthetic' is generated (n_clips, val_clips, rules, seed); "
                    "data.root, data.splits and data.options are for a real dataset"
                )
            return
        if self.root is None or not str(self.root).strip():
            raise DualFlowError(
                f"data.root: dataset {self.dataset!r} needs its folder; set data.root: /path/to/{self.dataset}"
            )
        if not Path(self.root).expanduser().is_dir():
            raise DualFlowError(
                f"data.root: {self.root} is not a folder (dataset {self.dataset!r}); "
                "point data.root at the dataset's top folder"
            )

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
    def from_dict(d: dict, where: str = "data") -> TrainingDataConfig:
        known = {f.name for f in fields(TrainingDataConfig)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise DualFlowError(f"{where}: unknown field(s) {unknown}; valid fields: {sorted(known)}")
        return TrainingDataConfig(**d)
