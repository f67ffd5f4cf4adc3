"""The transport interface the control loop talks to.

Units: radians, rad/s, newton-metres, degrees Celsius, volts, in the order of the
transport's ``joint_names`` (the robot's MJCF joint order). Servo ticks and other
wire units never leave a transport.

Life cycle, enforced by the bridge's safety supervisor rather than by each transport:
``open()`` → ``read_state()`` → ``write_goal(present)`` → ``set_torque(True)`` →
(``write_goal`` / ``read_state`` each tick) → ``safe_stop(policy)`` → ``close()``.
``close()`` must leave the hardware in its safe state even when called after an error,
and must be safe to call twice.

A transport may also offer ``position_limits() -> (lower (n,), upper (n,))``: the limits it
enforces after ``open()`` (e.g. narrowed to the servos' EEPROM limits). The control loop
then adopts the intersection with its own, so it never asks for what the transport would
refuse.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

#: What ``safe_stop`` does: keep holding the present position with torque on, or
#: switch torque off (the servo goes limp).
STOP_POLICIES = ("hold", "limp")


@dataclass(frozen=True)
class ImuReading:
    """One sample of a body-mounted IMU (e.g. the OP3's OpenCR, or a MuJoCo IMU site).

    Frame: the IMU's own axes, x forward, y left, z up when the robot stands upright.
    ``gyro`` (3,) angular rate in rad/s; ``accel`` (3,) specific force in m/s^2 (about
    +9.81 on z when upright and still); ``quat`` (4,) w, x, y, z: the IMU frame's
    orientation in the world (gravity along -z), all NaN where the device reports none.
    ``stamp``: the ``time.monotonic()`` second at which the sample was read.
    """

    gyro: np.ndarray
    accel: np.ndarray
    quat: np.ndarray
    stamp: float


@dataclass
class JointState:
    """One reading of every joint, arrays of shape (n,) in ``joint_names`` order.

    Fields that a transport cannot measure are NaN (never invented). ``errors`` maps a
    joint name to a short decoded description of its hardware-error status
    (e.g. "overheating"); it is empty when all is well. ``stamp`` is the
    ``time.monotonic()`` second at which the reading completed. ``imu`` is the body
    IMU's sample from the same cycle (None where the robot has no IMU device).
    """

    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    temperature: np.ndarray
    voltage: np.ndarray
    torque_enabled: np.ndarray
    stamp: float
    errors: dict[str, str] = field(default_factory=dict)
    #: the body IMU's reading taken in the same bus cycle, or None on a robot without one
    imu: ImuReading | None = None

    @classmethod
    def unknown(cls, n: int, stamp: float = 0.0) -> "JointState":
        nan = np.full(n, np.nan)
        return cls(nan.copy(), nan.copy(), nan.copy(), nan.copy(), nan.copy(), np.zeros(n, bool), stamp)


@runtime_checkable
class Transport(Protocol):
    """What the control loop needs from a bus, a microcontroller link or the virtual robot."""

    joint_names: tuple[str, ...]

    def open(self) -> None:
        """Acquire the port or start the simulation; raise the package error on failure."""

    def read_state(self) -> JointState:
        """Present positions every call; slower-changing fields may be refreshed at lower rates."""

    def write_goal(self, positions: np.ndarray) -> None:
        """Send goal positions (n,) in radians. The caller has already applied every limit."""

    def set_torque(self, enabled: bool) -> None:
        """Switch torque on or off on every joint."""

    def safe_stop(self, policy: str = "hold") -> None:
        """Immediately apply the stop policy ('hold' or 'limp') on every joint."""

    def close(self) -> None:
        """Leave the hardware safe (torque per the configured stop policy) and release it."""
