"""The hand-over between the slow stages (generation, retargeting) and the control loop.

The pipeline thread pushes robot joint targets at the motion frame rate (30 fps by
default), each stamped with its place on the motion timeline and the monotonic second
the actor frame that completed it arrived. The control loop samples the buffer at its
own rate (100 Hz by default), interpolating between frames, and never waits on it: if
the next frame is not there yet, :meth:`TargetBuffer.sample` says so (``starved``) and
the loop holds.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class TargetFrame:
    """One robot pose on the motion timeline.

    index: frame number (time = index / fps). q: (n,) rad. source_arrival: monotonic second
    the actor frame that completed this target arrived (for end-to-end latency).
    generator_latency / retarget_latency: seconds those stages spent on it.
    """

    index: int
    q: np.ndarray
    source_arrival: float
    actor_frame: int = -1
    generator_latency: float = float("nan")
    retarget_latency: float = float("nan")


@dataclass(frozen=True)
class Sample:
    q: np.ndarray | None  #: interpolated target, None when no frame covers the time yet
    starved: bool  #: the loop asked for a time beyond the newest frame
    newest: TargetFrame | None  #: the newest frame at or before the sampled time
    finished: bool  #: the producer said no more frames will come and all were played
    extrapolated: bool = False  #: q continues the newest frames' velocity past the newest frame
    #: (newest frame index, stream closed) of the buffer state this sample was taken from: it
    #: changes exactly when the curve may have (a frame arrived, or the stream ended)
    revision: tuple[int, bool] = (-1, False)


class TargetBuffer:
    """Thread-safe ring of recent target frames (the producer pushes, the loop samples).

    ``interpolation`` between frames k and k + 1: "linear", or "cubic": the cubic Hermite
    segment through q_k and q_k+1 whose end tangents come from earlier frames only
    (``_tangent``). The velocity is then continuous at every frame, and a segment needs
    nothing after frame k + 1: the loop may play frame k as soon as k + 1 is there, and the
    segment it plays never changes under it. (Catmull-Rom's central tangent at k + 1 needs
    frame k + 2; while that has not arrived the segment must fall back to another curve
    and switch, a jump in velocity each time.)
    """

    def __init__(self, fps: float, capacity: int = 512, interpolation: str = "linear", extrapolate: float = 0.0):
        if interpolation not in ("linear", "cubic"):
            raise ValueError(f"interpolation must be 'linear' or 'cubic', got {interpolation!r}")
        if not extrapolate >= 0:
            raise ValueError(f"extrapolate must be >= 0 frames, got {extrapolate!r}")
        self.fps = float(fps)
        self.interpolation = interpolation
        #: frames past the newest one over which ``sample`` continues it instead of holding
        #: q_n: along its tangent m_n (``_tangent``) with the speed fading linearly to zero,
        #: q_n + m_n (s - s² / 2E) for s <= E = ``extrapolate``, then held at q_n + m_n E / 2.
        #: Lets the loop play frame n as soon as it arrives, not one frame later (interpolating
        #: toward n + 1 needs n + 1); the fade makes a stalled stream come to rest without a jump
        #: in position or velocity, and the next frame then takes over (:class:`RevisionSmoother`).
        self.extrapolate = float(extrapolate)
        self._frames: deque[TargetFrame] = deque(maxlen=capacity)
        self._lock = threading.Lock()
        self._closed = False
        self._ready = threading.Event()
        self.error: BaseException | None = None  #: set by a producer that died

    def push(self, frame: TargetFrame) -> None:
        with self._lock:
            if self._frames and frame.index != self._frames[-1].index + 1:
                raise ValueError(f"target frames must be consecutive: got {frame.index} after {self._frames[-1].index}")
            self._frames.append(frame)
        self._ready.set()

    def close(self, error: BaseException | None = None) -> None:
        """The producer is done (or failed with ``error``)."""
        self.error = error
        self._closed = True
        self._ready.set()

    @property
    def closed(self) -> bool:
        return self._closed

    def wait_first(self, timeout: float) -> bool:
        return self._ready.wait(timeout)

    def first(self) -> TargetFrame | None:
        with self._lock:
            return self._frames[0] if self._frames else None

    def newest(self) -> TargetFrame | None:
        with self._lock:
            return self._frames[-1] if self._frames else None

    def _tangent(self, frames: list[TargetFrame], i: int) -> np.ndarray:
        """Velocity (per frame) at frames[i] from frames up to i only. Cubic: the slope at
        frame i of the parabola through frames i - 2, i - 1, i, (3 q_i - 4 q_i-1 + q_i-2) / 2
        (exact for constant acceleration), the backward difference while fewer frames are
        there; linear: the backward difference (the slope of the segment that ends at i)."""
        if i == 0:
            return np.zeros_like(frames[0].q)
        if self.interpolation == "cubic" and i >= 2:
            return 1.5 * frames[i].q - 2.0 * frames[i - 1].q + 0.5 * frames[i - 2].q
        return frames[i].q - frames[i - 1].q

    def sample(self, t: float) -> Sample:
        """Target at motion time ``t`` seconds (frame k is at k / fps)."""
        with self._lock:  # one consistent state: another thread may push or close meanwhile
            frames = list(self._frames)
            closed = self._closed
        if not frames:
            return Sample(None, True, None, closed, revision=(-1, closed))
        first, last = frames[0].index, frames[-1].index
        revision = (last, closed)
        pos = max(t * self.fps, first)  # before the first frame: hold the first frame
        if pos >= last:
            over = pos - last
            if not closed and over > 0 and self.extrapolate > 0 and len(frames) >= 2:
                s = min(over, self.extrapolate)
                q = frames[-1].q + (s - s * s / (2.0 * self.extrapolate)) * self._tangent(frames, len(frames) - 1)
                starved = over > self.extrapolate  # come to rest: held where the fade ended
                return Sample(q, starved, frames[-1], False, not starved, revision)
            return Sample(frames[-1].q.copy(), not closed and pos > last, frames[-1], closed, revision=revision)
        k = int(np.floor(pos))
        i = k - first
        w = pos - k
        a, b = frames[i], frames[i + 1]
        if self.interpolation == "cubic":
            # cubic Hermite through q_k and q_k+1 with the causal tangents: the velocity is
            # continuous at every frame, and this segment needs no frame after k + 1
            d = b.q - a.q
            m1, m2 = self._tangent(frames, i), self._tangent(frames, i + 1)
            q = a.q + w * m1 + (w * w) * ((3.0 - 2.0 * w) * (d - m1) + (w - 1.0) * (m2 - m1))
        else:
            q = (1.0 - w) * a.q + w * b.q
        return Sample(q, False, a if w < 1.0 else b, False, revision=revision)


class RevisionSmoother:
    """The buffer's curve as the loop plays it, with its revisions smoothed out.

    The loop plays frame n as soon as it arrives and extrapolates past it (``TargetBuffer``'s
    ``extrapolate``); when frame n + 1 then comes, the curve the loop was following changes
    under it: at the time last played the new curve is elsewhere (position) and moves
    otherwise (velocity). Sampling the new curve directly jumps by that difference, which
    the safety filter's acceleration limit then spreads over the next ticks (bang-bang).
    Instead the difference is carried as an offset e added to the curve, with the velocity
    difference as its rate, and e decays as a critically damped second-order system,

        ë = -2 ω ė - ω² e,   e(t) = (e0 + (ė0 + ω e0) t) exp(-ω t),

    so the command's position and velocity are continuous across every revision and it joins
    the new curve within a few 1 / ω (``omega`` rad/s; 0: off, the curve as it is).

    ``sample(t, now)`` at motion time t (s) and monotonic ``now`` (s) returns the buffer's
    :class:`Sample` with ``q`` = curve + offset. A revision is a new frame (or the stream's
    end) since the last call; the curve is then re-sampled at the last two played times to
    measure what changed. ``reset()`` forgets the offset (after the loop held or ramped
    on its own).

    ``join(offset, duration, clock)``: the command is ``offset`` (rad, (n,)) away from the curve
    at ``clock`` (the loop starts following the curve from a pose that is not on it: the rest
    pose at the stream's start, the held pose after a hold) and joins it along a minimum-jerk
    fade of that offset over ``duration`` s: offset · (1 - (10 s³ - 15 s⁴ + 6 s⁵)), s = elapsed /
    duration, whose velocity and acceleration are zero at both ends. ``clock`` (s) is the loop's
    tick time (tick number x period), passed again to every ``sample``: a run paced by ticks
    blends the same every time, and the blend runs on smoothly while the playback clock waits
    for a late frame (in motion time it would stop and restart in one tick each). It adds to the revision
    offset above and ends with ``reset()``.
    """

    def __init__(self, buffer: TargetBuffer, omega: float):
        if not omega >= 0:
            raise ValueError(f"omega must be >= 0 rad/s, got {omega!r}")
        self.buffer = buffer
        self.omega = float(omega)
        self.reset()

    def reset(self) -> None:
        self.offset: np.ndarray | float = 0.0  #: e: command minus curve (rad)
        self._rate: np.ndarray | float = 0.0  #: de/dt (rad/s)
        self._played: list[tuple[float, np.ndarray]] = []  # (motion time, curve there), the last two
        self._seen: tuple[int, bool] | None = None  # (newest index, closed) at the last call
        self._now: float | None = None
        self._join: tuple[np.ndarray, float, float] | None = None  # (offset, start, duration)

    def join(self, offset: np.ndarray, duration: float, clock: float) -> None:
        self._join = (np.asarray(offset, float).copy(), float(clock), float(duration)) if duration > 0 else None

    def _join_offset(self, clock: float) -> np.ndarray | float:
        if self._join is None:
            return 0.0
        offset, start, duration = self._join
        x = (clock - start) / duration
        if x >= 1.0:
            self._join = None
            return 0.0
        x = max(0.0, x)
        return offset * (1.0 - x * x * x * (10.0 - 15.0 * x + 6.0 * x * x))

    def sample(self, t: float, now: float, clock: float = 0.0) -> Sample:
        """The curve at motion time t (s), plus the revision offset and the join's (at ``clock``)."""
        s = self._sample(t, now)
        if s.q is None or self._join is None:
            return s
        return replace(s, q=s.q + self._join_offset(clock))

    def _sample(self, t: float, now: float) -> Sample:
        buf = self.buffer
        s = buf.sample(t)
        if s.q is None or self.omega == 0:
            return s
        seen = s.revision  # the state s came from (reading the buffer again could see a newer one)
        if self._seen is not None and seen != self._seen and len(self._played) == 2:
            (t2, c2), (t1, c1) = self._played
            n2, n1 = buf.sample(t2).q, buf.sample(t1).q
            self.offset = self.offset + (c1 - n1)
            if t1 > t2:
                self._rate = self._rate + ((c1 - c2) - (n1 - n2)) / (t1 - t2)
            self._played = [(t2, n2), (t1, n1)]
        self._seen = seen
        if self._now is not None:
            dt = max(0.0, now - self._now)
            w = self.omega
            decay = math.exp(-w * dt)
            a = self._rate + w * self.offset
            self.offset, self._rate = (self.offset + a * dt) * decay, (self._rate - w * a * dt) * decay
        self._now = now
        self._played = (self._played + [(t, s.q)])[-2:]
        return replace(s, q=s.q + self.offset)
