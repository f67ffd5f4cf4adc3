"""Control tables of non-servo devices on a Dynamixel bus (the OP3's OpenCR), as data.

A :class:`DeviceModel` is what the hardware config's ``devices[].model`` names: its model
number (what PING returns), protocol, the instructions its firmware answers, its registers
(:class:`firmware_cfg.servo_models.Register`) and, for an IMU, how the raw registers map
to SI units in the robot's IMU frame (x forward, y left, z up). Transports and the bus
emulator read these; nothing here does I/O.

Depends on nothing else of this project but :mod:`firmware_cfg.servo_models`' Register.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from firmware_cfg.errors import ConfigError
from firmware_cfg.servo_models import Register

#: Standard gravity (m/s^2): the OpenCR's accelerometer counts in g.
STANDARD_GRAVITY = 9.80665


@dataclass(frozen=True)
class ImuLayout:
    """Where a device keeps its IMU sample and the units of each register.

    ``gyro`` / ``accel`` / ``rpy``: register names of x, y, z (roll, pitch, yaw for ``rpy``,
    Z-Y-X Euler angles of the board in the world). Units per raw count: ``gyro_rad_s``,
    ``accel_m_s2`` (specific force: +1 g on z when level and still), ``rpy_rad``.
    ``mount``: the sign of each board axis in the robot's IMU frame (the board sits turned
    180 deg about z on the OP3: x and y flip), i.e. v_robot = mount * v_board, a rotation."""

    gyro: tuple[str, str, str]
    accel: tuple[str, str, str]
    rpy: tuple[str, str, str]
    gyro_rad_s: float
    accel_m_s2: float
    rpy_rad: float
    mount: tuple[int, int, int]


@dataclass(frozen=True)
class DeviceModel:
    """One device model: name (and aliases), model number, protocol, the instruction
    names its firmware answers, registers by name, and its IMU layout (None: no IMU)."""

    name: str
    model_number: int
    protocol: int
    firmware_version: int
    instructions: frozenset[str]
    registers: dict[str, Register]
    imu: ImuLayout | None = None
    aliases: tuple[str, ...] = ()

    def register(self, name: str) -> Register:
        try:
            return self.registers[name]
        except KeyError:
            raise ConfigError(f"device model {self.name} has no register {name!r}") from None

    @property
    def table_size(self) -> int:
        return max(r.end for r in self.registers.values())

    def block(self, names) -> tuple[int, int]:
        """(start address, length) of the smallest span holding the registers ``names``."""
        regs = [self.register(n) for n in names]
        start = min(r.address for r in regs)
        return start, max(r.end for r in regs) - start

    @property
    def imu_registers(self) -> tuple[str, ...]:
        """The IMU's registers in the order gyro xyz, accel xyz, roll pitch yaw."""
        return () if self.imu is None else self.imu.gyro + self.imu.accel + self.imu.rpy


def _reg(name, address, size, access, area, initial=0, signed=False, rng=None) -> Register:
    return Register(name, address, size, access, area, initial, rng, signed)


