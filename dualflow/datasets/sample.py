"""One sample format for every two-person dataset: :class:`DuetSample`.

Contract: every loader of :mod:`dualflow.datasets` returns DuetSamples, so training, retrieval
and evaluation read one thing: ``motion`` (a TwoPersonMotion in the project's world frame,
22 SMPL joints, actor = person A), ``features()`` ((T-1, 2, 262) float32 InterGen features,
one code path for every dataset), ``texts`` / ``focused`` descriptions, per-frame ``music``
(T, D) with its ``music_kind``, ``genre`` / ``style`` labels, ``roles`` (the dataset's names of
the two people, actor first), ``source`` and ``name``. numpy only.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from dualflow.decompose import FocusedDescriptions
from dualflow.errors import DualFlowError
from dualflow.motion.container import Motion, TwoPersonMotion
from dualflow.motion.features import FEATURE_DIM, encode_pair
from dualflow.motion.skeleton import N_JOINTS

#: Music feature kinds a sample can carry, with their widths (None: any width).
MUSIC_KIND_DIMS: dict[str, int | None] = {"duolando54": 54, "edge35": 35, "jukebox": 4800, "beats4": 4, "other": None}


@dataclass
class DuetSample:
    """One two-person clip with its conditions (see the module docstring for every field)."""

    source: str
    name: str
    motion: TwoPersonMotion
    texts: tuple[str, ...] = ()
    focused: FocusedDescriptions | None = None
    music: np.ndarray | None = None
    music_kind: str | None = None
    music_path: Path | None = None
    genre: str | None = None
    style: str | None = None
    roles: tuple[str, str] = ("actor", "reactor")
    meta: dict = field(default_factory=dict)
    _features: np.ndarray | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.motion, TwoPersonMotion):
            raise DualFlowError(f"{self.source}/{self.name}: motion must be a TwoPersonMotion")
        self.texts = tuple(str(t) for t in self.texts)
        if self.music is not None:
            music = np.asarray(self.music, dtype=np.float32)
            if music.ndim != 2 or music.shape[0] < 1 or not np.isfinite(music).all():
                raise DualFlowError(
                    f"{self.source}/{self.name}: music features must be a finite (T, D) array, got shape {music.shape}"
                )
            kind = self.music_kind or "other"
            want = MUSIC_KIND_DIMS.get(kind, "unknown")
            if want == "unknown":
                raise DualFlowError(
                    f"{self.source}/{self.name}: unknown music_kind {kind!r}; use one of {sorted(MUSIC_KIND_DIMS)}"
                )
            if want is not None and music.shape[1] != want:
                raise DualFlowError(
                    f"{self.source}/{self.name}: {kind} music features must have {want} columns, got {music.shape[1]}"
                )
            self.music = music
            self.music_kind = kind

    # -- views ------------------------------------------------------------------------

    @property
    def text(self) -> str:
        """The first annotation sentence ('' when the clip has none)."""
        return self.texts[0] if self.texts else ""

    @property
    def fps(self) -> float:
        return self.motion.fps

    @property
    def n_frames(self) -> int:
        return self.motion.n_frames

    def features(self) -> np.ndarray:
        """(T-1, 2, 262) float32 InterGen features, actor then reactor (module docstring)."""
        if self._features is None:
            feats, _ = encode_pair(self.motion)
            self._features = np.ascontiguousarray(feats, dtype=np.float32)
        return self._features

    def music_rows(self, n_frames: int) -> np.ndarray | None:
        """Music features trimmed (or last-row padded) to ``n_frames`` rows, or None."""
        if self.music is None:
            return None
        m = self.music[:n_frames]
        if len(m) < n_frames:
            m = np.concatenate([m, np.repeat(m[-1:], n_frames - len(m), axis=0)])
        return m

    def window(self, start: int, length: int) -> DuetSample:
        """Frames [start, start + length) of the clip (music cut alike), as a new sample."""
        if start < 0 or length < 2 or start + length > self.n_frames:
            raise DualFlowError(
                f"{self.source}/{self.name}: window [{start}, {start + length}) "
                f"is outside the clip's {self.n_frames} frames"
            )
        music = None if self.music is None else self.music[start : start + length]
        if music is not None and len(music) == 0:
            music = None
        return replace(
            self,
            name=f"{self.name}@{start}",
            motion=self.motion.slice(start, start + length),
            music=music,
            music_kind=self.music_kind if music is not None else None,
            _features=None,
        )


def positions_motion(positions_yup: np.ndarray, fps: float, name: str, where: str) -> Motion:
    """A :class:`Motion` from (T, >=22, 3) or (T, >=66) Y-up positions in metres (first 22 SMPL joints).

    The datasets here store SMPL/SMPL-X joints in the SMPL world frame, Y up; the
    conversion to the project's Z-up frame is ``zup = yup[..., [2, 0, 1]]``
    (DESIGN.md, :mod:`dualflow.motion.features`).
    """
    arr = np.asarray(positions_yup, dtype=np.float64)
    if arr.ndim == 2:
        if arr.shape[1] < N_JOINTS * 3 or arr.shape[1] % 3:
            raise DualFlowError(f"{where}: expected (T, 3·J) joint positions with J >= 22, got shape {arr.shape}")
        arr = arr.reshape(len(arr), -1, 3)
    if arr.ndim != 3 or arr.shape[1] < N_JOINTS or arr.shape[2] != 3:
        raise DualFlowError(f"{where}: expected (T, J, 3) joint positions with J >= 22, got shape {arr.shape}")
    if len(arr) < 2:
        raise DualFlowError(f"{where}: a clip needs at least 2 frames, got {len(arr)}")
    if not np.isfinite(arr).all():
        raise DualFlowError(f"{where}: joint positions contain NaN or inf; re-export the clip")
    zup = arr[:, :N_JOINTS][..., [2, 0, 1]]
    return Motion(positions=zup, fps=float(fps), name=name)


def check_feature_array(features: np.ndarray, where: str) -> np.ndarray:
    """Validate a (N, T, 2, 262) or (T, 2, 262) feature array; float32."""
    f = np.asarray(features, dtype=np.float32)
    if f.shape[-2:] != (2, FEATURE_DIM):
        raise DualFlowError(f"{where}: expected (..., 2, {FEATURE_DIM}) features, got {f.shape}")
    return f
