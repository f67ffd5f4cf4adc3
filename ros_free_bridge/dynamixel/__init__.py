"""The Dynamixel path, one module per job (import from the module that holds a name):

- :mod:`.protocol`: packets of protocol 2.0 and 1.0 (framing, CRC, stuffing, error bits);
- :mod:`.group_codec`: the hot-path SYNC_WRITE / FAST_SYNC_READ / FAST_BULK_READ packets;
- :mod:`.port`: the serial port under dynamixel-sdk; :mod:`.bus`: PING/READ/WRITE with retries;
- :mod:`.servos`: joints ↔ ticks, limits, status units; :mod:`.cycle`: the per-tick packets,
  blocking or split phase; :mod:`.recovery`: alerts, reboot, Bus Watchdog;
  :mod:`.imu`: IMU devices on the bus (the OP3's OpenCR);
- :mod:`.transport`: :class:`~.transport.DynamixelTransport`, the control loop's transport.

The byte-level emulator is :mod:`ros_free_bridge.emulators`; the design: docs/dynamixel.md.
"""
