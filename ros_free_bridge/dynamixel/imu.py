"""An IMU device's registers <-> :class:`~ros_free_bridge.transports.base.ImuReading` (SI, robot frame).

The device model (:mod:`firmware_cfg.device_models`) says which registers hold the gyro,
accelerometer and roll/pitch/yaw, their units and how the board is mounted
(v_robot = mount * v_board, a rotation). :class:`ImuBlock` is the one READ span that holds
them and its decode; :func:`imu_raw_values` is the inverse, for the emulator. Quaternions
are w, x, y, z; roll/pitch/yaw are Z-Y-X Euler angles (R = Rz(yaw) Ry(pitch) Rx(roll)).
"""

from __future__ import annotations

import math
import struct
import time

import dynamixel_sdk as sdk
import numpy as np

from firmware_cfg.device_models import DeviceModel
from ros_free_bridge.errors import BridgeError
from ros_free_bridge.transports.base import ImuReading

_INT16 = (-32768, 32767)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a ⊗ b of two wxyz quaternions."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def quat_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """wxyz of R = Rz(yaw) Ry(pitch) Rx(roll), rad."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


def rpy_from_quat(q: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) rad of a wxyz quaternion, the inverse of :func:`quat_from_rpy`."""
    w, x, y, z = q / np.linalg.norm(q)
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.array([roll, pitch, yaw])


def rotate_into(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R(q)^T v: a world vector ``v`` (3,) expressed in the frame whose orientation is ``q``."""
    w, x, y, z = q / np.linalg.norm(q)
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    return r.T @ np.asarray(v, float)


def mount_quat(mount) -> np.ndarray:
    """The rotation (wxyz) whose matrix is diag(``mount``): identity or 180 deg about one axis."""
    if int(np.prod(mount)) != 1:
        raise ValueError(f"board mount {tuple(mount)} is a reflection, not a rotation")
    q = np.zeros(4)
    ones = [i for i, s in enumerate(mount) if s == 1]
    if len(ones) == 3:
        q[0] = 1.0
    else:
        q[1 + ones[0]] = 1.0
    return q


class ImuBlock:
    """The READ of a device's IMU registers (``start``, ``length`` bytes) and its decode.

    gyro rad/s = mount · counts · gyro unit; accel m/s^2 = mount · counts · accel unit;
    quat = q(roll, pitch, yaw of the board) ⊗ q(mount), the robot IMU frame in the world."""

    def __init__(self, model: DeviceModel) -> None:
        if model.imu is None:
            raise ValueError(f"device model {model.name} has no IMU")
        lay = model.imu
        self.model = model
        self.start, self.length = model.block(model.imu_registers)
        fmt = ["<"]
        pos = self.start
        for name in model.imu_registers:
            r = model.register(name)
            if r.address > pos:
                fmt.append(f"{r.address - pos}x")
            fmt.append(
                {(2, True): "h", (2, False): "H", (1, True): "b", (1, False): "B", (4, True): "i"}[r.size, r.signed]
            )
            pos = r.end
        self._unpack = struct.Struct("".join(fmt)).unpack
        m = np.asarray(lay.mount, float)
        self._scale = np.concatenate((m * lay.gyro_rad_s, m * lay.accel_m_s2))
        self._rpy_rad = lay.rpy_rad
        self._q_mount = mount_quat(lay.mount)

    def decode(self, data: bytes, stamp: float) -> ImuReading:
        """``length`` bytes read from ``start`` -> the reading, stamped ``stamp``."""
        raw = self._unpack(bytes(data[: self.length]))
        ga = np.asarray(raw[:6], float) * self._scale
        roll, pitch, yaw = (v * self._rpy_rad for v in raw[6:9])
        quat = quat_mul(quat_from_rpy(roll, pitch, yaw), self._q_mount)
        if quat[0] < 0:  # q and -q are one rotation: report the one with w >= 0
            quat = -quat
        return ImuReading(ga[:3], ga[3:], quat, stamp)


def imu_raw_values(model: DeviceModel, gyro, accel, quat) -> dict[str, int]:
    """The register values (counts, int16-clipped) a device reports for a sample in the
    robot frame: the inverse of :meth:`ImuBlock.decode` up to rounding."""
    lay = model.imu
    mount = np.asarray(lay.mount, float)
    q = np.asarray(quat, float)
    board_rpy = rpy_from_quat(quat_mul(q / np.linalg.norm(q), mount_quat(lay.mount)))  # q_mount⁻¹ = ±q_mount
    out = {}
    for names, values, unit in (
        (lay.gyro, mount * np.asarray(gyro, float), lay.gyro_rad_s),
        (lay.accel, mount * np.asarray(accel, float), lay.accel_m_s2),
        (lay.rpy, board_rpy, lay.rpy_rad),
    ):
        for name, v in zip(names, values):
            out[name] = int(np.clip(round(float(v) / unit), *_INT16))
    return out


