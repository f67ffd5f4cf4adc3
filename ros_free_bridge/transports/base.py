"""The transport interface the control loop talks to.

Units: radians, rad/s, newton-metres, degrees Celsius, volts, in the order of the
transport's ``joint_names`` (the robot's MJCF joint order). Servo ticks and other
wire units never leave a transport.

Life cycle, enforced by the bridge's safety supervisor rather than by each transport:
``open()`` → ``read_state()`` → ``write_goal(present)`` → ``set_torque(True)`` →
(``write_goal`` / ``read_state`` each tick) → ``safe_stop(policy)`` → ``close()``.
``close()`` must leave the hardware in its safe state even when called after an error,
and must be safe to call twice.

Two features a transport may lack answer plainly: ``position_limits()`` gives the limits it
enforces after ``open()`` (e.g. narrowed to the servos' EEPROM limits; the control loop adopts
the intersection with its own, so it never asks for what the transport would refuse) or None;
``pipeline(True)`` turns on a split-phase bus cycle where the transport has one and says
whether it did (False otherwise).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from firmware_cfg.readings import ImuReading, JointState

__all__ = ["STOP_POLICIES", "ImuReading", "JointState", "Transport"]

#: What ``safe_stop`` does: keep holding the present position with torque on, or
#: switch torque off (the servo goes limp).
STOP_POLICIES = ("hold", "limp")


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

    def position_limits(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(lower (n,), upper (n,)) rad that the transport enforces after ``open()``, or None."""

    def pipeline(self, enabled: bool = True) -> bool:
        """Split each bus cycle: a tick's write also sends the position read request whose reply
        the next tick's ``read_state`` takes (readings one tick old, no tick waits for the bus).
        Returns whether the split is on; False where the transport has no such cycle."""
