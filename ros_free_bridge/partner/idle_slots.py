"""When the generator does catch-up work: in the gap before the next actor frame is due.

:class:`IdleSlots` is the gate (a piece starts only if it should end before the next frame,
or the source paused, or its kind is urgent); :class:`CatchUpScheduler` is the bridge's side
of :class:`dualflow.streaming.CatchUpWork`, one piece at a time through that gate. The rule
and why: docs/partner_pipeline.md.
"""

from __future__ import annotations

import time
from collections import deque


class IdleSlots:
    """Gate for catch-up work. ``period``: seconds between actor frames (1 / fps); ``kind``
    (any hashable, e.g. "feed"): which piece of work, each kind timed on its own; ``urgent``:
    the kinds that may start in any gap; ``guard`` s of slack before the next frame; ``late``:
    how long past its due time the next frame may be before the source counts as paused
    (None: half a period); ``history``: how many recent pieces of a kind its estimate uses."""

    def __init__(self, period: float, guard: float = 0.002, late: float | None = None, history: int = 16, urgent=()):
        if not period > 0:
            raise ValueError(f"period must be > 0 s, got {period!r}")
        self.period = float(period)
        self.guard = float(guard)
        self.late = 0.5 * self.period if late is None else float(late)
        self.history = int(history)
        self.urgent = frozenset(urgent)
        self._passes: dict = {}  # kind -> deque of its recent durations
        self._newest: float | None = None  # arrival of the newest actor frame

    def arrived(self, arrival: float) -> None:
        """An actor frame that arrived at ``arrival`` (monotonic s) was fed."""
        if self._newest is None or arrival > self._newest:
            self._newest = float(arrival)

    def ran(self, seconds: float, kind="pass") -> None:
        """A piece of catch-up work of ``kind`` took ``seconds``."""
        self._passes.setdefault(kind, deque(maxlen=self.history)).append(float(seconds))

    def estimate(self, kind="pass") -> float:
        """The longest of the recent pieces of ``kind`` (0 before the first)."""
        return max(self._passes.get(kind, ()), default=0.0)

    def fits(self, now: float, kind="pass") -> bool:
        """Whether a piece of ``kind`` may start at ``now``: it is urgent, or it ends before the
        next frame is due (or the source paused)."""
        if self._newest is None or kind in self.urgent:
            return True
        due = self._newest + self.period
        return now + self.estimate(kind) + self.guard <= due or now > due + self.late

    def wait(self, now: float, kind="pass") -> float:
        """Seconds until a piece of ``kind`` may start if no frame comes first (0: now)."""
        if self.fits(now, kind):
            return 0.0
        return max(0.0, self._newest + self.period + self.late - now) + 1e-4


class CatchUpScheduler:
    """Drives a :class:`dualflow.streaming.CatchUpWork` (``idle_jobs``, ``urgent_jobs``,
    ``prepare``) from the gaps between actor frames. ``work`` None: there is none (imitation).
    ``period``: seconds between actor frames. Times in monotonic seconds (``now`` None: now)."""

    def __init__(self, work, period: float):
        self.work = work
        self.slots = IdleSlots(period, urgent=work.urgent_jobs if work is not None else ())

    def arrived(self, arrival: float) -> None:
        """An actor frame that arrived at ``arrival`` was fed to the generator."""
        self.slots.arrived(arrival)

    def _jobs(self) -> list[str]:
        return [] if self.work is None else self.work.idle_jobs()

    def _fitting_job(self, now: float | None) -> str | None:
        """The first due kind whose piece fits before the next actor frame, or is urgent."""
        now = time.monotonic() if now is None else now
        return next((k for k in self._jobs() if self.slots.fits(now, k)), None)

    def ready(self, now: float | None = None) -> bool:
        """Catch-up work is due and a piece of it fits before the next actor frame or is urgent."""
        return self._fitting_job(now) is not None

    def wait(self, now: float | None = None) -> float | None:
        """Seconds until a piece may start if no actor frame comes first: 0 now, None when no
        catch-up work is due."""
        jobs = self._jobs()
        if not jobs:
            return None
        now = time.monotonic() if now is None else now
        return min(self.slots.wait(now, k) for k in jobs)

    def step(self, now: float | None = None) -> None:
        """Run one piece (a few ms): the first due kind that fits or is urgent, timed for that kind."""
        job = self._fitting_job(now)
        if job is not None:
            t0 = time.monotonic()
            self.work.prepare(1, kinds=(job,))
            self.slots.ran(time.monotonic() - t0, job)
