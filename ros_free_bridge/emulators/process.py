"""A Dynamixel bus emulator in a child process (its own interpreter and GIL).

In-process, the emulator's Python competes with the code under test for the GIL, which
inflates timing figures; benchmarks and users who want a bus that behaves like separate
hardware run it here instead::

    with EmulatorProcess(baud=2_000_000, wire_timing=True) as emu:
        transport = DynamixelTransport(bus, port=emu.port)

Only the port path crosses the process boundary; fault injection and goal records need the
in-process :class:`~ros_free_bridge.emulators.DynamixelBusEmulator`.
"""

from __future__ import annotations

import multiprocessing as mp
import os


def _child(servos, baud: int, protocol: int, wire_timing: bool, nice: int, conn) -> None:
    from ros_free_bridge.emulators import DynamixelBusEmulator

    if nice:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
        except OSError:
            pass  # raising priority needs privileges; run at the default
    emu = DynamixelBusEmulator(servos=servos, baud=baud, protocol=protocol, wire_timing=wire_timing,
                               return_delay_us=0.0).start()
    conn.send(emu.port_path)
    conn.recv()  # wait for "stop"
    emu.stop()


class EmulatorProcess:
    """``servos``: IDs or (id, model) pairs (default IDs 1-20, XM430-W350)."""

    def __init__(self, servos=range(1, 21), baud: int = 2_000_000, protocol: int = 2, wire_timing: bool = True,
                 nice: int = 0):
        ctx = mp.get_context("fork")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_child, args=(list(servos), baud, protocol, wire_timing, nice, child),
                                 daemon=True)
        self._proc.start()
        self.port: str = self._conn.recv()

    def stop(self) -> None:
        if self._proc.is_alive():
            self._conn.send("stop")
            self._proc.join(timeout=5)
            if self._proc.is_alive():
                self._proc.kill()

    def __enter__(self) -> "EmulatorProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
