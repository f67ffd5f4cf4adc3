"""The serial port under dynamixel-sdk: exclusive, low-latency, no busy waiting.

:class:`ExclusivePortHandler` subclasses the SDK's ``PortHandler`` (port layer only; the
SDK's packet code is untouched): the device is opened exclusively (pyserial ``flock`` and
TIOCEXCL), reply timeouts are sized from the latency timer in force instead of the SDK's
fixed 16 ms, writes and reads are single ``os.write`` / ``os.read`` calls, and a wait for a
reply sleeps in ``poll``. :func:`set_latency_timer` lowers an FTDI adapter's latency timer
to 1 ms where the sysfs file is writable. Why each of these matters: docs/dynamixel.md.
"""

from __future__ import annotations

import fcntl
import os
import select
import termios
from pathlib import Path

import dynamixel_sdk as sdk

SYSFS_USB_SERIAL = Path("/sys/bus/usb-serial/devices")


def set_latency_timer(port_name: str, ms: int = 1) -> tuple[int | None, str]:
    """Lower the USB-serial (FTDI) latency timer of ``port_name`` to ``ms``.

    Returns (the timer now in force in ms, or None when the device has none, a note)."""
    tty = Path(os.path.realpath(port_name)).name
    path = SYSFS_USB_SERIAL / tty / "latency_timer"
    if not path.exists():
        return None, f"{port_name}: no USB-serial latency timer (a pty or CDC-ACM device); nothing to set"
    try:
        current = int(path.read_text().strip())
    except (OSError, ValueError) as exc:
        return None, f"{path}: unreadable ({exc})"
    if current <= ms:
        return current, f"{path}: latency timer already {current} ms"
    try:
        path.write_text(str(ms))
        return ms, f"{path}: latency timer {current} → {ms} ms"
    except OSError as exc:
        return current, (
            f"{path}: latency timer stays {current} ms ({exc.strerror}); each reply may wait up to "
            f'{current} ms. Fix: a udev rule setting ATTR{{latency_timer}}="1", or run once as root'
        )


class ExclusivePortHandler(sdk.PortHandler):
    """The SDK's port with exclusive access and realistic reply timeouts.

    Only the port layer is changed: ``setupPort`` opens with ``exclusive=True`` and sets
    TIOCEXCL; ``setPacketTimeout`` uses ``latency_ms`` (the latency timer in force) instead
    of the SDK's fixed 16 ms: timeout = bytes · 10 bits / baud + 2 · latency + margin."""

    def __init__(self, port_name: str, latency_ms: float = 16.0, margin_ms: float = 3.0) -> None:
        super().__init__(port_name)
        self.latency_ms = latency_ms
        self.margin_ms = margin_ms
        self._poll: select.poll | None = None
        self._fd = -1

    def setupPort(self, cflag_baud):  # noqa: N802 - SDK naming
        import serial

        if self.is_open:
            self.closePort()
        self.ser = serial.Serial(
            port=self.port_name, baudrate=self.baudrate, bytesize=serial.EIGHTBITS, timeout=0, exclusive=True
        )
        try:
            fcntl.ioctl(self.ser.fileno(), termios.TIOCEXCL)
        except OSError:
            pass  # not a tty that supports it; the flock still guards
        try:
            self.ser.set_low_latency_mode(True)  # ASYNC_LOW_LATENCY for drivers that honour it
        except (ValueError, OSError, AttributeError):
            pass  # a pty (and some drivers) have no such flag; best effort
        self.is_open = True
        self.ser.reset_input_buffer()
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
        self._fd = self.ser.fileno()
        self._poll = select.poll()
        self._poll.register(self._fd, select.POLLIN)
        return True

    def closePort(self):  # noqa: N802 - SDK naming
        self._poll = None
        self._fd = -1
        super().closePort()

    def writePort(self, packet):  # noqa: N802 - SDK naming
        """Write ``packet`` (bytes, or the SDK's list of ints) with ``os.write`` on the
        port's descriptor: pyserial's ``write`` adds a ``select`` and a timeout object to
        every call. A partial write (a full kernel buffer) waits for room, at most 1 s;
        OS errors propagate (the bus turns them into a BridgeError)."""
        if not isinstance(packet, (bytes, bytearray)):
            packet = bytes(packet)
        total, fd = len(packet), self._fd
        try:
            done = os.write(fd, packet)
        except BlockingIOError:
            done = 0
        while done < total:
            if not select.select([], [fd], [], 1.0)[1]:
                raise OSError(f"{self.port_name}: write of {total} bytes stalled after {done}")
            try:
                done += os.write(fd, packet[done:])
            except BlockingIOError:
                pass
        return done

    def discardInput(self) -> None:  # noqa: N802 - SDK naming style
        """Drop received bytes not yet read (pyserial's ``reset_input_buffer``: TCIFLUSH)."""
        termios.tcflush(self._fd, termios.TCIFLUSH)

    def setPacketTimeout(self, packet_length):  # noqa: N802 - SDK naming
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + 2.0 * self.latency_ms + self.margin_ms

    def readPort(self, length):  # noqa: N802 - SDK naming
        """What has arrived, up to ``length`` bytes; when nothing has, first sleep in
        ``poll`` until a byte arrives or the packet timeout ends. The SDK's reply loops call
        this back to back: with the port's read timeout of 0 they would spin a whole core
        while the reply is on the wire, a core the rest of the machine (on a 2-core host:
        an emulator, the motion generator) needs."""
        if length <= 0 or self._poll is None:  # nothing asked for: nothing to wait for
            return self.ser.read(length) if length > 0 else b""
        data = self._read_now(length)
        if data:
            return data
        left_ms = self.packet_timeout - self.getTimeSinceStart()
        if left_ms > 0 and self._poll.poll(left_ms):
            data = self._read_now(length)
        return data

    def _read_now(self, length: int) -> bytes:
        """What has arrived, up to ``length`` bytes, without waiting: one ``os.read`` on the
        non-blocking descriptor (pyserial's ``read`` puts a ``select`` before every read).
        The port is in raw mode with VMIN = VTIME = 0, so an empty read means either nothing
        has arrived or the device is gone; only then is ``poll`` asked, and a port that
        reports readiness yet reads empty twice is gone: an OSError, as pyserial raises."""
        fd = self._fd
        try:
            data = os.read(fd, length)
        except BlockingIOError:
            data = b""
        if data or not self._poll.poll(0):
            return data
        try:
            data = os.read(fd, length)  # bytes that arrived after the first read
        except BlockingIOError:
            data = b""
        if not data:
            raise OSError(f"{self.port_name}: the device reports readiness to read but returns no data (disconnected?)")
        return data
