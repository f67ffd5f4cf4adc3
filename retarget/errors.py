"""The one user-error type of the ``retarget`` package."""


class RetargetError(ValueError):
    """A user error in retargeting: a bad trajectory or profile, an unknown body,
    an infeasible clip. The message names the file or field and the fix."""
