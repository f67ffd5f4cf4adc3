"""Motion containers: one person's joint positions over time, and a two-person pair.

Shapes and units: positions are (T, 22, 3) float64 metres in the Z-up world frame
(SMPL joint order, see :mod:`dualflow.motion.skeleton`); ``fps`` is frames per
second; contacts, when present, are (T, 4) bool in the column order of
``FOOT_JOINTS`` (left ankle, left foot, right ankle, right foot).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dualflow.errors import DualFlowError
from dualflow.motion.skeleton import N_JOINTS

DEFAULT_FPS = 30.0


def _check_positions(positions: np.ndarray, what: str) -> np.ndarray:
    arr = np.asarray(positions, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (N_JOINTS, 3):
        raise DualFlowError(f"{what}: positions must have shape (T, {N_JOINTS}, 3), got {tuple(arr.shape)}")
    if arr.shape[0] < 1:
        raise DualFlowError(f"{what}: motion has zero frames; give at least one frame")
    bad = ~np.isfinite(arr)
    if bad.any():
        frame, joint, _ = np.argwhere(bad)[0]
        raise DualFlowError(
            f"{what}: positions contain NaN or inf (first at frame {frame}, joint {joint}); clean or drop those frames"
        )
    return arr


@dataclass(frozen=True)
class Motion:
    """One person's motion: joint positions (T, 22, 3) in metres at ``fps`` frames/s.

    ``contacts`` (T, 4) bool is optional; ``name`` is a free label (e.g. the source file).
    Construction validates shapes, finiteness and fps, raising DualFlowError.
    """

    positions: np.ndarray
    fps: float = DEFAULT_FPS
    contacts: np.ndarray | None = None
    name: str = ""

    def __post_init__(self) -> None:
        what = self.name or "motion"
        pos = _check_positions(self.positions, what)
        try:
            fps = float(self.fps)
        except (TypeError, ValueError):
            raise DualFlowError(f"{what}: fps must be a number, got {self.fps!r}") from None
        if not np.isfinite(fps) or fps <= 0:
            raise DualFlowError(f"{what}: fps must be > 0, got {self.fps!r}")
        contacts = self.contacts
        if contacts is not None:
            contacts = np.asarray(contacts).astype(bool)
            if contacts.shape != (pos.shape[0], 4):
                raise DualFlowError(
                    f"{what}: contacts must have shape ({pos.shape[0]}, 4), got {tuple(contacts.shape)}"
                )
        pos.setflags(write=False)
        object.__setattr__(self, "positions", pos)
        object.__setattr__(self, "fps", fps)
        object.__setattr__(self, "contacts", contacts)

    # -- basic properties -------------------------------------------------
    @property
    def n_frames(self) -> int:
        return int(self.positions.shape[0])

    def __len__(self) -> int:
        return self.n_frames

    @property
    def duration(self) -> float:
        """Seconds from the first to the last frame."""
        return (self.n_frames - 1) / self.fps

    @property
    def times(self) -> np.ndarray:
        """(T,) time stamp of each frame in seconds, starting at 0."""
        return np.arange(self.n_frames) / self.fps

    # -- derived motions --------------------------------------------------
    def replace(self, **changes) -> Motion:
        fields = {"positions": self.positions, "fps": self.fps, "contacts": self.contacts, "name": self.name}
        fields.update(changes)
        return Motion(**fields)

    def slice(self, start: int, stop: int | None = None) -> Motion:
        """Frames [start, stop) as a new motion."""
        contacts = None if self.contacts is None else self.contacts[start:stop]
        return self.replace(positions=self.positions[start:stop], contacts=contacts)

    def translated(self, offset) -> Motion:
        """The same motion moved by ``offset`` (3,) metres."""
        return self.replace(positions=self.positions + np.asarray(offset, dtype=np.float64))

    def resample(self, fps: float) -> Motion:
        """Resample to ``fps`` by linear interpolation of positions over time.

        The new clip spans the same duration (its last frame is at or before the
        old last frame). Contacts take the value of the nearest source frame.
        """
        fps = float(fps)
        if not np.isfinite(fps) or fps <= 0:
            raise DualFlowError(f"resample: fps must be > 0, got {fps!r}")
        if abs(fps - self.fps) < 1e-9:
            return self
        n_new = int(np.floor(self.duration * fps + 1e-6)) + 1
        t_new = np.arange(n_new) / fps
        src = t_new * self.fps  # fractional source frame index
        i0 = np.clip(np.floor(src).astype(int), 0, self.n_frames - 1)
        i1 = np.clip(i0 + 1, 0, self.n_frames - 1)
        w = (src - i0)[:, None, None]
        pos = (1.0 - w) * self.positions[i0] + w * self.positions[i1]
        contacts = None
        if self.contacts is not None:
            nearest = np.clip(np.rint(src).astype(int), 0, self.n_frames - 1)
            contacts = self.contacts[nearest]
        return Motion(positions=pos, fps=fps, contacts=contacts, name=self.name)


@dataclass(frozen=True)
class TwoPersonMotion:
    """Actor (person A, the human) and reactor (person B, the robot's role).

    Both share one world frame, one fps and one length. ``text`` is an optional
    description of the interaction.
    """

    actor: Motion
    reactor: Motion
    text: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.actor, Motion) or not isinstance(self.reactor, Motion):
            raise DualFlowError("two-person motion: actor and reactor must both be Motion objects")
        if abs(self.actor.fps - self.reactor.fps) > 1e-9:
            raise DualFlowError(
                f"two-person motion: actor is {self.actor.fps:g} fps but reactor is "
                f"{self.reactor.fps:g} fps; resample one of them first"
            )
        if self.actor.n_frames != self.reactor.n_frames:
            raise DualFlowError(
                f"two-person motion: actor has {self.actor.n_frames} frames but reactor has "
                f"{self.reactor.n_frames}; trim both to the same length"
            )

    @property
    def fps(self) -> float:
        return self.actor.fps

    @property
    def n_frames(self) -> int:
        return self.actor.n_frames

    def __len__(self) -> int:
        return self.n_frames

    def resample(self, fps: float) -> TwoPersonMotion:
        return TwoPersonMotion(self.actor.resample(fps), self.reactor.resample(fps), self.text, dict(self.meta))

    def slice(self, start: int, stop: int | None = None) -> TwoPersonMotion:
        return TwoPersonMotion(
            self.actor.slice(start, stop), self.reactor.slice(start, stop), self.text, dict(self.meta)
        )

    @classmethod
    def from_pair(cls, actor: Motion, reactor: Motion, text: str = "") -> TwoPersonMotion:
        """Pair two motions recorded in one world frame, resampling the reactor to the
        actor's fps and trimming both to the shorter length."""
        if abs(actor.fps - reactor.fps) > 1e-9:
            reactor = reactor.resample(actor.fps)
        n = min(actor.n_frames, reactor.n_frames)
        return cls(actor.slice(0, n), reactor.slice(0, n), text)
