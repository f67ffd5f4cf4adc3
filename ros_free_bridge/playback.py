"""The control loop's playback clock: when target frame k is played.

Frame k is played at t0 + k / fps (motion time (now - t0) seconds). A fixed t0, set when the
first frame arrives, makes that first frame's lateness the latency of the whole run: a slow
first window (or a start while the machine is busy) costs every later frame the same, and a
first window faster than the later ones makes them all late. The adaptive clock instead keeps
t0 at the earliest value at which the recent frames were all on time:

    a_k  = arrival_k - k / fps                       (frame k's arrival offset)
    t0*  = q-quantile of a_k over the frames of the last ``window_s`` seconds + lead / fps + margin

(``lead`` frames: the interpolation between frames k and k + 1 needs frame k + 1 when
frame k is played, 0 when the buffer may extrapolate the newest frame for a frame
(``TargetBuffer(extrapolate=1)``); ``margin``: reserve for arrival jitter; ``quantile`` q,
default 0.9: the odd frame later than the rest (a busy CPU) does not hold the clock back for
a whole window: it is played when it comes, the buffer's extrapolation covering for it
meanwhile (``TargetBuffer.extrapolate``, its arrival smoothed by ``RevisionSmoother``), and
its latency counts as it is). t0 moves toward t0* at a bounded
rate: earlier (playing faster than real time, at most 1 + ``speed_up``) when frames arrive
sooner than needed, later (slower, down to 1 - ``slow_down``) when they come late, so motion
time never jumps or runs backwards. The latency then follows the generator's actual delay
instead of the first frame's.
"""

from __future__ import annotations

from collections import deque


class PlaybackClock:
    """Motion time for the loop. ``fixed=True``: t0 stays where the first frame put it."""

    def __init__(self, fps: float, first_index: int, now: float, margin: float, lead_frames: float = 1.0,
                 window_s: float = 1.0, speed_up: float = 0.2, slow_down: float = 0.5, fixed: bool = False,
                 quantile: float = 0.9):
        self.fps = float(fps)
        self.margin = float(margin)
        self.lead = float(lead_frames) / self.fps
        self.window_s = float(window_s)
        self.speed_up = float(speed_up)
        self.slow_down = float(slow_down)
        self.fixed = bool(fixed)
        self.quantile = float(quantile)
        self.t0 = now + self.margin - first_index / self.fps  # the fixed clock's t0 (as before)
        self._offsets: deque[tuple[float, float]] = deque()  # (arrival, a_k)
        self._seen = first_index
        self._offsets.append((now, now - first_index / self.fps))
        self._last = now
        self._want: float | None = None  # t0* of the current offsets (None: to recompute)

    def arrived(self, newest_index: int, now: float) -> None:
        """The newest target frame is ``newest_index`` at ``now`` (call every tick; frames newer
        than the last call count as arrived now)."""
        n = len(self._offsets)
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
        return now - self.t0
