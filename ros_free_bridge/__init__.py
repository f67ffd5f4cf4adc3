"""The real-time bridge: sources, safety, transports and the command line."""

from ros_free_bridge.errors import BridgeError

__all__ = ["BridgeError"]
