"""A loaded dataset split: its samples and what was left out, with the reason."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from dualflow.datasets.sample import DuetSample


@dataclass
class DuetSet:
    """One split of one dataset.

    name: registry name ("interhuman", "dd100", ...); split: "train" | "val" | "test" | ...;
    root: the dataset folder (None for the synthetic set); samples: the clips;
    skipped: clip name -> reason for every clip the loader left out on purpose
    (ignore list, too short, no actor label, no music file where the authors'
    loader also drops it). Malformed files are errors, never skipped.
    """

    name: str
    split: str
    root: Path | None
    samples: list[DuetSample]
    skipped: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.samples)

    def __iter__(self) -> Iterator[DuetSample]:
        return iter(self.samples)

    def __getitem__(self, i: int) -> DuetSample:
        return self.samples[i]

    @property
    def texts(self) -> list[str]:
        return [s.text for s in self.samples]

    def summary(self) -> str:
        frames = sum(s.n_frames for s in self.samples)
        fps = self.samples[0].fps if self.samples else 30.0
        extras = []
        if any(s.music is not None for s in self.samples):
            extras.append("music " + ",".join(sorted({s.music_kind for s in self.samples if s.music_kind})))
        if any(s.focused is not None for s in self.samples):
            extras.append("focused texts")
        more = f" ({'; '.join(extras)})" if extras else ""
        return (
            f"{self.name}/{self.split}: {len(self.samples)} clips, {frames / fps / 60:.1f} min at {fps:g} fps"
            f"{more}; {len(self.skipped)} skipped"
        )
