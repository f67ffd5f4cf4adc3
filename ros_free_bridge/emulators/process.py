"""A Dynamixel bus emulator in a child process (its own interpreter and GIL).

In-process, the emulator's Python competes with the code under test for the GIL and
inflates timing figures; :class:`EmulatorProcess` runs it like separate hardware. Only the
port path, the allowed goal ranges and, on :meth:`EmulatorProcess.stop`, the counts of goal
writes and of violations cross the process boundary; fault injection and goal records need
the in-process :class:`~ros_free_bridge.emulators.DynamixelBusEmulator`.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from dataclasses import dataclass


@dataclass(frozen=True)
class _BusPlan:
    """The bus the child emulates: units as ``DynamixelBusEmulator`` takes them, baud in
    bit/s, protocol 1 or 2, and {servo id: (lo, hi) ticks} of allowed goals."""

    servos: list
    baud: int
    protocol: int
    wire_timing: bool
    allowed: dict | None


@dataclass(frozen=True)
class _ProcessSettings:
    """How the child runs: ``nice`` increment, SCHED_FIFO ``realtime`` priority (0: normal),
    and the ``parent`` pid it must not outlive (``pdeathsig``: the starting thread lives as
    long as the parent, so the kernel's parent-death signal may be used; see lifeline)."""

    nice: int = 0
    realtime: int = 0
    parent: int | None = None
    pdeathsig: bool = False


def _child(bus: _BusPlan, settings: _ProcessSettings, conn) -> None:
    """The child's main: serve the bus until the parent says "stop", then send the counts."""
    _settle_child(settings)
    from ros_free_bridge.emulators import DynamixelBusEmulator

    emu = DynamixelBusEmulator(
        servos=bus.servos, baud=bus.baud, protocol=bus.protocol, wire_timing=bus.wire_timing, return_delay_us=0.0
    ).start()
    for servo_id, (lo, hi) in (bus.allowed or {}).items():
        emu.allowed_range(servo_id, lo, hi)
    conn.send(emu.port_path)
    conn.recv()  # wait for "stop"
    emu.stop()
    conn.send({"goal_writes": sum(len(v) for v in emu.goal_history.values()), "violations": len(emu.violations)})


def _settle_child(settings: _ProcessSettings) -> None:
    """Tie the child to its parent, ignore the terminal's Ctrl-C and set its scheduling
    (before the emulator's reader thread starts, which inherits the policy)."""
    import signal

    from ros_free_bridge.lifeline import die_with_parent

    if settings.parent is not None:
        # never outlive the bridge, even after its SIGKILL
        die_with_parent(settings.parent, pdeathsig=settings.pdeathsig)
    # A Ctrl-C reaches the whole process group: the bus must stay up while the bridge applies
    # its e-stop policy (real servos do not hear the terminal either); the parent stops it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if settings.nice:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, settings.nice)
        except OSError:
            pass  # raising priority needs privileges; run at the default
    if settings.realtime:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(settings.realtime))
        except (OSError, AttributeError):
            pass  # needs CAP_SYS_NICE; run at normal priority


class EmulatorProcess:
    """``servos``: IDs or (id, model) pairs (default IDs 1-20, XM430-W350). ``allowed``:
    {servo id: (lo, hi) ticks}; goals outside are counted as violations. ``realtime``: a
    SCHED_FIFO priority for the emulator (1-99; needs privileges, else ignored), so that on
    a busy machine it answers like hardware, which no scheduler delays; 0: normal.

    Use: ``with EmulatorProcess(baud=2_000_000) as emu: DynamixelTransport(bus, port=emu.port)``."""

    def __init__(
        self,
        servos=range(1, 21),
        baud: int = 2_000_000,
        protocol: int = 2,
        wire_timing: bool = True,
        nice: int = 0,
        allowed: dict | None = None,
        realtime: int = 0,
    ):
        from ros_free_bridge.lifeline import parent_thread_lives_on

        bus = _BusPlan(list(servos), baud, protocol, wire_timing, allowed)
        settings = _ProcessSettings(nice, realtime, os.getpid(), parent_thread_lives_on())
        ctx = mp.get_context("fork")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_child, args=(bus, settings, child), daemon=True)
        self._proc.start()
        self.port: str = self._conn.recv()
        self.stats: dict = {}

    def stop(self) -> dict:
        """Stop the emulator; returns (and keeps in ``stats``) its goal-write and violation counts."""
        if self._proc.is_alive():
            self._conn.send("stop")
            if self._conn.poll(5):
                self.stats = self._conn.recv()
            self._proc.join(timeout=5)
            if self._proc.is_alive():
                self._proc.kill()
        return self.stats

    def __enter__(self) -> EmulatorProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
