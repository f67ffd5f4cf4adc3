"""Emulated hardware for trying the bridge without a robot (tests use them too).

- :mod:`.dynamixel_protocol`: the Dynamixel packet codec (protocol 2.0 CRC-16 and byte
  stuffing, protocol 1.0 checksum).
- :mod:`.emulated_servo`: one servo's control table, write rules and motor model.
- :mod:`.dynamixel_bus`: :class:`DynamixelBusEmulator`, a multi-servo bus on a
  pseudo-terminal that dynamixel-sdk opens like a USB adapter.

Importing this package is light (no thread or pty starts until ``start()``).
"""

from ros_free_bridge.emulators.dynamixel_bus import DynamixelBusEmulator, ServoSpec
from ros_free_bridge.emulators.emulated_servo import EmulatedServo, GoalRecord

__all__ = ["DynamixelBusEmulator", "ServoSpec", "EmulatedServo", "GoalRecord"]