# ROBOTIS OpenCR running the OP3 sub-controller firmware (ID 200 on the OP3's servo bus).
# Sources (facts only): the firmware's control-table layout and model number,
# ROBOTIS-GIT/OpenCR arduino/opencr_arduino/opencr/libraries/OP3/examples/opencr_op3/
# dxl_node_op3.h (model number 0x7400, firmware 2, ID 200, baud register 4) and
# dxl_node_op3.cpp (instructions registered: PING, READ, WRITE, SYNC_READ, SYNC_WRITE,
# BULK_READ, BULK_WRITE; no FAST_* reads); dxl_hw_op3.cpp (roll/pitch/yaw = degrees x 10,
# raw MPU-9250 gyro/accelerometer counts); the ROBOTIS Framework's device file
# robotis_device/devices/sensor/OPEN-CR.device (the same table); and ROBOTIS-OP3's
# open_cr_module (gyro 2000 deg/s per 32800 counts, accelerometer 2 g per 32768 counts,
# g = 9.80665 m/s^2, x and y negated to align the board with the robot).
_OPENCR_REGS = (
    _reg("model_number", 0, 2, "R", "EEPROM", 0x7400),
    _reg("firmware_version", 2, 1, "R", "EEPROM", 2),
    _reg("id", 3, 1, "RW", "EEPROM", 200, rng=(0, 252)),
    _reg("baud_rate", 4, 1, "RW", "EEPROM", 4, rng=(0, 252)),
    _reg("return_delay_time", 5, 1, "RW", "EEPROM", 0, rng=(0, 254)),
    _reg("status_return_level", 16, 1, "RW", "EEPROM", 2, rng=(0, 2)),
    _reg("roll_offset", 18, 2, "RW", "EEPROM", 0, signed=True),
    _reg("pitch_offset", 20, 2, "RW", "EEPROM", 0, signed=True),
    _reg("yaw_offset", 22, 2, "RW", "EEPROM", 0, signed=True),
    _reg("dynamixel_power", 24, 1, "RW", "RAM", 1, rng=(0, 1)),
    _reg("led", 25, 1, "RW", "RAM", 0, rng=(0, 7)),
    _reg("led_rgb", 26, 2, "RW", "RAM", 0x1F, rng=(0, 32767)),
    _reg("buzzer", 28, 2, "RW", "RAM", 0),
    _reg("button", 30, 1, "R", "RAM", 0),
    _reg("present_voltage", 31, 1, "R", "RAM", 120),  # 0.1 V
    _reg("gyro_x", 32, 2, "R", "RAM", 0, signed=True),
    _reg("gyro_y", 34, 2, "R", "RAM", 0, signed=True),
    _reg("gyro_z", 36, 2, "R", "RAM", 0, signed=True),
    _reg("acc_x", 38, 2, "R", "RAM", 0, signed=True),
    _reg("acc_y", 40, 2, "R", "RAM", 0, signed=True),
    _reg("acc_z", 42, 2, "R", "RAM", 16384, signed=True),
    _reg("roll", 44, 2, "R", "RAM", 0, signed=True),
    _reg("pitch", 46, 2, "R", "RAM", 0, signed=True),
    _reg("yaw", 48, 2, "R", "RAM", 0, signed=True),
    _reg("imu_control", 50, 1, "RW", "RAM", 0, rng=(0, 255)),
)

OPENCR = DeviceModel(
    name="OpenCR",
    model_number=0x7400,
    protocol=2,
    firmware_version=2,
    instructions=frozenset({"PING", "READ", "WRITE", "SYNC_READ", "SYNC_WRITE", "BULK_READ", "BULK_WRITE"}),
    registers={r.name: r for r in _OPENCR_REGS},
    imu=ImuLayout(
        gyro=("gyro_x", "gyro_y", "gyro_z"),
        accel=("acc_x", "acc_y", "acc_z"),
        rpy=("roll", "pitch", "yaw"),
        gyro_rad_s=2000.0 / 32800.0 * math.pi / 180.0,
        accel_m_s2=2.0 / 32768.0 * STANDARD_GRAVITY,
        rpy_rad=0.1 * math.pi / 180.0,
        mount=(-1, -1, 1),
    ),
    aliases=("OPEN-CR",),
)

#: Every bundled device model.
DEVICE_MODELS: tuple[DeviceModel, ...] = (OPENCR,)


def device_model_names() -> list[str]:
    return [m.name for m in DEVICE_MODELS]


def find_device_model(key: str | int) -> DeviceModel | None:
    """The model named ``key`` (name or alias, any case) or with model number ``key``; None if unknown."""
    for m in DEVICE_MODELS:
        if isinstance(key, int) and not isinstance(key, bool):
            if m.model_number == key:
                return m
        elif str(key).lower() in {m.name.lower(), *(a.lower() for a in m.aliases)}:
            return m
    return None


def load_device_model(key: str | int) -> DeviceModel:
    """:func:`find_device_model`, or a ConfigError listing the known models."""
    m = find_device_model(key)
    if m is None:
        raise ConfigError(f"unknown device model {key!r}; known: {', '.join(device_model_names())}")
    return m
