"""An emulated serial-link microcontroller on a pseudo-terminal, speaking DFSL v1
(``firmware_cfg/serial_link.md``), so the serial-link transport can be tried and tested
without a board::

    with SerialMcuEmulator(n_channels=20) as mcu:
        transport = SerialLinkTransport(bus_config, port=mcu.port)   # mcu.port: "/dev/pts/N"

Model: each channel moves its position towards its target at ``max_speed`` (rad/s) while
enabled and not faulted; temperatures sit at ``ambient_c``. The board follows the
normative behaviour of the spec (targets outside limits rejected, ENABLE only after a
target, watchdog). ``target_log`` records every target the board *accepted* (time,
channel, rad) and ``rejected_log`` every target it refused, so tests can assert on the
board side that nothing outside the limits was ever driven.

Fault injection: :meth:`drop_replies`, :meth:`corrupt_replies`, :meth:`stall`,
:meth:`overheat`, :meth:`vanish` (the port disappears, like a USB cable pulled).
With ``baud`` set, replies are delayed by their bytes' time on the wire (10 bits/byte).
"""

from __future__ import annotations

import math
import os
import select
import threading
import time
import tty
from dataclasses import dataclass

from firmware_cfg import serial_link as sl

#: Firmware version the emulator reports.
FW_VERSION = (1, 0)


@dataclass
class _Channel:
    position: float = 0.0  # rad, servo side
    target: float | None = None
    enabled: bool = False
    fault: bool = False
    stalled: bool = False
    temperature: float = 30.0
    lower: int = -32767
    upper: int = 32767


@dataclass
class _Faults:
    drop: int = 0
    corrupt: int = 0