#: Consecutive missed IMU reads after which the device counts as lost (a fault note),
#: and the pause between tries while it is lost (each try may cost a reply timeout).
IMU_MISS_LIMIT = 3
IMU_RETRY_S = 1.0


class ImuDevice:
    """The bus side of one IMU device (e.g. the OP3's OpenCR, ID 200): the model check at
    ``open``, and one READ of its IMU block per bus cycle, blocking (:meth:`read`) or split
    (:meth:`send` leaves the reply on the wire, :meth:`collect` takes it before the next
    transfer). ``reading`` is the last cycle's sample (None when that read failed or was
    skipped). A device that does not answer is never an exception: after
    :data:`IMU_MISS_LIMIT` misses in a row ``fault`` says so (and ``notes`` gets a line),
    and it is tried again every ``retry_s`` (:data:`IMU_RETRY_S`) s; the first good reply clears it.

    ``bus``: a :class:`~ros_free_bridge.dynamixel.bus.DynamixelBus` (open);
    ``notes``: a list that receives one line per fault change."""

    def __init__(self, bus, device_id: int, model: DeviceModel, notes: list[str]) -> None:
        self.bus, self.id, self.model, self.notes = bus, device_id, model, notes
        self.block = ImuBlock(model)
        self.retry_s = IMU_RETRY_S  #: pause between tries while the device is lost, s
        self.reading: ImuReading | None = None
        self.fault: str | None = None
        self.reads = self.misses = 0
        self._in_row = 0
        self._retry_at = 0.0
        self._sent = 0.0
        self._ready: tuple | None = None  # (data, COMM code, error byte, stamp) of a split read

    @property
    def label(self) -> str:
        return f"{self.model.name} (ID {self.id}, IMU)"

    def open(self) -> None:
        """PING the device and check its model number; a silent device is a fault note (the
        robot runs without ``JointState.imu``), a different model a BridgeError."""
        try:
            number = self.bus.ping(self.id)
        except BridgeError as exc:
            self._lost(f"no answer to PING ({exc})")
            return
        if number != self.model.model_number:
            raise BridgeError(
                f"{self.label} on {self.bus.port_name}: model number {number} but the config says "
                f"{self.model.name} ({self.model.model_number}); fix the config's devices or the wiring"
            )
        self.read()

    def due(self) -> bool:
        """Whether this cycle reads the device (always, unless it is lost and waiting)."""
        return self.fault is None or time.monotonic() >= self._retry_at

    def read(self) -> None:
        """One blocking READ of the IMU block (no retries: a missed sample is skipped)."""
        stamp = time.monotonic()
        data, result, error = self.bus.call(
            self.bus.ph.readTxRx, self.id, self.block.start, self.block.length, malformed=([], sdk.COMM_RX_CORRUPT, 0)
        )
        self._apply(data, result, error, stamp)

    def send(self) -> bool:
        """Split phase: send the READ request, leave its reply on the wire; False if the
        write failed (counted as a miss)."""
        self._sent = time.monotonic()

        def op(port) -> int:
            port.discardInput()
            return self.bus.ph.readTx(port, self.id, self.block.start, self.block.length)

        if self.bus.call(op) != sdk.COMM_SUCCESS:
            self._apply([], sdk.COMM_TX_FAIL, 0, self._sent)
            return False
        return True

    def collect(self) -> None:
        """Split phase: read the reply of :meth:`send` (waiting at most its timeout)."""
        data, result, error = self.bus.call(
            self.bus.ph.readRx, self.id, self.block.length, malformed=([], sdk.COMM_RX_CORRUPT, 0)
        )
        self._ready = (data, result, error, self._sent)

    def take(self) -> None:
        """Apply a collected split-phase reply to ``reading``, if there is one."""
        if self._ready is not None:
            ready, self._ready = self._ready, None
            self._apply(*ready)

    def reset(self) -> None:
        self._ready = None

    def _apply(self, data, result: int, error: int, stamp: float) -> None:
        if result == sdk.COMM_SUCCESS and len(data) == self.block.length and not error & 0x7F:
            self.reading = self.block.decode(bytes(data), stamp)
            self.reads += 1
            self._in_row = 0
            if self.fault is not None:
                self.notes.append(f"{self.label}: answers again; IMU readings resume")
                self.fault = None
            return
        self.reading = None
        self.misses += 1
        self._in_row += 1
        why = (
            f"READ refused ({self.bus.error_text(error)})"
            if result == sdk.COMM_SUCCESS and error & 0x7F
            else self.bus.comm_text(result)
        )
        if self.fault is not None:
            self._retry_at = time.monotonic() + self.retry_s
        elif self._in_row >= IMU_MISS_LIMIT:
            self._lost(f"{self._in_row} reads in a row failed ({why})")

    def _lost(self, why: str) -> None:
        self.fault = (
            f"{self.label} on {self.bus.port_name}: {why}; JointState.imu is None until it answers "
            f"(tried again every {self.retry_s:g} s); check its cable, power and ID"
        )
        self.notes.append(self.fault)
        self.reading = None
        self._retry_at = time.monotonic() + self.retry_s
