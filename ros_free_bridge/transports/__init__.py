"""Transports: where the bridge's joint commands go (servo buses, the virtual robot, a recorder).

Every transport implements :class:`ros_free_bridge.transports.base.Transport`.
"""
