"""A byte-level emulated Dynamixel bus on a pseudo-terminal, for dynamixel-sdk to open.

``DynamixelBusEmulator(servos, baud, protocol)`` serves servos (and devices such as the
OP3's OpenCR) that answer protocol 2.0 and 1.0 instructions as real ones do, at
``emu.port_path``; faults are injected and what reached each servo is inspected by method,
all state under ``emu.lock``. Behaviour, fault and inspection API, and dynamixel-sdk's
quirks on a pty: docs/dynamixel.md, "The byte-level emulator".
"""

from __future__ import annotations

import collections
import errno
import fcntl
import os
import select
import struct
import termios
import threading
import time
import tty
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from firmware_cfg.device_models import find_device_model
from firmware_cfg.servo_models import BAUD_TOLERANCE, load_servo_model
from ros_free_bridge.dynamixel import protocol as dp
from ros_free_bridge.emulators.emulated_device import EmulatedDevice, ImuSource
from ros_free_bridge.emulators.emulated_servo import (
    EmulatedServo,
    GoalRecord,
)
from ros_free_bridge.errors import BridgeError

#: Default model per protocol for servos given by ID only.
DEFAULT_MODELS = {2: "XM430-W350", 1: "AX-12A"}

_P2_WRITE_ERRORS = {
    "access": dp.ERR_ACCESS,
    "length": dp.ERR_DATA_LENGTH,
    "range": dp.ERR_DATA_RANGE,
    "limit": dp.ERR_DATA_LIMIT,
}
_P1_WRITE_ERRORS = {"access": dp.ERR1_RANGE, "length": dp.ERR1_RANGE, "range": dp.ERR1_RANGE, "limit": dp.ERR1_ANGLE}

#: CLEAR's parameters for the multi-turn count: option 1, then the fixed key "DXL\"".
_CLEAR_MULTI_TURN = bytes((0x01, 0x44, 0x58, 0x4C, 0x22))

_TCGETS2 = 0x802C542A
_BOTHER = 0o010000
_BAUD_CONSTANTS = {
    getattr(termios, name): int(name[1:]) for name in dir(termios) if name.startswith("B") and name[1:].isdigit()
}


@dataclass(frozen=True)
class ServoSpec:
    """One servo on the emulated bus: its ID, model (name or number; a device model's name,
    e.g. ``OpenCR``, makes a non-servo device instead), start position in ticks (None: the model's
    center) and an optional allowed goal range in ticks; a goal
    outside it is recorded in ``emu.violations`` (it is still applied if the servo's own
    limits accept it)."""

    id: int
    model: str | int = "XM430-W350"
    position: float | None = None
    allowed_range: tuple[int, int] | None = None


@dataclass
class _Instruction:
    """A valid protocol 2.0 instruction packet as the listening servos see it, and the
    replies it draws, in sending order (None where a fault swallowed one)."""

    inst: int
    params: bytes
    target: int  #: the ID it is addressed to (``dp.BROADCAST_ID``: all)
    servos: dict[int, EmulatedServo]  #: the servos that hear it, by ID
    replies: list[tuple[EmulatedServo, bytes] | None] = field(default_factory=list)

    @property
    def broadcast(self) -> bool:
        return self.target == dp.BROADCAST_ID

    @property
    def unicast(self) -> EmulatedServo | None:
        """The addressed servo, if it hears the packet."""
        return self.servos.get(self.target)

    def group(self) -> list[EmulatedServo]:
        """Every listener for a broadcast packet, else the addressed one (if it hears)."""
        return list(self.servos.values()) if self.broadcast else [self.unicast] if self.unicast else []

    def sent(self) -> list[tuple[EmulatedServo, bytes]]:
        return [r for r in self.replies if r is not None]


def _supports(unit: EmulatedServo | EmulatedDevice, name: str) -> bool:
    """Whether the unit's firmware has the instruction (a servo has them all)."""
    return getattr(unit, "supports", lambda _: True)(name)


def _narrow_to_capable(req: _Instruction, name: str) -> bool:
    """Keep only the listeners whose firmware has instruction ``name`` (a device answers only
    its own); False when the addressed unit lacks it."""
    if req.unicast is not None and not _supports(req.unicast, name):
        return False
    req.servos = {i: s for i, s in req.servos.items() if _supports(s, name)}
    return True


