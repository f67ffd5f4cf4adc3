"""The one user-error type of the ``sim`` package."""


class SimError(ValueError):
    """A user error in simulation: a bad trajectory, an unknown robot, a missing
    display. The message names the file or field and the fix."""
