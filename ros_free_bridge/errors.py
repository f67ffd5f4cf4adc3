"""The one user-error type of the ``ros_free_bridge`` package."""


class BridgeError(RuntimeError):
    """A user-facing failure in the bridge: a missing port, a bad source, a safety
    stop. The message names what is wrong and the fix."""
