"""Replay a recorded (or synthetic) actor motion in real time.

The clock starts at :meth:`MotionReplaySource.start` (the control loop calls it once
the robot is at its rest pose), and :meth:`poll` returns every frame whose time has
come since the last call, never blocking. Frame k is due at ``start + k / fps``; its
``arrival`` is stamped as that due time, so latency figures measured downstream do
not depend on how often the caller polls.
"""

from __future__ import annotations

import time

from dualflow.motion import Motion
from ros_free_bridge.sources.udp import ActorFrame


class MotionReplaySource:
    """Frames of ``motion`` at its own fps, once (``loop=False``) or repeatedly."""

    live = False  #: frames exist before start(); nothing is lost by waiting

    def __init__(self, motion: Motion, loop: bool = False, clock=time.monotonic):
        self.motion = motion
        self.fps = motion.fps
        self.loop = loop
        self._clock = clock
        self._t0: float | None = None
        self._next = 0

    def start(self) -> None:
        self._t0 = self._clock()
        self._next = 0

    @property
    def started(self) -> bool:
        return self._t0 is not None

    @property
    def finished(self) -> bool:
        return not self.loop and self._next >= self.motion.n_frames

    def next_due(self) -> float | None:
        """Monotonic second the next frame is due (None: not started, or no frame left)."""
        if self._t0 is None or self.finished:
            return None
        return self._t0 + self._next / self.fps

    def poll(self) -> list[ActorFrame]:
        if self._t0 is None:
            return []
        now = self._clock()
        due_count = int((now - self._t0) * self.fps + 1e-9) + 1  # frames due by now
        frames = []
        n = self.motion.n_frames
        while self._next < due_count and (self.loop or self._next < n):
            k = self._next
            frames.append(ActorFrame(k, self.motion.positions[k % n], self._t0 + k / self.fps))
            self._next += 1
        return frames

    def close(self) -> None:
        pass
