"""Dynamixel transport over the real ``dynamixel_sdk`` (protocol 2.0 and 1.0).

Per control tick (protocol 2.0):

- ``write_goal``: one SYNC_WRITE of Goal Position to every servo (broadcast, no reply);
- ``read_state``: one FAST_SYNC_READ of Present Position (falls back to the SDK's
  GroupSyncRead when the servos do not answer the fast form), then the *slow* fields of
  ``slow_per_cycle`` servos, round robin: one individual READ of the contiguous block
  Present Current .. Present Temperature. Individual reads, because the SDK's group reads
  drop each servo's status error byte and with it the hardware-alert bit (0x80); when
  that bit is set the transport reads Hardware Error Status (register 70), decodes it and
  recovers by policy (:class:`RecoveryPolicy`).

Hot path (protocol 2.0, every tick): the SYNC_WRITE packet is packed with ``struct`` and its
CRC taken (fastcrc, compiled); the FAST_SYNC_READ / FAST_BULK_READ reply is checked (its
CRC) and read with one ``struct`` unpack
(:mod:`ros_free_bridge.dynamixel_codec`, byte for byte the packets of the SDK's
GroupSyncWrite / GroupSyncRead.fastSyncRead / GroupBulkRead, tested); goal limits, ticks and
positions are converted element by element with Python floats (the numpy forms' operations,
same values, tested). For 20 servos a control tick's cost is the number of interpreter and
numpy dispatch steps, not bytes: on a 2-core VM this halved the host time per split-phase
cycle (``bench/servo_bus.py``). Port reads and writes are single ``os.read`` / ``os.write``
calls on the SDK port's descriptor (pyserial adds a ``select`` to each). The fast reply
also keeps each servo's status error byte, so a hardware alert is seen the same tick.
Everything else (PING, READ, WRITE, REBOOT, the SYNC_READ fallback) is the SDK's.

Split-phase cycle (:meth:`DynamixelTransport.pipeline`, switched on by the control loop):
``write_goal`` sends SYNC_WRITE and the read request and returns; the next ``read_state``
takes the reply that arrived meanwhile. The request is a FAST_BULK_READ of every Present
Position plus one servo's status block (round robin; :class:`FastBulkReadDecoder`), so a
cycle is two packets out and one reply. A loop tick then never waits for the bus; the
positions it reads were sampled one tick earlier (``JointState.stamp``).

Protocol 1.0 buses (AX/MX) have no sync read: positions are read servo by servo, and the
status error byte itself carries the hardware bits.

Units: joint side rad, rad/s, N·m (current × stall torque / stall current, a linear
torque-constant estimate), °C, V. Mapping, per servo (``firmware_cfg.config``)::

    servo_rad = direction · joint_rad + zero_offset
    tick      = center_tick + servo_rad · ticks_per_turn / 2π      (ServoModel.rad_to_ticks)

Port handling: the SDK's ``PortHandler`` is subclassed (port layer only; packet code is
untouched) to open the device with ``exclusive=True`` (pyserial ``flock``) plus
``TIOCEXCL``, and to size reply timeouts from the real latency instead of the SDK's fixed
16 ms. On Linux the FTDI latency timer is set to 1 ms through
``/sys/bus/usb-serial/devices/<tty>/latency_timer`` when writable (needs root or a udev
rule, e.g. ``ACTION=="add", SUBSYSTEM=="usb-serial", DRIVERS=="ftdi_sio",
ATTR{latency_timer}="1"``); a pty or a CDC-ACM device has no such file and is skipped.
While a reply is on the wire, ``readPort`` sleeps in ``poll`` instead of returning nothing at
once (the SDK's reply loops would otherwise spin a core).
Every SDK call resets the SDK's ``is_using`` flag in ``finally``, and the port is closed
in ``finally`` on any failure, so it is never left "in use".

Safety: torque is switched on only after Goal Position = Present Position; ``close``,
errors and interpreter exit apply the stop policy ('hold': keep the present position
with torque on; 'limp': torque off). For a crash no hook survives (SIGKILL, a hung
process), the config's ``bus_watchdog_ms`` arms each servo's Bus Watchdog(98): a servo
that hears nothing for that long stops where it is. The transport clears a tripped
watchdog (0, goal = present, period again) when its status reads find one, and at
``open``. Every failure is a :class:`BridgeError` naming the servo ID, its joint and
what happened.
"""

from __future__ import annotations

import atexit
import fcntl
import math
import operator
import os
import select
import termios
import time
import weakref
from dataclasses import dataclass, field
from pathlib import Path

import dynamixel_sdk as sdk
import numpy as np

from firmware_cfg.config import BusConfig, ServoConfig
from firmware_cfg.servo_models import _RPM_TO_RAD_S, Register, ServoModel, load_servo_model
from ros_free_bridge.dynamixel_codec import FastBulkReadDecoder, FastSyncReadDecoder, PacketError, SyncWriteEncoder
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.transports.base import STOP_POLICIES, JointState

#: Hardware Error Status (register 70, X series) bits → names.
HW_ERROR_BITS = {
    0x01: "input voltage",
    0x04: "overheating",
    0x08: "motor encoder",
    0x10: "electrical shock",
    0x20: "overload",
}
#: Protocol 1.0 status error byte bits → names.
P1_ERROR_BITS = {0x01: "input voltage", 0x02: "angle limit", 0x04: "overheating", 0x08: "range",
                 0x10: "checksum", 0x20: "overload", 0x40: "instruction"}
P1_HARDWARE_MASK = 0x01 | 0x04 | 0x20
ALERT_BIT = 0x80
_NONE: frozenset[int] = frozenset()
#: Profile Acceleration unit of X-series servos: 214.577 rev/min² in rad/s².
ACCEL_UNIT_RAD_S2 = 214.577 * 2.0 * math.pi / 3600.0
SYSFS_USB_SERIAL = Path("/sys/bus/usb-serial/devices")


def decode_hardware_error(bits: int, protocol: int = 2) -> list[str]:
    """Hardware Error Status bits (protocol 2.0) or status error bits (1.0) → names."""
    table = HW_ERROR_BITS if protocol == 2 else P1_ERROR_BITS
    names = [name for bit, name in table.items() if bits & bit]
    unknown = bits & ~sum(table)
    if unknown:
        names.append(f"unknown bits 0x{unknown:02X}")
    return names


@dataclass(frozen=True)
class RecoveryPolicy:
    """What to do on a hardware alert. ``reboot_on``: the decoded error names for which
    the servo is rebooted automatically (then settings re-applied, goal = present, torque
    back on if it was on); at most ``max_reboots`` per servo per session. Overheating is
    not in the default set: a hot servo must cool down, not restart."""

    reboot: bool = True
    reboot_on: frozenset[str] = frozenset({"overload", "electrical shock", "input voltage"})
    max_reboots: int = 3
    reboot_wait_s: float = 2.0


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
        return current, (f"{path}: latency timer stays {current} ms ({exc.strerror}); each reply may wait up to "
                         f"{current} ms. Fix: a udev rule setting ATTR{{latency_timer}}=\"1\", or run once as root")


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
        self.ser = serial.Serial(port=self.port_name, baudrate=self.baudrate, bytesize=serial.EIGHTBITS,
                                 timeout=0, exclusive=True)
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
            raise OSError(f"{self.port_name}: the device reports readiness to read but returns no data "
                          "(disconnected?)")
        return data