class DynamixelBusEmulator:
    """An emulated multi-servo Dynamixel bus behind a pseudo-terminal (see module docstring)."""

    def __init__(
        self,
        servos: Iterable[ServoSpec | tuple[int, str | int] | int] = (1,),
        baud: int = 1_000_000,
        protocol: int = 2,
        *,
        wire_timing: bool = False,
        return_delay_us: float | None = 0.0,
        reboot_time_s: float = 0.05,
        match_baud: bool = True,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """``servos``: IDs (the protocol's default model), ``(id, model)`` pairs or
        :class:`ServoSpec`; a device model's name (``(200, "OpenCR")``) adds a non-servo
        device. ``baud`` in bit/s. ``wire_timing``: replies leave when their bytes would have
        crossed the wire. ``return_delay_us`` sets every unit's Return Delay Time register
        (None keeps the factory 250 = 500 µs); ``reboot_time_s``: how long a rebooted servo
        stays silent; ``match_baud``: a servo hears the host only at its own baud rate;
        ``clock``: seconds, monotonic. Firmware without some instructions: :attr:`unsupported`."""
        if protocol not in (1, 2):
            raise BridgeError(f"emulator protocol must be 1 or 2, got {protocol!r}")
        self.baud = int(baud)
        self.protocol = protocol
        self.wire_timing = wire_timing
        self.reboot_time_s = reboot_time_s
        self.match_baud = match_baud
        self.clock = clock
        self._unsupported: frozenset[str] = frozenset()
        self.lock = threading.RLock()
        self._servos: list[EmulatedServo | EmulatedDevice] = [
            self._unit(self._spec(item), return_delay_us) for item in servos
        ]
        ids = [s.servo_id for s in self._servos]
        if len(set(ids)) != len(ids):
            raise BridgeError(f"emulated bus has duplicate servo IDs: {sorted(ids)}")
        self._master: int | None = None
        self._slave: int | None = None
        self._port_path = ""
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._parser = dp.StreamParser(protocol=None)
        self._bus_free_at = 0.0
        self.instruction_counts: dict[str, int] = {}
        self.received: collections.deque[bytes] = collections.deque(maxlen=64)
        self.rx_bytes = 0
        self.tx_bytes = 0
        self.crc_errors = 0
        self.vanished = False
        self._has_devices = any(isinstance(s, EmulatedDevice) for s in self._servos)

    @property
    def unsupported(self) -> frozenset[str]:
        """Protocol 2.0 instruction names the servos' firmware lacks (e.g.
        ``{"FAST_SYNC_READ", "FAST_BULK_READ"}`` for X series firmware before v45): they are
        answered like an unknown instruction (broadcast: silence). Settable at any time."""
        return self._unsupported

    @unsupported.setter
    def unsupported(self, names: Iterable[str]) -> None:
        names = frozenset(names)
        unknown = names - set(dp.INSTRUCTION_NAMES.values())
        if unknown:
            raise BridgeError(
                f"emulator unsupported={sorted(unknown)}: not instruction names; "
                f"use names from {sorted(dp.INSTRUCTION_NAMES.values())}"
            )
        self._unsupported = names

    def _unit(self, spec: ServoSpec, return_delay_us: float | None) -> EmulatedServo | EmulatedDevice:
        """The servo, or the device when ``spec.model`` names a device model, at the bus's baud."""
        device = find_device_model(spec.model) if isinstance(spec.model, str) else None
        if device is not None:
            return self._device(device, spec.id, return_delay_us)
        model = load_servo_model(spec.model)
        servo = EmulatedServo(model, spec.id, spec.position, clock=self.clock)
        try:
            servo.set("baud_rate", model.baud_to_register(self.baud))
        except Exception as exc:
            raise BridgeError(f"emulated servo {spec.id} ({model.name}) cannot run at {self.baud} bps: {exc}") from None
        if return_delay_us is not None:
            servo.set("return_delay_time", int(round(return_delay_us / model.return_delay_us)))
        servo.allowed_range = spec.allowed_range
        return servo

    def _device(self, model, device_id: int, return_delay_us: float | None) -> EmulatedDevice:
        """A non-servo device (e.g. the OP3's OpenCR) at ``device_id``, at the bus's baud."""
        dev = EmulatedDevice(model, device_id, clock=self.clock)
        for code in range(7):
            dev.set("baud_rate", code)
            if dev.baud() == self.baud:
                break
        else:
            raise BridgeError(f"emulated {model.name} (ID {device_id}) cannot run at {self.baud} bps")
        if return_delay_us is not None:
            dev.set("return_delay_time", int(round(return_delay_us / 2.0)))
        return dev

    def _spec(self, item: ServoSpec | tuple | int) -> ServoSpec:
        if isinstance(item, ServoSpec):
            return item
        if isinstance(item, int):
            return ServoSpec(item, DEFAULT_MODELS[self.protocol])
        if isinstance(item, tuple) and len(item) == 2:
            return ServoSpec(int(item[0]), item[1])
        raise BridgeError(f"emulator servo entry must be an ID, (id, model) or ServoSpec, got {item!r}")

    # ------------------------------------------------------------------ life cycle
    def start(self, threaded: bool = True) -> DynamixelBusEmulator:
        """Open the pty and, with ``threaded``, start the reader thread. With
        ``threaded=False`` nothing answers until the caller calls :meth:`pump`."""
        if self._master is not None:
            return self
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        tty.setraw(self._master)
        os.set_blocking(self._master, False)
        self._port_path = os.ttyname(self._slave)
        self._stop.clear()
        if threaded:
            self._thread = threading.Thread(target=self._run, name="dxl-bus-emulator", daemon=True)
            self._thread.start()
        return self

    def pump(self) -> int:
        """Handle every complete packet the host has written so far, in the calling thread
        (for an emulator started with ``threaded=False``, e.g. to measure the host's CPU
        time without a second thread). Returns the number of packets handled."""
        if self._thread is not None:
            raise BridgeError("pump() is for an emulator started with threaded=False; this one has a reader thread")
        if self._master is None:
            raise BridgeError("the emulator is not started (or its port vanished)")
        handled = 0
        while True:
            t_first = self.clock()
            try:
                data = os.read(self._master, 65536)
            except (BlockingIOError, InterruptedError):
                return handled
            except OSError as exc:
                if exc.errno == errno.EIO:
                    return handled
                raise
            if not data:
                return handled
            self.rx_bytes += len(data)
            for frame in self._parser.feed(data):
                self._handle(frame, t_first)
                handled += 1

    def stop(self) -> None:
        """Stop the reader thread and close the pty (safe to call twice)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._thread = None
        self._close_fds()

    close = stop

    def __enter__(self) -> DynamixelBusEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _close_fds(self) -> None:
        for name in ("_master", "_slave"):
            fd = getattr(self, name)
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
                setattr(self, name, None)

    @property
    def port_path(self) -> str:
        """The pty device to give to ``PortHandler`` (e.g. /dev/pts/7)."""
        if not self._port_path:
            raise BridgeError("the emulator is not started: use it as a context manager or call start()")
        return self._port_path

    # ------------------------------------------------------------------ servo access
    @property
    def servos(self) -> list[EmulatedServo]:
        """The servos (not the devices) on the bus."""
        return [s for s in self._servos if not isinstance(s, EmulatedDevice)]

    @property
    def devices(self) -> list[EmulatedDevice]:
        """The non-servo devices (e.g. the OpenCR) on the bus."""
        return [s for s in self._servos if isinstance(s, EmulatedDevice)]

    def servo(self, servo_id: int) -> EmulatedServo:
        """The servo whose ID register is ``servo_id`` now."""
        for s in self._servos:
            if s.servo_id == servo_id:
                return s
        raise BridgeError(f"no emulated servo with ID {servo_id} (IDs: {sorted(s.servo_id for s in self._servos)})")

    def device(self, device_id: int) -> EmulatedDevice:
        """The non-servo device (e.g. the OpenCR) whose ID register is ``device_id`` now."""
        found = self.servo(device_id)
        if not isinstance(found, EmulatedDevice):
            raise BridgeError(f"ID {device_id} on the emulated bus is a servo, not a device")
        return found

    def set_imu(self, device_id: int, gyro=None, accel=None, quat=None) -> None:
        """The IMU sample device ``device_id`` reports (robot IMU frame: gyro rad/s, accel
        m/s^2, quat wxyz; see :meth:`EmulatedDevice.set_imu`)."""
        with self.lock:
            self.device(device_id).set_imu(gyro, accel, quat)

    def set_imu_source(self, device_id: int, source: ImuSource | None) -> None:
        """Report what ``source()`` returns at every read, (gyro, accel, quat): e.g. a
        physics model's IMU site. None: back to the values of :meth:`set_imu`."""
        with self.lock:
            self.device(device_id).imu_source = source

    def read_register(self, servo_id: int, name: str) -> int:
        """A register's value, with the motor model brought up to now."""
        with self.lock:
            s = self.servo(servo_id)
            s.advance()
            return s.get(name)

    def write_register(self, servo_id: int, name: str, value: int) -> None:
        """Set a register behind the bus's back (no access rules): e.g. a calibration offset."""
        with self.lock:
            s = self.servo(servo_id)
            s.advance()
            s.set(name, value)

    @property
    def goal_history(self) -> dict[int, list[GoalRecord]]:
        """Every Goal Position that reached each servo, by the servo's ID at creation order."""
        with self.lock:
            return {s.servo_id: list(s.goal_history) for s in self._servos}

    @property
    def violations(self) -> list[GoalRecord]:
        """Goals outside a servo's ``allowed_range`` (any servo), in time order."""
        with self.lock:
            return sorted((r for s in self._servos for r in s.violations), key=lambda r: r.stamp)

    def allowed_range(self, servo_id: int, lo: int | None, hi: int | None = None) -> None:
        """Set (or with ``lo=None`` clear) the goal range, in ticks, that counts as safe."""
        with self.lock:
            self.servo(servo_id).allowed_range = None if lo is None else (int(lo), int(hi))

    # ------------------------------------------------------------------ fault injection
    def drop_replies(self, servo_id: int, count: int | None = None) -> None:
        """Lose the next ``count`` replies of this servo (None: all until cleared)."""
        with self.lock:
            self.servo(servo_id).faults.drop_replies = -1 if count is None else int(count)

    def corrupt_replies(self, servo_id: int, count: int | None = None) -> None:
        """Send the next ``count`` replies with a broken CRC (None: all until cleared)."""
        with self.lock:
            self.servo(servo_id).faults.corrupt_replies = -1 if count is None else int(count)

    def disconnect(self, servo_id: int, disconnected: bool = True) -> None:
        """The servo drops off the bus: it neither hears nor answers."""
        with self.lock:
            self.servo(servo_id).faults.disconnected = disconnected

    def set_hardware_error(self, servo_id: int, bits: int, *, survives_reboot: bool = False) -> None:
        """Force Hardware Error Status bits (e.g. 0x20 overload); the alert bit follows."""
        with self.lock:
            s = self.servo(servo_id)
            s.advance()
            s.faults.injected_hw_error = int(bits)
            s.faults.hw_error_survives_reboot = survives_reboot
            s.refresh()

    def overheat(self, servo_id: int, celsius: float | None = None) -> None:
        """Hold the temperature at ``celsius`` (default: Temperature Limit + 5 °C)."""
        with self.lock:
            s = self.servo(servo_id)
            s.advance()
            if celsius is None:
                celsius = s.get("temperature_limit") + 5.0
            s.faults.held_temperature_c = float(celsius)
            s.refresh()

    def set_supply_voltage(self, servo_id: int, volts: float | None) -> None:
        """Supply voltage seen by the servo (None: its rated voltage)."""
        with self.lock:
            s = self.servo(servo_id)
            s.advance()
            s.faults.supply_v = volts
            s.refresh()

    def stick(self, servo_id: int, stuck: bool = True) -> None:
        """Block the motor: goal changes give stall current and, after 1 s, overload."""
        with self.lock:
            s = self.servo(servo_id)
            s.advance()
            s.faults.stuck = stuck

    def push(self, servo_id: int, ticks: float) -> None:
        """Move the horn by hand to ``ticks``."""
        with self.lock:
            self.servo(servo_id).push(ticks)

    def clear_faults(self, servo_id: int | None = None) -> None:
        """Undo injected faults (one servo or all); the temperature returns to ambient."""
        with self.lock:
            for s in self._servos if servo_id is None else [self.servo(servo_id)]:
                s.advance()
                held = s.faults.held_temperature_c is not None
                s.faults = type(s.faults)()
                if held:
                    s._temp = s.ambient_c
                s.refresh()

    def vanish(self) -> None:
        """Close the pty as if the adapter were unplugged."""
        with self.lock:
            self.vanished = True
            self._stop.set()
            self._close_fds()

    # ------------------------------------------------------------------ reader thread
    def _run(self) -> None:
        while not self._stop.is_set():
            master = self._master
            if master is None:
                return
            try:
                ready, _, _ = select.select([master], [], [], 0.05)
            except (OSError, ValueError):
                return
            if not ready:
                continue
            t_first = self.clock()
            try:
                data = os.read(master, 65536)
            except BlockingIOError:
                continue
            except OSError as exc:
                if exc.errno == errno.EIO:  # no process holds the slave open right now
                    time.sleep(0.01)
                    continue
                return
            if not data:
                continue
            self.rx_bytes += len(data)
            for frame in self._parser.feed(data):
                try:
                    self._handle(frame, t_first)
                except OSError:
                    return

    def _host_baud(self) -> int | None:
        """The baud rate the host configured on the pty (termios), or None if unknown."""
        try:
            attrs = termios.tcgetattr(self._master)
        except (termios.error, TypeError):
            return None
        speed = attrs[5]
        if speed in _BAUD_CONSTANTS and speed != 0:
            return _BAUD_CONSTANTS[speed]
        if speed == _BOTHER or speed & _BOTHER:
            try:
                buf = fcntl.ioctl(self._master, _TCGETS2, bytes(44))
                return struct.unpack_from("I", buf, 40)[0]
            except OSError:
                return None
        return None

    def _listeners(
        self, protocol: int, now: float, host_baud: int | None
    ) -> tuple[dict[int, EmulatedServo], list[EmulatedServo]]:
        """Servos that hear this packet (right protocol, connected, not booting, and at
        ``host_baud`` unless it is None), by ID; plus the servos whose ID another listener
        already has (an ID clash)."""
        out: dict[int, EmulatedServo] = {}
        twins: list[EmulatedServo] = []
        for s in self._servos:
            if s.protocol != protocol or s.faults.disconnected or now < s.booting_until:
                continue
            if host_baud is not None:
                servo_baud = s.baud()
                if servo_baud is None or abs(servo_baud - host_baud) > BAUD_TOLERANCE * host_baud:
                    continue
            sid = s.servo_id
            if sid in out:
                twins.append(s)
            else:
                out[sid] = s
        return out, twins

    def _handle(self, frame: dp.Frame, t_first: float) -> None:
        with self.lock:
            self.received.append(frame.raw)
            now = self.clock()
            host_baud = self._host_baud()  # one termios read per packet
            wire_baud = host_baud or self.baud
            t_start = max(t_first, self._bus_free_at)
            t_end_in = t_start + 10.0 * len(frame.raw) / wire_baud
            self._bus_free_at = t_end_in
            listeners, twins = self._listeners(frame.protocol, now, host_baud if self.match_baud else None)
            if frame.valid:
                for s in list(listeners.values()) + twins:
                    s.heard(now)  # restarts each servo's Bus Watchdog interval
            dispatch = self._dispatch2 if frame.protocol == 2 else self._dispatch1
            replies = dispatch(frame, listeners)
            target = frame.raw[4] if frame.protocol == 2 else frame.raw[2]
            clash = [t for t in twins if t.servo_id == target]
            if clash:
                # two servos with one ID: each executes the instruction and they answer at
                # once; the host receives the overlap as one packet with a broken CRC
                for twin in clash:
                    replies += dispatch(frame, {**listeners, target: twin}, count=False)
                if len(replies) > 1:
                    first_servo, raw = replies[0]
                    replies = [(first_servo, raw[:-1] + bytes((raw[-1] ^ 0xFF,)))]
            self._emit(replies, t_end_in, wire_baud)

    def _emit(self, replies: list[tuple[EmulatedServo, bytes]], t_end_in: float, baud: int) -> None:
        t = t_end_in
        for servo, raw in replies:
            if self._master is None:
                return
            if self.wire_timing:
                t = t + servo.return_delay_s() + 10.0 * len(raw) / baud
                _sleep_until(t, self.clock)
            os.write(self._master, raw)
            self.tx_bytes += len(raw)
        if self.wire_timing:
            self._bus_free_at = max(self._bus_free_at, t)

    def _count(self, instruction: int) -> None:
        name = dp.INSTRUCTION_NAMES.get(instruction, f"0x{instruction:02X}")
        self.instruction_counts[name] = self.instruction_counts.get(name, 0) + 1

    # ------------------------------------------------------------------ protocol 2.0
    def _status2(
        self, servo: EmulatedServo, error: int = 0, params: bytes = b"", reply_id: int | None = None
    ) -> tuple[EmulatedServo, bytes] | None:
        """A status packet from ``servo`` unless a fault swallows it. ``reply_id``: the ID
        the instruction addressed (a write that changes the ID is answered from the old one)."""
        if servo.faults.take("drop_replies"):
            return None
        sid = servo.servo_id if reply_id is None else reply_id
        raw = dp.encode_status(sid, error | servo.status_error(), params)
        if servo.faults.take("corrupt_replies"):
            raw = raw[:-2] + bytes((raw[-2] ^ 0xFF, raw[-1] ^ 0xFF))
        return servo, raw

    def _dispatch2(
        self, frame: dp.Frame, servos: dict[int, EmulatedServo], count: bool = True
    ) -> list[tuple[EmulatedServo, bytes]]:
        """The replies a protocol 2.0 packet draws from ``servos`` (the listeners, by ID), in
        the order they go out. ``count``: add the packet to the statistics (False when an ID
        clash makes a second servo execute it)."""
        target = frame.raw[4]
        if not frame.valid:
            self.crc_errors += count
            s = servos.get(target)
            rep = self._status2(s, dp.ERR_CRC) if s is not None else None
            return [rep] if rep else []
        pkt = dp.decode_packet(frame.raw)
        if pkt.is_status:
            return []  # another device's reply (or our own echo): not for servos
        if count:
            self._count(pkt.instruction)
        req = _Instruction(pkt.instruction, pkt.params, target, servos)
        name = dp.INSTRUCTION_NAMES.get(req.inst, "")
        if name in self.unsupported or (self._has_devices and not _narrow_to_capable(req, name)):
            self._refuse2(req)
        else:
            self._HANDLERS2.get(req.inst, DynamixelBusEmulator._refuse2)(self, req)
        return req.sent()

    def _reply2(self, req: _Instruction, servo: EmulatedServo, level: int, error: int = 0, data: bytes = b"") -> None:
        """``servo`` answers a packet addressed to it (not broadcast) when its Status Return
        Level is at least ``level`` (0: PING only, 1: reads too, 2: everything)."""
        if not req.broadcast and servo.status_return_level() >= level:
            req.replies.append(self._status2(servo, error, data, reply_id=req.target))

    def _refuse2(self, req: _Instruction) -> None:
        """An instruction the servo does not take (unknown, missing from its firmware, or a
        group instruction not sent to the broadcast ID): an instruction error."""
        if req.unicast is not None:
            self._reply2(req, req.unicast, 0, dp.ERR_INSTRUCTION)

    def _ping2(self, req: _Instruction) -> None:
        """Model number (2 bytes) and firmware version; a broadcast PING is answered by all."""
        group = sorted(req.servos.values(), key=lambda s: s.servo_id) if req.broadcast else req.group()
        for s in group:
            req.replies.append(
                self._status2(
                    s, 0, s.model.model_number.to_bytes(2, "little") + bytes((s.get("firmware_version") & 0xFF,))
                )
            )

    def _read2(self, req: _Instruction) -> None:
        s = req.unicast
        if s is None:
            return
        if len(req.params) != 4:
            self._reply2(req, s, 1, dp.ERR_DATA_LENGTH)
            return
        data = s.read(_u16(req.params, 0), _u16(req.params, 2))
        self._reply2(req, s, 1, dp.ERR_ACCESS if data is None else 0, data or b"")

    def _write2(self, req: _Instruction) -> None:
        """WRITE, and REG_WRITE (held until ACTION)."""
        for s in req.group():
            if len(req.params) < 3:
                self._reply2(req, s, 2, dp.ERR_DATA_LENGTH)
                continue
            addr, data = _u16(req.params, 0), req.params[2:]
            result = s.write(addr, data) if req.inst == dp.WRITE else s.reg_write(addr, data)
            self._reply2(req, s, 2, 0 if result.ok else _P2_WRITE_ERRORS[result.error])

    def _action2(self, req: _Instruction) -> None:
        for s in req.group():
            done = s.action()
            self._reply2(req, s, 2, 0 if done else dp.ERR_INSTRUCTION)

    def _reboot2(self, req: _Instruction) -> None:
        for s in req.group():
            self._reply2(req, s, 2)
            s.reboot(self.reboot_time_s)

    def _factory_reset2(self, req: _Instruction) -> None:
        option = req.params[0] if req.params else 0xFF
        if req.broadcast and option == 0xFF:
            return  # resetting everything, IDs included, by broadcast is refused (silence)
        for s in req.group():
            self._reply2(req, s, 2)
            s.factory_reset(option)

    def _clear2(self, req: _Instruction) -> None:
        """CLEAR of the multi-turn count; any other option or key is a data range error."""
        if req.unicast:
            ok = req.params[:5] == _CLEAR_MULTI_TURN
            self._reply2(req, req.unicast, 2, 0 if ok else dp.ERR_DATA_RANGE)

    def _sync_read2(self, req: _Instruction) -> None:
        """SYNC_READ and FAST_SYNC_READ: one address and length, then the IDs."""
        if not (req.broadcast and len(req.params) >= 4):
            self._refuse2(req)
            return
        addr, length = _u16(req.params, 0), _u16(req.params, 2)
        self._group_read2(req, [(i, addr, length) for i in req.params[4:]])

    def _bulk_read2(self, req: _Instruction) -> None:
        """BULK_READ and FAST_BULK_READ: (ID, address, length) per servo."""
        if not req.broadcast:
            self._refuse2(req)
            return
        p = req.params
        self._group_read2(req, [(p[k], _u16(p, k + 1), _u16(p, k + 3)) for k in range(0, len(p) - 4, 5)])

    def _group_read2(self, req: _Instruction, items: list[tuple[int, int, int]]) -> None:
        """The (ID, address, length) reads of a group read: one status packet per servo in
        order, or for the fast forms one packet they build together."""
        if req.inst in (dp.FAST_SYNC_READ, dp.FAST_BULK_READ):
            req.replies.extend(self._fast_read(items, req.servos))
            return
        for i, addr, length in items:
            s = req.servos.get(i)
            if s is not None and s.status_return_level() >= 1:
                data = s.read(addr, length)
                req.replies.append(self._status2(s, dp.ERR_ACCESS if data is None else 0, data or b""))

    def _sync_write2(self, req: _Instruction) -> None:
        """One address and length, then (ID, data) per servo; never answered."""
        if not (req.broadcast and len(req.params) >= 4):
            self._refuse2(req)
            return
        addr, length = _u16(req.params, 0), _u16(req.params, 2)
        body = req.params[4:]
        for k in range(0, len(body) - length, length + 1):
            s = req.servos.get(body[k])
            if s is not None:
                s.write(addr, body[k + 1 : k + 1 + length], "SYNC_WRITE")

    def _bulk_write2(self, req: _Instruction) -> None:
        """(ID, address, length, data) per servo; never answered."""
        if not req.broadcast:
            self._refuse2(req)
            return
        p, k = req.params, 0
        while k + 5 <= len(p):
            i, addr, length = p[k], _u16(p, k + 1), _u16(p, k + 3)
            s = req.servos.get(i)
            if s is not None:
                s.write(addr, p[k + 5 : k + 5 + length], "BULK_WRITE")
            k += 5 + length

    #: The handler of each protocol 2.0 instruction; any other gets an instruction error.
    _HANDLERS2: dict[int, Callable[[DynamixelBusEmulator, _Instruction], None]] = {
        dp.PING: _ping2,
        dp.READ: _read2,
        dp.WRITE: _write2,
        dp.REG_WRITE: _write2,
        dp.ACTION: _action2,
        dp.REBOOT: _reboot2,
        dp.FACTORY_RESET: _factory_reset2,
        dp.CLEAR: _clear2,
        dp.SYNC_READ: _sync_read2,
        dp.FAST_SYNC_READ: _sync_read2,
        dp.SYNC_WRITE: _sync_write2,
        dp.BULK_READ: _bulk_read2,
        dp.FAST_BULK_READ: _bulk_read2,
        dp.BULK_WRITE: _bulk_write2,
    }

    def _fast_read(
        self, items: list[tuple[int, int, int]], servos: dict[int, EmulatedServo]
    ) -> list[tuple[EmulatedServo, bytes]]:
        """FAST_SYNC_READ / FAST_BULK_READ: one packet built servo by servo. A silent
        servo breaks the chain: the reply is cut where its part should begin."""
        parts, owners = [], []
        for i, addr, length in items:
            s = servos.get(i)
            if s is None or s.status_return_level() < 1 or s.faults.take("drop_replies"):
                break
            data = s.read(addr, length)
            parts.append((s.status_error() | (dp.ERR_ACCESS if data is None else 0), i, data or bytes(length)))
            owners.append(s)
        if not parts:
            return []
        announced = 1 + sum(4 + length for _, _, length in items)
        raw = bytearray(dp.encode_fast_status(parts, announced))
        pos = 8
        for (_err, _i, data), s in zip(parts, owners):
            if s.faults.take("corrupt_replies"):
                raw[pos + 2 if data else pos] ^= 0xFF  # flip a byte; the packet CRC no longer holds
            pos += 4 + len(data)
        # the whole packet goes out at once; its timing is charged to the last servo in it
        return [(owners[-1], bytes(raw))]

    # ------------------------------------------------------------------ protocol 1.0
    def _status1(
        self, servo: EmulatedServo, error: int = 0, params: bytes = b"", reply_id: int | None = None
    ) -> tuple[EmulatedServo, bytes] | None:
        if servo.faults.take("drop_replies"):
            return None
        sid = servo.servo_id if reply_id is None else reply_id
        raw = dp.encode_status1(sid, error | servo.status_error(), params)
        if servo.faults.take("corrupt_replies"):
            raw = raw[:-1] + bytes((raw[-1] ^ 0xFF,))
        return servo, raw

    def _dispatch1(
        self, frame: dp.Frame, servos: dict[int, EmulatedServo], count: bool = True
    ) -> list[tuple[EmulatedServo, bytes]]:
        raw = frame.raw
        target = raw[2]
        broadcast = target == dp.BROADCAST_ID
        unicast = servos.get(target)
        if not frame.valid:
            self.crc_errors += count
            rep = self._status1(unicast, dp.ERR1_CHECKSUM) if unicast is not None else None
            return [rep] if rep else []
        pkt = dp.decode_packet1(raw, status=False)
        inst, params = pkt.instruction, pkt.params
        if count:
            self._count(inst)
        replies: list[tuple[EmulatedServo, bytes] | None] = []

        def reply_level(servo: EmulatedServo, level: int, error: int = 0, data: bytes = b"") -> None:
            if not broadcast and servo.status_return_level() >= level:
                replies.append(self._status1(servo, error, data, reply_id=target))

        group = list(servos.values()) if broadcast else [unicast] if unicast else []
        if inst == dp.PING:
            if unicast:
                replies.append(self._status1(unicast))
        elif inst == dp.READ:
            if unicast and len(params) == 2:
                data = unicast.read(params[0], params[1])
                reply_level(unicast, 1, dp.ERR1_RANGE if data is None else 0, data or b"")
        elif inst in (dp.WRITE, dp.REG_WRITE):
            for s in group:
                if len(params) < 2:
                    reply_level(s, 2, dp.ERR1_RANGE)
                    continue
                result = s.write(params[0], params[1:]) if inst == dp.WRITE else s.reg_write(params[0], params[1:])
                reply_level(s, 2, 0 if result.ok else _P1_WRITE_ERRORS[result.error])
        elif inst == dp.ACTION:
            for s in group:
                done = s.action()
                reply_level(s, 2, 0 if done else dp.ERR1_INSTRUCTION)
        elif inst == dp.FACTORY_RESET:
            for s in group:
                reply_level(s, 2)
                s.factory_reset(0xFF)
        elif inst == dp.SYNC_WRITE and broadcast and len(params) >= 2:
            addr, length = params[0], params[1]
            body = params[2:]
            for k in range(0, len(body) - length, length + 1):
                s = servos.get(body[k])
                if s is not None:
                    s.write(addr, body[k + 1 : k + 1 + length], "SYNC_WRITE")
        elif inst == dp.BULK_READ and broadcast and params:
            body = params[1:]
            for k in range(0, len(body) - 2, 3):
                length, i, addr = body[k], body[k + 1], body[k + 2]
                s = servos.get(i)
                if s is not None and s.status_return_level() >= 1:
                    data = s.read(addr, length)
                    replies.append(self._status1(s, dp.ERR1_RANGE if data is None else 0, data or b""))
        elif unicast is not None:
            reply_level(unicast, 0, dp.ERR1_INSTRUCTION)
        return [r for r in replies if r is not None]


def _u16(data: bytes, at: int) -> int:
    return data[at] | (data[at + 1] << 8)


def _sleep_until(t: float, clock: Callable[[], float]) -> None:
    """Sleep until ``t``. Never spins: a spinning emulator thread would hold the GIL the
    host's SDK (in the same process) needs; sleep overshoots by ~0.1 ms on Linux."""
    left = t - clock()
    while left > 0:
        time.sleep(left)
        left = t - clock()


__all__ = ["DynamixelBusEmulator", "ServoSpec", "DEFAULT_MODELS"]
