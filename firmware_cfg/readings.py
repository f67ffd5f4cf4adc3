"""What one reading of a robot's hardware is: every joint's state and the body IMU's sample.

The one type every source of readings returns: the bridge's transports (a Dynamixel bus, a
serial link, the record transport) and the MuJoCo virtual robot (``sim.virtual_robot``), so
the control loop, the balance stabilizer and the check read them alike. Units: rad, rad/s,
N m, deg C, V; arrays (n,) in the robot's joint order.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


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
    def unknown(cls, n: int, stamp: float = 0.0) -> JointState:
        nan = np.full(n, np.nan)
        return cls(nan.copy(), nan.copy(), nan.copy(), nan.copy(), nan.copy(), np.zeros(n, bool), stamp)
