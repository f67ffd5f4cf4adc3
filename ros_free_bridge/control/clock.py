"""A drift-free fixed-rate clock on ``time.monotonic``.

Tick k is due at ``start + k · period``: deadlines are absolute, so sleeping late on one
tick never shifts the ones after it. When the loop falls more than a whole period behind,
the missed ticks are skipped (counted as deadline misses) rather than run in a burst,
since a burst of servo commands is worse than a gap.
"""

from __future__ import annotations

import time
from dataclasses import dataclass


@dataclass(frozen=True)
class Tick:
    index: int  #: tick number since start (skipped ticks keep their numbers)
    due: float  #: monotonic second the tick was due
    woke: float  #: monotonic second the loop actually woke
    skipped: int  #: ticks skipped just before this one because the loop was too late

    @property
    def lateness(self) -> float:
        return self.woke - self.due


class FixedRateClock:
    """Wait for each tick of a ``rate_hz`` loop. ``sleep``/``now`` are injectable for tests."""

    def __init__(self, rate_hz: float, *, now=time.monotonic, sleep=time.sleep, spin_s: float = 0.0005):
        if not rate_hz > 0:
            raise ValueError(f"rate must be > 0 Hz, got {rate_hz}")
        self.rate_hz = float(rate_hz)
        self.period = 1.0 / self.rate_hz
        self._now = now
        self._sleep = sleep
        self._spin = spin_s
        self._start: float | None = None
        self._next = 0
        self.missed = 0  #: ticks skipped because the loop was more than a period late
        self.late = 0  #: ticks that started later than half a period after their deadline

    def start(self) -> None:
        self._start = self._now()
        self._next = 0

    def wait(self) -> Tick:
        """Sleep until the next tick is due and return it."""
        if self._start is None:
            self.start()
        due = self._start + self._next * self.period
        now = self._now()
        skipped = 0
        if now - due >= self.period:
            skipped = int((now - due) // self.period)
            self._next += skipped
            self.missed += skipped
            due = self._start + self._next * self.period
        remaining = due - now
        if remaining > self._spin:
            self._sleep(remaining - self._spin)
        while self._now() < due:  # short spin for sub-millisecond accuracy
            pass
        woke = self._now()
        if woke - due > 0.5 * self.period:
            self.late += 1
        tick = Tick(self._next, due, woke, skipped)
        self._next += 1
        return tick
