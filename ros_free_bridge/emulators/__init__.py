"""Emulated hardware for trying the bridge without a robot (tests use them too).

- :mod:`.emulated_servo`: one servo's control table, write rules and motor model.
- :mod:`.emulated_device`: a non-servo device on the bus (the OP3's OpenCR and its IMU).
- :mod:`.dynamixel_bus`: :class:`DynamixelBusEmulator`, a multi-servo bus on a
  pseudo-terminal that dynamixel-sdk opens like a USB adapter.

The packet codec they speak is :mod:`ros_free_bridge.dynamixel.protocol`; docs/dynamixel.md
describes all of it.

Importing this package is light (no thread or pty starts until ``start()``).
"""

from ros_free_bridge.emulators.dynamixel_bus import DynamixelBusEmulator, ServoSpec
from ros_free_bridge.emulators.emulated_device import EmulatedDevice
from ros_free_bridge.emulators.emulated_servo import EmulatedServo, GoalRecord

__all__ = ["DynamixelBusEmulator", "ServoSpec", "EmulatedServo", "EmulatedDevice", "GoalRecord"]
