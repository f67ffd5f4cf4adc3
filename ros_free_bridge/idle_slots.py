"""When the generator may do catch-up work: in the gap before the next actor frame is due.

The incremental streamer (``dualflow.streaming``, ``prepare``) has work that no frame waits
for: feeding the other window starts. It is done in passes of one network pass each (4-11
ms on a 2-core CPU). A pass still running when an actor frame arrives delays that frame's
partner frame by what is left of it, and that tail is what the loop's playback clock has to
allow for on every frame (``ros_free_bridge.playback``: a quantile of the frames' delays).
Actor frames come at the source's rate, so the next one is due at ``a + period`` (``a``: the
newest frame's arrival) and a pass starts only when it should be over by then:

    start now  iff  now + d + guard <= a + period     (it ends before the next frame)
               or   now > a + period + late           (the source paused or stalled)

with ``d`` the longest of the recent passes. The second case keeps a paused source from
starving the catch-up work; the streamer still does any work a window needs in that window.
"""

from __future__ import annotations

from collections import deque


class IdleSlots:
    """Gate for catch-up passes. ``period``: seconds between actor frames (1 / fps)."""

    def __init__(self, period: float, guard: float = 0.002, late: float | None = None, history: int = 16):
        if not period > 0:
            raise ValueError(f"period must be > 0 s, got {period!r}")
        self.period = float(period)
        self.guard = float(guard)
        #: how long past its due time the next frame may be before the source counts as paused
        self.late = 0.5 * self.period if late is None else float(late)
        self._passes: deque[float] = deque(maxlen=int(history))
        self._newest: float | None = None  # arrival of the newest actor frame

    def arrived(self, arrival: float) -> None:
        """An actor frame that arrived at ``arrival`` (monotonic s) was fed."""
        if self._newest is None or arrival > self._newest:
            self._newest = float(arrival)

    def ran(self, seconds: float) -> None:
        """A catch-up pass took ``seconds``."""
        self._passes.append(float(seconds))

    @property
    def pass_estimate(self) -> float:
        """The longest of the recent passes (0 before the first)."""
        return max(self._passes, default=0.0)

    def fits(self, now: float) -> bool:
        """Whether a pass started at ``now`` ends before the next frame is due (or the source paused)."""
        if self._newest is None:
            return True
        due = self._newest + self.period
        return now + self.pass_estimate + self.guard <= due or now > due + self.late

    def wait(self, now: float) -> float:
        """Seconds until a pass may start if no frame comes first (0: now)."""
        if self.fits(now):
            return 0.0
        return max(0.0, self._newest + self.period + self.late - now) + 1e-4
