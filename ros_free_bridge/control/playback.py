"""The control loop's playback clock: when target frame k is played.

Frame k plays at t0 + k / fps. :class:`PlaybackClock` moves t0, at a bounded rate, toward the
earliest value at which (a quantile of) the recent frames arrived in time, so the latency
follows the generator's actual delay rather than the first frame's; motion time never jumps
or runs backwards. With ``run_ahead`` set, motion time also never runs more than that many
frames past the newest frame (none past the first frame while it is the only one): while the
stream stalls the clock stops, and the motion resumes where it stopped when frames come,
instead of jumping to where the clock had run meanwhile. Times in seconds. The reasoning and
the formula: docs/bridge_timing.md.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class PlaybackPolicy:
    """How the clock places t0 (docs/bridge_timing.md).

    ``margin``: s of reserve for arrival jitter. ``lead_frames``: frames that must have
    arrived beyond the one played (1 for interpolation, 0 when the buffer may extrapolate).
    ``window_s``: s of recent arrivals considered. ``quantile``: the share of them that must
    be in time (1.0: all). ``speed_up`` / ``slow_down``: the largest rate (s per s) at which t0
    moves earlier / later, i.e. playback at most 1 + speed_up and at least 1 - slow_down
    times real time. ``fixed``: t0 stays where the first frame put it (but for ``run_ahead``).
    ``run_ahead``: the most frames motion time may run past the newest frame that has arrived
    (the buffer's extrapolation horizon; 0 while only the first frame is in): at that point t0
    moves later with the wall clock, i.e. playback stops until the next frame comes. None: no
    bound (motion time runs on through a stall, and the played motion skips ahead when the
    late frames come)."""

    margin: float
    lead_frames: float = 1.0
    window_s: float = 1.0
    speed_up: float = 0.2
    slow_down: float = 0.5
    quantile: float = 0.9
    fixed: bool = False
    run_ahead: float | None = None


class PlaybackClock:
    """Motion time for the loop, from the first frame (``first_index``, arrived at ``now``)
    on, under ``policy``."""

    def __init__(self, fps: float, first_index: int, now: float, policy: PlaybackPolicy):
        self.fps = float(fps)
        self.margin = float(policy.margin)
        self.lead = float(policy.lead_frames) / self.fps
        self.window_s = float(policy.window_s)
        self.speed_up = float(policy.speed_up)
        self.slow_down = float(policy.slow_down)
        self.fixed = bool(policy.fixed)
        self.quantile = float(policy.quantile)
        self.run_ahead = None if policy.run_ahead is None else float(policy.run_ahead)
        self.first_index = first_index
        self.stalled = 0.0  #: seconds the run-ahead bound has stopped motion time so far
        self.t0 = now + self.margin - first_index / self.fps  # the fixed clock's t0 (as before)
        self._offsets: deque[tuple[float, float]] = deque()  # (arrival, a_k)
        self._seen = first_index
        self._offsets.append((now, now - first_index / self.fps))
        self._last = now
        self._want: float | None = None  # t0* of the current offsets (None: to recompute)

    def arrived(self, newest_index: int, now: float, timed: bool = True) -> None:
        """The newest target frame is ``newest_index`` at ``now`` (call every tick; frames newer
        than the last call count as arrived now). ``timed`` False: frames that no actor frame
        paced (made all at once, e.g. the robot's return to its stance after a stream): they
        extend what may be played but not the arrival statistics (a burst of them arriving
        early would speed playback up by ``speed_up``)."""
        n = len(self._offsets)
        if timed:
            for k in range(self._seen + 1, newest_index + 1):
                self._offsets.append((now, now - k / self.fps))
        self._seen = max(self._seen, newest_index)
        expired = 0
        while self._offsets and self._offsets[0][0] < now - self.window_s:
            self._offsets.popleft()
            expired += 1
        if expired or len(self._offsets) != n:
            self._want = None  # the offsets changed (about twice per frame, not every tick)

    def target_t0(self) -> float | None:
        """t0*: the earliest t0 at which every recent frame was on time (None: no recent frame)."""
        if not self._offsets:
            return None
        if self._want is None:
            # the q-quantile with linear interpolation between order statistics (numpy's
            # default method), on a few dozen floats: sorted() is far cheaper than np.quantile
            offsets = sorted(a for _, a in self._offsets)
            pos = min(self.quantile, 1.0) * (len(offsets) - 1)
            lo = int(pos)
            hi = min(lo + 1, len(offsets) - 1)
            self._want = offsets[lo] + (offsets[hi] - offsets[lo]) * (pos - lo) + self.lead + self.margin
        return self._want

    def motion_time(self, now: float) -> float:
        """Seconds of motion to play at ``now`` (frame k at k / fps); advances t0 toward t0*."""
        dt = max(0.0, now - self._last)
        self._last = now
        want = None if self.fixed else self.target_t0()
        if want is not None:
            if want < self.t0:
                self.t0 = max(want, self.t0 - self.speed_up * dt)
            else:
                self.t0 = min(want, self.t0 + self.slow_down * dt)
        if self.run_ahead is not None:
            # frames past the newest that may be played: none past the first frame alone (the
            # buffer can extrapolate only from two); the clock waits there for the next one
            ahead = 0.0 if self._seen == self.first_index else self.run_ahead
            bound = (self._seen + ahead) / self.fps + 1e-9  # a hair past it: k / fps * fps may round below k
            if now - self.t0 > bound:
                later = now - bound
                self.stalled += later - self.t0
                self.t0 = later
        return now - self.t0
