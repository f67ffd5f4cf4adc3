"""A Dynamixel bus emulator in a child process (its own interpreter and GIL).

In-process, the emulator's Python competes with the code under test for the GIL, which
inflates timing figures; benchmarks and users who want a bus that behaves like separate
hardware run it here instead::

    with EmulatorProcess(baud=2_000_000, wire_timing=True) as emu:
        transport = DynamixelTransport(bus, port=emu.port)

Only the port path, the allowed goal ranges and, on :meth:`EmulatorProcess.stop`, the counts
of goal writes and of goals outside the allowed ranges cross the process boundary; fault
injection and full goal records need the in-process
:class:`~ros_free_bridge.emulators.DynamixelBusEmulator`.
"""

from __future__ import annotations

import multiprocessing as mp
import os


def _child(servos, baud: int, protocol: int, wire_timing: bool, nice: int, allowed, conn, realtime: int = 0,
           parent: int | None = None, pdeathsig: bool = False) -> None:
    import signal

    from ros_free_bridge.emulators import DynamixelBusEmulator
    from ros_free_bridge.lifeline import die_with_parent

    if parent is not None:
        die_with_parent(parent, pdeathsig=pdeathsig)  # never outlive the bridge, even after its SIGKILL
    # A Ctrl-C reaches the whole process group: the bus must stay up while the bridge applies
    # its e-stop policy (real servos do not hear the terminal either); the parent stops it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    if nice:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
        except OSError:
            pass  # raising priority needs privileges; run at the default
    if realtime:
        try:  # before the reader thread starts, which inherits the policy
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(realtime))
        except (OSError, AttributeError):
            pass  # needs CAP_SYS_NICE; run at normal priority
    emu = DynamixelBusEmulator(servos=servos, baud=baud, protocol=protocol, wire_timing=wire_timing,
                               return_delay_us=0.0).start()
    for servo_id, (lo, hi) in (allowed or {}).items():
        emu.allowed_range(servo_id, lo, hi)
    conn.send(emu.port_path)
    conn.recv()  # wait for "stop"
    emu.stop()
    conn.send({"goal_writes": sum(len(v) for v in emu.goal_history.values()), "violations": len(emu.violations)})


class EmulatorProcess:
    """``servos``: IDs or (id, model) pairs (default IDs 1-20, XM430-W350). ``allowed``:
    {servo id: (lo, hi) ticks}; goals outside are counted as violations. ``realtime``: a
    SCHED_FIFO priority for the emulator (1-99; needs privileges, else ignored), so that on
    a busy machine it answers like hardware, which no scheduler delays; 0: normal."""

    def __init__(self, servos=range(1, 21), baud: int = 2_000_000, protocol: int = 2, wire_timing: bool = True,
                 nice: int = 0, allowed: dict | None = None, realtime: int = 0):
        from ros_free_bridge.lifeline import parent_thread_lives_on

        ctx = mp.get_context("fork")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_child, args=(list(servos), baud, protocol, wire_timing, nice, allowed, child,
                                                      realtime, os.getpid(), parent_thread_lives_on()), daemon=True)
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

    def __enter__(self) -> "EmulatorProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
