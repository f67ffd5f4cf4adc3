"""Both partner stages behind one call, ``feed(new actor frames) -> (targets, events)``.

:class:`PartnerCore` keeps up with the actor's clock: a backlog is generated in wider
windows, one per call; beyond ``max_lag`` frames the stale work is dropped and the stream
restarts at the newest actor frames (held targets and a ``generator_behind`` event say so).
Catch-up work runs only in idle gaps (:mod:`ros_free_bridge.partner.idle_slots`).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from ros_free_bridge.partner.idle_slots import CatchUpScheduler


@dataclass(frozen=True)
class PartnerTarget:
    """One robot target from :class:`PartnerCore`: q (n,) rad, the partner pose (22, 3) m it
    came from, and its timing. ``held``: a stand-in that repeats the previous pose for a frame
    the generator skipped to catch up (``gen_latency`` is NaN then). ``settle``: a frame of
    the robot's return to its own stance after the stream's end (RetargetStage.settle): no
    partner pose of its own (``positions`` repeats the last one)."""

    index: int
    q: np.ndarray
    positions: np.ndarray
    arrival: float
    actor_frame: int
    gen_latency: float
    rt_latency: float
    held: bool = False
    settle: bool = False
    #: the partner's foot contacts (4,) bool that the retargeter was given (None: none)
    contacts: np.ndarray | None = None


class PartnerCore:
    """Actor frames in, robot targets out, keeping up with the actor's clock.

    ``feed(frames)`` takes every actor frame that arrived since the last call (objects with
    ``index``, ``positions`` (22, 3) m, ``arrival``) and returns the targets they completed
    and any events. ``reactor`` (a :class:`~ros_free_bridge.partner.reactor.ReactorStage`)
    None: the robot retargets the actor itself (imitation). ``retarget``: a
    :class:`~ros_free_bridge.partner.retarget_stage.RetargetStage`.

    Timing stamp: partner frame i depends on actor frames up to c(i) = i + A, A =
    ``reactor.frames_ahead`` (the look-ahead L, + 1 when the last feature row waits for the
    next frame), so its target carries ``arrival`` = the arrival of actor frame c(i) and
    ``actor_frame`` = c(i).

    Real-time policy. When actor frame N has arrived, ``overdue = N - A + 1 - next_index``
    frames have all their inputs but are not generated yet; at most ``hop`` while the
    generator keeps up. A backlog is worked off in windows of up to the streamer's ``max_new``
    frames, one window per ``feed``. If ``overdue`` exceeds ``max_lag`` the stream restarts at
    a = N - A + 1 - hop, frames [next_index, a) repeat the last pose (``held``) and a
    ``generator_behind`` event reports them. Latency stays bounded by the model's delay +
    ``max_lag`` frames + one window's compute (docs/partner_pipeline.md).
    """

    def __init__(self, reactor, retarget, max_lag: int | None = None):
        self.reactor = reactor
        self.retarget = retarget
        if reactor is not None:
            hop = reactor.streamer.config.hop
            self.max_lag = max(int(max_lag) if max_lag is not None else self.default_max_lag(reactor), hop + 1)
            self._recent: deque = deque(maxlen=reactor.look_ahead + hop + 2)
        self.frames_dropped = 0
        #: catch-up pieces only in the gap before the next actor frame (the frames' rate: the reactor's fps)
        self.catch_up = CatchUpScheduler(reactor, 1.0 / (reactor.fps if reactor is not None else 30.0))
        self._arrivals: dict[int, float] = {}  # actor index -> arrival, for frames not yet used as c(i)
        self._last_q: np.ndarray | None = None
        self._last_pos: np.ndarray | None = None
        self._last_contacts: np.ndarray | None = None
        self._last_index = -1  # the last target's index
        self._last: tuple[float, int] = (0.0, -1)

    @staticmethod
    def default_max_lag(reactor) -> int:
        """hop + the streamer's max_new: one wide window can still clear such a backlog."""
        return reactor.streamer.config.hop + reactor.streamer.max_new

    @property
    def delay_frames(self) -> int | None:
        return None if self.reactor is None else self.reactor.delay_frames

    @property
    def frames_ahead(self) -> int:
        """Partner frame i is complete when actor frame i + frames_ahead has arrived (0: imitation)."""
        return 0 if self.reactor is None else self.reactor.frames_ahead

    @property
    def backlog(self) -> bool:
        """True when ``feed([])`` would generate (frames are due): call it again before waiting."""
        return self.reactor is not None and self.reactor.backlog

    def feed(self, frames) -> tuple[list[PartnerTarget], list[dict]]:
        """New actor frames (may be empty) → (targets, events). Generates at most one window per
        call, so that the lag is checked against the newest input between windows."""
        if frames:
            self._last = (frames[-1].arrival, frames[-1].index)
        if self.reactor is None:
            return [self._target(f.index, f.positions, None, f.arrival, f.index, 0.0) for f in frames], []
        self._recent.extend(frames)
        for f in frames:
            self._arrivals[f.index] = f.arrival
            self.catch_up.arrived(f.arrival)
        out, events = self._drop_to_newest()
        if events:
            frames = [f for f in self._recent if f.index >= self.reactor.next_index]
        out += self._targets(self.reactor.push_many(frames, max_windows=1))
        return out, events

    def _drop_to_newest(self) -> tuple[list[PartnerTarget], list[dict]]:
        """The real-time policy (class docstring): held targets and an event, or nothing."""
        r = self.reactor
        arrival, newest = self._last
        overdue = newest - r.frames_ahead + 1 - r.next_index
        restart_at = newest - r.frames_ahead + 1 - r.streamer.config.hop
        if not (
            overdue > self.max_lag
            and restart_at > r.next_index
            and self._recent
            and restart_at >= self._recent[0].index
        ):
            return [], []
        skipped = restart_at - r.next_index
        held = []
        if self._last_q is not None:
            last = (self._last_q, self._last_pos)
            held = [
                PartnerTarget(k, *last, arrival, newest, float("nan"), 0.0, True, contacts=self._last_contacts)
                for k in range(r.next_index, restart_at)
            ]
        self.frames_dropped += skipped
        event = {
            "kind": "generator_behind",
            "overdue_frames": int(overdue),
            "dropped_frames": int(skipped),
            "restart_frame": int(restart_at),
            "max_lag": self.max_lag,
        }
        r.restart(restart_at)
        return held, [event]

    def finish(self) -> list[PartnerTarget]:
        """End of the actor stream: the remaining partner frames (none for imitation), then the
        robot's return to its stance (``settle`` targets)."""
        return [t for targets, _ in self.finish_stream() for t in targets]

    def finish_stream(self):
        """End of the actor stream: yield (targets, events) batches, one window at a time (so
        the loop plays them while the rest is generated), the drop-to-newest policy first; last,
        the robot's return to its stance in small batches and a ``settle`` event (:meth:`_settle`)."""
        yield from self._flush()
        yield from self._settle()

    def _flush(self):
        """The reactor's remaining partner frames, batch by batch (finish_stream)."""
        if self.reactor is None or self._last[1] < 0:
            return
        held, events = self._drop_to_newest()
        if events:  # the restarted stream needs its actor frames again
            self.reactor.push_many([f for f in self._recent if f.index >= self.reactor.next_index], max_windows=0)
        if held or events:
            yield held, events
        while True:
            batch = self._targets(self.reactor.flush(*self._last, max_windows=1))
            if not batch:
                return
            yield batch, []

    SETTLE_BATCH = 3  #: settle frames sent together (a frame takes ~1 ms: the loop never waits for them)

    def _settle(self):
        """After the last partner frame: yield batches of the frames that step the robot back
        to its own stance and bring it to rest (:meth:`RetargetStage.settle`), on the partner's
        clock, made as they are sent; the last batch carries a ``settle`` event with their
        length and steps. Nothing before any frame was emitted."""
        if self._last_q is None:
            return
        batch, count, nan = [], 0, float("nan")
        frames = iter(self.retarget.settle())
        while True:
            t0 = time.perf_counter()
            q = next(frames, None)
            if q is None:
                break
            rt = time.perf_counter() - t0
            self._last_index += 1
            # no actor frame completed it: no arrival, so no end-to-end latency either
            actor = self._last_index + self.frames_ahead
            batch.append(PartnerTarget(self._last_index, q, self._last_pos, nan, actor, nan, rt, settle=True))
            self._last_q, count = q, count + 1
            if len(batch) == self.SETTLE_BATCH:
                yield batch, []
                batch = []
        if count:
            seconds = round(count / self.retarget.fps, 2)
            yield batch, [{"kind": "settle", "frames": count, "seconds": seconds, "steps": self.retarget.settle_steps}]

    def _targets(self, reactor_frames) -> list[PartnerTarget]:
        out = []
        for p in reactor_frames:
            c = p.index + self.reactor.frames_ahead  # the last actor frame partner frame i depends on
            if c in self._arrivals:
                arrival, actor = self._arrivals[c], c
            else:
                # the stream's end: actor frame c never came (the look-ahead was cut at the last
                # frame); stamp the arrival it would have had on the actor's clock, so that the
                # loop's figure stays "beyond the look-ahead" for these frames too
                last_arrival, last = self._last
                arrival, actor = last_arrival + (c - last) / self.reactor.fps, c
            out.append(self._target(p.index, p.positions, p.contacts, arrival, actor, p.latency))
        if out:
            done = out[-1].index + self.reactor.frames_ahead
            for k in [k for k in self._arrivals if k < done]:
                del self._arrivals[k]
        return out

    # -- idle time ---------------------------------------------------------------------------
    def idle_ready(self, now: float | None = None) -> bool:
        """Catch-up work is due and a piece of it fits before the next actor frame or is urgent."""
        return self.catch_up.ready(now)

    def idle_wait(self, now: float | None = None) -> float | None:
        """Seconds until a piece of catch-up work may start if no actor frame comes first: 0
        now, None when there is no catch-up work."""
        return self.catch_up.wait(now)

    def idle_step(self, now: float | None = None) -> None:
        """One short piece of the reactor's catch-up work (a few ms), if one fits or is urgent."""
        self.catch_up.step(now)

    def idle(self, seconds: float) -> None:
        """Nothing arrived: do a piece of catch-up work if it fits before the next actor frame,
        else wait up to ``seconds`` (the process variant waits on its pipe instead)."""
        wait = self.idle_wait()
        if wait == 0.0:
            self.idle_step()
        else:
            time.sleep(seconds if wait is None else min(seconds, wait))

    def close(self) -> None:
        """Nothing to release in-process (the process variant ends its worker)."""

    def _target(self, index, positions, contacts, arrival, actor_frame, gen_latency) -> PartnerTarget:
        t0 = time.perf_counter()
        q = self.retarget.step(positions, contacts)
        rt = time.perf_counter() - t0
        self._last_q, self._last_pos, self._last_index = q, np.asarray(positions), index
        self._last_contacts = None if contacts is None else np.asarray(contacts, dtype=bool)
        return PartnerTarget(
            index, q, np.asarray(positions), arrival, actor_frame, gen_latency, rt, contacts=self._last_contacts
        )