class SerialMcuEmulator:
    """A DFSL board on a pty. ``port`` is the path a client opens; start with ``with`` or
    :meth:`start`, stop with :meth:`stop` (idempotent)."""

    def __init__(
        self,
        n_channels: int = 20,
        *,
        name: str = "dfsl-emu",
        max_speed: float = 6.0,
        supply_mv: int = 11100,
        ambient_c: float = 30.0,
        baud: int | None = None,
        initial_positions: list[float] | None = None,
        version: int = sl.PROTOCOL_VERSION,
    ) -> None:
        if not 1 <= n_channels <= sl.MAX_CHANNELS:
            raise ValueError(f"n_channels must be 1..{sl.MAX_CHANNELS}")
        self.n_channels = n_channels
        self.name = name
        self.max_speed = max_speed
        self.supply_mv = supply_mv
        self.baud = baud
        self.overtemp_c = 80.0
        self.version = version
        self.channels = [_Channel(temperature=ambient_c) for _ in range(n_channels)]
        if initial_positions is not None:
            for ch, p in zip(self.channels, initial_positions):
                ch.position = float(p)
        self.target_log: list[tuple[float, int, float]] = []
        self.rejected_log: list[tuple[float, int, float]] = []
        self.frames_received: list[sl.Frame] = []
        self.crc_errors_seen = 0
        self.watchdog_trips = 0
        self._faults = _Faults()
        self._lock = threading.Lock()
        self._ready = False
        self._watchdog_ms = 0
        self._last_rx = time.monotonic()
        self._last_seq = 0
        self._boot = time.monotonic()
        self._decoder = sl.FrameDecoder()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._master: int | None = None
        self._slave: int | None = None
        self.port = ""

    # ------------------------------------------------------------------ life cycle
    def start(self) -> SerialMcuEmulator:
        master, slave = os.openpty()
        tty.setraw(slave)
        self._master, self._slave = master, slave
        self.port = os.ttyname(slave)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="serial-mcu-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = None

    def __enter__(self) -> SerialMcuEmulator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------ faults
    def drop_replies(self, n: int) -> None:
        """Swallow the next ``n`` replies."""
        with self._lock:
            self._faults.drop += n

    def corrupt_replies(self, n: int) -> None:
        """Flip a CRC bit in the next ``n`` replies."""
        with self._lock:
            self._faults.corrupt += n

    def stall(self, channel: int) -> None:
        """The channel's servo stops moving (mechanically blocked): its position freezes
        and, since it cannot reach its target, the board faults it and switches it off."""
        with self._lock:
            self.channels[channel].stalled = True

    def overheat(self, channel: int, temperature_c: float = 85.0) -> None:
        """The channel reports ``temperature_c`` and the board faults and switches it off."""
        with self._lock:
            ch = self.channels[channel]
            ch.temperature = temperature_c
            ch.fault = True
            ch.enabled = False

    def vanish(self) -> None:
        """The port disappears (USB cable pulled): the emulator closes its side at once."""
        self.stop()

    # ------------------------------------------------------------------ state views
    def positions(self) -> list[float]:
        with self._lock:
            return [c.position for c in self.channels]

    def enabled(self) -> list[bool]:
        with self._lock:
            return [c.enabled for c in self.channels]

    def limits_rad(self) -> list[tuple[float, float]]:
        with self._lock:
            return [(sl.cdeg_to_rad(c.lower), sl.cdeg_to_rad(c.upper)) for c in self.channels]

    # ------------------------------------------------------------------ the board
    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.is_set():
            master = self._master
            if master is None:
                return
            try:
                ready, _, _ = select.select([master], [], [], 0.002)
            except (OSError, ValueError):
                return
            now = time.monotonic()
            with self._lock:
                self._physics(now - last)
                self._check_watchdog(now)
            last = now
            if not ready:
                continue
            try:
                data = os.read(master, 4096)
            except OSError:
                continue  # the client closed its side; keep serving the next open
            if not data:
                continue
            with self._lock:
                before = self._decoder.crc_errors
                frames = self._decoder.feed(data)
                if self._decoder.crc_errors > before:
                    self.crc_errors_seen += self._decoder.crc_errors - before
                    self._reply(self._last_seq, sl.MsgType.ERROR, sl.Error(sl.ErrorCode.BAD_CRC).pack())
                for frame in frames:
                    self._last_rx = time.monotonic()
                    self._last_seq = frame.seq
                    self.frames_received.append(frame)
                    self._handle(frame)

    def _physics(self, dt: float) -> None:
        step = self.max_speed * dt
        for ch in self.channels:
            if ch.temperature >= self.overtemp_c:
                ch.fault, ch.enabled = True, False
            if not ch.enabled or ch.fault or ch.target is None:
                continue
            if ch.stalled:
                if abs(ch.target - ch.position) > 0.05:
                    ch.fault = True
                    ch.enabled = False
                continue
            err = ch.target - ch.position
            ch.position += max(-step, min(step, err))

    def _check_watchdog(self, now: float) -> None:
        if self._ready and self._watchdog_ms and (now - self._last_rx) * 1000.0 > self._watchdog_ms:
            if any(c.enabled for c in self.channels):
                for c in self.channels:
                    c.enabled = False
                self.watchdog_trips += 1
                self._reply(self._last_seq, sl.MsgType.ERROR, sl.Error(sl.ErrorCode.WATCHDOG_EXPIRED).pack())

    def _handle(self, frame: sl.Frame) -> None:
        seq, t, p = frame.seq, frame.type, frame.payload
        try:
            if t == sl.MsgType.HELLO:
                hello = sl.Hello.unpack(p)
                if hello.version != self.version:
                    return self._error(seq, sl.ErrorCode.BAD_VERSION)
                self._ready = True
                self._watchdog_ms = hello.watchdog_ms
                ack = sl.HelloAck(self.version, FW_VERSION[0], FW_VERSION[1], self.n_channels, self.name)
                return self._reply(seq, sl.MsgType.HELLO_ACK, ack.pack())
            if not self._ready:
                return self._error(seq, sl.ErrorCode.NOT_READY)
            if t == sl.MsgType.TARGETS:
                msg = sl.Targets.unpack(p)
                if msg.first + len(msg.cdeg) > self.n_channels:
                    return self._error(seq, sl.ErrorCode.BAD_CHANNEL, min(msg.first + len(msg.cdeg) - 1, 254))
                now = time.monotonic()
                for k, value in enumerate(msg.cdeg):
                    c = msg.first + k
                    ch = self.channels[c]
                    if not ch.lower <= value <= ch.upper:
                        self.rejected_log.append((now, c, sl.cdeg_to_rad(value)))
                        self._error(seq, sl.ErrorCode.TARGET_OUT_OF_LIMITS, c)
                        continue
                    ch.target = sl.cdeg_to_rad(value)
                    self.target_log.append((now, c, ch.target))
                return None
            if t == sl.MsgType.ENABLE:
                mask = sl.Enable.unpack(p).mask
                for c, ch in enumerate(self.channels):
                    on = bool(mask >> c & 1)
                    if on and ch.target is None:
                        continue  # spec rule 4: never drive a channel that has no target yet
                    if on:
                        ch.fault = False  # cleared by the host; a stalled servo faults again
                    ch.enabled = on
                return self._reply(seq, sl.MsgType.ACK, sl.Ack(t).pack())
            if t == sl.MsgType.HEARTBEAT:
                if p:
                    return self._error(seq, sl.ErrorCode.BAD_LENGTH)
                return self._reply(seq, sl.MsgType.HEARTBEAT_ACK, sl.HeartbeatAck(self._uptime()).pack())
            if t == sl.MsgType.TELEMETRY_REQ:
                if p:
                    return self._error(seq, sl.ErrorCode.BAD_LENGTH)
                return self._reply(seq, sl.MsgType.TELEMETRY, self._telemetry().pack())
            if t == sl.MsgType.SET_LIMITS:
                msg = sl.SetLimits.unpack(p)
                if msg.first + len(msg.limits) > self.n_channels:
                    return self._error(seq, sl.ErrorCode.BAD_CHANNEL, min(msg.first + len(msg.limits) - 1, 254))
                for k, (lo, hi) in enumerate(msg.limits):
                    ch = self.channels[msg.first + k]
                    ch.lower, ch.upper = lo, hi
                return self._reply(seq, sl.MsgType.ACK, sl.Ack(t).pack())
            return self._error(seq, sl.ErrorCode.UNKNOWN_TYPE)
        except Exception:  # a payload that does not unpack: the board says so, never crashes
            return self._error(seq, sl.ErrorCode.BAD_LENGTH)

    def _telemetry(self) -> sl.Telemetry:
        en = sum(1 << c for c, ch in enumerate(self.channels) if ch.enabled)
        fault = sum(1 << c for c, ch in enumerate(self.channels) if ch.fault)
        pos = tuple(max(-32767, min(32767, int(round(ch.position * 18000.0 / math.pi)))) for ch in self.channels)
        temp = tuple(max(-127, min(127, int(round(ch.temperature)))) for ch in self.channels)
        return sl.Telemetry(self._uptime(), self.supply_mv, en, fault, pos, temp)

    def _uptime(self) -> int:
        return int((time.monotonic() - self._boot) * 1000) & 0xFFFFFFFF

    def _error(self, seq: int, code: sl.ErrorCode, detail: int = 0xFF) -> None:
        self._reply(seq, sl.MsgType.ERROR, sl.Error(code, detail).pack())

    def _reply(self, seq: int, mtype: int, payload: bytes) -> None:
        if self._faults.drop:
            self._faults.drop -= 1
            return
        raw = bytearray(sl.encode(sl.Frame(seq, mtype, payload)))
        if self._faults.corrupt:
            self._faults.corrupt -= 1
            raw[-1] ^= 0x01
        if self.baud:
            time.sleep(len(raw) * 10.0 / self.baud)
        master = self._master
        if master is None:
            return
        try:
            os.write(master, bytes(raw))
        except OSError:
            pass
