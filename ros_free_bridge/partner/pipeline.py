"""The thread between the actor source and the control loop's target buffer.

:class:`PartnerPipeline` polls the source, runs a partner core (in-process
:class:`~ros_free_bridge.partner.core.PartnerCore`, or the child process's handle
:class:`~ros_free_bridge.partner.process.GeneratorProcess`) and pushes
:class:`~ros_free_bridge.control.targets.TargetFrame` s. It never touches the transport: a slow
or failed stage can only starve the loop (which then holds and stops), never block it.
"""

from __future__ import annotations

import sys
import threading
import time

import numpy as np

from ros_free_bridge.control.targets import TargetBuffer, TargetFrame
from ros_free_bridge.partner.core import PartnerCore, PartnerTarget


class PartnerPipeline:
    """Run source → partner core in a thread, feeding ``buffer``.

    ``start_event``: wait for it (the loop's ``ready``) before starting the actor clock;
    actor frames that arrive earlier (a live stream) are discarded. ``reactor`` None makes
    the robot retarget the actor itself (imitation). ``core``: anything with the core's
    ``feed`` / ``finish_stream`` / ``idle`` / ``close`` (e.g. the generator process's handle)
    instead of a :class:`PartnerCore` built from ``reactor`` and ``retarget``. ``record``: keep
    every actor frame and every partner pose given to the retargeter (``actor_positions``,
    ``partner_positions``, lists of (22, 3) arrays) for videos and reports.
    ``on_event(kind, **info)``: the core's events (e.g. ``generator_behind``), for telemetry.
    """

    def __init__(
        self,
        source,
        reactor,
        retarget,
        buffer: TargetBuffer,
        start_event: threading.Event | None = None,
        record: bool = False,
        on_event=None,
        core=None,
    ):
        self.source = source
        self.core = core if core is not None else PartnerCore(reactor, retarget)
        self.buffer = buffer
        self.start_event = start_event
        self.on_event = on_event
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="partner-pipeline", daemon=True)
        self.frames_in = 0
        self.frames_out = 0  #: partner frames sent to the loop ...
        self.settle_frames = 0  #: ... and frames of the robot's return to its stance after them
        self.events: list[dict] = []
        self.record = record
        self.actor_positions: list[np.ndarray] = []
        self.actor_arrivals: list[float] = []  #: record: monotonic arrival of each actor frame
        self.partner_positions: list[np.ndarray] = []
        self.partner_contacts: list[np.ndarray | None] = []  #: record: the contacts the retargeter got

    @property
    def frames_dropped(self) -> int:
        """Partner frames skipped (held) to keep up with the actor's clock."""
        return self.core.frames_dropped

    def start(self) -> None:
        if isinstance(self.core, PartnerCore) and self.core.reactor is not None:
            # torch runs in this thread: short GIL slices so that the control-loop thread
            # wakes on time while torch, numpy and CasADi work here
            sys.setswitchinterval(0.0005)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def _run(self) -> None:
        try:
            if not self._wait_for_start():
                return
            self.source.start()
            while not self._stop.is_set():
                frames = self.source.poll()
                self.frames_in += len(frames)
                if self.record:
                    self.actor_positions += [f.positions for f in frames]
                    self.actor_arrivals += [f.arrival for f in frames]
                targets, events = self.core.feed(frames)
                self._emit(targets, events)
                if getattr(self.source, "finished", False):
                    self._finish()
                    break
                if not frames and not getattr(self.core, "backlog", False):
                    self.core.idle(self._poll_wait())
        except BaseException as exc:  # noqa: BLE001 - handed to the control loop, which stops safely
            self.buffer.close(exc)
        else:
            self.buffer.close()  # before the core's close, which may wait for a process to exit
        finally:
            self.core.close()

    def _wait_for_start(self) -> bool:
        """Wait for ``start_event``, dropping what a live stream sends meanwhile; False: stopped first."""
        while self.start_event is not None and not self.start_event.wait(0.01):
            if self._stop.is_set():
                return False
            if self.source.live:
                self.source.poll()  # drop what a live stream sends before the robot is ready
        return True

    def _finish(self) -> None:
        """The source ended: emit the rest of the partner, batch by batch, unless stopped."""
        for targets, events in self.core.finish_stream():
            self._emit(targets, events)
            if self._stop.is_set():
                break

    POLL_S = 0.002  #: longest wait between polls of the actor source

    def _poll_wait(self) -> float:
        """Seconds to wait before polling the source again: ``POLL_S``, or less when the
        source says when its next frame is due (a replay: its frames are stamped with their
        due time, so a late poll would count in the latency)."""
        due = getattr(self.source, "next_due", None)
        due = due() if due is not None else None
        if due is None:
            return self.POLL_S
        return min(self.POLL_S, max(0.0, due - time.monotonic()))

    def _emit(self, targets: list[PartnerTarget], events: list[dict]) -> None:
        for e in events:
            self.events.append(e)
            if self.on_event is not None:
                self.on_event(**e)
        for t in targets:
            self.buffer.push(TargetFrame(t.index, t.q, t.arrival, t.actor_frame, t.gen_latency, t.rt_latency))
            if t.settle:  # the robot's return to its stance: no partner pose
                self.settle_frames += 1
                continue
            if self.record:
                self.partner_positions.append(t.positions)
                self.partner_contacts.append(t.contacts)
            self.frames_out += 1
