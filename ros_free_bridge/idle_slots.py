"""When the generator may do catch-up work: in the gap before the next actor frame is due.

The incremental streamer (``dualflow.streaming``, ``prepare``) has work that no frame waits
for: making and feeding the other window starts, and the next generator's convolution
prefetch. It is done in pieces of a few ms each on a 2-core CPU, of a few kinds
(``ReactiveStreamer.idle_jobs``) whose costs differ several-fold: a prefetch is a fraction
of a network pass, making a start is about one. A piece still running when an actor frame
arrives delays that frame's partner frame by what is left of it, and that tail is what the
loop's playback clock has to allow for on every frame (``ros_free_bridge.control.playback``: a
quantile of the frames' delays). Actor frames come at the source's rate, so the next one is
due at ``a + period`` (``a``: the newest frame's arrival) and a piece starts only when it
should be over by then:

    start now  iff  now + d + guard <= a + period     (it ends before the next frame)
               or   now > a + period + late           (the source paused or stalled)

with ``d`` the longest of the recent pieces of that kind (one estimate for all kinds would
be the dearest kind's, and the cheap prefetch would wait behind it). The second case keeps a
paused source from starving the catch-up work; the streamer still does any work a window
needs in that window.

Work that a frame soon would do in full if idle time has not (``urgent`` kinds; the
streamer's ``URGENT_JOBS``: feeding the window start about to take over, making the next
start) is not gated: started in a gap too short for it, it delays the next frame by less
than its own cost, which the takeover frame would otherwise pay whole.
"""

from __future__ import annotations

from collections import deque


class IdleSlots:
    """Gate for catch-up work. ``period``: seconds between actor frames (1 / fps); ``kind``
    (any hashable, e.g. "feed"): which piece of work, each kind timed on its own; ``urgent``:
    the kinds that may start in any gap."""

    def __init__(self, period: float, guard: float = 0.002, late: float | None = None, history: int = 16,
                 urgent=()):
        if not period > 0:
            raise ValueError(f"period must be > 0 s, got {period!r}")
        self.period = float(period)
        self.guard = float(guard)
        #: how long past its due time the next frame may be before the source counts as paused
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
