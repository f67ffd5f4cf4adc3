"""Keeping a Python control loop on time while it runs: garbage collection in the ticks'
slack (:class:`LoopGc`), a short GIL switch interval (:func:`switch_interval`) and SCHED_FIFO
where permitted (:func:`realtime_priority`); all undone afterwards. Why: docs/bridge_timing.md.
"""

from __future__ import annotations

import gc
import os
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass


@dataclass
class GcStats:
    """Collections made by :class:`LoopGc`: in a tick's slack, forced, and their time (s)."""

    in_slack: int = 0
    forced: int = 0
    full: int = 0
    longest_s: float = 0.0


class LoopGc:
    """Garbage collection on the control loop's terms (see the module docstring).

    Use as a context manager around the loop; call :meth:`collect_in_slack` once per tick
    after the bus write with the seconds left before the next deadline. A young-generation
    pass runs when ``gc.get_count()[0]`` has reached ``threshold`` and at least
    ``min_slack_s`` are left, or unconditionally past ``hard_limit``; a full pass (of what
    was allocated since the freeze) every ``full_every_s`` seconds, in slack only."""

    def __init__(
        self, threshold: int = 700, hard_limit: int = 50_000, min_slack_s: float = 0.001, full_every_s: float = 10.0
    ) -> None:
        self.threshold = threshold
        self.hard_limit = hard_limit
        self.min_slack_s = min_slack_s
        self.full_every_s = full_every_s
        self.stats = GcStats()
        self._was_enabled = True
        self._last_full = 0.0

    def __enter__(self) -> LoopGc:
        self._was_enabled = gc.isenabled()
        gc.disable()
        gc.collect()  # start clean: what is left now is long-lived
        gc.freeze()
        self._last_full = time.monotonic()
        return self

    def __exit__(self, *exc) -> None:
        gc.unfreeze()
        if self._was_enabled:
            gc.enable()

    def collect_in_slack(self, slack_s: float) -> None:
        pending = gc.get_count()[0]
        if pending < self.threshold:
            return
        now = time.monotonic()
        if slack_s >= self.min_slack_s:
            full = now - self._last_full >= self.full_every_s
            t0 = time.perf_counter()
            gc.collect(2 if full else 1)
            self._note(time.perf_counter() - t0)
            self.stats.in_slack += 1
            if full:
                self.stats.full += 1
                self._last_full = now
        elif pending >= self.hard_limit:
            t0 = time.perf_counter()
            gc.collect(1 if gc.get_count()[1] >= 10 else 0)  # the middle generation too, now and then
            self._note(time.perf_counter() - t0)
            self.stats.forced += 1

    def _note(self, seconds: float) -> None:
        if seconds > self.stats.longest_s:
            self.stats.longest_s = seconds


@contextmanager
def switch_interval(seconds: float = 0.0005):
    """Lower the interpreter's GIL switch interval while the block runs (process-wide)."""
    old = sys.getswitchinterval()
    sys.setswitchinterval(min(old, seconds))
    try:
        yield
    finally:
        sys.setswitchinterval(old)


@contextmanager
def realtime_priority(priority: int | None):
    """Run the calling thread in SCHED_FIFO at ``priority`` (1-99) while the block runs;
    ``None`` or 0 leaves scheduling alone. Yields a note: what was done, or why not (the
    loop still runs, at normal priority)."""
    if not priority:
        yield "normal scheduling"
        return
    if not hasattr(os, "sched_setscheduler"):
        yield "SCHED_FIFO is not available on this OS; normal scheduling"
        return
    try:
        old_policy, old_param = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(priority)))
    except (OSError, ValueError) as exc:
        yield (
            f"SCHED_FIFO priority {priority} not granted ({getattr(exc, 'strerror', None) or exc}); "
            "normal scheduling. Fix: run with CAP_SYS_NICE or set an rtprio limit in /etc/security/limits.conf"
        )
        return
    try:
        yield f"SCHED_FIFO priority {priority}"
    finally:
        try:
            os.sched_setscheduler(0, old_policy, old_param)
        except OSError:
            pass