def servo_register_settings(servo: ServoConfig, model: ServoModel) -> dict[str, int]:
    """The control-table values a servo's config implies, register name → raw value.

    EEPROM: return delay, temperature and voltage limits, position limits (the joint
    limits mapped to ticks, rounded inwards). RAM: status return level (EEPROM on 1.0),
    PID gains, profile velocity/acceleration, bus watchdog. Registers a model lacks are
    skipped."""
    out: dict[str, int] = {}

    def put(name: str, value: int | None) -> None:
        if value is not None and model.has(name):
            out[name] = int(value)

    put("return_delay_time", None if servo.return_delay_us is None else round(servo.return_delay_us / model.return_delay_us))
    put("temperature_limit", servo.temperature_limit_c)
    if servo.voltage_limits_v is not None:
        put("min_voltage_limit", math.ceil(servo.voltage_limits_v[0] / model.voltage_v - 1e-9))
        put("max_voltage_limit", math.floor(servo.voltage_limits_v[1] / model.voltage_v + 1e-9))
    lo_t, hi_t = servo_tick_limits(servo, model)
    if model.has("min_position_limit"):
        put("min_position_limit", lo_t)
        put("max_position_limit", hi_t)
    elif model.has("cw_angle_limit"):
        put("cw_angle_limit", lo_t)
        put("ccw_angle_limit", hi_t)
    put("status_return_level", servo.status_return_level)
    if servo.pid is not None:
        if model.has("position_p_gain"):
            put("position_p_gain", servo.pid.p)
            put("position_i_gain", servo.pid.i)
            put("position_d_gain", servo.pid.d)
        else:
            for name, v in (("p_gain", servo.pid.p), ("i_gain", servo.pid.i), ("d_gain", servo.pid.d)):
                if model.has(name):
                    rng = model.register(name).range
                    put(name, min(v, rng[1]) if rng else v)
    if servo.profile_velocity is not None and model.has("profile_velocity"):
        put("profile_velocity", model.rad_s_to_velocity(servo.profile_velocity))
    if servo.profile_acceleration is not None and model.has("profile_acceleration"):
        put("profile_acceleration", round(servo.profile_acceleration / ACCEL_UNIT_RAD_S2))
    if servo.bus_watchdog_ms is not None:
        put("bus_watchdog", servo.bus_watchdog_ms // 20)
    return out


def servo_tick_limits(servo: ServoConfig, model: ServoModel) -> tuple[int, int]:
    """The joint limits in the servo's ticks, rounded inwards (never wider than the config)."""
    lo, hi = servo.servo_limits()
    c, k = model.position.center_tick, model.ticks_per_rad
    return (max(model.position.min_tick, math.ceil(c + lo * k - 1e-6)),
            min(model.position.max_tick, math.floor(c + hi * k + 1e-6)))


class DynamixelBus:
    """One open bus: the SDK port + packet handler with bounded retries and errors that
    name the servo. Used by the transport and by the ``servo`` commands.

    ``names``: servo ID → a label for messages (the joint name)."""

    def __init__(self, port: str, baud: int, protocol: float = 2.0, *, retries: int = 2,
                 latency_ms: float = 16.0, names: dict[int, str] | None = None) -> None:
        self.port_name = port
        self.baud = baud
        self.protocol = float(protocol)
        self.retries = retries
        self.names = dict(names or {})
        self.latency_note = ""
        self._latency_ms = latency_ms
        self.port: ExclusivePortHandler | None = None
        self.ph = sdk.PacketHandler(self.protocol)
        #: Called (once, then cleared) before the next transfer: a transport that left a
        #: request's reply on the wire sets it, so nothing is sent over that reply (the bus
        #: is half duplex). See DynamixelTransport.pipeline.
        self.before_io = None

    # ------------------------------------------------------------------ life cycle
    def open(self) -> None:
        if self.port is not None:
            return
        timer, self.latency_note = set_latency_timer(self.port_name, 1)
        port = ExclusivePortHandler(self.port_name, latency_ms=timer if timer is not None else self._latency_ms)
        if port.getCFlagBaud(self.baud) <= 0:
            raise BridgeError(f"Dynamixel bus {self.port_name}: baud {self.baud} is not one the SDK can set")
        port.baudrate = self.baud
        try:
            port.setBaudRate(self.baud)
        except Exception as exc:  # serial.SerialException, OSError
            try:
                if port.ser is not None:
                    port.ser.close()
            except Exception:
                pass
            text = str(exc)
            hint = ("another program holds the port; close it (e.g. a second bridge, Dynamixel Wizard)"
                    if "lock" in text.lower() or "busy" in text.lower() or "resource temporarily" in text.lower()
                    else "check the cable and the port name (ls /dev/ttyUSB* /dev/ttyACM*)")
            raise BridgeError(f"Dynamixel bus {self.port_name}: cannot open ({text}); {hint}") from None
        self.port = port

    def close(self) -> None:
        port, self.port = self.port, None
        self.before_io = None
        if port is not None:
            try:
                port.is_using = False
                if port.ser is not None:
                    port.closePort()
            except Exception:
                pass

    def __enter__(self) -> "DynamixelBus":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ primitives
    def label(self, sid: int) -> str:
        name = self.names.get(sid)
        return f"servo ID {sid}" + (f" ({name})" if name else "")

    def call(self, fn, *args, malformed=None):
        """Run one SDK call; the port's ``is_using`` flag is cleared whatever happens and
        OS-level failures (the port vanished) become BridgeError. With ``malformed`` given,
        an exception inside the SDK's reply parsing (e.g. an IndexError on a truncated
        fast-sync-read reply) returns ``malformed`` instead, so it counts as a failed try."""
        if self.port is None:
            raise BridgeError(f"Dynamixel bus {self.port_name}: not open; call open() first")
        if self.before_io is not None:
            settle, self.before_io = self.before_io, None
            settle()
        try:
            return fn(self.port, *args)
        except BridgeError:
            raise
        except (IndexError, KeyError) as exc:
            if malformed is not None:
                return malformed
            raise BridgeError(f"Dynamixel bus {self.port_name}: malformed reply during {getattr(fn, '__name__', 'a call')} "
                              f"({type(exc).__name__}: {exc}); check for noise or a wrong baud rate") from None
        except Exception as exc:  # serial.SerialException, OSError, TypeError from a dead fd
            raise BridgeError(f"Dynamixel bus {self.port_name}: port failed during {getattr(fn, '__name__', 'a call')} "
                              f"({type(exc).__name__}: {exc}); the adapter was unplugged or lost power") from None
        finally:
            if self.port is not None:
                self.port.is_using = False

    def _comm(self, result: int) -> str:
        return self.ph.getTxRxResult(result).replace("[TxRxResult] ", "").rstrip("!")

    def _error_text(self, error: int) -> str:
        if self.protocol == 2.0:
            return self.ph.getRxPacketError(error & ~ALERT_BIT).replace("[RxPacketError] ", "").rstrip("!")
        return ", ".join(decode_hardware_error(error, 1))

    def ping(self, sid: int, retries: int | None = None) -> int:
        """Model number of ``sid``; BridgeError after the retries."""
        last = 0
        for _ in range((self.retries if retries is None else retries) + 1):
            model, result, error = self.call(self.ph.ping, sid)
            if result == sdk.COMM_SUCCESS:
                return model
            last = result
        raise BridgeError(f"{self.label(sid)} on {self.port_name}: no answer to PING after "
                          f"{(self.retries if retries is None else retries) + 1} tries ({self._comm(last)}); "
                          f"check its power, ID and baud {self.baud}")

    def read_raw(self, sid: int, address: int, length: int, what: str = "") -> tuple[bytes, int]:
        """Bytes [address, address+length) of ``sid`` and the status error byte."""
        last = 0
        for _ in range(self.retries + 1):
            data, result, error = self.call(self.ph.readTxRx, sid, address, length)
            if result == sdk.COMM_SUCCESS and len(data) == length:
                if self.protocol == 2.0 and error & 0x7F:
                    raise BridgeError(f"{self.label(sid)}: READ {what or address} refused: {self._error_text(error)}")
                return bytes(data), error
            last = result
        raise BridgeError(f"{self.label(sid)} on {self.port_name}: READ {what or f'address {address}'} failed after "
                          f"{self.retries + 1} tries ({self._comm(last)})")

    def read(self, sid: int, reg: Register) -> tuple[int, int]:
        """(value, status error byte) of one register."""
        data, error = self.read_raw(sid, reg.address, reg.size, reg.name)
        return reg.decode(data), error

    def write(self, sid: int, reg: Register, value: int) -> int:
        """Write one register, waiting for the status; returns the status error byte.
        A refused write (range, access, EEPROM locked by torque) is a BridgeError."""
        data = list(reg.encode(value))
        last = 0
        for _ in range(self.retries + 1):
            result, error = self.call(self.ph.writeTxRx, sid, reg.address, reg.size, data)
            if result == sdk.COMM_SUCCESS:
                refused = (error & 0x7F) if self.protocol == 2.0 else (error & ~P1_HARDWARE_MASK & 0x7F)
                if refused:
                    hint = " (EEPROM is locked while torque is on; switch torque off first)" if reg.eeprom else ""
                    raise BridgeError(f"{self.label(sid)}: WRITE {reg.name}={value} refused: {self._error_text(error)}{hint}")
                return error
            last = result
        raise BridgeError(f"{self.label(sid)} on {self.port_name}: WRITE {reg.name}={value} failed after "
                          f"{self.retries + 1} tries ({self._comm(last)})")

    def reboot(self, sid: int) -> None:
        if self.protocol != 2.0:
            raise BridgeError(f"{self.label(sid)}: REBOOT exists on protocol 2.0 only; power-cycle the servo")
        last = 0
        for _ in range(self.retries + 1):
            result, error = self.call(self.ph.reboot, sid)
            if result == sdk.COMM_SUCCESS:
                return
            last = result
        raise BridgeError(f"{self.label(sid)}: REBOOT failed after {self.retries + 1} tries ({self._comm(last)})")

    def sync_write(self, reg: Register, values: dict[int, int]) -> None:
        """One GroupSyncWrite of ``reg`` (broadcast: no reply to wait for)."""
        group = sdk.GroupSyncWrite(self.port, self.ph, reg.address, reg.size)
        for sid, v in values.items():
            group.addParam(sid, list(reg.encode(v)))
        result = self.call(lambda port: group.txPacket())
        if result != sdk.COMM_SUCCESS:
            raise BridgeError(f"Dynamixel bus {self.port_name}: SYNC_WRITE {reg.name} failed ({self._comm(result)})")


@dataclass
class _Servo:
    cfg: ServoConfig
    model: ServoModel
    goal: Register
    present: Register
    torque: Register
    settings: dict[str, int]
    reboots: int = 0


@dataclass
class DynamixelStats:
    """Counters for diagnostics: cycles, retries, fallbacks and recoveries."""

    cycles: int = 0
    read_retries: int = 0
    alerts: int = 0
    reboots: int = 0
    watchdog_trips: int = 0
    fast_sync_read: bool = True
    notes: list[str] = field(default_factory=list)


class DynamixelTransport:
    """:class:`~ros_free_bridge.transports.base.Transport` for one Dynamixel bus of a
    robot's hardware config. Use as a context manager or open()/close()."""

    def __init__(self, bus: BusConfig, *, port: str | None = None, joint_names: tuple[str, ...] | None = None,
                 stop_policy: str = "hold", recovery: RecoveryPolicy | None = None, retries: int = 2,
                 slow_per_cycle: int = 1, apply_settings: bool = True, latency_ms: float = 16.0) -> None:
        if bus.protocol not in ("1.0", "2.0"):
            raise BridgeError(f"bus {bus.name!r} uses {bus.protocol}; the Dynamixel transport needs protocol 1.0 or 2.0")
        if stop_policy not in STOP_POLICIES:
            raise BridgeError(f"stop_policy {stop_policy!r} is not one of {STOP_POLICIES}")
        by_joint = {s.joint: s for s in bus.servos}
        names = tuple(joint_names) if joint_names is not None else tuple(s.joint for s in bus.servos)
        missing = [j for j in names if j not in by_joint]
        if missing:
            raise BridgeError(f"Dynamixel bus {bus.name!r}: joints {missing} have no servo in the hardware config")
        self.joint_names = names
        self.bus_cfg = bus
        self.stop_policy = stop_policy
        self.recovery = recovery or RecoveryPolicy()
        self.slow_per_cycle = max(0, int(slow_per_cycle))
        self.apply_settings = apply_settings
        self.stats = DynamixelStats()
        self.servos: list[_Servo] = []
        for j in names:
            s = by_joint[j]
            m = load_servo_model(s.model)
            self.servos.append(_Servo(s, m, m.register("goal_position"), m.register("present_position"),
                                      m.register("torque_enable"), servo_register_settings(s, m)))
        first = self.servos[0]
        for sv in self.servos[1:]:
            if (sv.goal.address, sv.goal.size, sv.present.address, sv.present.size) != \
               (first.goal.address, first.goal.size, first.present.address, first.present.size):
                raise BridgeError(f"Dynamixel bus {bus.name!r}: {sv.model.name} and {first.model.name} place Goal/Present "
                                  "Position at different addresses; put them on separate buses")
        self.bus = DynamixelBus(port or bus.port, bus.baud, bus.protocol_version, retries=retries,
                                latency_ms=latency_ms, names={s.cfg.id: s.cfg.joint for s in self.servos})
        self._ids = [s.cfg.id for s in self.servos]
        self._lower = np.array([s.cfg.lower for s in self.servos], float)
        self._upper = np.array([s.cfg.upper for s in self.servos], float)
        self._half_tick = np.array([0.5 / s.model.ticks_per_rad for s in self.servos])
        tick_limits = np.array([servo_tick_limits(s.cfg, s.model) for s in self.servos], dtype=float)
        self._tick_lo, self._tick_hi = tick_limits[:, 0], tick_limits[:, 1]
        self._center = np.array([s.model.position.center_tick for s in self.servos], float)
        self._tpr = np.array([s.model.ticks_per_rad for s in self.servos])
        self._dir = np.array([s.cfg.direction for s in self.servos], float)
        self._off = np.array([s.cfg.zero_offset for s in self.servos])
        self._slow_next = 0
        # position, velocity, effort, temperature, voltage: one block, so read_state copies it once
        self._block = np.full((5, len(self.servos)), np.nan)
        self._state = JointState(*self._block, np.zeros(len(self.servos), bool), 0.0)
        self._goal_cache: tuple | None = None  # _goal_rows, for the limits in force
        self._joint_rows = tuple(zip(self._center.tolist(), self._tpr.tolist(), self._off.tolist(), self._dir.tolist()))
        self._status_rows = [self._status_scales(sv) for sv in self.servos]
        self._reader = None  # SDK GroupSyncRead: the SYNC_READ fallback (protocol 2.0)
        self._writer: SyncWriteEncoder | None = None
        self._fast: FastSyncReadDecoder | None = None
        self._fast_values: tuple[int, ...] = (0,) * len(self.servos)  # ticks of the last fast reply
        self._fast_errors: tuple[int, ...] = (0,) * len(self.servos)  # its status error bytes
        self._torque_on = np.zeros(len(self.servos), bool)   # last known state on the servo
        self._torque_cmd = np.zeros(len(self.servos), bool)  # what the host asked for
        self._atexit = None
        # split-phase bus cycle (see pipeline())
        self._pipelined = False
        # a reply still on the wire: ("fast", -1), ("bulk", status servo j) or ("slow", servo i)
        self._pending: tuple[str, int] | None = None
        self._fast_sent = 0.0  # monotonic second the pending position read request left
        self._fast_ready: tuple[int, float] | None = None  # (COMM code, request time) of a collected fast read
        self._slow_ready: tuple[int, list, int, int] | None = None  # (servo index, data, COMM code, error byte)
        self._slow_blocks: dict[int, tuple[dict[str, Register], int, int]] = {}
        # per status servo j: (FAST_BULK_READ of all positions + j's status block, getter of the
        # positions among its decoded values, (field, index, Register) of j's status registers there);
        # None: FSR + a status READ
        self._bulk: list[tuple[FastBulkReadDecoder, operator.itemgetter, tuple]] | None = None
        self._bulk_refused = False  # the servos did not answer FAST_BULK_READ
        self._bulk_status: tuple[int, dict, int] | None = None  # (servo index, status values by field, error byte)
        self._alerted: frozenset[int] = frozenset()  # servos whose alert the last fast reply handled
        self._rx_carry = b""  # reply bytes _read_arrived took but left to the general path

    # ------------------------------------------------------------------ life cycle
    def open(self) -> None:
        if self.bus.port is not None:
            return
        self.bus.open()
        try:
            if self.bus.latency_note:
                self.stats.notes.append(self.bus.latency_note)
            for sv in self.servos:
                number = self.bus.ping(sv.cfg.id)
                if number != sv.model.model_number:
                    try:
                        found = load_servo_model(number, protocol=sv.model.protocol).name
                    except Exception:
                        found = "unknown model"
                    raise BridgeError(f"{self.bus.label(sv.cfg.id)}: model number {number} ({found}) but the config "
                                      f"says {sv.model.name} ({sv.model.model_number}); fix the config or the wiring")
            for i, sv in enumerate(self.servos):
                self._torque_on[i] = self._torque_cmd[i] = bool(self.bus.read(sv.cfg.id, sv.torque)[0])
                self._narrow_to_eeprom(i)
            if self.apply_settings:
                for sv in self.servos:
                    self._apply_ram_settings(sv)
            self._make_groups()
            self._read_positions()
        except BaseException:
            self.bus.close()
            raise
        ref = weakref.ref(self)
        self._atexit = lambda: (ref() is not None and ref().close())
        atexit.register(self._atexit)

    def close(self) -> None:
        if self.bus.port is None:
            return
        try:
            self.safe_stop(self.stop_policy)
        except BridgeError:
            if self.stop_policy == "limp":
                self._broadcast_torque_off()
        finally:
            self.bus.close()
            self._pending = self._fast_ready = self._slow_ready = self._bulk_status = None
            self._rx_carry = b""
            if self._atexit is not None:
                atexit.unregister(self._atexit)
                self._atexit = None

    def __enter__(self) -> "DynamixelTransport":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ Transport
    def read_state(self) -> JointState:
        """Present positions of every servo, plus the status block of ``slow_per_cycle``
        servos (round robin). In the split-phase cycle (:meth:`pipeline`) the positions are
        the reply to the request that ``write_goal`` sent on the previous tick, collected
        without waiting when it has arrived, and ``stamp`` is when that request left; the
        last status READ of the call is sent but collected on the next bus transfer."""
        pending = self._pending
        if pending is not None and (pending[0] == "bulk" and self.slow_per_cycle == 1
                                    or pending[0] == "fast" and self.slow_per_cycle == 0):
            state = self._read_arrived()
            if state is not None:
                return state
        try:
            if self._pending is not None:
                self._settle()
            if self._fast_ready is not None:
                self._finish_fast()
            else:
                self._read_positions()
            if self._slow_ready is not None:
                self._finish_slow()
            if self._bulk_status is not None:
                (i, val, error), self._bulk_status = self._bulk_status, None
                self._apply_status(i, val, error, alert_handled=i in self._alerted)
            bulk = self._pipelined and self._bulk is not None
            k = min(self.slow_per_cycle, len(self.servos)) - bulk  # one status block rides with each bulk read
            for j in range(k):
                i = self._slow_next
                self._slow_next = (i + 1) % len(self.servos)
                if self._pipelined and not bulk and j == k - 1:
                    self._send_slow(i)
                else:
                    self._read_slow(i)
        except BridgeError:
            self._on_error()
            raise
        self.stats.cycles += 1
        return self._reading()

    def _read_arrived(self) -> JointState | None:
        """The split-phase cycle's common tick in one pass: the pending read's reply has fully
        arrived, is valid (length, header, CRC, IDs) and carries no status error bit, and it
        is all the tick reads (a FAST_BULK_READ with ``slow_per_cycle`` 1: its one status
        block rides with it; a FAST_SYNC_READ with ``slow_per_cycle`` 0). Then: its positions
        (and status block) into the state, and the reading; the same values
        :meth:`read_state`'s general path gives (tested). Anything else - bytes still on the
        wire, a corrupt reply, an error bit - returns None with the bytes read kept for the
        general path (``_rx_carry``), which then proceeds as if it had read them itself
        (waits, retries, alerts)."""
        if self._fast_ready is not None or self._slow_ready is not None or self._bulk_status is not None:
            return None
        j = self._pending[1]
        if j >= 0:
            dec, positions, status = self._bulk[j]
        else:
            dec, positions, status = self._fast, None, None
        port = self.bus.port
        try:
            raw = port._read_now(dec.reply_length)
        except OSError:
            return None  # the general path reads again and reports the port's failure
        try:
            errors, values = dec.decode_fields(raw)
        except PacketError:
            self._rx_carry = raw
            return None
        if any(errors):
            self._rx_carry = raw
            return None
        self._pending = None
        self.bus.before_io = None
        if positions is None:
            self._set_position(values)
        else:
            self._set_position(positions(values) if len(errors) > 1 else (positions(values),))
        self._state.stamp = self._fast_sent
        self._alerted = _NONE
        if status is not None:
            try:
                self._apply_status(j, self._status_values(status, values), 0)
            except BridgeError:
                self._on_error()
                raise
        self.stats.cycles += 1
        return self._reading()

    def _reading(self) -> JointState:
        """The state as the caller's own copy (one copy of the state block: position,
        velocity, current, temperature, voltage rows)."""
        st = self._state
        b = self._block.copy()
        return JointState(b[0], b[1], b[2], b[3], b[4], self._torque_on.copy(), st.stamp, dict(st.errors))

    def write_goal(self, positions: np.ndarray) -> None:
        q = np.asarray(positions, float)
        if q.shape != (len(self.servos),):
            raise BridgeError(f"Dynamixel: write_goal needs shape ({len(self.servos)},), got {q.shape}")
        ticks = self._goal_ticks(q.tolist())
        try:
            if self._pipelined:
                self._send_cycle(ticks)
            else:
                self._send_goal_ticks(ticks)
        except BridgeError:
            self._on_error()
            raise

    def pipeline(self, enabled: bool = True) -> bool:
        """Switch the split-phase bus cycle on or off; returns whether it is on.

        On (protocol 2.0 buses whose servos answer FAST_SYNC_READ; elsewhere this returns
        False and nothing changes): ``write_goal`` sends SYNC_WRITE and then the
        FAST_SYNC_READ request and returns without waiting; the next ``read_state`` takes
        the reply that arrived meanwhile (it waits, up to the reply timeout, only for bytes
        still missing). A control loop then never blocks for the bus time of a cycle
        (1.6 ms at 2 Mbit/s for 20 servos); the price is that the positions it reads are
        those sampled when the previous tick's request reached the servos (``stamp``).
        With ``slow_per_cycle`` > 0 the read request is a FAST_BULK_READ that brings, with
        every servo's Present Position, one servo's status block (round robin), so a cycle
        is one request and one reply; servos that do not answer FAST_BULK_READ get the
        FAST_SYNC_READ and a status READ split the same way (sent by ``read_state``,
        collected before the next packet goes out).

        Faults keep the blocking path's policy: a reply that is missing, short or garbled
        counts as a retry and is read again at once with the usual bounded retries (then
        the error names the silent servo); a port that vanished is a BridgeError. The bus
        is half duplex, so any transfer (a write, an e-stop, recovery) first collects a
        reply still on the wire (``DynamixelBus.before_io``)."""
        if self.bus.port is not None:
            self._settle()
        self._fast_ready = None
        self._pipelined = bool(enabled) and self._fast is not None and self.stats.fast_sync_read
        if self._pipelined and self.slow_per_cycle > 0 and self._bulk is None and not self._bulk_refused:
            self._make_bulk()
        return self._pipelined

    @property
    def pipelined(self) -> bool:
        """Whether the split-phase bus cycle is on (:meth:`pipeline`)."""
        return self._pipelined

    def set_torque(self, enabled: bool) -> None:
        if enabled:
            self._read_positions()
            present = np.clip(self._state.position, self._lower, self._upper)
            self._send_goal_ticks(self._to_ticks(present))
        for i, sv in enumerate(self.servos):
            self._torque_cmd[i] = enabled
            self.bus.write(sv.cfg.id, sv.torque, 1 if enabled else 0)
            self._torque_on[i] = enabled

    def safe_stop(self, policy: str = "hold") -> None:
        if policy not in STOP_POLICIES:
            raise BridgeError(f"safe_stop: policy {policy!r} is not one of {STOP_POLICIES}")
        if policy == "limp":
            self._torque_cmd[:] = False
            self._broadcast_torque_off()
            failures = []
            for i, sv in enumerate(self.servos):
                try:
                    self.bus.write(sv.cfg.id, sv.torque, 0)
                    self._torque_on[i] = False
                except BridgeError as exc:
                    failures.append(str(exc))
            if failures:
                raise BridgeError("safe_stop limp: " + "; ".join(failures))
            return
        self._read_positions()
        present = np.clip(self._state.position, self._lower, self._upper)
        self._send_goal_ticks(self._to_ticks(present))

    @property
    def lower(self) -> np.ndarray:
        """Joint lower limits (n,) rad in force: the config's, narrowed at ``open`` to the
        servo's EEPROM position limits, so never wider than either."""
        return self._lower.copy()

    @property
    def upper(self) -> np.ndarray:
        return self._upper.copy()

    def position_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) (n,) rad in force; the control loop adopts them after ``open``."""
        return self.lower, self.upper

    def _narrow_to_eeprom(self, i: int) -> None:
        sv = self.servos[i]
        names = (("min_position_limit", "max_position_limit") if sv.model.has("min_position_limit")
                 else ("cw_angle_limit", "ccw_angle_limit") if sv.model.has("cw_angle_limit") else None)
        if names is None:
            return
        lo_t = self.bus.read(sv.cfg.id, sv.model.register(names[0]))[0]
        hi_t = self.bus.read(sv.cfg.id, sv.model.register(names[1]))[0]
        if lo_t >= hi_t:
            return  # wheel / multi-turn setting: no position limits in EEPROM
        a, b = (sv.cfg.to_joint(sv.model.ticks_to_rad(t)) for t in (lo_t, hi_t))
        lo, hi = max(self._lower[i], min(a, b)), min(self._upper[i], max(a, b))
        if lo >= hi:
            raise BridgeError(f"{self.bus.label(sv.cfg.id)}: EEPROM position limits [{lo_t}, {hi_t}] ticks do not overlap "
                              f"the config limits [{sv.cfg.lower:.3f}, {sv.cfg.upper:.3f}] rad; run `dualflow-bridge servo provision`")
        if (lo, hi) != (self._lower[i], self._upper[i]):
            self.stats.notes.append(f"{self.bus.label(sv.cfg.id)}: limits narrowed to the EEPROM's [{lo:.4f}, {hi:.4f}] rad")
        self._lower[i], self._upper[i] = lo, hi
        self._tick_lo[i] = max(self._tick_lo[i], lo_t)
        self._tick_hi[i] = min(self._tick_hi[i], hi_t)
        self._goal_cache = None

    # ------------------------------------------------------------------ recovery
    def recover(self, joint: str) -> str:
        """Recover one servo after a hardware alert: read register 70, reboot (protocol 2.0),
        wait, re-apply settings, goal = present, torque on if it was on. Returns what was done."""
        i = self.joint_names.index(joint)
        sv = self.servos[i]
        sid = sv.cfg.id
        was_on = bool(self._torque_cmd[i])  # what the host commanded, not what Shutdown left
        bits = self.bus.read(sid, sv.model.register("hardware_error_status"))[0] if sv.model.has("hardware_error_status") else 0
        self.bus.reboot(sid)
        self.stats.reboots += 1
        sv.reboots += 1
        # poll with PINGs rather than sleeping: every packet on the bus also feeds the other
        # servos' Bus Watchdog, which a silent wait of this length would trip
        deadline = time.monotonic() + self.recovery.reboot_wait_s
        time.sleep(0.02)
        while True:
            try:
                self.bus.ping(sid, retries=0)
                break
            except BridgeError:
                if time.monotonic() > deadline:
                    raise BridgeError(f"{self.bus.label(sid)}: did not come back within "
                                      f"{self.recovery.reboot_wait_s:.1f} s of REBOOT; power-cycle it") from None
                time.sleep(0.01)
        if sv.model.has("hardware_error_status"):
            left = self.bus.read(sid, sv.model.register("hardware_error_status"))[0]
            if left:
                self._torque_on[i] = False
                raise BridgeError(f"{self.bus.label(sid)}: hardware error persists after REBOOT: "
                                  f"{', '.join(decode_hardware_error(left))}; torque stays off, inspect the servo")
        self._torque_on[i] = False  # a reboot switches torque off
        self._apply_ram_settings(sv)
        value, _ = self.bus.read(sid, sv.present)
        goal = int(np.clip(value, *servo_tick_limits(sv.cfg, sv.model)))
        self.bus.write(sid, sv.goal, goal)
        if was_on:
            self.bus.write(sid, sv.torque, 1)
            self._torque_on[i] = True
        done = f"rebooted after {', '.join(decode_hardware_error(bits)) or 'alert'}; settings re-applied, goal = present" + \
               (", torque on" if was_on else "")
        self._state.errors.pop(joint, None)
        return done

    # ------------------------------------------------------------------ internals
    def _to_ticks(self, q: np.ndarray) -> np.ndarray:
        """Joint rad (n,) → goal ticks (n,) int64: round(center + (direction · q + offset) ·
        ticks_per_rad), then clipped to each servo's tick limits (the config's limits rounded
        inwards): a goal exactly at a limit must not round one tick beyond it."""
        ticks = np.rint(self._center + (self._dir * q + self._off) * self._tpr)
        return np.clip(ticks, self._tick_lo, self._tick_hi).astype(np.int64)

    def _to_joint(self, ticks: np.ndarray) -> np.ndarray:
        """Present ticks (n,) → joint rad: direction · ((ticks − center) / ticks_per_rad − offset)."""
        return self._dir * ((ticks - self._center) / self._tpr - self._off)

    def _goal_rows(self) -> tuple:
        """Per servo, the floats and ints :meth:`_goal_ticks` needs, made from the limits in
        force (``_narrow_to_eeprom``, the only place that changes them, drops the cache)."""
        if self._goal_cache is None:
            self._goal_cache = tuple(zip((self._lower - self._half_tick).tolist(), (self._upper + self._half_tick).tolist(),
                             self._lower.tolist(), self._upper.tolist(), self._center.tolist(), self._dir.tolist(),
                             self._off.tolist(), self._tpr.tolist(), [int(v) for v in self._tick_lo],
                             [int(v) for v in self._tick_hi]))
        return self._goal_cache

    def _goal_ticks(self, q: list[float]) -> list[int]:
        """Joint rad (a list of n floats) → goal ticks (n ints): the limit check, the clip and
        :meth:`_to_ticks` with Python floats, element by element. The same IEEE operations
        in the same order as the numpy form (``round`` is ``rint``'s round half to even), so
        the same ticks (tested); for 20 servos a few Python steps each cost less than a
        dozen numpy calls. A goal outside a joint's limits (by more than the half tick of
        slack the EEPROM's limits, rounded inwards, leave), NaN or inf is a BridgeError
        naming the servo, and nothing is sent."""
        out = []
        put = out.append
        for x, (lo_ok, hi_ok, lo, hi, center, d, off, tpr, t_lo, t_hi) in zip(q, self._goal_cache or self._goal_rows()):
            if not lo_ok <= x <= hi_ok:  # NaN fails both comparisons
                i = len(out)
                raise BridgeError(f"{self.bus.label(self._ids[i])}: goal {x:.4f} rad is outside the joint limits "
                                  f"[{lo:.4f}, {hi:.4f}]; refusing to send")
            x = lo if x < lo else hi if x > hi else x
            tick = round(center + (d * x + off) * tpr)
            put(t_lo if tick < t_lo else t_hi if tick > t_hi else tick)
        return out

    def _set_position(self, ticks) -> None:
        """Present ticks (a tuple of n ints, or an array) → the state's joint positions, rad.
        A tuple takes :meth:`_to_joint`'s operations with Python floats (same values)."""
        if isinstance(ticks, np.ndarray):
            self._state.position[:] = self._to_joint(ticks)
            return
        self._state.position[:] = [d * ((t - c) / r - o) for t, (c, r, o, d) in zip(ticks, self._joint_rows)]

    def _make_groups(self) -> None:
        """Protocol 2.0: the hot path's SYNC_WRITE encoder and FAST_SYNC_READ decoder (ours;
        the same bytes as the SDK's groups), and the SDK's GroupSyncRead for buses
        whose servos do not answer FAST_SYNC_READ (firmware < v45 on X series)."""
        if self.bus.protocol != 2.0:
            return
        first = self.servos[0]
        self._writer = SyncWriteEncoder(first.goal.address, first.goal.size, self._ids, first.goal.signed)
        self._fast = FastSyncReadDecoder(first.present.address, first.present.size, self._ids, first.present.signed)
        self._reader = sdk.GroupSyncRead(self.bus.port, self.bus.ph, first.present.address, first.present.size)
        for sid in self._ids:
            self._reader.addParam(sid)
        reader = self._reader
        self._sync_op = lambda port: reader.txRxPacket()
        # decide once whether the servos answer FAST_SYNC_READ
        if self.bus.call(self._fast_read_op) != sdk.COMM_SUCCESS:
            if self.bus.call(self._sync_op, malformed=sdk.COMM_RX_CORRUPT) == sdk.COMM_SUCCESS:
                self.stats.fast_sync_read = False
                self.stats.notes.append("servos did not answer FAST_SYNC_READ; using SYNC_READ")

    @staticmethod
    def _tx_op(port, packet: bytes) -> int:
        """Send one instruction packet through the SDK's port as its ``txPacket`` does
        (busy flag, ``writePort``); no reply is awaited. Unlike ``txPacket`` it does not
        call ``clearPort`` first: that is pyserial's ``flush`` (tcdrain), which on a USB
        adapter blocks until the previous packet has left the wire (0.57 ms for a 20-servo
        SYNC_WRITE at 2 Mbit/s), and the UART keeps the packets' order anyway."""
        if port.is_using:
            return sdk.COMM_PORT_BUSY
        port.is_using = True
        return sdk.COMM_SUCCESS if port.writePort(packet) == len(packet) else sdk.COMM_TX_FAIL

    def _fast_read_op(self, port) -> int:
        """One FAST_SYNC_READ of Present Position, blocking: :meth:`_fast_send_op` then
        :meth:`_fast_collect_op`. Returns an SDK COMM_* code."""
        result = self._fast_send_op(port)
        if result != sdk.COMM_SUCCESS:
            return result
        return self._fast_collect_op(port)

    def _fast_send_op(self, port) -> int:
        """Send the prebuilt FAST_SYNC_READ request and start the SDK's sync-read timeout.
        Stale input (a reply that came after an earlier timeout) is discarded first, so it
        cannot be taken for this one's."""
        if port.is_using:
            return sdk.COMM_PORT_BUSY
        port.discardInput()
        self._rx_carry = b""
        result = self._tx_op(port, self._fast.request)
        if result == sdk.COMM_SUCCESS:
            port.setPacketTimeout((11 + self._fast.size) * self._fast.n)  # the SDK's sync-read timeout
        return result

    def _fast_collect_op(self, port) -> int:
        """Collect the FAST_SYNC_READ reply's known number of bytes through
        ``port.readPort`` (which sleeps while the reply is on the wire) until the timeout
        started by :meth:`_fast_send_op`, and parse it in one numpy pass into
        ``self._fast_values`` / ``self._fast_errors``. Returns an SDK COMM_* code."""
        result, buf = self._collect_reply(port, self._fast.reply_length, self._fast.head)
        if result != sdk.COMM_SUCCESS:
            return result
        try:
            self._fast_errors, self._fast_values = self._fast.decode_fields(buf)
        except PacketError:
            return sdk.COMM_RX_CORRUPT
        return sdk.COMM_SUCCESS

    def _collect_reply(self, port, need: int, head: bytes) -> tuple[int, bytes]:
        """(COMM code, the reply's ``need`` bytes) read through ``port.readPort`` until the
        packet timeout, after any bytes :meth:`_read_arrived` already took
        (``_rx_carry``); bytes before the header are skipped (resync)."""
        head = head[:5]
        buf, self._rx_carry = self._rx_carry, b""
        if buf:
            if not buf.startswith(head):  # garbage before the header: resync
                at = buf.find(head)
                buf = buf[at:] if at >= 0 else buf[-4:]
            if len(buf) >= need:
                return sdk.COMM_SUCCESS, buf[:need]
        while True:
            chunk = port.readPort(need - len(buf))
            if chunk:
                buf += chunk
                if not buf.startswith(head):  # garbage before the header: resync
                    at = buf.find(head)
                    buf = buf[at:] if at >= 0 else buf[-4:]
                if len(buf) >= need:
                    return sdk.COMM_SUCCESS, buf[:need]
            elif port.isPacketTimeout():
                return (sdk.COMM_RX_TIMEOUT if not buf else sdk.COMM_RX_CORRUPT), buf

    def _make_bulk(self) -> None:
        """Build the FAST_BULK_READ of every position + servo j's status block, for each j,
        and check once that the servos answer it (firmware without FAST_BULK_READ: keep the
        FAST_SYNC_READ and a separate status READ). Each decoder reads, in one unpack, every
        servo's Present Position and servo j's status registers (``decode_fields``)."""
        pres = self.servos[0].present
        bulk = []
        for j in range(len(self.servos)):
            regs, start, length = self._slow_block(j)
            b0, b1 = min(start, pres.address), max(start + length, pres.end)  # j's span holds its position too
            # j's fields, by offset in its span: its status registers and its position; a
            # sign-magnitude register is read unsigned and decoded by its Register
            span = sorted([(r.address - b0, r.size, r.signed and r.sign_bit is None, key) for key, r in regs.items()]
                          + [(pres.address - b0, pres.size, pres.signed, "position")])
            fields = [[(0, pres.size, pres.signed)] if k != j else [f[:3] for f in span] for k in range(len(self.servos))]
            dec = FastBulkReadDecoder([(sv.cfg.id, b0, b1 - b0) if k == j else (sv.cfg.id, pres.address, pres.size)
                                       for k, sv in enumerate(self.servos)], fields)
            keys = [f[3] for f in span]
            at_j = j + keys.index("position")  # where j's position lands among the decoded values
            pos = [k if k < j else at_j if k == j else k + len(span) - 1 for k in range(len(self.servos))]
            status = [(key, j + m, regs[key]) for m, key in enumerate(keys) if key != "position"]
            bulk.append((dec, operator.itemgetter(*pos), tuple(status)))
        self._bulk = bulk

        def probe(port) -> int:
            result = self._bulk_send_op(port, 0)
            return self._bulk_collect_op(port, 0) if result == sdk.COMM_SUCCESS else result

        for _ in range(self.bus.retries + 1):
            if self.bus.call(probe, malformed=sdk.COMM_RX_CORRUPT) == sdk.COMM_SUCCESS:
                self._bulk_status = None  # a probe, not a status reading to act on
                return
        self._bulk, self._bulk_refused = None, True
        self.stats.notes.append("servos did not answer FAST_BULK_READ; split phase uses FAST_SYNC_READ + a status READ")

    def _bulk_send_op(self, port, j: int) -> int:
        """Send servo j's FAST_BULK_READ (see :meth:`_make_bulk`), start the SDK's bulk-read timeout."""
        if port.is_using:
            return sdk.COMM_PORT_BUSY
        port.discardInput()
        self._rx_carry = b""
        dec = self._bulk[j][0]
        result = self._tx_op(port, dec.request)
        if result == sdk.COMM_SUCCESS:
            port.setPacketTimeout(dec.timeout_bytes)
        return result

    def _bulk_collect_op(self, port, j: int) -> int:
        """Collect servo j's FAST_BULK_READ reply: every position into ``_fast_values`` /
        ``_fast_errors`` (as a fast sync read), j's status registers into ``_bulk_status``."""
        dec, positions, status = self._bulk[j]
        result, buf = self._collect_reply(port, dec.reply_length, dec.head)
        if result != sdk.COMM_SUCCESS:
            return result
        try:
            errors, values = dec.decode_fields(buf)
        except PacketError:
            return sdk.COMM_RX_CORRUPT
        self._fast_values = positions(values) if len(errors) > 1 else (positions(values),)
        self._fast_errors = errors
        self._bulk_status = (j, self._status_values(status, values), errors[j])
        return sdk.COMM_SUCCESS

    @staticmethod
    def _status_values(status: tuple, values: tuple) -> dict[str, int]:
        """Servo j's status registers by field from a decoded FAST_BULK_READ reply (``_bulk``'s
        third entry: (field, index in ``values``, Register)); a sign-magnitude register was
        read unsigned and is decoded here."""
        return {key: values[at] if reg.sign_bit is None else reg.decode(values[at].to_bytes(reg.size, "little"))
                for key, at, reg in status}

    def _send_goal_ticks(self, ticks: np.ndarray) -> None:
        if self._writer is None:  # protocol 1.0: SYNC_WRITE exists there too
            first = self.servos[0]
            self.bus.sync_write(first.goal, dict(zip(self._ids, np.asarray(ticks).tolist())))
            return
        result = self.bus.call(self._tx_op, self._writer.encode(ticks))
        if result != sdk.COMM_SUCCESS:
            raise BridgeError(f"Dynamixel bus {self.bus.port_name}: SYNC_WRITE goal position failed ({self.bus._comm(result)})")

    def _send_cycle(self, ticks: np.ndarray) -> None:
        """Split phase: the SYNC_WRITE of ``ticks`` and, right behind it in the same write,
        the position read request (the FAST_BULK_READ carrying the next servo's status
        block, else the FAST_SYNC_READ), whose reply is left on the wire (collected by
        :meth:`_settle`). One system call and one wake-up of the other end per cycle; the
        reply timeout counts the SYNC_WRITE's bytes too. A failed write is a BridgeError, as
        for the blocking path."""
        goals = self._writer.encode(ticks)
        if self._bulk is not None:
            j = self._slow_next
            self._slow_next = (j + 1) % len(self.servos)
            dec = self._bulk[j][0]
            request, timeout_bytes, pending = dec.request, dec.timeout_bytes, ("bulk", j)
        else:
            fast = self._fast
            request, timeout_bytes, pending = fast.request, (11 + fast.size) * fast.n, ("fast", -1)
        packets = goals + request

        def op(port) -> int:
            if port.is_using:
                return sdk.COMM_PORT_BUSY
            port.discardInput()  # stale input cannot be taken for this reply
            self._rx_carry = b""
            port.is_using = True
            if port.writePort(packets) != len(packets):
                return sdk.COMM_TX_FAIL
            port.setPacketTimeout(len(goals) + timeout_bytes)
            return sdk.COMM_SUCCESS

        result = self.bus.call(op)
        if result != sdk.COMM_SUCCESS:
            raise BridgeError(f"Dynamixel bus {self.bus.port_name}: SYNC_WRITE goal position + read request failed "
                              f"({self.bus._comm(result)})")
        self._fast_sent = time.monotonic()
        self._pending = pending
        self.bus.before_io = self._settle

    def _send_slow(self, i: int) -> None:
        """Split phase: send servo ``i``'s status-block READ, leave its reply on the wire."""
        _, start, length = self._slow_block(i)
        sid, ph = self.servos[i].cfg.id, self.bus.ph

        def op(port) -> int:
            port.discardInput()
            self._rx_carry = b""
            return ph.readTx(port, sid, start, length)

        if self.bus.call(op) != sdk.COMM_SUCCESS:
            self._read_slow(i)  # blocking, with the usual retries
            return
        self._pending = ("slow", i)
        self.bus.before_io = self._settle

    def _settle(self) -> None:
        """Collect the reply of the split-phase request still on the wire, if any, into
        ``_fast_ready`` / ``_slow_ready`` (for ``read_state`` to use). Waits only for bytes
        not yet arrived, at most until the request's reply timeout. Never raises for a
        missing or garbled reply (that is recorded as the COMM code); a dead port raises."""
        pending, self._pending = self._pending, None
        self.bus.before_io = None
        if pending is None:
            return
        kind, i = pending
        if kind == "fast":
            result = self.bus.call(self._fast_collect_op, malformed=sdk.COMM_RX_CORRUPT)
            self._fast_ready = (result, self._fast_sent)
        elif kind == "bulk":
            result = self.bus.call(lambda port: self._bulk_collect_op(port, i), malformed=sdk.COMM_RX_CORRUPT)
            self._fast_ready = (result, self._fast_sent)
        else:
            _, _, length = self._slow_block(i)
            data, result, error = self.bus.call(self.bus.ph.readRx, self.servos[i].cfg.id, length,
                                                malformed=([], sdk.COMM_RX_CORRUPT, 0))
            self._slow_ready = (i, data, result, error)
        if result != sdk.COMM_SUCCESS:
            self.stats.read_retries += 1  # counted here: a newer request may supersede it before it is used

    def _finish_fast(self) -> None:
        """Use a collected split-phase position read; a failed one (counted as a retry by
        :meth:`_settle`) is replaced by a blocking read (bounded retries, then an error
        naming the silent servo)."""
        (result, sent), self._fast_ready = self._fast_ready, None
        if result != sdk.COMM_SUCCESS:
            self._read_positions()
            return
        self._set_position(self._fast_values)
        self._state.stamp = sent
        self._alerted = frozenset()
        if any(self._fast_errors):
            self._alerted = self._on_fast_read_errors(np.array(self._fast_errors, np.uint8))

    def _finish_slow(self) -> None:
        """Use a collected split-phase status READ; a failed or refused one is read again
        the blocking way (which retries, and raises on a refusal)."""
        (i, data, result, error), self._slow_ready = self._slow_ready, None
        _, _, length = self._slow_block(i)
        if result == sdk.COMM_SUCCESS and len(data) == length and not error & 0x7F:
            self._apply_slow(i, bytes(data), error)
        else:
            self.stats.read_retries += result == sdk.COMM_SUCCESS  # a short or refused reply (failures: _settle)
            self._read_slow(i)

    def _read_positions(self) -> None:
        fast = self._reader is not None and self.stats.fast_sync_read
        if self._reader is None:
            ticks = np.empty(len(self.servos))
            for i, sv in enumerate(self.servos):
                value, error = self.bus.read(sv.cfg.id, sv.present)
                ticks[i] = value
                if self.bus.protocol == 1.0:
                    self._note_p1_error(i, error)
        else:
            op = self._fast_read_op if fast else self._sync_op
            result = sdk.COMM_TX_FAIL
            for attempt in range(self.bus.retries + 1):
                result = self.bus.call(op, malformed=sdk.COMM_RX_CORRUPT)
                if result == sdk.COMM_SUCCESS:
                    break
                self.stats.read_retries += 1
            if result != sdk.COMM_SUCCESS:
                self._raise_missing("present position", result)
            if fast:
                ticks = self._fast_values
            else:
                reg = self.servos[0].present
                get = self._reader.getData
                ticks = np.array([get(sid, reg.address, reg.size) for sid in self._ids], dtype=np.int64)
                if reg.signed:
                    ticks[ticks >= 1 << (8 * reg.size - 1)] -= 1 << (8 * reg.size)
        self._set_position(ticks)
        self._state.stamp = time.monotonic()
        self._fast_ready = None  # a split-phase reply collected meanwhile is older than this
        self._alerted = frozenset()
        if fast and any(self._fast_errors):
            self._alerted = self._on_fast_read_errors(np.array(self._fast_errors, np.uint8))

    def _on_fast_read_errors(self, errors: np.ndarray) -> frozenset[int]:
        """The fast reply keeps every servo's status error byte (the SDK's group reads drop
        it): a hardware alert (bit 0x80) is handled at once rather than when the round-robin
        status read next reaches that servo. A servo already reported stays with the status
        read (which clears the report once the alert is gone). Returns the servos handled."""
        done = set()
        for i in np.flatnonzero(errors & ALERT_BIT):
            if self.joint_names[i] not in self._state.errors:
                self._on_alert(int(i))
                done.add(int(i))
        return frozenset(done)

    def _raise_missing(self, what: str, result: int) -> None:
        """A group read failed: find which servo is silent, to name it."""
        for sid in self._ids:
            try:
                self.bus.ping(sid, retries=0)
            except BridgeError:
                raise BridgeError(f"{self.bus.label(sid)}: no status packet for {what} after "
                                  f"{self.bus.retries + 1} tries; check its cable and power") from None
        raise BridgeError(f"Dynamixel bus {self.bus.port_name}: group read of {what} failed after "
                          f"{self.bus.retries + 1} tries ({self.bus._comm(result)}), though every servo answers PING; "
                          "check for noise or a wrong baud rate")

    def _slow_registers(self, sv: _Servo) -> dict[str, Register]:
        m = sv.model
        regs = {}
        for key, names in (("current", ("present_current", "present_load")), ("velocity", ("present_velocity", "present_speed")),
                           ("voltage", ("present_input_voltage", "present_voltage")), ("temperature", ("present_temperature",))):
            for name in names:
                if m.has(name):
                    regs[key] = m.register(name)
                    break
        if sv.settings.get("bus_watchdog", 0) > 0:
            regs["watchdog"] = m.register("bus_watchdog")  # same READ, from address 98 on
        return regs

    def _slow_block(self, i: int) -> tuple[dict[str, Register], int, int]:
        """(registers by field, start address, length) of servo ``i``'s status block."""
        block = self._slow_blocks.get(i)
        if block is None:
            regs = self._slow_registers(self.servos[i])
            start = min(r.address for r in regs.values())
            block = self._slow_blocks[i] = (regs, start, max(r.end for r in regs.values()) - start)
        return block

    def _read_slow(self, i: int) -> None:
        _, start, length = self._slow_block(i)
        data, error = self.bus.read_raw(self.servos[i].cfg.id, start, length, "status block")
        self._apply_slow(i, data, error)

    def _apply_slow(self, i: int, data: bytes, error: int, alert_handled: bool = False) -> None:
        """Decode servo ``i``'s status block (bytes from its start address) and apply it
        (:meth:`_apply_status`)."""
        regs, start, _ = self._slow_block(i)
        self._apply_status(i, {k: r.decode(data[r.address - start:r.end - start]) for k, r in regs.items()},
                           error, alert_handled)

    @staticmethod
    def _status_scales(sv: _Servo) -> tuple:
        """Servo ``sv``'s unit factors for :meth:`_apply_status`, as Python floats (None where
        the model lacks the quantity): (direction, velocity rpm per unit, current mA per unit,
        torque constant N·m/A, load % per unit, stall torque N·m, V per unit, °C per unit)."""
        m = sv.model
        return (float(sv.cfg.direction), m.velocity_rpm, m.current_ma,
                m.torque_constant_nm_per_a if m.current_ma is not None else None,
                m.load_percent, m.ratings.stall_torque_nm, m.voltage_v, m.temperature_c)

    def _apply_status(self, i: int, val: dict[str, int], error: int, alert_handled: bool = False) -> None:
        """Servo ``i``'s status registers (raw values by field: velocity, current, voltage,
        temperature, watchdog) into the state, in joint units; act on its status error byte
        (alert → register 70), unless ``alert_handled`` (the same reply's alert was just
        acted on). Units, with the model's factors (the servo model's conversions, with
        Python floats in the same order of operations)::

            velocity rad/s = direction · units · rpm_per_unit · 2π/60
            effort N·m     = direction · units · mA_per_unit / 1000 · torque constant
                             (load-reporting models: direction · units · %/unit / 100 · stall torque)
            voltage V      = units · V_per_unit;  temperature °C = units · °C_per_unit
        """
        d, rpm, ma, kt, load, stall, volt, degc = self._status_rows[i]
        st = self._state
        if "velocity" in val:
            st.velocity[i] = d * (val["velocity"] * rpm * _RPM_TO_RAD_S)
        if "current" in val:
            if ma is not None:
                st.effort[i] = d * (val["current"] * ma / 1000.0) * kt
            elif load is not None:
                st.effort[i] = d * val["current"] * load / 100.0 * stall
        if "voltage" in val:
            st.voltage[i] = val["voltage"] * volt
        if "temperature" in val:
            st.temperature[i] = val["temperature"] * degc
        if val.get("watchdog", 0) in (-1, 255):
            self._recover_bus_watchdog()
        if self.bus.protocol == 2.0:
            if error & ALERT_BIT:
                if not alert_handled:
                    self._on_alert(i)
            else:
                st.errors.pop(self.joint_names[i], None)
        else:
            self._note_p1_error(i, error)

    def _note_p1_error(self, i: int, error: int) -> None:
        bits = error & P1_HARDWARE_MASK
        if bits:
            self._state.errors[self.joint_names[i]] = ", ".join(decode_hardware_error(bits, 1))
        else:
            self._state.errors.pop(self.joint_names[i], None)

    def _on_alert(self, i: int) -> None:
        sv = self.servos[i]
        joint = self.joint_names[i]
        self.stats.alerts += 1
        bits = self.bus.read(sv.cfg.id, sv.model.register("hardware_error_status"))[0]
        names = decode_hardware_error(bits)
        text = ", ".join(names) or "alert without a hardware error bit"
        torque = bool(self.bus.read(sv.cfg.id, sv.torque)[0])
        if not torque:
            self._torque_on[i] = False  # the servo's Shutdown switched torque off
        pol = self.recovery
        if pol.reboot and names and set(names) <= pol.reboot_on and sv.reboots < pol.max_reboots:
            try:
                done = self.recover(joint)
                self.stats.notes.append(f"{self.bus.label(sv.cfg.id)}: {done}")
                return
            except BridgeError as exc:
                self._state.errors[joint] = f"{text}; recovery failed: {exc}"
                return
        reason = ("policy does not reboot on this" if set(names) - pol.reboot_on or not pol.reboot
                  else f"already rebooted {sv.reboots} times")
        self._state.errors[joint] = f"{text} (servo ID {sv.cfg.id}; torque {'on' if torque else 'off'}; {reason})"

    def _apply_ram_settings(self, sv: _Servo) -> None:
        for name, value in sv.settings.items():
            reg = sv.model.register(name)
            if reg.eeprom:
                continue
            if name == "bus_watchdog":
                self.bus.write(sv.cfg.id, reg, 0)  # clears a tripped watchdog (-1) before a new period
            self.bus.write(sv.cfg.id, reg, value)

    def _recover_bus_watchdog(self) -> None:
        """The host was silent for longer than a servo's Bus Watchdog(98) period: tripped
        servos have stopped where they were and refuse goals. For every servo on the bus:
        clear the watchdog (write 0), goal = present, set the period again."""
        for i, sv in enumerate(self.servos):
            period = sv.settings.get("bus_watchdog", 0)
            if period <= 0:
                continue
            reg = sv.model.register("bus_watchdog")
            if self.bus.read(sv.cfg.id, reg)[0] not in (-1, 255):
                continue
            self.bus.write(sv.cfg.id, reg, 0)
            ticks = self.bus.read(sv.cfg.id, sv.present)[0]
            self.bus.write(sv.cfg.id, sv.goal, int(np.clip(ticks, *servo_tick_limits(sv.cfg, sv.model))))
            self.bus.write(sv.cfg.id, reg, period)
            self.stats.watchdog_trips += 1
            self.stats.notes.append(f"{self.bus.label(sv.cfg.id)}: bus watchdog had expired (host silent > "
                                    f"{period * 20} ms); cleared, goal = present")

    def _broadcast_torque_off(self) -> None:
        """One SYNC_WRITE Torque Enable = 0 to every servo (no reply needed): the cheapest
        way to make the bus safe when individual writes are failing."""
        try:
            self.bus.sync_write(self.servos[0].torque, {sid: 0 for sid in self._ids})
            self._torque_on[:] = False
        except BridgeError:
            pass

    def _on_error(self) -> None:
        """After a communication failure: 'limp' switches torque off by broadcast;
        'hold' leaves the servos on their last goal, which is holding."""
        if self.stop_policy == "limp":
            self._broadcast_torque_off()
