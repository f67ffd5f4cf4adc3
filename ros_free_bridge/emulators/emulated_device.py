"""One emulated non-servo device on the bus: the OP3's OpenCR sub-controller and its IMU.

Its control table is the device model's (:mod:`firmware_cfg.device_models`); the bus
emulator calls it like a servo (same lock, same duck-typed interface: ``read``, ``write``,
``status_error`` ...) but it answers only the instructions its firmware has
(``supports``). The IMU registers are filled at every read from ``imu_source``: a callable
returning ``(gyro (3,) rad/s, accel (3,) m/s^2, quat (4,) wxyz)`` in the robot's IMU frame
(x forward, y left, z up), e.g. a physics model's IMU site; without one, the values set
with :meth:`EmulatedDevice.set_imu` (default: a still, upright robot: gyro 0, accel +g on
z, identity attitude). Values are turned into raw counts with the model's units and its
board mounting, exactly inverting what the transport does.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from firmware_cfg.device_models import STANDARD_GRAVITY, DeviceModel
from ros_free_bridge.dynamixel.imu import imu_raw_values, rotate_into
from ros_free_bridge.emulators.emulated_servo import Faults, WriteResult

ImuSource = Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]]


class EmulatedDevice:
    """A device's state. ``servo_id`` is read from its ID register (it can be rewritten)."""

    def __init__(
        self,
        model: DeviceModel,
        device_id: int,
        *,
        clock: Callable[[], float] = time.monotonic,
        imu_source: ImuSource | None = None,
    ) -> None:
        self.model = model
        self.clock = clock
        self.faults = Faults()
        self.goal_history: list = []  # a device takes no goals; kept for the bus's inspection API
        self.violations: list = []
        self.allowed_range = None
        self.booting_until = 0.0
        self.imu_source = imu_source
        self.imu_reads = 0
        self._mem = bytearray(model.table_size)
        for r in model.registers.values():
            self.set(r.name, r.initial or 0)
        self.set("id", device_id)
        self._imu = (np.zeros(3), np.array([0.0, 0.0, STANDARD_GRAVITY]), np.array([1.0, 0.0, 0.0, 0.0]))
        if model.imu is not None:
            self._imu_span = model.block(model.imu_registers)
        else:
            self._imu_span = (0, 0)

    # ------------------------------------------------------------------ what the bus calls
    @property
    def servo_id(self) -> int:
        return self.get("id")

    @property
    def protocol(self) -> int:
        return self.model.protocol

    def supports(self, instruction_name: str) -> bool:
        return instruction_name in self.model.instructions

    def has(self, name: str) -> bool:
        return name in self.model.registers

    def get(self, name: str) -> int:
        r = self.model.register(name)
        return r.decode(self._mem[r.address : r.end])

    def set(self, name: str, value: int) -> None:
        r = self.model.register(name)
        self._mem[r.address : r.end] = r.encode(value)

    def advance(self, now: float | None = None) -> None:
        """Nothing moves on its own (kept for the bus's register back door)."""

    def refresh(self) -> None:
        """Nothing to recompute (kept for the bus's fault API)."""

    def heard(self, now: float | None = None) -> None:
        """A valid packet was on the bus; the device has no watchdog."""

    def baud(self) -> int | None:
        """The OpenCR's Baud register counts like the X series' (4: 2 Mbit/s, 3: 1 Mbit/s, 1: 57600)."""
        return {0: 9600, 1: 57600, 2: 115200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000, 6: 4_000_000}.get(
            self.get("baud_rate")
        )

    def return_delay_s(self) -> float:
        return self.get("return_delay_time") * 2e-6

    def status_return_level(self) -> int:
        return self.get("status_return_level")

    def status_error(self) -> int:
        return 0

    def read(self, address: int, length: int) -> bytes | None:
        """Bytes [address, address+length), the IMU registers refreshed first; None when the
        span leaves the table (the firmware answers that with a length error)."""
        if address < 0 or length < 0 or address + length > len(self._mem):
            return None
        start, n = self._imu_span
        if n and address < start + n and address + length > start:
            self._refresh_imu()
        return bytes(self._mem[address : address + length])

    def write(self, address: int, data: bytes, instruction: str = "WRITE") -> WriteResult:
        """Writes to read-only bytes are ignored (as the firmware does); a span past the
        table is a length error."""
        if address + len(data) > len(self._mem):
            return WriteResult("length")
        for k, byte in enumerate(data):
            reg = next((r for r in self.model.registers.values() if r.address <= address + k < r.end), None)
            if reg is not None and reg.writable:
                self._mem[address + k] = byte
        return WriteResult(None)

    # ------------------------------------------------------------------ IMU
    def set_imu(self, gyro=None, accel=None, quat=None) -> None:
        """The sample to report while no ``imu_source`` is set, robot IMU frame, SI units.
        ``quat`` (wxyz) alone gives a still robot at that attitude: accel = R^T (0, 0, g)."""
        g0, a0, q0 = self._imu
        q = q0 if quat is None else np.asarray(quat, float) / np.linalg.norm(quat)
        if accel is None and quat is not None:
            accel = rotate_into(q, np.array([0.0, 0.0, STANDARD_GRAVITY]))
        self._imu = (
            g0 if gyro is None else np.asarray(gyro, float),
            a0 if accel is None else np.asarray(accel, float),
            q,
        )

    def _refresh_imu(self) -> None:
        gyro, accel, quat = self.imu_source() if self.imu_source is not None else self._imu
        self.imu_reads += 1
        for name, value in imu_raw_values(self.model, gyro, accel, quat).items():
            self.set(name, value)


__all__ = ["EmulatedDevice", "ImuSource"]
